"""The result of a solve: the final triple, its residuals, history and timings."""

from __future__ import annotations

import logging
import math
import numbers
from dataclasses import dataclass, field

import numpy as np

from ..errors import DataError, InputTypeError, NumericalError
from ..fem.scene import MAX_MAGNITUDE
from ..mesh.mesh import Mesh
from .writer import write_archive, write_export

__all__ = [
    "COMPONENTS",
    "Estimate",
    "ObstacleResult",
    "Result",
    "check_nodal",
    "check_result",
    "check_triple",
]

logger = logging.getLogger(__name__)


def check_nodal(mesh, value, name):
    """Validate one nodal vector; return a new C-contiguous float64 copy of shape (N,).

    Any real numeric dtype and memory layout is accepted (converted once).  Raises
    InputTypeError for non-real dtypes (bool, complex, object, strings) and objects
    that are not arrays, and DataError for a wrong shape, masked entries, NaN/inf or
    magnitudes beyond :data:`fastmem.fem.scene.MAX_MAGNITUDE` (1e90, where squares and
    energies would overflow float64), naming ``name``.
    """
    if isinstance(value, np.ma.MaskedArray) and np.ma.is_masked(value):
        raise DataError(f"{name} has masked entries")
    try:
        arr = np.asarray(value)
    except Exception as exc:  # ragged sequences and the like
        raise InputTypeError(f"{name} cannot be converted to an array of numbers: {exc}") from exc
    if arr.dtype.kind not in "iuf":
        raise InputTypeError(f"{name} must be real numbers, got dtype {arr.dtype}")
    n = mesh.n_vertices
    if arr.shape != (n,):
        raise DataError(f"{name} must have one value per vertex, shape ({n},), got {arr.shape}")
    with np.errstate(over="ignore"):  # longdouble beyond float64 becomes inf: refused below
        arr = np.array(arr, dtype=np.float64, order="C", copy=True)
    # the largest and smallest value: NaN and inf show in them (two passes over the
    # vector and no temporary, against four passes and two temporaries before)
    hi, lo = (float(arr.max()), float(arr.min())) if arr.size else (0.0, 0.0)
    if not (math.isfinite(hi) and math.isfinite(lo)):
        raise DataError(f"{name} contains NaN or inf at {int((~np.isfinite(arr)).sum())} vertices")
    big = max(hi, -lo, 0.0)
    if big > MAX_MAGNITUDE:
        raise DataError(
            f"{name} has values up to {big:.3g}, beyond the supported magnitude "
            f"{MAX_MAGNITUDE:g}; rescale the problem (fastmem computes in float64)"
        )
    return arr


def check_triple(mesh, triple, prefix=""):
    """Validate a nodal triple ``(u1, u2, lam)``; return three C-contiguous float64 copies.

    Raises InputTypeError for non-real dtypes and DataError for wrong shapes
    or non-finite values, naming the array (``prefix`` + name).
    """
    if not isinstance(triple, (tuple, list)) or len(triple) != 3:
        raise InputTypeError(f"{prefix}(u1, u2, lam) must be a triple of nodal arrays")
    return [
        check_nodal(mesh, a, prefix + name)
        for name, a in zip(("u1", "u2", "lam"), triple, strict=True)
    ]


_NODAL_FIELDS = ("u1", "u2", "lam", "r1", "r2")

#: The three components of the bound, ``eta <= eta_disc + eta_lin + eta_alg``.
COMPONENTS = ("eta_disc", "eta_lin", "eta_alg")


