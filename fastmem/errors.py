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
