r"""The guaranteed bound of the obstacle family (docs/obstacle.md §2.3-§6).

For any iterate ``(u_h, lambda)`` of an :class:`~fastmem.fem.obstacle.Obstacle`
(exact, inexact, infeasible) :func:`estimate` returns

.. math::

    |||u - u_h||| \le \eta = \min(\eta_I, \eta_{II}),
    \qquad \eta_I \le \eta_{disc} + \eta_{lin} + \eta_{alg},

with the terms of docs/obstacle.md §4.1: the RT1 flux of the one membrane
(the two-membrane patch kernel with the second column switched off), the
oscillation of a callable load, the distance of the clamp to ``u_h``, the
complementarity and obstacle-approximation terms (exact for P1 obstacles,
guaranteed piecewise bounds on red sub-triangles of the obstacle band for
obstacles with an ``envelope``, §5.2), the Dirichlet lifting of a callable
``g`` (§4.5) and the global residual term.

The work is split as the solver needs it: :func:`cheap_terms` (O(N) vector
work and one pass of the cut kernel: ``eta_alg``, ``eta_lin``) and the rest
(flux reconstruction, obstacle pieces), which :func:`estimate` adds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numba
import numpy as np

from ..errors import DataError, NumericalError
from ..fem.callables import evaluate_callable, run_blocks
from ..fem.loaddata import integrals
from ..fem.quadrature import triangle_rule
from ..kernels import cut as _cut
from ..kernels import flux as _kf
from ..kernels import obstacle as _kob
from ..kernels import pool as _par
from ..linalg.sparse import threaded
from .flux import _coloring, _mu_array, band_plan, banded_norms, patch_classes
from .terms import friedrichs_constant, mass_matrix

__all__ = ["ObstacleEstimate", "cheap_terms", "estimate", "residual", "split_multiplier"]


@dataclass
class ObstacleEstimate:
    """The bound of one iterate and its parts (docs/obstacle.md §4, §6).

    Attributes
    ----------
    eta : float
        The guaranteed bound ``min(eta_I, eta_II)`` of the energy error.
    eta_I, eta_II : float
        The two forms of Theorem 4.1.
    components : dict
        ``eta_disc``, ``eta_lin``, ``eta_alg`` (Proposition 6.1:
        ``eta <= eta_disc + eta_lin + eta_alg``).
    indicators : ndarray (M,)
        Refinement indicators ``eta_K`` (§6).
    terms : dict
        The scalar ingredients (``a``, ``a0``, ``D``, ``c``, ``c_disc``,
        ``c_lin``, ``eta_glob``, ``D_nc``, ``D_boundary``, ...).
    guaranteed : bool
        False when an obstacle term is estimated (a callable obstacle without
        ``envelope``) or the premise of case (i) failed (``reason`` says which).
    case : str
        ``"i"`` (the clamp lies in the admissible set) or ``"ii"``
        (Lewy-Stampacchia, for obstacles with an envelope).
    """

    eta: float
    eta_I: float
    eta_II: float
    components: dict
    indicators: np.ndarray = field(repr=False)
    terms: dict
    guaranteed: bool = True
    case: str = "i"
    reason: str = ""

    @property
    def eta_disc(self) -> float:
        """Discretisation component."""
        return self.components["eta_disc"]

    @property
    def eta_lin(self) -> float:
        """Linearisation component."""
        return self.components["eta_lin"]

    @property
    def eta_alg(self) -> float:
        """Algebraic component."""
        return self.components["eta_alg"]


# ----------------------------------------------------------------------- the iterate
def residual(problem, u, lam) -> np.ndarray:
    """``R_a = F_a - (mu A u)_a + B_a lam_a`` at interior vertices, 0 on the boundary."""
    mesh = problem.mesh
    r = problem.load - threaded(problem.weighted) @ u + mesh.lumped_mass * lam
    r[mesh.boundary_vertex_mask] = 0.0
    return r


def split_multiplier(problem, u, lam):
    """Rule (2.1): ``lam = ell_plus - ell_minus - eps``, nodal, 0 on the boundary.

    A positive value is the lower obstacle's pressure where the iterate is at
    least as close to the lower obstacle as to the upper one; a negative value
    the upper obstacle's where it is at least as close to the upper one; the
    rest is left over (``eps``), 0 at the discrete solution (§2.3, P3).
    """
    bnd = problem.mesh.boundary_vertex_mask
    lam = np.where(bnd, 0.0, lam)
    psi, chi = problem.psi, problem.chi
    d_lo = np.inf if psi is None else u - psi
    d_up = np.inf if chi is None else chi - u
    lower_ok = (lam > 0) & (d_lo <= d_up) if psi is not None else np.zeros(lam.shape, bool)
    upper_ok = (lam < 0) & (d_up <= d_lo) if chi is not None else np.zeros(lam.shape, bool)
    lp = np.where(lower_ok, lam, 0.0)
    lm = np.where(upper_ok, -lam, 0.0)
    eps = lp - lm - lam
    return lp, lm, eps


def _mass_norm(problem, v) -> float:
    m = threaded(mass_matrix(problem))  # the product in the kernel threads, scipy's bits
    return math.sqrt(max(float(v @ (m @ v)), 0.0))


def _mu_min(problem) -> float:
    return float(np.min(problem.mu))


def _global_factor(problem) -> float:
    """``C_F mu_min^(-1/2)``, cached."""
    if "glob_factor" not in problem._cache:
        problem._cache["glob_factor"] = friedrichs_constant(problem.mesh) / math.sqrt(
            _mu_min(problem)
        )
    return problem._cache["glob_factor"]


# ----------------------------------------------------------------- cheap terms
def cheap_terms(problem, u, lam, r=None) -> dict:
    """``eta_alg``, the P1-level contact terms and the pieces of ``eta_lin`` (O(N) work).

    Returns a dict with ``rho``, ``eps``, ``ell_plus``, ``ell_minus``,
    per-triangle ``nc`` (clamp distance, §4.1) and ``c_p1`` (the P1 part of the
    complementarity), the scalars ``eta_alg``, ``eta_eps``, ``D_nc``.
    """
    mesh = problem.mesh
    u = np.ascontiguousarray(u, dtype=np.float64)
    if r is None:
        r = residual(problem, u, lam)
    bnd = mesh.boundary_vertex_mask
    rho = np.where(bnd, 0.0, r / mesh.lumped_mass)
    lp, lm, eps = split_multiplier(problem, u, lam)
    factor = _global_factor(problem)
    mu = _mu_array(problem.mu)
    m = mesh.n_triangles
    nc2 = np.zeros(m)
    c_p1 = {}  # (ell+, (u - psi_h)+)_K, (ell-, (chi_h - u)+)_K: exact for P1 obstacles
    for side, vals, ell, sign in (
        ("lower", problem.psi, lp, 1.0),
        ("upper", problem.chi, lm, -1.0),
    ):
        if vals is None:
            continue
        gap = np.ascontiguousarray(sign * (u - vals))
        nc, c_p1[side] = _cut.contact_terms(mesh.vertices, mesh.triangles, gap, ell, mu)
        nc2 += nc * nc
    nc = np.sqrt(nc2)
    return {
        "rho": rho,
        "eps": eps,
        "ell_plus": lp,
        "ell_minus": lm,
        "nc": nc,
        "c_p1": c_p1,
        "eta_alg": factor * _mass_norm(problem, rho),
        "eta_eps": factor * _mass_norm(problem, eps),
        "eta_glob": factor * _mass_norm(problem, rho + eps),
        "D_nc": float(np.sqrt(np.sum(nc2))),
    }


# ----------------------------------------------------------------- flux
def flux_terms(problem, u, lam_signed, rho, shaped=None) -> np.ndarray:
    """``eta_F,K`` of the equilibrated RT1 flux of the iterate (§3), shape (M,).

    The two-membrane patch kernel (:func:`fastmem.kernels.flux.reconstruct_colored`)
    with membrane 1 = this membrane and membrane 2 given a compatible zero
    problem (residual ``-lam``): its patch solves share membrane 1's
    factorisation (same tension) and give the zero flux.  ``shaped``: the
    shaped contact loads of :func:`shaped_load` (their vertices carry no
    ``lam_a phi_a``; the kernel adds their moments instead).
    """
    mesh = problem.mesh
    u = np.ascontiguousarray(u, dtype=np.float64)
    bnd = np.ascontiguousarray(mesh.boundary_vertex_mask)
    lam_all = np.where(bnd, 0.0, lam_signed)
    lam_i = lam_all if shaped is None else np.where(shaped["flags"], 0.0, lam_all)
    chi_row = chi_mom = None
    if shaped is not None:
        chi_row, chi_mom = shaped["chi_row"], shaped["chi_mom"]
    mom = integrals(problem, 1, moments=True)["moments"]
    const = float(problem.f) if mom is None else 0.0
    mom = np.zeros((1, 3, 3)) if mom is None else mom
    mu = _mu_array(problem.mu)
    zero = np.zeros(mesh.n_vertices)
    inputs = (
        mesh.vertices, mesh.triangles, mesh.diameters, mesh.triangle_edges,
        mesh.edge_triangles, bnd, mesh.patch_ptr, mesh.patch_triangles, mesh.patch_local,
        u, zero, lam_i, np.ascontiguousarray(rho), -lam_all, mu, mu, const, 0.0, mom,
        np.zeros((1, 3, 3)), np.zeros(1, dtype=np.bool_), np.zeros(1),
        int(np.diff(mesh.patch_ptr).max()), numba.get_num_threads(),
    )  # fmt: skip
    extra = {"chi_row": chi_row, "chi_mom": chi_mom}
    extra["classes"] = patch_classes(mesh, problem.mu, problem.mu)
    # constant tension on a mesh numbered in rows: band by band, the flux not stored
    plan = band_plan(mesh) if np.ndim(problem.mu) == 0 else None
    if plan is not None:
        return banded_norms(mesh, plan, inputs, extra)[0]
    order, color_ptr = _coloring(mesh)
    coef = _kf.reconstruct_colored(order, color_ptr, *inputs, **extra)
    bary, w = triangle_rule(5)
    out = _kf.flux_estimators(
        mesh.vertices,
        mesh.triangles,
        mesh.diameters,
        coef,
        u,
        zero,
        mu,
        mu,
        np.ascontiguousarray(bary),
        np.ascontiguousarray(w),
    )
    return out[0]


# ----------------------------------------------------------------- load shaping
def shaped_load(problem, side_name: str, ell: np.ndarray):
    r"""Load shaping at the jumps of a piecewise-constant obstacle (docs/obstacle.md §5.5).

    At a vertex whose patch sees the obstacle below its nodal value on some
    triangles (a vertex on a step edge), the pressure ``ell_a`` is put on the
    triangles ``omega_a^=`` where the obstacle equals its nodal value:
    ``ell^a = s_a phi_a 1_{omega_a^=}`` with ``s_a = ell_a B_a / (phi_a, 1_{omega_a^=})``
    (the same mass, non-negative, P1 on each triangle: Lemma 3.1 holds).

    Returns None when no vertex qualifies, else a dict with ``flags`` (N,),
    ``chi_row`` (M,), ``chi_mom`` (S, 3, 3) (signed: the upper obstacle's load
    pushes down) and ``values`` (M, 3): the contact load's vertex values on
    every triangle, for the complementarity term.
    """
    mesh = problem.mesh
    tris = mesh.triangles
    side = _Side(problem, side_name)
    psi_k = side.sign * np.asarray(side.func.triangle_values(mesh), dtype=np.float64)
    equal = side.h[tris] <= psi_k[:, None]  # (M, 3): the obstacle reaches the nodal value on K
    lower = ~equal & (ell[tris] > 0)
    flags = np.zeros(mesh.n_vertices, dtype=bool)
    flags[tris[lower]] = True
    area3 = np.repeat(mesh.areas[:, None] / 3.0, 3, axis=1)
    mass_eq = np.zeros(mesh.n_vertices)
    np.add.at(mass_eq, tris, np.where(equal, area3, 0.0))
    flags &= mass_eq > 0
    values = np.where(flags[tris], 0.0, ell[tris])
    if not flags.any():
        return None
    scale = np.zeros(mesh.n_vertices)
    scale[flags] = ell[flags] * mesh.lumped_mass[flags] / mass_eq[flags]
    on = flags[tris] & equal  # (M, 3): shaped vertex i puts s_a phi_a on K
    values = values + np.where(on, scale[tris], 0.0)
    rows = np.flatnonzero(on.any(axis=1))
    chi_row = np.full(mesh.n_triangles, -1, dtype=np.int32)
    chi_row[rows] = np.arange(rows.size, dtype=np.int32)
    mass = (np.eye(3) + 1.0) / 12.0
    s_on = np.where(on[rows], scale[tris[rows]], 0.0)  # (S, 3): s_a of the shaped vertex i
    chi_mom = side.sign * s_on[:, :, None] * mass[None] * mesh.areas[rows][:, None, None]
    return {"flags": flags, "chi_row": chi_row, "chi_mom": chi_mom, "values": values}


def _merge_shaped(mesh, shaped: dict):
    """One kernel input from the shaped loads of both sides (None without any)."""
    if not shaped:
        return None
    if len(shaped) == 1:
        return next(iter(shaped.values()))
    full = np.zeros((mesh.n_triangles, 3, 3))
    flags = np.zeros(mesh.n_vertices, dtype=bool)
    for load in shaped.values():
        rows = np.flatnonzero(load["chi_row"] >= 0)
        full[rows] += load["chi_mom"][load["chi_row"][rows]]
        flags |= load["flags"]
    rows = np.flatnonzero(np.abs(full).sum(axis=(1, 2)) > 0)
    chi_row = np.full(mesh.n_triangles, -1, dtype=np.int32)
    chi_row[rows] = np.arange(rows.size, dtype=np.int32)
    return {"flags": flags, "chi_row": chi_row, "chi_mom": full[rows]}


# ----------------------------------------------------------------- Dirichlet lifting
_GAUSS_POINTS = 8


def boundary_lifting(problem) -> np.ndarray:
    r"""``eta_partial,K = mu_K^(1/2) ||grad L phi||_K`` of a callable ``g`` (§4.5), shape (M,).

    Zero for constant and nodal ``g``.  The 1D integral over each boundary
    edge uses an 8-point Gauss-Legendre rule; ``phi'`` along the edge comes
    from the degree-7 polynomial through the 8 values (an estimate of the
    term, exact to round-off for smooth ``g``).  Cached on the problem.
    """
    if "eta_partial" in problem._cache:
        return problem._cache["eta_partial"]
    mesh = problem.mesh
    out = np.zeros(mesh.n_triangles)
    if callable(problem.g):
        edges = _boundary_edges(mesh)
        tri, p, q, o = edges
        xv = mesh.vertices
        s, ws = np.polynomial.legendre.leggauss(_GAUSS_POINTS)
        s = 0.5 * (s + 1.0)
        ws = 0.5 * ws
        vander = np.vander(s, _GAUSS_POINTS, increasing=True)
        dvander = np.zeros_like(vander)
        dvander[:, 1:] = vander[:, :-1] * np.arange(1, _GAUSS_POINTS)
        dmat = dvander @ np.linalg.inv(vander)  # values at the nodes -> derivative there
        xp, xq, xo = xv[p], xv[q], xv[o]
        pts = xp[:, None, :] + s[None, :, None] * (xq - xp)[:, None, :]  # (E, 8, 2)
        gvals = evaluate_callable(problem.g, pts[..., 0].ravel(), pts[..., 1].ravel(), "g")
        gvals = gvals.reshape(pts.shape[:2])
        gb = problem.boundary_values
        phi = gvals - ((1.0 - s)[None, :] * gb[p][:, None] + s[None, :] * gb[q][:, None])
        dphi = phi @ dmat.T
        # G(s) = [y(s) - o, q - p]; solve G^T v = (phi, phi')
        a11 = pts[..., 0] - xo[:, None, 0]
        a21 = pts[..., 1] - xo[:, None, 1]
        a12 = np.broadcast_to((xq - xp)[:, None, 0], a11.shape)
        a22 = np.broadcast_to((xq - xp)[:, None, 1], a11.shape)
        det = a11 * a22 - a12 * a21
        # G^T = [[a11, a21], [a12, a22]]; v = G^-T (phi, dphi)
        v1 = (a22 * phi - a21 * dphi) / det
        v2 = (-a12 * phi + a11 * dphi) / det
        integral = (v1 * v1 + v2 * v2) @ ws
        mu = _mu_array(problem.mu)
        mu_t = mu[tri] if mu.shape[0] > 1 else mu[0]
        val = mu_t * mesh.areas[tri] * integral
        sq = np.zeros(mesh.n_triangles)
        np.add.at(sq, tri, val)  # a triangle with two boundary edges gets both liftings
        out = np.sqrt(sq)
        problem._cache["sup_phi"] = _sup_per_triangle(mesh, tri, np.abs(phi).max(axis=1))
    problem._cache["eta_partial"] = out
    return out


def _box_envelope(problem, side) -> tuple[float, float]:
    """``(M-, M+)`` of an obstacle on the mesh's bounding box (two triangles), cached.

    The obstacle's envelope must hold there: global bounds of its curvature.
    """
    key = f"box_envelope_{side.side}"
    if key not in problem._cache:
        x0, x1, y0, y1 = problem.mesh.bounding_box
        bx = np.array([[x0, x1, x1], [x0, x1, x0]], dtype=np.float64)
        by = np.array([[y0, y0, y1], [y0, y1, y1]], dtype=np.float64)
        mm, mp, _ = side.envelope(bx, by)
        problem._cache[key] = (float(np.max(mm)), float(np.max(mp)))
    return problem._cache[key]


def _boundary_curvature(problem, sign) -> float:
    """Return a bound of the obstacle curvature for the boundary margin (0 for P1 ones)."""
    side = "lower" if sign > 0 else "upper"
    if problem.obstacle_kind(side) != "guaranteed":
        return 0.0
    return max(_box_envelope(problem, _Side(problem, side)))


def _sup_per_triangle(mesh, tri, values):
    out = np.zeros(mesh.n_triangles)
    np.maximum.at(out, tri, values)
    return out


def _boundary_edges(mesh):
    """``(triangle, p, q, o)`` of every boundary edge: owner, end points, opposite vertex."""
    et = mesh.edge_triangles
    bnd = np.flatnonzero(et[:, 1] < 0)
    tri = et[bnd, 0]
    ends = mesh.edges[bnd]
    verts = mesh.triangles[tri]
    opposite = verts[(verts != ends[:, :1]) & (verts != ends[:, 1:])]
    return tri, ends[:, 0], ends[:, 1], opposite


# ----------------------------------------------------------------- obstacle pieces
def _red_pieces(s: int) -> np.ndarray:
    """Barycentric vertices of the ``4^s`` pieces of ``s`` red refinements, (P, 3, 3).

    Counter-clockwise like their parent (each child keeps the orientation).
    """
    pieces = np.eye(3)[None, :, :]
    for _ in range(s):
        a, b, c = pieces[:, 0], pieces[:, 1], pieces[:, 2]
        ab, bc, ca = 0.5 * (a + b), 0.5 * (b + c), 0.5 * (c + a)
        pieces = np.concatenate(
            [
                np.stack([a, ab, ca], axis=1),
                np.stack([ab, b, bc], axis=1),
                np.stack([ca, bc, c], axis=1),
                np.stack([bc, ca, ab], axis=1),
            ]
        )
    return pieces


#: Relative rounding-up of :func:`enclosing_radius` (the envelope must not fall short).
RADIUS_SLACK = 1e-13


def enclosing_radius(px, py) -> np.ndarray:
    r"""Radius of the smallest disc containing each triangle, rounded up by ``RADIUS_SLACK``.

    Half the longest edge for a right or obtuse triangle, the circumradius
    :math:`abc / (4|T|)` for an acute one; docs/obstacle.md Lemma 5.1 bounds
    :math:`q_T \le r_T^2` with it.  ``px``, ``py``: vertex coordinates, shape (P, 3).
    """
    px = np.asarray(px, dtype=np.float64)
    py = np.asarray(py, dtype=np.float64)
    n = px.shape[0]
    if n > ENVELOPE_ROWS:  # per triangle: in blocks whose temporaries stay in the caches
        out = np.empty(n)
        for start in range(0, n, ENVELOPE_ROWS):
            rows = slice(start, min(start + ENVELOPE_ROWS, n))
            out[rows] = enclosing_radius(px[rows], py[rows])
        return out
    ex = np.roll(px, -1, axis=1) - px
    ey = np.roll(py, -1, axis=1) - py
    l2 = np.sort(ex * ex + ey * ey, axis=1)  # squared edge lengths, ascending
    area2 = np.abs(ex[:, 0] * ey[:, 1] - ey[:, 0] * ex[:, 1])  # twice the area
    obtuse = l2[:, 2] >= l2[:, 0] + l2[:, 1]
    half_longest = 0.5 * np.sqrt(l2[:, 2])
    safe = np.where(obtuse | (area2 == 0.0), 1.0, area2)
    circum = np.sqrt(l2[:, 0] * l2[:, 1] * l2[:, 2]) / (2.0 * safe)
    return np.where(obtuse, half_longest, circum) * (1.0 + RADIUS_SLACK)


def _pos_product(px, py, z, v) -> np.ndarray:
    """``(v, z+)_T`` for affine ``v``, ``z`` given at the vertices of pieces (P, 3)."""
    n = px.shape[0]
    verts = np.stack([px.ravel(), py.ravel()], axis=1)
    tris = np.arange(3 * n, dtype=np.int64).reshape(n, 3)
    return _cut.positive_product(
        verts, tris, np.ascontiguousarray(z.ravel()), np.ascontiguousarray(v.ravel())
    )


def _pos_weighted(px, py, y, z) -> np.ndarray:
    """Bound ``(y+, z+)_T`` from above: exact where ``y >= 0`` on T, else ``(max y)+ (1, z+)_T``."""
    exact = y.min(axis=1) >= 0.0
    out = np.empty(px.shape[0])
    if exact.any():
        out[exact] = _pos_product(px[exact], py[exact], z[exact], y[exact])
    rest = ~exact
    if rest.any():
        ymax = np.maximum(y[rest].max(axis=1), 0.0)
        ones = np.ones_like(y[rest])
        out[rest] = ymax * _pos_product(px[rest], py[rest], z[rest], ones)
    return out


class _Side:
    """One obstacle seen as a lower obstacle (the upper one mirrored, §7)."""

    def __init__(self, problem, side: str):
        self.problem = problem
        self.side = side
        self.sign = 1.0 if side == "lower" else -1.0
        self.func = problem.lower if side == "lower" else problem.upper
        nodal = problem.psi if side == "lower" else problem.chi
        self.h = self.sign * nodal
        other = problem.chi if side == "lower" else problem.psi
        self.other_h = None if other is None else self.sign * other  # upper bound, mirrored
        self.kind = problem.obstacle_kind(side)

    def values(self, x, y):
        return self.sign * evaluate_callable(self.func, x, y, self.side)

    def envelope(self, px, py):
        """``(m_minus, m_plus, U)`` of the mirrored obstacle.

        Over more than :data:`ENVELOPE_ROWS` triangles the obstacle's ``envelope`` is
        called on consecutive slices of that many (its bounds are per triangle), so
        that the NumPy temporaries of a vectorised envelope stay in the caches; with
        the problem's ``parallel_callables`` the slices run in all threads.
        """
        n = px.shape[0]
        if n <= ENVELOPE_ROWS:
            return self._envelope(px, py)
        mm, mp, lam_up = np.empty(n), np.empty(n), np.empty((n, 3))

        def rows(start, stop):
            mm[start:stop], mp[start:stop], lam_up[start:stop] = self._envelope(
                px[start:stop], py[start:stop]
            )

        run_blocks(rows, n, ENVELOPE_ROWS, _callable_threads(self.problem))
        return mm, mp, lam_up

    def _envelope(self, px, py):
        mm, mp, lam_up = self.func.envelope(px, py)
        mm, mp = np.asarray(mm, dtype=np.float64), np.asarray(mp, dtype=np.float64)
        lam_up = np.asarray(lam_up, dtype=np.float64)
        if lam_up.shape == mm.shape:
            lam_up = np.repeat(lam_up[:, None], 3, axis=1)
        if self.sign < 0:
            mm, mp = mp, mm
        return mm, mp, lam_up


def _callable_threads(problem) -> int:
    """Threads for blocks of the problem's callables: all with ``parallel_callables``, else 1."""
    return _par.n_threads() if getattr(problem, "parallel_callables", False) else 1


