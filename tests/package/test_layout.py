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

import ast
import importlib
import pathlib
import re
import sys

import pytest

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
    ("problems", ("fastmem.problems",)),
    ("sweeps", ("fastmem.sweeps",)),
    ("cli", ("fastmem.cli",)),
    ("root", ("fastmem", "fastmem.__main__")),
)

#: Third-party packages a function may import on first use: the optional extras.
OPTIONAL = ("dask", "distributed", "pandas", "matplotlib", "gmsh", "tomli")

PACKAGE = pathlib.Path(fastmem.__file__).parent
KERNELS = pathlib.Path(fastmem.kernels.__file__).parent


def _modules():
    """(dotted name, path, is_package) of every module of fastmem and its kernels."""
    out = []
    for root, prefix in ((PACKAGE, "fastmem"), (KERNELS, "fastmem.kernels")):
        for path in sorted(root.rglob("*.py")):
            rel = path.relative_to(root).with_suffix("").parts
            if prefix == "fastmem" and rel[0] == "kernels":
                continue  # a source checkout with fastmem/kernels: counted under KERNELS
            parts = [prefix, *rel]
            is_pkg = parts[-1] == "__init__"
            if is_pkg:
                parts = parts[:-1]
            out.append((".".join(parts), path, is_pkg))
    return out


MODULES = _modules()


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


def _imports(name, path, is_pkg):
    """(line, target module, imported names, inside a function, source line) per import."""
    tree = ast.parse(path.read_text(), filename=str(path))
    lines = path.read_text().splitlines()
    parents = {}
    for node in ast.walk(tree):
        for child in ast.iter_child_nodes(node):
            parents[child] = node
    out = []
    for node in ast.walk(tree):
        if not isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        inner, q = False, node
        while q in parents:
            q = parents[q]
            if isinstance(q, (ast.FunctionDef, ast.AsyncFunctionDef)):
                inner = True
                break
        text = " ".join(lines[node.lineno - 1 : node.end_lineno])
        if isinstance(node, ast.Import):
            for alias in node.names:
                out.append((node.lineno, alias.name, (), inner, text))
            continue
        if node.level:
            base = name.split(".") if is_pkg else name.split(".")[:-1]
            base = base[: len(base) - (node.level - 1)]
            target = ".".join(base + ([node.module] if node.module else []))
        else:
            target = node.module
        out.append((node.lineno, target, tuple(a.name for a in node.names), inner, text))
    return out


def _targets(target, names):
    """The fastmem modules an import statement reaches (``from pkg import module`` too)."""
    known = {m for m, _, _ in MODULES}
    found = []
    for n in names or ("",):
        full = f"{target}.{n}" if n else target
        found.append(full if full in known else target)
    return found


def layer_violations():
    bad = []
    for name, path, is_pkg in MODULES:
        mine = layer_of(name)
        for line, target, names, _, _ in _imports(name, path, is_pkg):
            if not (target == "fastmem" or target.startswith("fastmem.")):
                continue
            for t in _targets(target, names):
                if layer_of(t) > mine:
                    bad.append(
                        f"{path.name}:{line} {name} ({LAYERS[mine][0]}) imports {t} "
                        f"({LAYERS[layer_of(t)][0]})"
                    )
    return bad


def private_imports():
    bad = []
    for name, path, is_pkg in MODULES:
        for line, target, names, _, _ in _imports(name, path, is_pkg):
            if not target.startswith("fastmem") or subpackage_of(target) == subpackage_of(name):
                continue
            parts = target.split(".")[2:] + [n for n in names]
            private = [p for p in parts if p.startswith("_") and not p.startswith("__")]
            if private:
                bad.append(f"{name}:{line} imports {private} from {target}")
    return bad


def function_imports():
    bad = []
    for name, path, is_pkg in MODULES:
        for line, target, _, inner, text in _imports(name, path, is_pkg):
            if not inner:
                continue
            if target.split(".")[0] in OPTIONAL:
                continue
            reason = re.search(r"#\s*lazy:.*\d", text)  # a measured reason: it has a number
            if reason is None:
                bad.append(f"{name}:{line} imports {target} inside a function")
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
