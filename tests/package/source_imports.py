"""Import statements read from source with :mod:`ast` (nothing imported): one reader for
the cycle test (test_imports.py) and the layer rules (test_layout.py)."""

from __future__ import annotations

import ast
import functools
from dataclasses import dataclass
from pathlib import Path


def modules(folder, package) -> dict:
    """Map module name -> source file for every ``.py`` file under ``folder``."""
    out = {}
    for path in sorted(Path(folder).rglob("*.py")):
        rel = path.relative_to(folder).with_suffix("")
        parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
        out[".".join((package, *parts))] = path
    return out


@dataclass(frozen=True)
class Statement:
    """One import statement: ``from base import names`` or ``import base`` (names empty)."""

    line: int
    base: str  # absolute module name, relative imports resolved
    names: tuple
    inside_function: bool
    text: str  # the statement's source lines, comments included

    def targets(self, known) -> list:
        """The modules of ``known`` it reaches (``from pkg import module`` names a module)."""
        if not self.names:
            return [self.base]
        return [
            f"{self.base}.{n}" if f"{self.base}.{n}" in known else self.base for n in self.names
        ]


def statements(name, path) -> list:
    """Every import statement of module ``name`` (source ``path``), also inside functions.

    Each file is parsed once per test session (four tests read every file's imports);
    a file that changes on disk is parsed again.
    """
    stat = Path(path).stat()
    return list(_statements(name, str(path), stat.st_mtime_ns, stat.st_size))


@functools.cache
def _statements(name, path, mtime_ns, size) -> tuple:
    source = Path(path).read_text(encoding="utf-8")
    lines = source.splitlines()
    tree = ast.parse(source, filename=str(path))
    package = name if Path(path).name == "__init__.py" else name.rpartition(".")[0]
    parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    out = []
    for node in ast.walk(tree):
        if not isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        inner, q = False, node
        while q in parents and not inner:
            q = parents[q]
            inner = isinstance(q, (ast.FunctionDef, ast.AsyncFunctionDef))
        text = "\n".join(lines[node.lineno - 1 : node.end_lineno])
        if isinstance(node, ast.Import):
            for alias in node.names:
                out.append(Statement(node.lineno, alias.name, (), inner, text))
            continue
        base = node.module or ""
        if node.level:
            parts = package.split(".")
            base = ".".join([*parts[: len(parts) - node.level + 1], *filter(None, [base])])
        names = tuple(alias.name for alias in node.names)
        out.append(Statement(node.lineno, base, names, inner, text))
    return tuple(out)