#: Triangles (or pieces) per call of an obstacle's ``envelope`` and per block of
#: :func:`enclosing_radius`: small enough that the NumPy temporaries stay in the caches
#: (as for callable loads, :data:`fastmem.fem.callables.BLOCK`).
ENVELOPE_ROWS = 1 << 13


def _triangle_envelope(problem, side: _Side, need_exact):
    """``delta_K``, ``delta'_K`` (§5.2 band test): exact where asked, bounds elsewhere.

    ``need_exact(bound_delta, bound_delta_p)`` returns the triangles that need
    their own envelope given the global bounds ``1/2 M r_K^2`` with ``M`` the
    envelope of the mesh's bounding box (two triangles covering it: the
    obstacle's envelope must hold there).  Cached per side; triangles enter
    the exact set as the band moves.
    """
    key = f"tri_env_{side.side}"
    mesh = problem.mesh
    cache = problem._cache.get(key)
    if cache is None:
        mm, mp = _box_envelope(problem, side)
        # the smallest enclosing disc of a triangle has radius <= diameter / sqrt(3)
        # (Jung's theorem in the plane): a bound of r_K^2 without computing it
        r2 = mesh.diameters**2 / 3.0
        cache = {
            "delta": 0.5 * mm * r2,
            "delta_p": 0.5 * mp * r2,
            "exact": np.zeros(mesh.n_triangles, dtype=bool),
            "U": np.zeros((mesh.n_triangles, 3)),
        }
        problem._cache[key] = cache
    tri = np.asarray(need_exact(cache["delta"], cache["delta_p"]))
    tri = tri[~cache["exact"][tri]]
    if tri.size:
        c = mesh.vertices[mesh.triangles[tri]]
        px, py = np.ascontiguousarray(c[..., 0]), np.ascontiguousarray(c[..., 1])
        mm, mp, lam_up = side.envelope(px, py)
        r2 = enclosing_radius(px, py) ** 2
        cache["delta"][tri] = 0.5 * mm * r2
        cache["delta_p"][tri] = 0.5 * mp * r2
        cache["U"][tri] = lam_up
        cache["exact"][tri] = True
    return cache["delta"], cache["delta_p"]


