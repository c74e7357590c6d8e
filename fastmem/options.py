"""Options of the solve pipeline: small frozen dataclasses, validated once where they are made.

:func:`fastmem.solve` takes every option as a plain keyword and groups them
here (:meth:`SolveOptions.from_keywords`); each layer of the pipeline reads
only its group:

- :class:`NewtonOptions`: the Newton-min loop (:mod:`fastmem.newton`) and the
  levels around it (:mod:`fastmem.levels`): method, path, step limit,
  outer stopping parameter, safeguard, nested iteration, final estimate;
- :class:`InnerOptions`: the AMG-CG linear steps (:mod:`fastmem.steps`):
  inner stopping parameter, iteration limit, check frequency, hierarchy reuse
  and the pyamg options;
- :class:`RecordOptions`: what is recorded and shown while solving (monitor
  callback, flux at every history row, iterates kept);
- :class:`AdaptOptions`: solving to a tolerance by adaptive refinement
  (:mod:`fastmem.afem`; only when ``tol`` or ``rtol`` is given).

The memory guard lives here too (:func:`check_memory`): before a solve (and
before :meth:`fastmem.Mesh.rectangle` allocates a mesh) the peak resident
memory is estimated from the mesh size, the method and whether the bound is
computed, and a run that cannot fit in the machine's memory is refused with
:class:`MemoryLimitError` instead of being killed by the operating system.
The limit is the machine's physical memory (or the cgroup limit when lower);
``fm.solve(..., memory_limit=...)`` or the environment variable
``FASTMEM_MEMORY_LIMIT`` (bytes, or with a K/M/G/T suffix; ``0``, ``off`` or
``none`` to disable) override it.

A value that does not fit raises :class:`~fastmem.errors.ParameterError` (or
:class:`~fastmem.errors.InputTypeError` for a wrong type) naming the option.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields
from types import MappingProxyType

import numpy as np

from . import errors as _errors
from .amg import check_amg_options
from .errors import InputTypeError, ParameterError

__all__ = [
    "EXACT_MAX_VERTICES",
    "MEMORY_LIMIT_ENV",
    "MAX_VERTICES",
    "METHODS",
    "PATHS",
    "AdaptOptions",
    "InnerOptions",
    "MemoryLimitError",
    "NewtonOptions",
    "RecordOptions",
    "SolveOptions",
    "check_memory",
    "estimate_memory",
    "memory_limit",
]

#: Solution methods of :func:`fastmem.solve` (how each linear step is solved).
METHODS = ("inexact", "exact-amg", "exact")
#: Linear-step formulations (docs/method.md §3.2 and 3.3).
PATHS = ("auto", "general", "decoupled")

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
    #: The memory limit of :func:`fastmem.solve` (None, False or bytes, as there): the
    #: memory the inexact step's spilling decision (:func:`fastmem.adaptive.memory_pressure`)
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
    """Solving to a tolerance: the refinement loop of :mod:`fastmem.afem`.

    ``None`` for ``max_vertices`` means :data:`MAX_VERTICES`
    (:data:`EXACT_MAX_VERTICES` with method "exact"), resolved by
    :meth:`SolveOptions.from_keywords`.
    """

    tol: float | None = None
    rtol: float | None = None
    theta: float = 0.5
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
        if name in ("max_vertices", "max_levels") and value is not None:
            return _number(name, value, integer=True)
        if name == "level_monitor" and value is not None and not callable(value):
            raise InputTypeError(f"level_monitor must be a callable taking one row, got {value!r}")
        return value

    def __post_init__(self):
        super().__post_init__()
        if self.tol is None and self.rtol is None:
            raise ParameterError("adaptive refinement needs tol or rtol (or both)")


#: Keywords of :class:`AdaptOptions` other than the tolerances, with the values that mean
#: "not given" (they need ``tol`` or ``rtol``).
_ADAPT_ONLY = {
    "theta": None,
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
MemoryLimitError = _errors.MemoryLimitError  # defined in fastmem.errors; kept importable here


#: Environment variable overriding the memory limit of the guard: bytes, or a number with
#: a K, M, G or T suffix (powers of 1024); ``0``, ``off`` or ``none`` disable the check.
MEMORY_LIMIT_ENV = "FASTMEM_MEMORY_LIMIT"

#: Resident memory of a process with fastmem, numpy, scipy, numba and pyamg loaded and
#: the kernels compiled (0.21 GB measured by bench/memory.py), with a margin.
BASE_BYTES = 300_000_000

#: Peak resident bytes per vertex of a solve with the bound on a mesh with about two
#: triangles per vertex (mesh -> scene -> fm.solve -> result.save; bench/memory.py,
#: default scene, "inexact": 1070 B/vertex above BASE_BYTES at n = 2048, 1280 at n = 1024
#: where freed heap memory is not returned to the system), with a margin; "exact-amg" is
#: not measured and keeps its former figure.  "exact" adds the sparse factorisation
#: (about 3 GB per million vertices, see :data:`EXACT_MAX_VERTICES`).
SOLVE_BYTES_PER_VERTEX = {"inexact": 1350, "exact-amg": 1800, "exact": 4650}

#: Part of the peak due to the flux reconstruction (RT1 coefficients of both membranes,
#: 256 bytes per vertex, and its work arrays): not needed with ``estimate=False``.
FLUX_BYTES_PER_VERTEX = 300

#: Peak resident bytes per vertex of building a mesh and its topology (Mesh.square, edges,
#: patches; bench/memory.py phase "mesh": 470 B/vertex above BASE_BYTES), with a margin.
MESH_BYTES_PER_VERTEX = 550

_SUFFIX = {"k": 2**10, "m": 2**20, "g": 2**30, "t": 2**40}


def _effective_vertices(n_vertices: int, n_triangles: int) -> float:
    """Vertices of a two-triangles-per-vertex mesh with the same work (per-triangle arrays)."""
    return max(float(n_vertices), 0.5 * float(n_triangles))


def estimate_memory(
    n_vertices: int, n_triangles: int, method: str = "inexact", estimate: bool = True
) -> int:
    """Estimated peak resident memory (bytes) of a solve on a mesh of this size.

    A model fitted to bench/memory.py (``BASE_BYTES + bytes per vertex * N``, with
    ``N`` replaced by ``M / 2`` for meshes with more than two triangles per vertex);
    ``method=None`` estimates building the mesh alone.  Pure arithmetic: nothing is
    allocated.
    """
    nv = _effective_vertices(n_vertices, n_triangles)
    if method is None:
        per_vertex = MESH_BYTES_PER_VERTEX
    else:
        if method not in METHODS:
            raise ParameterError(f"method must be one of {METHODS}, got {method!r}")
        per_vertex = SOLVE_BYTES_PER_VERTEX[method]
        if not estimate and method != "inexact":
            per_vertex -= FLUX_BYTES_PER_VERTEX
    return int(BASE_BYTES + per_vertex * nv)


def _machine_memory() -> int | None:
    """Physical memory of the machine, or the cgroup memory limit when it is lower."""
    total = None
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        pass
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(path, encoding="ascii") as fh:
                text = fh.read().strip()
        except OSError:
            continue
        if text.isdigit() and int(text) < (total or math.inf):
            total = int(text)
    return total


def _parse_limit(value, name):
    if value is None or value is False:
        return None
    if isinstance(value, str):
        text = value.strip().lower()
        if text in ("", "0", "off", "none", "false", "no"):
            return None
        scale = 1
        if text[-1] == "b":
            text = text[:-1]
        if text and text[-1] in _SUFFIX:
            scale, text = _SUFFIX[text[-1]], text[:-1]
        try:
            value = float(text) * scale
        except ValueError:
            raise ParameterError(
                f"{name} must be a number of bytes, optionally with a K, M, G or T suffix "
                f"(e.g. 20G), or 0/off/none; got {value!r}"
            ) from None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ParameterError(f"{name} must be a number of bytes, None or False, got {value!r}")
    if not math.isfinite(value) or value < 0:
        raise ParameterError(f"{name} must be a non-negative number of bytes, got {value!r}")
    return None if value == 0 else int(value)


def memory_limit(limit=None) -> tuple[int | None, str]:
    """Return the memory limit of the guard in bytes (None: no check) and its source.

    ``limit``: None (default) takes the environment variable :data:`MEMORY_LIMIT_ENV`
    if it is set, else the machine's memory; ``False`` or 0 disables the check; a
    number is a limit in bytes (a string may carry a K/M/G/T suffix).
    """
    if limit is not None:
        return _parse_limit(limit, "memory_limit"), "memory_limit"
    env = os.environ.get(MEMORY_LIMIT_ENV)
    if env is not None:
        return _parse_limit(env, MEMORY_LIMIT_ENV), MEMORY_LIMIT_ENV
    return _machine_memory(), "the machine's memory"


def _gb(x) -> str:
    return f"{x / 1e9:.1f} GB"


def check_memory(
    n_vertices: int,
    n_triangles: int,
    method: str | None = "inexact",
    estimate: bool = True,
    limit=None,
) -> int:
    """Refuse a run whose estimated peak memory exceeds the limit; return the estimate.

    Parameters
    ----------
    n_vertices, n_triangles : int
        Size of the mesh (nothing is allocated: a mesh that cannot fit is refused
        before it is built).
    method : str or None
        Solve method, or None for building the mesh alone.
    estimate : bool
        Whether the bound (flux reconstruction) is computed.
    limit : None, False, int or str
        See :func:`memory_limit`.

    Raises
    ------
    MemoryLimitError
        Naming the estimate, the limit and how to override it.
    """
    need = estimate_memory(n_vertices, n_triangles, method, estimate)
    lim, source = memory_limit(limit)
    if lim is not None and need > lim:
        what = "building this mesh" if method is None else f"solving with method={method!r}"
        bound = "" if method is None else (" with the bound" if estimate else " without the bound")
        raise MemoryLimitError(
            f"not enough memory: {what}{bound} on {n_vertices} vertices and {n_triangles} "
            f"triangles needs about {_gb(need)} (estimated peak), but {source} is "
            f"{_gb(lim)}; use a smaller mesh, or override the limit with "
            f"{'' if method is None else 'memory_limit=... (fm.solve) or '}the environment "
            f"variable {MEMORY_LIMIT_ENV} (bytes or e.g. 40G; 0 disables the check)"
        )
    return need
