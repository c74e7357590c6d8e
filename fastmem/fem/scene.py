"""The problem statement: mesh, tensions mu1, mu2, loads f1, f2, boundary value g.

A :class:`Scene` is validated on construction and knows which work it needs:
constant data are integrated without quadrature, constant tensions select the
decoupled solver path, and matrices and load vectors are assembled once, on
first use, and cached.
"""

from __future__ import annotations

import logging
import numbers

import numpy as np
import scipy.sparse as sp

from ..errors import (
    DataError,
    InputTypeError,
    ParameterError,
    ReadOnlyError,
    checked_keywords,
)
from ..kernels import pool as _par
from ..kernels.rows import active_rule_range, active_weight_range
from ..linalg.sparse import THREADED_ROWS, csr_diagonal, plain_float64, read_only
from ..mesh.mesh import Mesh
from .assembly import DEFAULT_LOAD_DEGREE, assemble_stiffness, evaluate_callable
from .loaddata import integrals

__all__ = ["Scene"]

logger = logging.getLogger(__name__)


#: Supported range of the tensions mu1, mu2 (each value).
MU_RANGE = (1e-100, 1e100)

#: Largest supported solution scale and contact-pressure scale (see :meth:`Scene.check_scale`).
MAX_MAGNITUDE = 1e90


def _is_real_scalar(x) -> bool:
    return (
        isinstance(x, numbers.Real)
        and not isinstance(x, bool)
        or (isinstance(x, np.ndarray) and x.ndim == 0 and x.dtype.kind in "iuf")
    )


def _pair(value, name):
    message = f"{name} must be a pair ({name}1, {name}2), got {type(value).__name__} {value!r:.80}"
    if isinstance(value, (str, bytes)):
        raise InputTypeError(message)
    try:
        if len(value) != 2:
            raise InputTypeError(message)
        return value[0], value[1]
    except InputTypeError:
        raise
    except Exception as exc:  # no len() (0-d arrays, iterators), dicts without keys 0 and 1
        raise InputTypeError(message) from exc


def _scalar(value, name, error) -> float:
    """Return a real scalar as a Python float; refuse Python ints beyond the float64 range."""
    try:
        return float(value)
    except OverflowError:
        raise error(f"{name} = {value!r:.40} is beyond the float64 range") from None


def _real_array(value, name, shape, what, error=DataError) -> np.ndarray:
    """Convert once to a new read-only C-contiguous float64 array of ``shape``.

    Dtype policy: any real numeric dtype and memory layout is accepted and copied (the
    caller's array is never aliased nor modified); bool, complex, object and string arrays
    and ragged sequences raise InputTypeError, a wrong shape or masked entries DataError,
    naming ``name``.
    """
    if isinstance(value, np.ma.MaskedArray) and np.ma.is_masked(value):
        raise DataError(
            f"{name} has {int(np.ma.count_masked(value))} masked entries; fill or remove them"
        )
    try:
        arr = np.asarray(value)
    except Exception as exc:  # ragged nested sequences and the like
        raise InputTypeError(f"{name} cannot be converted to an array of numbers: {exc}") from exc
    if arr.dtype.kind not in "iuf":
        raise InputTypeError(f"{name} must be real numbers, got dtype {arr.dtype}")
    if arr.shape != shape:
        raise error(f"{name} as an array must have {what}, shape {shape}, got {arr.shape}")
    with np.errstate(over="ignore"):  # longdouble beyond float64: inf, refused by the callers
        out = np.array(arr, dtype=np.float64, order="C", copy=True)
    out.flags.writeable = False
    return out