def check_result(result) -> None:
    """Check the invariants of a :class:`Result` (cheap, O(N + M), no copies).

    ``mesh`` is a Mesh; ``u1, u2, lam, r1, r2`` are real arrays of shape (N,) with
    finite values; ``active`` is a bool array of shape (N,); estimator maps have
    shape (M,).  Non-finite values raise :class:`~fastmem.errors.NumericalError`
    (the computation overflowed or broke down: never returned silently), wrong
    types InputTypeError and wrong shapes DataError, naming the field.
    """
    mesh = result.mesh
    if not isinstance(mesh, Mesh):
        raise InputTypeError(f"Result.mesh must be a fastmem.Mesh, got {type(mesh).__name__}")
    n = mesh.n_vertices
    for name in (*_NODAL_FIELDS, "active"):
        arr = getattr(result, name)
        if not isinstance(arr, np.ndarray):
            raise InputTypeError(f"Result.{name} must be a numpy array, got {type(arr).__name__}")
        kinds = "b" if name == "active" else "iuf"
        if arr.dtype.kind not in kinds:
            raise InputTypeError(f"Result.{name} has dtype {arr.dtype}, expected kind {kinds!r}")
        if arr.shape != (n,):
            raise DataError(f"Result.{name} must have shape ({n},), got {arr.shape}")
        if name != "active" and not np.isfinite(arr).all():
            raise NumericalError(
                f"Result.{name} contains NaN or inf at {int((~np.isfinite(arr)).sum())} "
                "vertices: the computation overflowed or broke down (data too large or "
                "badly scaled?)"
            )
    if result.estimate is not None:
        if not isinstance(result.estimate, Estimate):
            raise InputTypeError(
                f"Result.estimate must be an Estimate or None, got {type(result.estimate).__name__}"
            )
        m = mesh.n_triangles
        for key, value in result.estimate.maps.items():
            shape = np.shape(value)
            if shape != (m,):
                raise DataError(f"estimator map {key!r} must have shape ({m},), got {shape}")


@dataclass(repr=False)
class Estimate:
    """A posteriori error estimate of a triple (filled by the estimator module).

    Attributes
    ----------
    totals : dict of str to float
        Every global value: ``eta``, ``eta_disc``, ``eta_lin``, ``eta_alg`` and
        the diagnostics (see :attr:`components` and :attr:`diagnostics`).
    maps : dict of str to ndarray of shape (M,)
        Per-triangle indicator maps (e.g. ``eta_F1``, ``eta_C``), kept for adaptivity.
    marking : ndarray of shape (M,) or None
        Refinement indicators to mark with when they are not those of ``maps``:
        when the layer bound (:mod:`fastmem.estimators.layers`) is the smaller, ``eta`` and
        ``maps`` are its own and ``marking`` holds the standard bound's
        ``eta_K^2``, which refine the layers better (docs/heterogeneous.md
        §11).  Not stored in archives.

    Notes
    -----
    ``eta`` is the guaranteed bound; ``eta_disc``, ``eta_lin`` and ``eta_alg``
    are *not* a partition of it but three upper bounds of its parts, with
    ``eta <= eta_disc + eta_lin + eta_alg`` (docs/method.md §6).  So ``eta``
    may well be smaller than ``eta_disc`` alone.
    """

    totals: dict = field(default_factory=dict)
    maps: dict = field(default_factory=dict)
    marking: np.ndarray | None = None

    def __post_init__(self):

        eta = self.totals.get("eta")
        if eta is not None and not (isinstance(eta, numbers.Real) and math.isfinite(eta)):
            raise NumericalError(
                f"the error estimate eta = {eta!r} is not finite: the computation overflowed "
                "(data or triple too large or badly scaled?)"
            )

    @property
    def eta(self) -> float:
        """The guaranteed upper bound of the energy error."""
        return float(self.totals["eta"])

    @property
    def components(self) -> dict:
        """The three components of the bound: ``eta_disc``, ``eta_lin``, ``eta_alg``.

        Discretisation, linearisation and algebraic parts,
        ``eta <= eta_disc + eta_lin + eta_alg``.
        """
        return {k: float(self.totals[k]) for k in COMPONENTS if k in self.totals}

    @property
    def diagnostics(self) -> dict:
        """Everything in :attr:`totals` but ``eta`` and the three components.

        The constants of the bound (``C_F``, ``a``, ``c``, ``eta_nc``,
        ``eta_glob1``, ``eta_glob2``), the seed slides' unguaranteed variant
        (``eta_unguaranteed_slides``, for comparison only) and timings
        (``seconds_flux``, ``seconds_estimators``).
        """
        return {k: v for k, v in self.totals.items() if k != "eta" and k not in COMPONENTS}

    def __repr__(self) -> str:
        parts = ", ".join(f"{k}={v:.4e}" for k, v in self.components.items())
        eta = self.totals.get("eta")
        head = "eta=None" if eta is None else f"eta={eta:.4e}"
        return f"Estimate({head}{', ' if parts else ''}{parts}, maps={sorted(self.maps)})"