def _piece_data(problem, side: _Side, tri: np.ndarray):
    """Geometry, obstacle values and envelopes of the pieces of triangles ``tri``.

    In blocks of triangles (:data:`ENVELOPE_ROWS` pieces each: the NumPy temporaries
    of the obstacle's values and envelope stay in the caches), in all threads with
    the problem's ``parallel_callables``; every piece is computed by the same
    operations either way.
    """
    mesh = problem.mesh
    ref = _red_pieces(problem.sub_levels)  # (P, 3, 3) barycentric
    npc = ref.shape[0]
    rows = tri.size * npc
    px, py, psi_t, lam_up = (np.empty((rows, 3)) for _ in range(4))
    delta, delta_p = np.empty(rows), np.empty(rows)
    guaranteed = side.kind == "guaranteed"

    def block(b0, b1):
        corners = mesh.vertices[mesh.triangles[tri[b0:b1]]]  # (b, 3, 2)
        pts = np.einsum("pvk,bkd->bpvd", ref, corners)  # (b, P, 3, 2)
        r = slice(b0 * npc, b1 * npc)
        px[r] = pts[..., 0].reshape(-1, 3)
        py[r] = pts[..., 1].reshape(-1, 3)
        qx, qy = px[r], py[r]
        psi_t[r] = side.values(qx.ravel(), qy.ravel()).reshape(-1, 3)
        r2 = enclosing_radius(qx, qy) ** 2
        if guaranteed:
            mm, mp, lam_up[r] = side.envelope(qx, qy)
            delta[r], delta_p[r] = 0.5 * mm * r2, 0.5 * mp * r2
        else:
            delta[r] = delta_p[r] = 0.0
            lam_up[r] = _estimated_pressure(problem, side, qx, qy)

    run_blocks(block, tri.size, max(1, ENVELOPE_ROWS // npc), _callable_threads(problem))
    return {
        "ref": ref,
        "npc": npc,
        "px": px,
        "py": py,
        "psi": psi_t,
        "delta": delta,
        "delta_p": delta_p,
        "U": lam_up,
    }


def _estimated_pressure(problem, side, px, py):
    """``(-mu Lap psi - f)+`` at the piece vertices by a 5-point difference (not guaranteed)."""
    h = enclosing_radius(px, py)[:, None]  # the difference step: the piece's size
    x, y = px, py
    c = side.values(x.ravel(), y.ravel()).reshape(x.shape)
    lap = -4.0 * c
    for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
        lap += side.values((x + dx * h).ravel(), (y + dy * h).ravel()).reshape(x.shape)
    lap /= h * h
    mu = float(np.max(problem.mu))
    f = problem.f
    if callable(f):
        fv = evaluate_callable(f, x.ravel(), y.ravel(), "f").reshape(x.shape)
    elif isinstance(f, np.ndarray):
        fv = np.full(x.shape, float(np.abs(f).max()))
    else:
        fv = np.full(x.shape, float(f))
    return np.maximum(-mu * lap - side.sign * fv, 0.0)


def _side_pieces(problem, side: _Side, tri: np.ndarray):
    """Piece data of the triangles ``tri``, cached across iterates (the band moves little).

    Returns the cache: ``slot`` (M,) (the block of each cached triangle, -1 for
    none) and the piece arrays in blocks of ``npc`` rows, appended as new
    triangles enter the band.
    """
    key = f"pieces_{side.side}"
    cache = problem._cache.get(key)
    if cache is None:
        cache = {"slot": np.full(problem.mesh.n_triangles, -1, dtype=np.int64), "data": None}
        problem._cache[key] = cache
    slot = cache["slot"]
    missing = tri[slot[tri] < 0]
    if missing.size:
        new = _piece_data(problem, side, missing)
        start = 0 if cache["data"] is None else cache["size"]
        slot[missing] = start + np.arange(missing.size)
        if cache["data"] is None:
            cache["data"] = new
        else:
            old = cache["data"]
            cache["data"] = {
                k: (np.concatenate([old[k], v]) if k not in ("ref", "npc") else v)
                for k, v in new.items()
            }
        cache["size"] = start + missing.size
    return cache


def _select_pieces(cache, tri):
    """Return the cached piece rows of ``tri`` (the NumPy reference path)."""
    data = cache["data"]
    npc = data["npc"]
    rows = (cache["slot"][tri][:, None] * npc + np.arange(npc)[None, :]).ravel()
    return {k: (v[rows] if k not in ("ref", "npc") else v) for k, v in data.items()}


def _tri_xy(mesh):
    c = mesh.vertices[mesh.triangles]
    return np.ascontiguousarray(c[..., 0]), np.ascontiguousarray(c[..., 1])


def _band_numpy(side, band, d, us, ell, line1, tris):
    """Compute the band terms by NumPy over the pieces (the reference of the kernel)."""
    ref, npc = d["ref"], d["npc"]
    u_t = np.einsum("pvk,bk->bpv", ref, us[tris[band]]).reshape(-1, 3)
    ell_t = np.einsum("pvk,bk->bpv", ref, ell[tris[band]]).reshape(-1, 3)
    px, py = d["px"], d["py"]
    first = np.repeat(line1[band], npc)
    part = np.zeros(px.shape[0])
    if first.any():
        z = u_t[first] - d["psi"][first] + d["delta_p"][first][:, None]
        part[first] += _pos_product(px[first], py[first], z, ell_t[first])
    y = d["U"] - ell_t
    z = d["psi"] + d["delta"][:, None] - u_t
    part += _pos_weighted(px, py, y, z)
    c_disc = part.reshape(-1, npc).sum(axis=1)
    c_lin = np.zeros(band.size)
    if side.other_h is not None:
        oh_t = np.einsum("pvk,bk->bpv", ref, side.other_h[tris[band]]).reshape(-1, 3)
        c_lin = _pos_weighted(px, py, y, u_t - oh_t).reshape(-1, npc).sum(axis=1)
    return c_disc, c_lin


#: A band triangle is split into pieces only where its bound on the whole triangle
#: (s = 0) exceeds this fraction of its squared flux indicator (docs/obstacle.md §11)
PIECE_FRACTION = 0.1


def _obstacle_terms(problem, side: _Side, u, ell, shaped=None, reference=False, weight=None):
    """Per-triangle ``(c_disc, c_lin)`` of one obstacle (§5.2), and whether guaranteed.

    ``shaped``: the shaped contact load of this side (:func:`shaped_load`);
    ``reference``: the band by NumPy (:func:`_band_numpy`) instead of the kernel, on
    the pieces of every band triangle.  ``weight`` (M,): the squared flux
    indicators; with an envelope the band is first bounded on whole triangles
    (s = 0) and only the triangles whose bound exceeds :data:`PIECE_FRACTION`
    of their weight are split into pieces, where the smaller bound is kept.
    """
    mesh = problem.mesh
    m = mesh.n_triangles
    us = side.sign * u  # the iterate seen from this obstacle (mirrored for the upper one)
    tris = mesh.triangles
    c_disc = np.zeros(m)
    # infeasibility piece (ell, (psi_h - u)+)_K: the lin part (0 at feasible iterates)
    if shaped is None:
        c_lin = _cut.positive_product(
            mesh.vertices, tris, np.ascontiguousarray(side.h - us), np.ascontiguousarray(ell)
        )
    else:
        c_lin = _pos_product(*_tri_xy(mesh), (side.h - us)[tris], shaped["values"])
    if side.kind == "piecewise-constant":
        psi_k = side.sign * np.asarray(side.func.triangle_values(mesh), dtype=np.float64)
        if psi_k.shape != (m,):
            raise DataError(
                f"{side.side}.triangle_values(mesh) must return one value per triangle, "
                f"shape ({m},), got {psi_k.shape}"
            )
        # case (i) needs psi_h >= psi on every triangle (a P1 majorant, §5.5)
        ok = bool(np.all(side.h[tris].min(axis=1) >= psi_k))
        gap = us[tris] - psi_k[:, None]
        c_disc = _pos_product(
            *_tri_xy(mesh), gap, ell[tris] if shaped is None else shaped["values"]
        )
        return (
            c_disc,
            c_lin,
            ok,
            ""
            if ok
            else (
                f"the nodal values of the {side.side} obstacle are not a majorant on every triangle"
            ),
        )
    gap_h = us[tris] - side.h[tris]  # (M, 3)
    gap_min = gap_h.min(axis=1)
    has_ell = (ell[tris] > 0).any(axis=1)
    if side.kind == "guaranteed":
        delta_k, delta_pk = _triangle_envelope(
            problem, side, lambda d, dp: np.flatnonzero(has_ell | (gap_min < d))
        )
    else:
        delta_k = delta_pk = np.zeros(m)
    concave_ok = (delta_pk == 0.0) & (gap_h.max(axis=1) <= 0.0)
    line1 = has_ell & ~concave_ok
    upper_viol = np.zeros(m, dtype=bool)
    if side.other_h is not None:
        upper_viol = ((us - side.other_h)[tris] > 0).any(axis=1)
    line2 = (gap_min < delta_k) | upper_viol
    if side.kind == "estimated":
        line2 |= gap_h.min(axis=1) <= 0.0
    band = np.flatnonzero(line1 | line2)
    if band.size == 0:
        return c_disc, c_lin, side.kind == "guaranteed", ""
    other = side.other_h if side.other_h is not None and upper_viol.any() else np.zeros(0)
    other = np.ascontiguousarray(other, dtype=np.float64)
    staged = weight is not None and side.kind == "guaranteed" and not reference
    if staged:
        env = problem._cache[f"tri_env_{side.side}"]
        c0, l0 = _kob.band_terms(
            mesh.vertices,
            tris,
            band,
            band,
            np.eye(3)[None],
            np.ascontiguousarray(us),
            np.ascontiguousarray(ell),
            np.ascontiguousarray(side.h[tris]),
            delta_k,
            delta_pk,
            env["U"],
            np.ascontiguousarray(line1[band]),
            other,
        )
        c_disc[band] = c0
        c_lin[band] += l0
        split = (c0 + l0) > PIECE_FRACTION * weight[band]
        band = band[split]
        if band.size == 0:
            return c_disc, c_lin, True, ""
    cache = _side_pieces(problem, side, band)
    if reference:
        cd, cl = _band_numpy(side, band, _select_pieces(cache, band), us, ell, line1, tris)
    else:
        d = cache["data"]
        cd, cl = _kob.band_terms(
            mesh.vertices,
            tris,
            band,
            np.ascontiguousarray(cache["slot"][band]),
            d["ref"],
            np.ascontiguousarray(us),
            np.ascontiguousarray(ell),
            d["psi"],
            d["delta"],
            d["delta_p"],
            d["U"],
            np.ascontiguousarray(line1[band]),
            other,
        )
    if staged:  # both bound the same terms: keep the smaller
        cd = np.minimum(cd, c_disc[band])
        c_lin[band] = np.minimum(c_lin[band], cl + (c_lin[band] - l0[split]))
    else:
        c_lin[band] += cl
    c_disc[band] = cd
    guaranteed = side.kind == "guaranteed"
    return (
        c_disc,
        c_lin,
        guaranteed,
        ""
        if guaranteed
        else (f"the {side.side} obstacle is a callable without envelope: its terms are estimated"),
    )


# ----------------------------------------------------------------- the bound
def _forms(a, a0, d, c):
    if a * a + 4.0 * c < 0 or (a0 + d) ** 2 + 4.0 * (a0 * d + c) < 0:
        raise NumericalError(f"obstacle bound: negative discriminant (a={a:g}, c={c:g})")
    eta_1 = 0.5 * (a + math.sqrt(a * a + 4.0 * c)) + d
    big = a0 + d
    eta_2 = 0.5 * (big + math.sqrt(big * big + 4.0 * (a0 * d + c)))
    return eta_1, eta_2


def estimate(problem, u, lam, r=None, cheap: dict | None = None) -> ObstacleEstimate:
    """Bound the energy error of any iterate ``(u, lam)`` (docs/obstacle.md Theorem 4.1).

    Parameters
    ----------
    problem : Obstacle
    u, lam : ndarray of shape (N,)
        Nodal values of the membrane and of the multiplier (any values; the
        multiplier's boundary values are ignored).
    r : ndarray of shape (N,), optional
        The algebraic residual :func:`residual` (computed when omitted).
    cheap : dict, optional
        :func:`cheap_terms` of the same iterate, if already computed.

    Returns
    -------
    ObstacleEstimate
    """
    mesh = problem.mesh
    u = np.ascontiguousarray(u, dtype=np.float64)
    lam = np.ascontiguousarray(lam, dtype=np.float64)
    if r is None:
        r = residual(problem, u, lam)
    if cheap is None:
        cheap = cheap_terms(problem, u, lam, r)
    lam_i = np.where(mesh.boundary_vertex_mask, 0.0, lam)
    shaped = {}
    for side_name, ell_key in (("lower", "ell_plus"), ("upper", "ell_minus")):
        if problem.obstacle_kind(side_name) == "piecewise-constant":
            load = shaped_load(problem, side_name, cheap[ell_key])
            if load is not None:
                shaped[side_name] = load
    eta_f = flux_terms(problem, u, lam_i, cheap["rho"], _merge_shaped(mesh, shaped))
    osc = integrals(problem, 1, moments=True)["osc"]
    part = eta_f + osc
    guaranteed, reason, case = True, [], "i"
    c_disc_k = np.zeros(mesh.n_triangles)
    c_lin_k = np.zeros(mesh.n_triangles)
    for side_name, ell_key in (("lower", "ell_plus"), ("upper", "ell_minus")):
        if (problem.psi if side_name == "lower" else problem.chi) is None:
            continue
        side = _Side(problem, side_name)
        if side.kind == "p1":
            c_disc_k += cheap["c_p1"][side_name]
            continue
        cd, cl, ok, why = _obstacle_terms(
            problem, side, u, cheap[ell_key], shaped.get(side_name), weight=part * part
        )
        c_disc_k += cd
        c_lin_k += cl
        if side.kind in ("guaranteed", "estimated"):
            case = "ii"
            if not problem.constant_mu and ok:
                ok = False
                why = (
                    f"per-triangle mu with a non-P1 {side_name} obstacle: case (ii) of the "
                    "bound is not proved there (docs/obstacle.md §10.2)"
                )
        if not ok:
            guaranteed = False
            reason.append(why)
    eta_bd = boundary_lifting(problem)
    if callable(problem.g):
        sup_phi = problem._cache["sup_phi"]
        touch = sup_phi > 0
        if touch.any():
            # w carries the lifting on boundary triangles: (ell, sup|phi|) covers its effect
            ell = cheap["ell_plus"] + cheap["ell_minus"]
            pressure = _cut.positive_product(
                mesh.vertices, mesh.triangles, np.ones(mesh.n_vertices), np.ascontiguousarray(ell)
            )
            c_disc_k += sup_phi * pressure
            # the lifting may move w across an obstacle on a boundary triangle: covered
            # only where both obstacles stay further than sup|phi| (+ delta) from u_h
            tri = np.flatnonzero(touch)
            for vals, sign in ((problem.psi, 1.0), (problem.chi, -1.0)):
                if vals is None:
                    continue
                gap = (sign * (u - vals))[mesh.triangles[tri]].min(axis=1)
                margin = sup_phi[tri] + 0.5 * mesh.diameters[tri] ** 2 * _boundary_curvature(
                    problem, sign
                )
                if np.any(gap < margin):
                    guaranteed = False
                    reason.append(
                        "an obstacle comes within the Dirichlet lifting of the callable g on "
                        "the boundary (docs/obstacle.md §4.5): its contact terms are not covered"
                    )
                    break
    nc = cheap["nc"] + eta_bd
    flux_norm = float(np.sqrt(np.sum(part * part)))
    a = float(np.sqrt(np.sum((part + nc) ** 2))) + cheap["eta_glob"]
    a0 = flux_norm + cheap["eta_glob"]
    d = float(np.sqrt(np.sum(nc * nc)))
    c_disc = float(np.sum(c_disc_k))
    c_lin = float(np.sum(c_lin_k))
    c = max(c_disc + c_lin, 0.0)
    eta_1, eta_2 = _forms(a, a0, d, c)
    d_bd = float(np.sqrt(np.sum(eta_bd * eta_bd)))
    components = {
        "eta_disc": flux_norm + 2.0 * d_bd + math.sqrt(max(c_disc, 0.0)),
        "eta_lin": cheap["eta_eps"] + 2.0 * cheap["D_nc"] + math.sqrt(max(c_lin, 0.0)),
        "eta_alg": cheap["eta_alg"],
    }
    indicators = np.sqrt(part * part + nc * nc + np.maximum(c_disc_k + c_lin_k, 0.0))
    terms = {
        "a": a,
        "a0": a0,
        "D": d,
        "c": c,
        "c_disc": c_disc,
        "c_lin": c_lin,
        "eta_glob": cheap["eta_glob"],
        "D_nc": cheap["D_nc"],
        "D_boundary": d_bd,
        "flux": flux_norm,
    }
    return ObstacleEstimate(
        eta=min(eta_1, eta_2),
        eta_I=eta_1,
        eta_II=eta_2,
        components=components,
        indicators=indicators,
        terms=terms,
        guaranteed=guaranteed,
        case=case,
        reason="; ".join(reason),
    )