def _check_mu(value, name, n_triangles):
    lo, hi = MU_RANGE
    if _is_real_scalar(value):
        v = _scalar(value, name, ParameterError)
        if not np.isfinite(v) or v <= 0:
            raise ParameterError(f"{name} must be positive and finite, got {float(v)!r}")
        if not lo <= v <= hi:
            raise ParameterError(f"{name} = {v:g} is outside the supported range [{lo:g}, {hi:g}]")
        return v
    if isinstance(value, (np.ndarray, list, tuple)):
        arr = _real_array(value, name, (n_triangles,), "one value per triangle")
        bad = ~(np.isfinite(arr) & (arr > 0))
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ParameterError(
                f"{name} must be positive and finite on every triangle; "
                f"{int(bad.sum())} values are not (first: triangle {k}, value {float(arr[k])!r})"
            )
        out = (arr < lo) | (arr > hi)
        if out.any():
            k = int(np.flatnonzero(out)[0])
            raise ParameterError(
                f"{name} is outside the supported range [{lo:g}, {hi:g}] on {int(out.sum())} "
                f"triangles (first: triangle {k}, value {arr[k]:g})"
            )
        if (arr == arr[0]).all():
            return float(arr[0])
        return arr
    raise InputTypeError(
        f"{name} must be a positive number or an array of per-triangle values, "
        f"got {type(value).__name__}"
    )


def _check_load(value, name, n_vertices):
    if callable(value):
        return value
    if _is_real_scalar(value):
        v = _scalar(value, name, DataError)
        if not np.isfinite(v):
            raise DataError(f"{name} must be finite, got {float(v)!r}")
        return v
    if isinstance(value, (np.ndarray, list, tuple)):
        arr = _real_array(value, name, (n_vertices,), "one value per vertex")
        if not np.isfinite(arr).all():
            raise DataError(
                f"{name} contains NaN or inf at {int((~np.isfinite(arr)).sum())} vertices"
            )
        return arr
    raise InputTypeError(
        f"{name} must be a number, an array of per-vertex values or a callable f(x, y), "
        f"got {type(value).__name__}"
    )


def _max_abs(value) -> float | None:
    """Largest magnitude of constant or nodal data; None for a callable (not known yet)."""
    if callable(value):
        return None
    if isinstance(value, np.ndarray):
        return float(np.abs(value).max(initial=0.0))
    return abs(float(value))


def _describe(value):
    if callable(value):
        return {"kind": "callable", "name": getattr(value, "__qualname__", repr(value))}
    if isinstance(value, np.ndarray):
        return {"kind": "array", "size": int(value.size)}
    return {"kind": "constant", "value": value}


def _scaled(a, mu: float):
    """``mu A`` sharing ``A``'s pattern arrays (``A`` itself for ``mu = 1``).

    The values are those of ``A * mu`` bit for bit; only the 32 B/vertex copy of
    ``indices``/``indptr`` (and for ``mu = 1`` the 56 B/vertex of ``data``) is saved.
    """
    if mu == 1.0:
        return a
    out = sp.csr_matrix((a.data * mu, a.indices, a.indptr), shape=a.shape, copy=False)
    out.has_sorted_indices = a.has_sorted_indices
    return out


def boundary_data(mesh, g):
    """Validate a boundary value ``g``; return ``(stored, values at the boundary vertices)``.

    ``g`` is a number, an array of per-vertex values (only boundary vertices are
    read) or a callable evaluated once at the boundary vertices; finite values
    required, the datum named ``g`` in every error.
    """
    bnd = mesh.boundary_vertices
    if callable(g):
        return g, evaluate_callable(g, mesh.vertices[bnd, 0], mesh.vertices[bnd, 1], "g")
    if _is_real_scalar(g):
        stored = _scalar(g, "g", DataError)
        if not np.isfinite(stored):
            raise DataError(f"g must be finite, got {float(stored)!r}")
        return stored, np.full(bnd.size, stored)
    if isinstance(g, (np.ndarray, list, tuple)):
        stored = _real_array(g, "g", (mesh.n_vertices,), "one value per vertex")
        vals = stored[bnd]
        if not np.isfinite(vals).all():
            raise DataError("g contains NaN or inf at boundary vertices")
        return stored, vals
    raise InputTypeError(
        f"g must be a number, an array or a callable g(x, y), got {type(g).__name__}"
    )