def _freeze(result) -> None:
    """Make the arrays of a Result read-only, like those of Mesh and Scene.

    Arrays the caller passed in are frozen in place (no copy): a Result owns its data.
    """
    arrays = [getattr(result, name) for name in (*_NODAL_FIELDS, "active")]
    if result.estimate is not None:
        arrays += list(result.estimate.maps.values())
    for table in (result.history, result.adaptivity or {}):
        arrays += list(table.values())
    for arr in arrays:
        if isinstance(arr, np.ndarray):
            arr.flags.writeable = False


@dataclass(repr=False)
class Result:
    """Solution of a two-membrane contact problem with its provenance.

    Attributes
    ----------
    mesh : fastmem.Mesh
        The mesh the problem was solved on.
    u1, u2, lam : ndarray of shape (N,)
        Nodal values of the two membranes and of the contact pressure
        (``u1 = g``, ``u2 = 0``, ``lam = 0`` on boundary vertices).
    r1, r2 : ndarray of shape (N,)
        Algebraic residual vectors of the returned triple (docs/method.md §2),
        zero at boundary vertices.
    active : ndarray of bool, shape (N,)
        The contact (active) set of the last Newton-min step.
    history : dict of str to ndarray
        One column per recorded quantity, one row per Newton step (or estimator
        evaluation).
    timings : dict of str to float
        Seconds per phase (``assembly``, ``solve``, ...).
    parameters : dict
        JSON-serialisable description of the scene and solver settings.
    converged : bool
        True when every stopping criterion of the method was met.
    n_newton : int
        Number of Newton-min steps taken.
    method, path : str
        Solver method (``"exact"``, ...) and linear-step path (``"general"`` or
        ``"decoupled"``).
    estimate : Estimate or None
        The a posteriori estimate, when one was asked for (always for
        ``method="inexact"``).
    iterates : list of tuple or None
        With ``solve(..., keep_iterates=True)``: the triple ``(u1, u2, lam)``
        of every history row (not archived; with a tolerance, the final mesh's).
    adaptivity : dict of str to ndarray, or None
        With ``solve(..., tol=...)`` or ``rtol=``: one row per mesh of the
        adaptive loop, columns :data:`fastmem.adapt.loop.ADAPTIVITY_COLUMNS`
        (vertices, triangles, eta and its components, energy norm, target,
        marked fraction, Newton steps, CG iterations, seconds); archived.

    Notes
    -----
    The arrays of a Result (nodal fields, estimator maps, history and
    adaptivity columns) are read-only, like those of Mesh and Scene: copy
    one (``result.u1.copy()``) to modify it.

    Raises
    ------
    NumericalError
        On construction, when a nodal array holds NaN or inf: a result with
        non-finite values is never returned (see :func:`check_result`, which
        also checks types and shapes).
    """

    mesh: object
    u1: np.ndarray
    u2: np.ndarray
    lam: np.ndarray
    r1: np.ndarray
    r2: np.ndarray
    active: np.ndarray
    history: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    parameters: dict = field(default_factory=dict)
    converged: bool = False
    n_newton: int = 0
    method: str = ""
    path: str = ""
    estimate: Estimate | None = None
    iterates: list | None = None
    adaptivity: dict | None = None

    def __post_init__(self):
        check_result(self)
        _freeze(self)

    def __repr__(self) -> str:
        eta = "None" if self.eta is None else f"{self.eta:.4e}"
        adapt = "" if self.adaptivity is None else f", meshes={len(self.adaptivity['level'])}"
        return (
            f"Result({self.mesh!r}, method={self.method!r}, path={self.path!r}, "
            f"converged={self.converged}, n_newton={self.n_newton}, eta={eta}, "
            f"contact_fraction={self.contact_fraction:.4f}{adapt})"
        )

    @property
    def gap(self) -> np.ndarray:
        """Nodal gap ``u1 - u2``."""
        return self.u1 - self.u2

    @property
    def contact_fraction(self) -> float:
        """Area fraction of the domain in contact: ``sum(B_a, a active) / |Omega|``."""
        b = self.mesh.lumped_mass
        return float(b[self.active].sum() / b.sum())

    @property
    def eta(self) -> float | None:
        """The guaranteed error bound, or None without an estimate."""
        return None if self.estimate is None else self.estimate.eta

    @property
    def eta_components(self) -> dict | None:
        """``{"eta_disc", "eta_lin", "eta_alg"}`` of the estimate, or None without one.

        ``eta <= eta_disc + eta_lin + eta_alg``; the components bound parts of
        the error, so ``eta`` can be below ``eta_disc``.  Constants and timings
        are in ``result.estimate.diagnostics``.
        """
        return None if self.estimate is None else self.estimate.components

    # The writers live in fastmem.io.writer, which does not import this module;
    # fastmem.io.archive imports it to build loaded Results (no import circle).
    def save(self, path) -> None:
        """Write the result to an HDF5 archive atomically (see :func:`fastmem.io.archive.save`)."""
        check_result(self)  # fields may have been reassigned since construction
        write_archive(self, path)

    def export(self, path) -> None:
        """Write mesh and nodal fields to a VTU/XDMF file through meshio."""
        check_result(self)
        write_export(self, path)


