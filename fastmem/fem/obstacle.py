r"""The obstacle family: one membrane above, below or between rigid obstacles.

:class:`Obstacle` states the problem of docs/obstacle.md §1: find ``u`` with
``u = g`` on the boundary and ``psi <= u <= chi`` minimising
``1/2 (mu grad u, grad u) - (f, u)``.  It is validated on construction (every
check names the datum and the place) and caches its matrices and load vector
like :class:`fastmem.fem.scene.Scene`, whose data conventions it follows:

- ``mu``: a constant or one value per triangle;
- ``f``: a constant, nodal values of a P1 function, or a callable ``f(x, y)``;
- ``g``: a constant, nodal values (boundary vertices are read) or a callable;
- ``lower`` / ``upper``: None (absent), a constant, nodal values, or a callable.

How the bound treats an obstacle depends on what is known about it
(docs/obstacle.md §5.3); :attr:`Obstacle.obstacle_kind` reports it:

``"p1"``
    constants and nodal values: the obstacle *is* the P1 function of its nodal
    values, every term of the bound is exact (§4.4, remark 1);
``"guaranteed"``
    a callable with an ``envelope(px, py)`` method (Hessian bounds and an
    affine majorant of the largest pressure on given triangles, §5.1-5.3): the
    obstacle-approximation terms are guaranteed bounds;
``"piecewise-constant"``
    a callable with a ``triangle_values(mesh)`` method (constant on every
    triangle, e.g. the step-41 stairs on a mesh aligned with the jumps) and
    ``nodal_values(mesh)`` giving a P1 majorant: case (i) of Theorem 4.1;
``"estimated"``
    any other callable: the terms are estimated from the obstacle's values on
    sub-triangles (not guaranteed; the estimate says so).
"""

from __future__ import annotations

import numpy as np

from ..errors import DataError, InputTypeError, ParameterError, ReadOnlyError, checked_keywords
from ..mesh.mesh import Mesh
from .assembly import DEFAULT_LOAD_DEGREE, assemble_stiffness
from .callables import evaluate_callable
from .loaddata import integrals
from .scene import (
    _check_load,
    _check_mu,
    _describe,
    _is_real_scalar,
    _max_abs,
    _real_array,
    _scalar,
    _scaled,
    boundary_data,
    boundary_vector,
    check_flag,
)

__all__ = ["Obstacle", "TWO_MEMBRANE_ONLY"]

#: Options of :func:`fastmem.solve` that only the two-membrane scene has.
TWO_MEMBRANE_ONLY = ("path",)

#: Absolute slack allowed in the ordering checks (lower <= g <= upper, lower <= upper),
#: relative to the data's magnitude: round-off of data computed by the caller.
ORDER_SLACK = 1e-12


def _where(mesh, k) -> str:
    x, y = mesh.vertices[k]
    return f"vertex {int(k)} at ({x:.6g}, {y:.6g})"


def _check_bound(value, name, mesh) -> tuple[object, np.ndarray | None]:
    """Validate an obstacle; return ``(stored, nodal values or None)``."""
    if value is None:
        return None, None
    n = mesh.n_vertices
    if callable(value):
        nodal = getattr(value, "nodal_values", None)
        if nodal is not None:
            try:
                vals = np.asarray(nodal(mesh), dtype=np.float64)
            except Exception as exc:
                raise DataError(
                    f"{name}.nodal_values(mesh) raised {type(exc).__name__}: {exc}"
                ) from exc
            if vals.shape != (n,):
                raise DataError(
                    f"{name}.nodal_values(mesh) must return one value per vertex, shape ({n},), "
                    f"got {vals.shape}"
                )
        else:
            vals = evaluate_callable(value, mesh.vertices[:, 0], mesh.vertices[:, 1], name)
        stored = value
    elif _is_real_scalar(value):
        stored = _scalar(value, name, DataError)
        vals = np.full(n, stored)
    elif isinstance(value, (np.ndarray, list, tuple)):
        stored = _real_array(value, name, (n,), "one value per vertex")
        vals = np.array(stored)
    else:
        raise InputTypeError(
            f"{name} must be None, a number, an array of per-vertex values or a callable "
            f"{name}(x, y), got {type(value).__name__}"
        )
    bad = ~np.isfinite(vals)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"{name} is NaN or infinite at {int(bad.sum())} vertices (first: {_where(mesh, k)}, "
            f"value {vals[k]!r}); leave {name}=None for no obstacle"
        )
    vals.flags.writeable = False
    return stored, vals


