"""The house rules of the package layout (docs/architecture.md), checked on the source.

- imports point down the table of layers :data:`LAYERS` (or stay inside a layer);
- no module imports a ``_private`` name (or a ``_private`` module) of another subpackage;
- imports inside functions only for the optional dependencies, or with a measured
  import-time reason on the line (``# lazy: ...``);
- every subpackage names its public face in ``__init__.__all__``, and those names exist.

The checks read the source with :mod:`ast` (nothing is imported), so a violation is
reported with its file and line whether or not the code path runs.
"""

from __future__ import annotations

import importlib
import pathlib
import re
import sys

import pytest
from source_imports import modules, statements

import fastmem

#: Bottom to top: a module may import from its own layer and from the layers below.
LAYERS = (
    ("kernels", ("fastmem.kernels",)),
    ("ground", ("fastmem.errors", "fastmem.config", "fastmem.memory", "fastmem.about")),
    ("linalg", ("fastmem.linalg",)),
    ("mesh", ("fastmem.mesh",)),
    ("fem", ("fastmem.fem",)),
    ("io", ("fastmem.io",)),
    ("estimators", ("fastmem.estimators",)),
    ("solver", ("fastmem.solver",)),
    ("adapt", ("fastmem.adapt",)),
    ("pipeline", ("fastmem.pipeline",)),
    ("problems", ("fastmem.problems", "fastmem.twophase")),
    ("sweeps", ("fastmem.sweeps",)),
    ("cli", ("fastmem.cli",)),
    ("root", ("fastmem", "fastmem.__main__")),
)

#: Third-party packages a function may import on first use: the optional extras.
OPTIONAL = ("dask", "distributed", "pandas", "matplotlib", "gmsh", "tomli")

PACKAGE = pathlib.Path(fastmem.__file__).parent
KERNELS = pathlib.Path(fastmem.kernels.__file__).parent

#: (dotted name, path, is_package) of every module of fastmem and its kernels.
MODULES = [
    (name, path, path.name == "__init__.py")
    for name, path in {**modules(PACKAGE, "fastmem"), **modules(KERNELS, "fastmem.kernels")}.items()
]


def layer_of(name: str) -> int:
    """Index in :data:`LAYERS` of a dotted module name of fastmem (the longest prefix)."""
    best, depth = None, -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (name == p or name.startswith(p + ".")) and p.count(".") > depth:
                best, depth = i, p.count(".")
    if best is None:
        raise AssertionError(f"module {name} is in no layer of LAYERS")
    return best


def subpackage_of(name: str) -> str:
    parts = name.split(".")
    return ".".join(parts[:2]) if len(parts) > 1 else parts[0]


def layer_violations():
    bad = []
    known = {m for m, _, _ in MODULES}
    for name, path, _ in MODULES:
        mine = layer_of(name)
        for st in statements(name, path):
            if not (st.base == "fastmem" or st.base.startswith("fastmem.")):
                continue
            for t in st.targets(known):
                if layer_of(t) > mine:
                    bad.append(
                        f"{path.name}:{st.line} {name} ({LAYERS[mine][0]}) imports {t} "
                        f"({LAYERS[layer_of(t)][0]})"
                    )
    return bad


def private_imports():
    bad = []
    for name, path, _ in MODULES:
        for st in statements(name, path):
            if not st.base.startswith("fastmem") or subpackage_of(st.base) == subpackage_of(name):
                continue
            parts = st.base.split(".")[2:] + list(st.names)
            private = [p for p in parts if p.startswith("_") and not p.startswith("__")]
            if private:
                bad.append(f"{name}:{st.line} imports {private} from {st.base}")
    return bad


def function_imports():
    bad = []
    for name, path, _ in MODULES:
        for st in statements(name, path):
            if not st.inside_function or st.base.split(".")[0] in OPTIONAL:
                continue
            reason = re.search(r"#\s*lazy:.*\d", st.text)  # a measured reason: it has a number
            if reason is None:
                bad.append(f"{name}:{st.line} imports {st.base} inside a function")
    return bad


def test_layer_table_covers_every_module():
    for name, _, _ in MODULES:
        layer_of(name)


def test_imports_point_down_the_layers():
    assert layer_violations() == []


def test_no_private_imports_across_subpackages():
    assert private_imports() == []


def test_function_level_imports_are_optional_or_explained():
    assert function_imports() == []


def test_the_checks_can_fail(tmp_path, monkeypatch):
    """An upward, a private and a function-level import in a fake module are all caught."""
    fake = tmp_path / "fake.py"
    fake.write_text(
        "from ..cli.main import main\n"
        "from ..linalg.amg import _trim\n"
        "def f():\n    import json\n"
    )
    monkeypatch.setattr(sys.modules[__name__], "MODULES", [("fastmem.mesh.fake", fake, False)])
    assert len(layer_violations()) == 1
    assert len(private_imports()) == 1
    assert len(function_imports()) == 1


SUBPACKAGES = sorted({subpackage_of(m) for m, _, is_pkg in MODULES if is_pkg and m != "fastmem"})


@pytest.mark.parametrize("sub", SUBPACKAGES)
def test_public_face(sub):
    module = importlib.import_module(sub)
    assert module.__doc__, f"{sub} has no docstring"
    face = getattr(module, "__all__", None)
    assert face, f"{sub}.__init__ names no public face in __all__"
    for public in face:
        assert not public.startswith("_"), f"{sub}.__all__ names a private {public}"
        if sub == "fastmem.sweeps":
            continue  # needs the dask extra: resolved on first use
        assert hasattr(module, public), f"{sub}.__all__ names {public}, which it lacks"


def test_layer_of_knows_every_subpackage():
    assert [layer_of(s) for s in SUBPACKAGES]


def test_every_slow_entry_names_a_test():
    """The SLOW table of tests/conftest.py names files and tests that exist (it cannot rot)."""
    import conftest

    tests = pathlib.Path(conftest.__file__).parent
    for key in conftest.SLOW:
        file, _, rest = key.partition("::")
        path = tests / file
        assert path.is_file(), f"SLOW names a missing file {file}"
        if rest:
            name = rest.split("[", 1)[0]
            assert f"def {name}(" in path.read_text(), f"SLOW names a missing test {key}"
