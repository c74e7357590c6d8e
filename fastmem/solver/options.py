"""Options of the solve pipeline: small frozen dataclasses, validated once where they are made.

:func:`fastmem.solve` takes every option as a plain keyword and groups them
here (:meth:`SolveOptions.from_keywords`); each layer of the pipeline reads
only its group:

- :class:`NewtonOptions`: the Newton-min loop (:mod:`fastmem.solver.newton`) and the
  levels around it (:mod:`fastmem.solver.levels`): method, path, step limit,
  outer stopping parameter, safeguard, nested iteration, final estimate;
- :class:`InnerOptions`: the AMG-CG linear steps (:mod:`fastmem.solver.steps`):
  inner stopping parameter, iteration limit, check frequency, hierarchy reuse
  and the pyamg options;
- :class:`RecordOptions`: what is recorded and shown while solving (monitor
  callback, flux at every history row, iterates kept);
- :class:`AdaptOptions`: solving to a tolerance by adaptive refinement
  (:mod:`fastmem.adapt.loop`; only when ``tol`` or ``rtol`` is given).

The memory guard that :func:`fastmem.solve` runs first lives on the ground floor
(:mod:`fastmem.memory`).

A value that does not fit raises :class:`~fastmem.errors.ParameterError` (or
:class:`~fastmem.errors.InputTypeError` for a wrong type) naming the option.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from types import MappingProxyType

import numpy as np

from ..errors import InputTypeError, ParameterError
from ..linalg.amg import check_amg_options
from ..memory import memory_limit

__all__ = [
    "ALG_ESTIMATES",
    "EXACT_MAX_VERTICES",
    "MAX_VERTICES",
    "METHODS",
    "MULTIGRIDS",
    "PATHS",
    "AdaptOptions",
    "InnerOptions",
    "NewtonOptions",
    "RecordOptions",
    "SolveOptions",
]

#: Solution methods of :func:`fastmem.solve` (how each linear step is solved).
METHODS = ("inexact", "exact-amg", "exact")
#: Linear-step formulations (docs/method.md §3.2 and 3.3).
PATHS = ("auto", "general", "decoupled")
#: Multigrid preconditioners of the CG steps (``multigrid`` of :func:`fastmem.solve`).
MULTIGRIDS = ("auto", "geometric", "algebraic")
#: what the inner criterion of method "inexact" compares with its budget (InnerOptions)
ALG_ESTIMATES = ("bound", "cg")

#: Default vertex limit of the adaptive loop (about 10M triangles; ~6 GB at the
#: measured 1.1-1.3 KB per vertex of a solve with the bound).
MAX_VERTICES = 5_000_000
#: Vertex limit of the adaptive loop with method="exact" (default and largest accepted):
#: a sparse direct factorisation of the reduced system of a 1M-vertex mesh takes about
#: 40 s and 3 GB per Newton step (bench/direct_ordering.py, extrapolated).
EXACT_MAX_VERTICES = 1_000_000


def _flag(name, value) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise InputTypeError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def _number(name, value, integer=False, allow_zero=False):
    ok_type = (int, np.integer) if integer else (int, float, np.integer, np.floating)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, ok_type):
        kind = "an integer" if integer else "a number"
        raise ParameterError(f"{name} must be {kind}, got {value!r}")
    if not (math.isfinite(value) and (value >= 0 if allow_zero else value > 0)):
        bound = ">= 0" if allow_zero else "positive"
        raise ParameterError(f"{name} must be {bound}, got {value!r}")
    return int(value) if integer else float(value)


class _Frozen:
    """Validation hook: ``_check(name, value)`` returns the stored (normalised) value."""

    def __post_init__(self):
        for f in fields(self):
            object.__setattr__(self, f.name, self._check(f.name, getattr(self, f.name)))


@dataclass(frozen=True)
class NewtonOptions(_Frozen):
    """The Newton-min loop and the levels around it (see :func:`fastmem.solve`)."""

    method: str = "inexact"
    path: str = "auto"
    max_newton: int = 1000
    gamma_lin: float = 0.1
    safeguard: bool = True
    nested: bool | str = "auto"
    estimate: bool = False

    def _check(self, name, value):
        if name == "method" and value not in METHODS:
            raise ParameterError(f"method must be one of {METHODS}, got {value!r}")
        if name == "path" and value not in PATHS:
            raise ParameterError(f"path must be 'auto', 'general' or 'decoupled', got {value!r}")
        if name == "max_newton":
            return _number(name, value, integer=True)
        if name == "gamma_lin":
            return _number(name, value)
        if name in ("safeguard", "estimate"):
            return _flag(name, value)
        if name == "nested":
            if isinstance(value, str) and value == "auto":
                return value
            if not isinstance(value, (bool, np.bool_)):
                raise ParameterError(f"nested must be True, False or 'auto', got {value!r}")
            return bool(value)
        return value

    @property
    def exact(self) -> bool:
        """Every linear step is solved to round-off (methods "exact" and "exact-amg")."""
        return self.method != "inexact"

    @property
    def needs_estimate(self) -> bool:
        """The returned triple gets the guaranteed bound (always for "inexact")."""
        return self.estimate or self.method == "inexact"


@dataclass(frozen=True)
class InnerOptions(_Frozen):
    """The AMG-CG linear steps of methods "inexact" and "exact-amg"."""

    gamma_alg: float = 0.1
    max_inner: int = 500
    check_every: int = 1
    amg_reuse: float = 0.05
    amg_options: MappingProxyType = field(default=None)
    #: "geometric": on the levels of nested iteration the decoupled CGs take the
    #: geometric multigrid of the chain (:class:`fastmem.linalg.gmg.NestedMG`);
    #: "algebraic": pyamg's smoothed aggregation everywhere (the two-grid cycle for s);
    #: "auto": geometric on levels with at least
    #: :data:`fastmem.solver.levels.GEOMETRIC_MIN_UNKNOWNS` interior vertices.
    multigrid: str = "auto"
    #: What the inner criterion compares with ``gamma_alg max(eta_disc, eta_lin)``:
    #: "bound", the guaranteed eta_alg (docs/method.md §6); "cg", the smaller of it and
    #: the CG's own estimate of the energy-norm algebraic error
    #: (:meth:`fastmem.linalg.amg.PCG.error_estimate`), for a triple that is not
    #: returned: the adaptive loop's intermediate meshes
    #: (:func:`fastmem.adapt.loop.solve_to_tolerance`).  The bound of every triple is
    #: computed as always; only when the CG stops differs.
    alg_estimate: str = "bound"
    #: The memory limit of :func:`fastmem.solve` (None, False or bytes, as there): the
    #: memory the inexact step's spilling decision (:func:`fastmem.solver.inexact.memory_pressure`)
    #: measures its estimate against, like the guard before the solve.
    memory_limit: object = None

    def _check(self, name, value):
        if name == "memory_limit":
            memory_limit(value)  # a bad value is refused here, naming memory_limit
            return value
        if name in ("max_inner", "check_every"):
            return _number(name, value, integer=True)
        if name == "gamma_alg":
            return _number(name, value)
        if name == "amg_reuse":
            return _number(name, value, allow_zero=True)
        if name == "alg_estimate" and value not in ALG_ESTIMATES:
            raise ParameterError(f"alg_estimate must be one of {ALG_ESTIMATES}, got {value!r}")
        if name == "multigrid":
            if value not in MULTIGRIDS:
                raise ParameterError(f"multigrid must be one of {MULTIGRIDS}, got {value!r}")
            return value
        if name == "amg_options":
            if isinstance(value, MappingProxyType):
                value = dict(value)
            return MappingProxyType(check_amg_options(value))
        return value


@dataclass(frozen=True)
class RecordOptions(_Frozen):
    """What is recorded while solving."""

    monitor: object = None
    full_history: bool = False
    keep_iterates: bool = False

    def _check(self, name, value):
        if name == "monitor" and value is not None and not callable(value):
            raise InputTypeError(f"monitor must be a callable taking one row, got {value!r}")
        if name in ("full_history", "keep_iterates"):
            return _flag(name, value)
        return value


@dataclass(frozen=True)
class AdaptOptions(_Frozen):
    """Solving to a tolerance: the refinement loop of :mod:`fastmem.adapt.loop`.

    ``None`` for ``max_vertices`` means :data:`MAX_VERTICES`
    (:data:`EXACT_MAX_VERTICES` with method "exact"), resolved by
    :meth:`SolveOptions.from_keywords`.
    """

    tol: float | None = None
    rtol: float | None = None
    theta: float = 0.5
    #: each refinement makes at least this many times the vertices (more marked than
    #: Dörfler's set when it falls short; :mod:`fastmem.adapt.loop`, MARK)
    min_growth: float = 1.0
    #: rounds of bisection per step: the children of marked triangles are marked again
    #: (:func:`fastmem.mesh.refine.refine_marked`'s ``bisections``)
    bisections: int = 2
    max_vertices: int | None = None
    max_levels: int = 100
    time_budget: float | None = None
    level_monitor: object = None

    def _check(self, name, value):
        if name in ("tol", "rtol", "time_budget") and value is not None:
            return _number(name, value)
        if name == "theta":
            value = _number(name, value)
            if value > 1.0:
                raise ParameterError(f"theta must be in (0, 1], got {value!r}")
            return value
        if name == "min_growth":
            value = _number(name, value)
            if not 1.0 <= value <= 4.0:
                raise ParameterError(
                    f"min_growth must be in [1, 4] (1: Dörfler's mesh as it is; one round of "
                    f"bisection at most doubles the vertices, two rounds quadruple them), "
                    f"got {value!r}"
                )
            return value
        if name == "bisections":
            value = _number(name, value, integer=True)
            if not 1 <= value <= 3:
                raise ParameterError(
                    f"bisections must be 1, 2 or 3 (rounds of bisection per refinement), "
                    f"got {value!r}"
                )
            return value
        if name in ("max_vertices", "max_levels") and value is not None:
            return _number(name, value, integer=True)
        if name == "level_monitor" and value is not None and not callable(value):
            raise InputTypeError(f"level_monitor must be a callable taking one row, got {value!r}")
        return value

    def __post_init__(self):
        super().__post_init__()
        if self.tol is None and self.rtol is None:
            raise ParameterError("adaptive refinement needs tol or rtol (or both)")
        if self.min_growth > 2.0**self.bisections:
            raise ParameterError(
                f"min_growth={self.min_growth:g} needs bisections >= 2: {self.bisections} "
                f"round(s) of bisection make at most {2**self.bisections} times the vertices"
            )


#: Keywords of :class:`AdaptOptions` other than the tolerances, with the values that mean
#: "not given" (they need ``tol`` or ``rtol``).
_ADAPT_ONLY = {
    "theta": None,
    "min_growth": None,
    "bisections": None,
    "max_vertices": None,
    "max_levels": None,
    "time_budget": None,
    "level_monitor": None,
}


def _adapt_options(keywords, method) -> AdaptOptions | None:
    names = [f.name for f in fields(AdaptOptions)]
    given = {n: keywords.pop(n) for n in names if n in keywords}
    if given.get("tol") is None and given.get("rtol") is None:
        extra = sorted(n for n, v in given.items() if n in _ADAPT_ONLY and v is not None)
        if extra:
            raise ParameterError(
                f"{', '.join(extra)} only apply to adaptive refinement: give tol or rtol too"
            )
        return None
    given = {n: v for n, v in given.items() if v is not None}
    limit = EXACT_MAX_VERTICES if method == "exact" else None
    opts = AdaptOptions(**given)
    if opts.max_vertices is None:
        opts = AdaptOptions(**{**given, "max_vertices": limit or MAX_VERTICES})
    elif limit is not None and opts.max_vertices > limit:
        raise ParameterError(
            f"max_vertices={opts.max_vertices} is too large for method='exact' (sparse direct "
            f"solves; at most {limit}): use method='inexact' or a smaller max_vertices"
        )
    return opts


@dataclass(frozen=True)
class SolveOptions:
    """All options of one solve, one group per layer (``adapt`` is None without a tolerance)."""

    newton: NewtonOptions = field(default_factory=NewtonOptions)
    inner: InnerOptions = field(default_factory=InnerOptions)
    record: RecordOptions = field(default_factory=RecordOptions)
    adapt: AdaptOptions | None = None

    @classmethod
    def from_keywords(cls, **keywords) -> SolveOptions:
        """Group the keywords of :func:`fastmem.solve`; an unknown keyword is an error."""
        groups = {}
        for group_cls in (NewtonOptions, InnerOptions, RecordOptions):
            names = [f.name for f in fields(group_cls)]
            groups[group_cls] = group_cls(**{n: keywords.pop(n) for n in names if n in keywords})
        adapt = _adapt_options(keywords, groups[NewtonOptions].method)
        if keywords:
            raise ParameterError(f"unknown solve options {sorted(keywords)}")
        return cls(groups[NewtonOptions], groups[InnerOptions], groups[RecordOptions], adapt)


# --------------------------------------------------------------------- memory guard