def _kind(value) -> str:
    if value is None:
        return "none"
    if not callable(value):
        return "p1"
    if hasattr(value, "envelope"):
        return "guaranteed"
    if hasattr(value, "triangle_values"):
        return "piecewise-constant"
    return "estimated"


class Obstacle:
    """One membrane above ``lower``, below ``upper``, or between them (docs/obstacle.md §1).

    Parameters
    ----------
    mesh : Mesh
    mu : float or ndarray of shape (M,)
        Tension, positive: a constant or one value per triangle.
    f : float, ndarray of shape (N,), or callable
        Load: a constant, nodal values of a P1 function, or ``f(x, y)``.
    g : float, ndarray of shape (N,), or callable
        Dirichlet value on the boundary (any sign).  The bound is exact for
        constant and nodal ``g``; a callable ``g`` adds the lifting term of
        docs/obstacle.md §4.5.
    lower, upper : None, float, ndarray of shape (N,), or callable
        The obstacles ``psi <= u <= chi``; at least one is required.  See the
        module docstring for what a callable may carry.
    active_c : float
        Constant of the active-set rule (docs/obstacle.md §2.1), relative to the
        natural scale ``mu_a / h_a^2`` of each vertex; it only decides the first
        active set of a given initial iterate.
    load_degree : int
        Quadrature degree for callable loads (default 5).
    sub_levels : int
        Red refinements of the obstacle band's triangles for the obstacle
        terms of a non-P1 obstacle (docs/obstacle.md §5.2; default 2).
    parallel_callables : bool
        The callable data (the load ``f``, the obstacles and their ``envelope``)
        may be called from several threads at once (as for
        :class:`~fastmem.fem.scene.Scene`; default False): the load's quadrature
        and the obstacles' envelopes on the band triangles then run in all threads,
        with the same results bit for bit.

    Raises
    ------
    InputTypeError, ParameterError, DataError
        Naming the datum and, for the ordering checks, the first vertex where
        it fails: ``lower > upper``, an obstacle above (below) ``g`` on the
        boundary, NaN or infinite obstacle values, no obstacle at all.

    Examples
    --------
    >>> import fastmem as fm
    >>> problem = fm.Obstacle(fm.Mesh.square(8), mu=1.0, f=-10.0, lower=-0.2)
    >>> problem.sides
    'lower'
    """

    kind = "obstacle"

    @checked_keywords("fastmem.Obstacle")
    def __init__(
        self,
        mesh: Mesh,
        mu=1.0,
        f=0.0,
        g=0.0,
        *,
        lower=None,
        upper=None,
        active_c: float = 1.0,
        load_degree: int = DEFAULT_LOAD_DEGREE,
        sub_levels: int = 2,
        parallel_callables: bool = False,
    ):
        if not isinstance(mesh, Mesh):
            raise InputTypeError(f"mesh must be a fastmem.Mesh, got {type(mesh).__name__}")
        self.mesh = mesh
        self._cache: dict = {}
        self.mu = _check_mu(mu, "mu", mesh.n_triangles)
        self.f = _check_load(f, "f", mesh.n_vertices)
        self.g = self._check_g(g)
        if lower is None and upper is None:
            raise ParameterError(
                "an Obstacle needs lower=..., upper=... or both (for a membrane without "
                "obstacle use a plain linear solve)"
            )
        self.lower, lo = _check_bound(lower, "lower", mesh)
        self.upper, up = _check_bound(upper, "upper", mesh)
        self._cache["psi"] = lo
        self._cache["chi"] = up
        self._check_order(lo, up)
        if not _is_real_scalar(active_c) or not (np.isfinite(active_c) and active_c > 0):
            raise ParameterError(f"active_c must be positive and finite, got {active_c!r}")
        self.active_c = float(active_c)
        for name, value, lo_, hi_ in (
            ("load_degree", load_degree, 1, 30),
            ("sub_levels", sub_levels, 0, 5),
        ):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ParameterError(f"{name} must be an integer, got {value!r}")
            if not lo_ <= value <= hi_:
                raise ParameterError(f"{name} must be in [{lo_}, {hi_}], got {value}")
        self.load_degree = int(load_degree)
        self.sub_levels = int(sub_levels)
        self.parallel_callables = check_flag(parallel_callables, "parallel_callables")
        self._frozen = True

    # two-membrane names used by the shared load and flux layers (membrane 1 = this one)
    @property
    def mu1(self):
        """The tension (the name the shared load/flux layers read)."""
        return self.mu

    mu2 = mu1

    @property
    def f1(self):
        """The load (the name the shared load layer reads)."""
        return self.f

    f2 = 0.0

    def __setattr__(self, name, value):
        if not name.startswith("_") and getattr(self, "_frozen", False):
            raise ReadOnlyError(
                f"Obstacle.{name} cannot be assigned: an Obstacle is immutable; build a new one"
            )
        object.__setattr__(self, name, value)

    def _check_g(self, g):
        stored, vals = boundary_data(self.mesh, g)
        self._cache["gB"] = boundary_vector(self.mesh, vals)
        return stored

    def _check_order(self, lo, up):
        mesh = self.mesh
        bnd = mesh.boundary_vertices
        gb = self._cache["gB"][bnd]
        scale = max(1.0, float(np.abs(gb).max(initial=0.0)))
        for vals in (lo, up):
            if vals is not None:
                scale = max(scale, float(np.abs(vals).max(initial=0.0)))
        slack = ORDER_SLACK * scale
        if lo is not None and up is not None:
            bad = lo > up + slack
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                raise DataError(
                    f"lower > upper at {int(bad.sum())} vertices (first: {_where(mesh, k)}: "
                    f"lower = {lo[k]:.6g} > upper = {up[k]:.6g}); the admissible set is empty"
                )
        if lo is not None:
            bad = lo[bnd] > gb + slack
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                raise DataError(
                    f"the lower obstacle is above the boundary value g at {int(bad.sum())} "
                    f"boundary vertices (first: {_where(mesh, bnd[k])}: lower = "
                    f"{lo[bnd[k]]:.6g} > g = {gb[k]:.6g}); no admissible membrane exists: "
                    "lower the obstacle or raise g there"
                )
        if up is not None:
            bad = up[bnd] < gb - slack
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                raise DataError(
                    f"the upper obstacle is below the boundary value g at {int(bad.sum())} "
                    f"boundary vertices (first: {_where(mesh, bnd[k])}: upper = "
                    f"{up[bnd[k]]:.6g} < g = {gb[k]:.6g}); no admissible membrane exists: "
                    "raise the obstacle or lower g there"
                )

    # ----------------------------------------------------------------- derived
    @property
    def sides(self) -> str:
        """``"lower"``, ``"upper"`` or ``"both"``."""
        if self.lower is not None and self.upper is not None:
            return "both"
        return "lower" if self.lower is not None else "upper"

    @property
    def psi(self) -> np.ndarray | None:
        """Nodal values of the lower obstacle (read-only), None without one."""
        return self._cache["psi"]

    @property
    def chi(self) -> np.ndarray | None:
        """Nodal values of the upper obstacle (read-only), None without one."""
        return self._cache["chi"]

    def obstacle_kind(self, side: str) -> str:
        """How the bound treats the ``"lower"`` or ``"upper"`` obstacle (module docstring)."""
        return _kind(self.lower if side == "lower" else self.upper)

    @property
    def constant_mu(self) -> bool:
        """True when the tension is one constant."""
        return isinstance(self.mu, float)

    @property
    def stiffness(self):
        """Plain P1 stiffness matrix A (coefficient 1), CSR, assembled once."""
        if "A" not in self._cache:
            self._cache["A"] = assemble_stiffness(self.mesh)
        return self._cache["A"]

    @property
    def weighted(self):
        """``mu A`` (per-triangle mu supported), CSR, cached; read-only."""
        if "Amu" not in self._cache:
            if isinstance(self.mu, float):
                self._cache["Amu"] = _scaled(self.stiffness, self.mu)
            else:
                self._cache["Amu"] = assemble_stiffness(self.mesh, self.mu)
        return self._cache["Amu"]

    def weighted_stiffness(self, i: int = 1):
        """``mu A`` under the two-membrane name (both "membranes" are this one)."""
        return self.weighted

    @property
    def load(self) -> np.ndarray:
        """Load vector ``F_a = (f, phi_a)``, assembled once."""
        if "F" not in self._cache:
            vec = integrals(self, 1, moments=False)["F"]
            if not np.isfinite(vec).all():
                raise DataError(
                    f"the load vector of f overflows float64 ({int((~np.isfinite(vec)).sum())} "
                    "NaN or inf entries): f is too large; rescale the problem"
                )
            self._cache["F"] = vec
        return self._cache["F"]

    @property
    def boundary_values(self) -> np.ndarray:
        """Nodal vector of g on boundary vertices (zero elsewhere), shape (N,), read-only."""
        return self._cache["gB"]

    def data_kind(self, name: str) -> str:
        """Kind of a datum: constant, array or callable (``f1`` is ``f``)."""
        name = {"f1": "f", "f2": "f2", "mu1": "mu", "mu2": "mu"}.get(name, name)
        if name == "f2":
            return "constant"
        return _describe(getattr(self, name))["kind"]

    @property
    def active_scale(self) -> np.ndarray:
        """``c mu_a / h_a^2`` at every vertex: the weight of a gap against a pressure.

        ``mu_a / h_a^2`` is ``A_aa / B_a`` up to a factor of order one (the
        diagonal of ``mu A`` over the lumped mass), the pressure that a unit gap
        over one mesh width produces.
        """
        if "cscale" not in self._cache:
            d = self.weighted.diagonal()
            self._cache["cscale"] = self.active_c * d / self.mesh.lumped_mass
        return self._cache["cscale"]

    def parameters(self) -> dict:
        """JSON-serialisable description of the problem."""
        mu = self.mu
        return {
            "problem": "obstacle",
            "n_vertices": self.mesh.n_vertices,
            "n_triangles": self.mesh.n_triangles,
            "mu": mu
            if isinstance(mu, float)
            else {"kind": "per-triangle", "min": float(mu.min()), "max": float(mu.max())},
            "f": _describe(self.f),
            "g": _describe(self.g),
            "lower": None if self.lower is None else _describe(self.lower),
            "upper": None if self.upper is None else _describe(self.upper),
            "lower_kind": self.obstacle_kind("lower"),
            "upper_kind": self.obstacle_kind("upper"),
            "active_c": self.active_c,
            "load_degree": self.load_degree,
            "sub_levels": self.sub_levels,
        }

    def __repr__(self) -> str:
        p = self.parameters()

        def short(d):
            return "None" if d is None else d.get("value", d["kind"])

        mu = p["mu"] if isinstance(p["mu"], float) else "per-triangle"
        return (
            f"Obstacle({self.mesh!r}, mu={mu}"
            f", f={short(p['f'])}, g={short(p['g'])}, lower={short(p['lower'])}, "
            f"upper={short(p['upper'])})"
        )


def scale_of(problem) -> float:
    """Return a magnitude of the problem's data (for relative tolerances)."""
    vals = [_max_abs(problem.f) or 0.0, float(np.abs(problem.boundary_values).max(initial=0.0))]
    for v in (problem.psi, problem.chi):
        if v is not None:
            vals.append(float(np.abs(v).max(initial=0.0)))
    return max(vals)
