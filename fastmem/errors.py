"""Exceptions and warnings raised by fastmem.

Every error fastmem raises on purpose derives from :class:`FastmemError`, and
each one also subclasses the built-in exception a Python user would expect
(``ValueError`` for bad values, ``TypeError`` for bad types, ``RuntimeError``
for solver failures, ``OSError`` for unreadable archives), so both
``except fastmem.FastmemError`` and ``except ValueError`` work.
(``ArithmeticError`` for computations that left the float64 range,
``AttributeError`` for assignments to immutable objects.)

Messages name the offending field and, where short, its value.
"""

from __future__ import annotations

import difflib
import functools
import inspect

__all__ = [
    "ArchiveError",
    "ConvergenceError",
    "CyclingError",
    "DataError",
    "FastmemError",
    "FastmemWarning",
    "InputTypeError",
    "MeshError",
    "MeshFileError",
    "MeshWarning",
    "MemoryLimitError",
    "NumericalError",
    "ParameterError",
    "ReadOnlyError",
]
# Also here, for the entry points of every layer (not exported: __all__ lists the
# exception classes): closest_name and checked_keywords, at the end of the module.


class FastmemError(Exception):
    """Base class of all errors raised by fastmem on purpose."""


class InputTypeError(FastmemError, TypeError):
    """An argument has the wrong type or dtype (e.g. a string where an array is expected)."""


class MeshError(FastmemError, ValueError):
    """A mesh is invalid: wrong shapes, degenerate, tangled or non-manifold elements."""


class MeshFileError(MeshError, OSError):
    """A mesh file is missing or cannot be read (also an ``OSError``, like a missing archive)."""


class ParameterError(FastmemError, ValueError):
    """A scalar parameter is out of range (e.g. a non-positive mu or a negative g)."""


class ReadOnlyError(FastmemError, AttributeError):
    """An attribute of an immutable object (a Mesh or a Scene) was assigned: build a new one."""


class DataError(FastmemError, ValueError):
    """Problem data (f, g, nodal vectors) have a wrong shape or non-finite values."""


class ArchiveError(FastmemError, OSError):
    """A result archive cannot be read or written (foreign, corrupt or future format)."""


class NumericalError(FastmemError, ArithmeticError):
    """A computation produced NaN or inf (float64 overflow or breakdown).

    Raised instead of returning non-finite results, e.g. when the data are so large or so
    badly scaled that the solution, the residuals or the estimate overflow.
    """


class MemoryLimitError(FastmemError, MemoryError):
    """A run would need more memory than the machine has (:func:`fastmem.memory.check_memory`).

    Raised before anything large is allocated; the message names the estimate, the
    limit and how to override it (``memory_limit=`` or ``FASTMEM_MEMORY_LIMIT``).
    """


class ConvergenceError(FastmemError, RuntimeError):
    """An iterative solver failed in a way that leaves no usable result."""

    def __init__(self, message: str, history=None):
        super().__init__(message)
        self.history = history


class CyclingError(ConvergenceError):
    """Newton-min returned to an active set it had already visited (it cycles)."""


class FastmemWarning(UserWarning):
    """Base class of fastmem warnings."""


class MeshWarning(FastmemWarning):
    """A mesh was accepted after a repair (e.g. clockwise triangles re-oriented)."""


# ----------------------------------------------------------------------------- unknown keywords


def closest_name(name: str, choices) -> str | None:
    """Return the entry of ``choices`` a misspelt ``name`` most likely meant, or None.

    Names are compared without case, leading dashes and the difference between
    ``-`` and ``_``.  A match that differs only in those wins outright (``"N"`` ->
    ``"n"``, ``"--N"`` -> ``"--n"``, ``"--gamma_alg"`` -> ``"--gamma-alg"``);
    otherwise the closest by :func:`difflib.get_close_matches`, if any is close
    enough (similarity 0.6 or more).

    Parameters
    ----------
    name : str
        The unknown name (a keyword, or a command-line option with its dashes).
    choices : iterable of str
        The valid names.

    Returns
    -------
    str or None
        The suggestion, spelt as in ``choices``.
    """

    def norm(text: str) -> str:
        return text.lstrip("-").casefold().replace("_", "-")

    spelt = {}
    for choice in choices:
        spelt.setdefault(norm(choice), choice)
    key = norm(name)
    if key in spelt:
        return spelt[key]
    close = difflib.get_close_matches(key, list(spelt), n=1)
    return spelt[close[0]] if close else None


def checked_keywords(public_name: str):
    """Make a function refuse unknown keywords with a ParameterError that names the fix.

    Python's own ``TypeError`` ("got an unexpected keyword argument") names
    neither the closest valid keyword nor the valid ones; the wrapper checks the
    keyword names before the call (one set difference) and raises
    :class:`~fastmem.errors.ParameterError` with both.  The signature seen by
    :func:`inspect.signature` and ``help()`` is the wrapped function's.

    Parameters
    ----------
    public_name : str
        The name users call the function by (``"fastmem.solve"``), for the message.

    Returns
    -------
    callable
        A decorator.
    """

    def decorate(func):
        kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
        params = inspect.signature(func).parameters.values()
        names = [p.name for p in params if p.kind in kinds and p.name != "self"]
        accepted = frozenset(names)

        @functools.wraps(func)
        def wrapper(*args, **keywords):
            unknown = keywords.keys() - accepted
            if unknown:
                raise ParameterError(_unknown_keywords(public_name, sorted(unknown), names))
            return func(*args, **keywords)

        return wrapper

    return decorate


def _unknown_keywords(where: str, unknown: list[str], names: list[str]) -> str:
    fixes = []
    for name in unknown:
        best = closest_name(name, names)
        fixes.append(f"{name!r} (did you mean {best!r}?)" if best else repr(name))
    word = "keyword" if len(unknown) == 1 else "keywords"
    valid = ", ".join(names)
    return f"{where}() got the unknown {word} {', '.join(fixes)}; valid keywords: {valid}"