@dataclass(repr=False)
class ObstacleResult(Result):
    """Solution of an obstacle problem (:class:`fastmem.Obstacle`), a :class:`Result`.

    The two-membrane fields are reused so that archives, ``fastmem info``,
    export and sweeps handle both kinds: ``u1`` is the membrane ``u`` (also
    :attr:`u`), ``lam`` the signed nodal multiplier (positive: the lower
    obstacle pushes up; negative: the upper one pushes down), ``r1`` the
    algebraic residual, ``u2`` and ``r2`` zero, ``active`` the union of the two
    contact sets.  ``parameters["problem"]`` is ``"obstacle"``.

    Attributes
    ----------
    lower, upper : ndarray of shape (N,) or None
        Nodal values of the obstacles the problem was solved with.
    """

    lower: np.ndarray | None = None
    upper: np.ndarray | None = None

    def __post_init__(self):
        for name in ("lower", "upper"):
            val = getattr(self, name)
            if val is not None:
                setattr(self, name, check_nodal(self.mesh, val, f"Result.{name}"))
        super().__post_init__()
        for val in (self.lower, self.upper):
            if val is not None:
                val.flags.writeable = False

    def __repr__(self) -> str:
        eta = "None" if self.eta is None else f"{self.eta:.4e}"
        return (
            f"ObstacleResult({self.mesh!r}, method={self.method!r}, converged={self.converged}, "
            f"n_newton={self.n_newton}, eta={eta}, contact_area={self.contact_area:.6g})"
        )

    @property
    def u(self) -> np.ndarray:
        """Nodal values of the membrane."""
        return self.u1

    def _touching(self, which):
        obst = self.lower if which == "lower" else self.upper
        if obst is None:
            return np.zeros(self.mesh.n_vertices, dtype=bool)
        other = self.upper if which == "lower" else self.lower
        d = np.abs(self.u1 - obst)
        if other is None:
            return self.active.copy()
        return self.active & (d <= np.abs(self.u1 - other))

    @property
    def active_lower(self) -> np.ndarray:
        """Vertices where the membrane lies on the lower obstacle (bool (N,))."""
        return self._touching("lower")

    @property
    def active_upper(self) -> np.ndarray:
        """Vertices where the membrane touches the upper obstacle (bool (N,))."""
        return self._touching("upper")

    @property
    def contact_area(self) -> float:
        """Discrete contact area ``sum(B_a, a active)`` (both obstacles)."""
        return float(self.mesh.lumped_mass[self.active].sum())

    @property
    def gap(self) -> np.ndarray:
        """Distance to the nearer obstacle, ``min(u - lower, upper - u)`` (N,)."""
        d = np.full(self.mesh.n_vertices, np.inf)
        if self.lower is not None:
            d = np.minimum(d, self.u1 - self.lower)
        if self.upper is not None:
            d = np.minimum(d, self.upper - self.u1)
        return d
