"""The import graph of fastmem and bench has no cycles, and every module imports alone.

The graph is read from the source (every ``import`` and ``from ... import``
statement anywhere in a file, also inside functions), so a lazy import that
closes a circle is found as well as a module-level one.  The direction of every
import (down the table of layers) is checked by tests/package/test_layout.py.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import fastmem.kernels
import pytest
from source_imports import modules, statements

import fastmem

ROOT = Path(__file__).resolve().parents[2]
BENCH = ROOT / "bench"

#: Optional dependencies (the test, plot and bench extras): no fastmem module may need
#: them to import, and the bench modules import without matplotlib.
EXTRAS = ("matplotlib", "skfem", "gmsh", "sympy", "pytest", "hypothesis")


FASTMEM = {
    **modules(Path(fastmem.__file__).parent, "fastmem"),
    **modules(Path(fastmem.kernels.__file__).parent, "fastmem.kernels"),
}
BENCH_MODULES = modules(BENCH, "bench") if (BENCH / "__init__.py").is_file() else {}
SOURCES = {**FASTMEM, **BENCH_MODULES}


def _imports(name, path, known):
    """Yield ``(module, line)`` for every import in ``path`` of a module in ``known``."""
    for statement in statements(name, path):
        for target in statement.targets(known):
            if target in known and target != name:
                yield target, statement.line


def import_graph(sources):
    """``{module: {imported module: first line}}`` over the modules of ``sources``."""
    graph = {}
    for name, path in sources.items():
        edges = graph[name] = {}
        for target, line in _imports(name, path, sources):
            edges.setdefault(target, line)
    return graph


def strongly_connected(graph):
    """Tarjan's algorithm (iterative): the strongly connected components of ``graph``."""
    index, low, on_stack, stack, components = {}, {}, set(), [], []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(graph[root]))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, successors = work[-1]
            for succ in successors:
                if succ not in index:
                    index[succ] = low[succ] = len(index)
                    stack.append(succ)
                    on_stack.add(succ)
                    work.append((succ, iter(graph[succ])))
                    break
                if succ in on_stack:
                    low[node] = min(low[node], index[succ])
            else:
                work.pop()
                if work:
                    parent = work[-1][0]
                    low[parent] = min(low[parent], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    components.append(sorted(component))
    return components


def _cycle(graph, component):
    """One import cycle through the first module of ``component``, as a list of edges."""
    members = set(component)
    start = component[0]
    previous = {start: None}
    frontier = [start]
    while frontier:  # breadth first inside the component, back to start
        following = []
        for node in frontier:
            for succ in sorted(graph[node]):
                if succ == start:
                    path = [node]
                    while previous[path[-1]] is not None:
                        path.append(previous[path[-1]])
                    path.reverse()
                    return list(zip(path, [*path[1:], start], strict=True))
                if succ in members and succ not in previous:
                    previous[succ] = node
                    following.append(succ)
        frontier = following
    raise AssertionError(f"{component} is not a cycle")  # pragma: no cover


def _describe(graph, component):
    edges = _cycle(graph, component)
    steps = ", ".join(
        f"{a} -> {b} ({SOURCES[a].relative_to(SOURCES[a].parents[1])}:{graph[a][b]})"
        for a, b in edges
    )
    return f"{' <-> '.join(component)}: {steps}"


def test_tarjan_finds_cycles():
    graph = {"a": {"b": 1}, "b": {"c": 1}, "c": {"a": 1, "d": 1}, "d": {}, "e": {"e": 1}}
    components = sorted(strongly_connected(graph))
    assert components == [["a", "b", "c"], ["d"], ["e"]]
    assert _cycle(graph, ["a", "b", "c"]) == [("a", "b"), ("b", "c"), ("c", "a")]


def test_imports_resolve_relative_and_lazy(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("from . import a\n")
    (pkg / "a.py").write_text("def f():\n    from .sub import b\n    import pkg.sub\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "b.py").write_text("from .. import a\nfrom ..a import f\nimport numpy\n")
    graph = import_graph(modules(pkg, "pkg"))
    assert graph["pkg"] == {"pkg.a": 1}
    assert graph["pkg.a"] == {"pkg.sub.b": 2, "pkg.sub": 3}
    assert graph["pkg.sub.b"] == {"pkg.a": 1}
    assert [c for c in strongly_connected(graph) if len(c) > 1] == [["pkg.a", "pkg.sub.b"]]


@pytest.fixture(scope="module")
def graph():
    graph = import_graph(SOURCES)
    assert "fastmem.io.result" in graph
    assert "fastmem.kernels.assembly" in graph
    return graph


def test_no_import_cycles(graph):
    """No circle of imports in fastmem, fastmem.kernels and bench (lazy imports included)."""
    cycles = [_describe(graph, c) for c in strongly_connected(graph) if len(c) > 1]
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_kernels_import_nothing_from_fastmem(graph):
    def kernel(name):
        return name == "fastmem.kernels" or name.startswith("fastmem.kernels.")

    for name, edges in graph.items():
        if kernel(name):
            outside = [t for t in edges if not kernel(t)]
            assert not outside, f"{name} imports {outside}"


# ----------------------------------------------------------------------------- import alone

# Imports each named module in turn, each time after removing fastmem and bench from
# sys.modules (third-party packages stay loaded: they are not under test), with the
# optional extras made unimportable.  Prints {module: traceback or None} as JSON.
_IMPORTER = """
import importlib, json, sys, traceback
for extra in sys.argv[1].split(","):
    sys.modules[extra] = None  # "import extra" raises ModuleNotFoundError
outcome = {}
for name in sys.argv[2:]:
    for key in [k for k in sys.modules if k.split(".")[0] in ("fastmem", "bench")]:
        del sys.modules[key]
    try:
        importlib.import_module(name)
        outcome[name] = None
    except BaseException:
        outcome[name] = traceback.format_exc()
print(json.dumps(outcome))
"""

#: Entry points that run a program when imported (``python -m``): not imported here.
ENTRY_POINTS = ("fastmem.__main__",)

ALONE = sorted(n for n in SOURCES if n not in ENTRY_POINTS)


def _start(names, extras, cwd, env):
    """Start a subprocess importing ``names`` in turn (see ``_IMPORTER``)."""
    command = [sys.executable, "-c", _IMPORTER, ",".join(extras), *names]
    pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True}
    return subprocess.Popen(command, cwd=cwd, env=env, **pipes)


@pytest.fixture(scope="module")
def imported_alone(tmp_path_factory):
    """Import every module alone; fastmem as installed, bench as run: from the root.

    Three subprocesses run at once (two halves of fastmem, and bench): about 10 s
    on two cores.
    """
    env = dict(os.environ)
    bench_env = dict(env)
    bench_env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    outside = tmp_path_factory.mktemp("import-alone")  # not the root: the installed fastmem
    fastmem_names = [n for n in ALONE if n in FASTMEM]
    bench_names = [n for n in ALONE if n in BENCH_MODULES]
    half = len(fastmem_names) // 2
    jobs = [
        (fastmem_names[:half], EXTRAS, outside, env),
        (fastmem_names[half:], EXTRAS, outside, env),
        (bench_names, ("matplotlib",), ROOT, bench_env),
    ]
    outcome = {}
    for proc in [_start(*job) for job in jobs if job[0]]:
        out, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err[-3000:]
        outcome.update(json.loads(out.splitlines()[-1]))
    return outcome


@pytest.mark.parametrize("name", ALONE)
def test_module_imports_alone(imported_alone, name):
    error = imported_alone[name]
    assert error is None, f"import {name} in a fresh interpreter failed:\n{error}"