def check_flag(value, name: str) -> bool:
    """``value`` as a bool; ParameterError naming ``name`` unless it is True or False."""
    if not isinstance(value, (bool, np.bool_)):
        raise ParameterError(
            f"{name} must be True or False, got {type(value).__name__} {value!r:.40}"
        )
    return bool(value)


def boundary_vector(mesh, vals) -> np.ndarray:
    """Nodal vector with ``vals`` at the boundary vertices and 0 inside, read-only."""
    out = np.zeros(mesh.n_vertices)
    out[mesh.boundary_vertices] = vals
    out.flags.writeable = False
    return out


class Scene:
    """A two-membrane contact problem on a mesh (docs/method.md §1).

    Parameters
    ----------
    mesh : Mesh
    mu : pair of (float or ndarray of shape (M,))
        Tensions mu1, mu2 > 0: constants, or one value per triangle (then the
        general solver path is used).
    f : pair of (float, ndarray of shape (N,), or callable)
        Loads f1, f2: constants, nodal values of P1 functions, or callables
        ``f(x, y)`` evaluated on arrays.
    g : float, ndarray of shape (N,), or callable
        Boundary value of membrane 1, ``g >= 0``: a constant, nodal values (only
        boundary vertices are read) or a callable evaluated at boundary
        vertices.  The a posteriori bound is exact when g is constant or
        piecewise linear on boundary edges.
    active_c : float
        Constant c > 0 of the active-set rule ``lambda_a > c * gap_a``
        (:meth:`active_rule`, docs/method.md §3.1); it decides only the first active set
        of a triple given as ``initial``.
    load_degree : int
        Quadrature degree for callable loads (default 5).
    parallel_callables : bool
        The callable data may be called from several threads at once (default
        False: they are called from the calling thread only).  Set it for callables
        that are vectorised NumPy code without shared mutable state: the blocks of
        quadrature points of the loads are then evaluated in all of fastmem's
        threads (:func:`fastmem.set_threads`), with the same results bit for bit.
        The coarser scenes of nested iteration and the refined scenes of the
        adaptive loop inherit it.

    Raises
    ------
    InputTypeError
        A datum of the wrong type or dtype (string, None, complex, bool,
        object array, ragged list), naming the field.
    ParameterError
        A tension that is not positive and finite or is outside
        ``MU_RANGE = [1e-100, 1e100]``; ``g < 0`` on the boundary; bad
        ``active_c`` or ``load_degree``.
    DataError
        Arrays of the wrong length, NaN or inf in the data, a callable that
        raises or returns values of the wrong shape or type, or data so large
        that the solution would leave the float64 range (:meth:`check_scale`).

    Notes
    -----
    Dtype policy: arrays (per-triangle ``mu``, per-vertex ``f`` and ``g``) may
    have any real numeric dtype (float16/32/64, longdouble, any integer
    width) and any memory layout (Fortran order, strided views, read-only);
    each is converted **once** to a new read-only C-contiguous float64 array,
    so the scene never aliases nor modifies the caller's arrays and gives the
    same result as the float64 array of the same values.  Scalars may be any
    real number (Python or numpy, int, float, Fraction).  Bool, complex,
    object and string values or arrays are refused with InputTypeError;
    masked arrays with masked entries with DataError.
    Callables are evaluated on float64 arrays; their results are converted
    to float64 (integers and bools included) and must be finite.

    A Scene is immutable: assigning a public attribute raises
    :class:`~fastmem.errors.ReadOnlyError` (it would bypass the validation and
    leave cached matrices stale).

    Validation is O(N + M) and vectorised.  Callable ``g`` is evaluated once,
    here; callable loads when the load vectors are first needed
    (:attr:`loads`), where the same checks apply.

    Examples
    --------
    >>> import fastmem as fm
    >>> scene = fm.Scene(fm.Mesh.square(8), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    >>> scene.constant_mu
    True
    """

    @checked_keywords("fastmem.Scene")
    def __init__(
        self,
        mesh: Mesh,
        mu=(1.0, 1.0),
        f=(0.0, 0.0),
        g=0.0,
        *,
        active_c: float = 1.0,
        load_degree: int = DEFAULT_LOAD_DEGREE,
        parallel_callables: bool = False,
    ):
        if not isinstance(mesh, Mesh):
            raise InputTypeError(f"mesh must be a fastmem.Mesh, got {type(mesh).__name__}")
        self.mesh = mesh
        self._cache: dict = {}
        mu1, mu2 = _pair(mu, "mu")
        self.mu1 = _check_mu(mu1, "mu1", mesh.n_triangles)
        self.mu2 = _check_mu(mu2, "mu2", mesh.n_triangles)
        f1, f2 = _pair(f, "f")
        self.f1 = _check_load(f1, "f1", mesh.n_vertices)
        self.f2 = _check_load(f2, "f2", mesh.n_vertices)
        self.g = self._check_g(g)
        if not _is_real_scalar(active_c) or not (np.isfinite(active_c) and active_c > 0):
            raise ParameterError(f"active_c must be positive and finite, got {active_c!r}")
        self.active_c = float(active_c)
        if isinstance(load_degree, bool) or not isinstance(load_degree, (int, np.integer)):
            raise ParameterError(f"load_degree must be an integer, got {load_degree!r}")
        if not 1 <= load_degree <= 30:
            raise ParameterError(f"load_degree must be in [1, 30], got {load_degree}")
        self.load_degree = int(load_degree)
        self.parallel_callables = check_flag(parallel_callables, "parallel_callables")
        self.check_scale()
        self._frozen = True

    def __setattr__(self, name, value):
        if not name.startswith("_") and getattr(self, "_frozen", False):
            raise ReadOnlyError(
                f"Scene.{name} cannot be assigned: a Scene is immutable (it was validated "
                "and caches its matrices and load vectors); build a new Scene"
            )
        object.__setattr__(self, name, value)

    def _check_g(self, g):
        mesh = self.mesh
        stored, vals = boundary_data(mesh, g)
        if (vals < 0).any():
            k = int(np.argmin(vals))
            raise ParameterError(
                f"g must be >= 0 on the boundary (membrane 1 above membrane 2 there), "
                f"got {float(vals[k])!r} at vertex {int(mesh.boundary_vertices[k])}"
            )
        self._cache["gB"] = boundary_vector(mesh, vals)
        return stored

    def check_scale(self, fmax1: float | None = None, fmax2: float | None = None) -> None:
        """Refuse data whose solution would leave the float64 range fastmem computes in.

        With ``D`` the diameter of the bounding box and ``h`` the smallest triangle
        height, the solution scale ``U = max|g| + D^2 max_i(max|f_i| / min mu_i)`` and
        the pressure scale ``P = max_i max|f_i| + max_i(max mu_i) U / h^2`` must not
        exceed ``MAX_MAGNITUDE = 1e90``: then every product the solver and the
        estimators form (energies, squared residuals) stays finite.  Callable loads
        enter once their load vectors are assembled (``fmax1``, ``fmax2``).

        Raises
        ------
        DataError
            Naming the datum that dominates the offending scale.
        """
        mesh = self.mesh
        fmax = [
            _max_abs(self.f1) if fmax1 is None else fmax1,
            _max_abs(self.f2) if fmax2 is None else fmax2,
        ]
        fmax = [0.0 if f is None else f for f in fmax]
        gmax = float(self.boundary_values.max(initial=0.0))
        mu_min = (float(np.min(self.mu1)), float(np.min(self.mu2)))
        mu_max = (float(np.max(self.mu1)), float(np.max(self.mu2)))
        x0, x1, y0, y1 = mesh.bounding_box
        d2 = (x1 - x0) ** 2 + (y1 - y0) ** 2
        h = mesh.min_height
        terms = {"g": gmax, "f1": d2 * fmax[0] / mu_min[0], "f2": d2 * fmax[1] / mu_min[1]}
        u_scale = sum(terms.values())
        if not u_scale <= MAX_MAGNITUDE:
            worst = max(terms, key=terms.get)
            raise DataError(
                f"data out of the supported range: the solution scale max|g| + "
                f"diam^2 max|f_i|/min mu_i = {u_scale:.3g} (dominated by {worst}) exceeds "
                f"{MAX_MAGNITUDE:g}; rescale the problem (fastmem computes in float64)"
            )
        terms = {
            "f1": fmax[0],
            "f2": fmax[1],
            "mu1": mu_max[0] * u_scale / (h * h),
            "mu2": mu_max[1] * u_scale / (h * h),
        }
        p_scale = max(fmax) + max(terms["mu1"], terms["mu2"])
        if not p_scale <= MAX_MAGNITUDE:
            worst = max(terms, key=terms.get)
            raise DataError(
                f"data out of the supported range: the contact pressure scale max|f_i| + "
                f"max mu_i U / h^2 = {p_scale:.3g} (dominated by {worst}; solution scale "
                f"U = {u_scale:.3g}, smallest triangle height h = {h:.3g}) exceeds "
                f"{MAX_MAGNITUDE:g}; rescale the problem (fastmem computes in float64)"
            )

    # ----------------------------------------------------------------- derived
    @property
    def constant_mu(self) -> bool:
        """True when both tensions are constants (the decoupled path applies)."""
        return isinstance(self.mu1, float) and isinstance(self.mu2, float)

    @property
    def mu_max(self) -> tuple[float, float]:
        """Largest value of mu1 and of mu2 (for scaling)."""
        return float(np.max(self.mu1)), float(np.max(self.mu2))

    @property
    def stiffness(self):
        """Plain P1 stiffness matrix A (coefficient 1), CSR, assembled once."""
        if "A" not in self._cache:
            self._cache["A"] = assemble_stiffness(self.mesh)
        return self._cache["A"]

    def weighted_stiffness(self, i: int):
        """``mu_i A`` for membrane i in {1, 2} (per-triangle mu supported), CSR, cached.

        For a constant ``mu_i`` the matrix shares the pattern of :attr:`stiffness`
        (and is :attr:`stiffness` itself for ``mu_i = 1``): treat it as read-only.
        """
        key = f"A{i}"
        if key not in self._cache:
            mu = self.mu1 if i == 1 else self.mu2
            if isinstance(mu, float):
                self._cache[key] = _scaled(self.stiffness, mu)
            else:
                self._cache[key] = assemble_stiffness(self.mesh, mu)
        return self._cache[key]

    @property
    def active_weight(self) -> np.ndarray:
        """``kappa_a B_a`` at the interior vertices: the weight of lambda in the gap equation.

        ``kappa_a = A_aa / (mu1 A)_aa + A_aa / (mu2 A)_aa`` and ``B_a`` the lumped
        mass.  For constant tensions ``kappa = 1/mu1 + 1/mu2`` and ``kappa_a B_a lam_a``
        is the nodal term of lam in the gap equation ``A w = F_w + kappa B lam``
        (docs/method.md §3.3), a length like the gap; for per-triangle tensions the diagonal
        ratios are vertex averages of ``1/mu_i`` (a scale, not an equation).  Used
        for the first active set of a prolonged triple
        (:func:`fastmem.solver.nested.warm_active_set`).
        """
        if "kB" not in self._cache:
            ii = self.mesh.interior_vertices
            if ii.size >= THREADED_ROWS:  # one pass of the kernel threads, the same bits
                mats = (self.stiffness, self.weighted_stiffness(1), self.weighted_stiffness(2))
                diagonals = {}
                for m in mats:
                    if id(m) not in diagonals:
                        diagonals[id(m)] = read_only(csr_diagonal(m))
                d, d1, d2 = (diagonals[id(m)] for m in mats)
                kb = np.empty(ii.size)
                lumped = read_only(np.ascontiguousarray(self.mesh.lumped_mass, dtype=np.float64))
                _par.parallel_for(
                    active_weight_range, ii.size, read_only(ii), d, d1, d2, lumped, kb
                )
                self._cache["kB"] = kb
                return kb
            a = self.stiffness.diagonal()[ii]
            kappa = a / self.weighted_stiffness(1).diagonal()[ii]
            kappa += a / self.weighted_stiffness(2).diagonal()[ii]
            self._cache["kB"] = kappa * self.mesh.lumped_mass[ii]
        return self._cache["kB"]

    def active_rule(self, u1, u2, lam) -> np.ndarray:
        """Active set ``{a interior : lam_a > c (u1_a - u2_a)}`` of a triple (docs/method.md §3.1).

        After a linear step ``gap = 0`` holds exactly on the active set and
        ``lam = 0`` on the inactive one, so the next set does not depend on c;
        c only matters for a triple given as ``initial`` (the first active set
        of a triple prolonged by nested iteration is chosen by
        :func:`fastmem.solver.nested.warm_active_set` instead).
        """
        ii = self.mesh.interior_vertices
        if ii.size >= THREADED_ROWS and plain_float64((u1, u2, lam), self.mesh.n_vertices):
            out = np.empty(ii.size, dtype=np.bool_)
            _par.parallel_for(
                active_rule_range, ii.size, read_only(ii), float(self.active_c),
                read_only(u1), read_only(u2), read_only(lam), out,
            )  # fmt: skip
            return out
        return lam[ii] > self.active_c * (u1[ii] - u2[ii])

    @property
    def loads(self) -> tuple[np.ndarray, np.ndarray]:
        """Load vectors ``(F1, F2)`` with ``F_i,a = (f_i, psi_a)``, assembled once.

        Callable loads are evaluated here (DataError if one raises or returns values of
        the wrong shape, type, or non-finite values) and then pass :meth:`check_scale`.
        """
        if "F" not in self._cache:
            loads = tuple(integrals(self, i, moments=False)["F"] for i in (1, 2))
            for vec, name in zip(loads, ("f1", "f2"), strict=True):
                if not np.isfinite(vec).all():
                    raise DataError(
                        f"the load vector of {name} overflows float64 "
                        f"({int((~np.isfinite(vec)).sum())} NaN or inf entries): {name} is "
                        "too large; rescale the problem"
                    )
            if callable(self.f1) or callable(self.f2):
                # nodal averages (f, psi_a) / |psi_a| bound the size of a callable load
                b = self.mesh.lumped_mass
                fmax = [
                    float(np.max(np.abs(vec) / b)) if callable(f) else None
                    for vec, f in zip(loads, (self.f1, self.f2), strict=True)
                ]
                self.check_scale(*fmax)
            self._cache["F"] = loads
        return self._cache["F"]

    @property
    def boundary_values(self) -> np.ndarray:
        """Nodal vector of g on boundary vertices (zero elsewhere), shape (N,), read-only.

        Computed once, on construction, from the validated values of g.
        """
        return self._cache["gB"]

    def data_kind(self, name: str) -> str:
        """Kind of a datum ``"f1"``, ``"f2"`` or ``"g"``: constant, array or callable."""
        return _describe(getattr(self, name))["kind"]

    def parameters(self) -> dict:
        """JSON-serialisable description of the scene."""

        def mu_desc(mu):
            return (
                mu
                if isinstance(mu, float)
                else {"kind": "per-triangle", "min": float(mu.min()), "max": float(mu.max())}
            )

        return {
            "n_vertices": self.mesh.n_vertices,
            "n_triangles": self.mesh.n_triangles,
            "mu1": mu_desc(self.mu1),
            "mu2": mu_desc(self.mu2),
            "f1": _describe(self.f1),
            "f2": _describe(self.f2),
            "g": _describe(self.g),
            "active_c": self.active_c,
            "load_degree": self.load_degree,
        }

    def __repr__(self) -> str:
        p = self.parameters()
        f1, f2, g = (p[k].get("value", p[k]["kind"]) for k in ("f1", "f2", "g"))
        return f"Scene({self.mesh!r}, mu=({p['mu1']}, {p['mu2']}), f=({f1}, {f2}), g={g})"
