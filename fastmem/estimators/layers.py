r"""Layer-resolving variant of the bound for floppy membranes (issue 16).

Why.  Where one membrane is much softer than the other (per-triangle tensions,
:math:`\mu_{soft} \ll \mu_{stiff}`) and pushed onto it, the true solution drapes
the soft membrane onto the stiff one within a layer of width
:math:`\delta = (2\mu_{soft}\,\mathrm{gap}/\chi)^{1/2}` next to every place
that holds it up (the boundary, a stiff neighbour): 4.5e-4 for
:math:`\mu_1 = 10^{-6}`, far below the mesh size.  The discrete pressure
:math:`\lambda_a` of an open vertex is 0, so the patch fluxes of docs/method.md
§4 make the soft membrane carry the load of the triangles between an open and
a closed vertex, at the price :math:`\mu_{soft}^{-1/2}`: checkerboard
:math:`\mu_1 \in \{1, 10^{-6}\}`, n = 16: :math:`\eta = 24.3` against an error
of 0.07 (docs/heterogeneous.md §10).

What this module builds: a second guaranteed bound, from three changes to the
proof of docs/method.md §5, each valid for any choice made in it.

1. **Contact load.**  On the closed triangles (gap <= 0 at the three vertices,
   :math:`\chi^* > 0`) and on the *layer triangles* (floppy:
   :math:`\min_i\mu_{i,K} \le` :data:`LAYER_RATIO` :math:`\max_i\mu_{i,K}`;
   the glued pressure :math:`\chi^* = (\mu_1\Pi f_2 - \mu_2\Pi f_1)/(\mu_1+\mu_2)`
   positive; a vertex open and none negative; :math:`\delta_K \le`
   :data:`LAYER_BETA` :math:`h_K`) the contact load is :math:`\chi =
   (\chi^*)^+` (P1 on K), split over the patches as :math:`\chi\psi_a`;
   elsewhere :math:`\lambda_a\psi_a` as before.
2. **Patch masses.**  The patch problems of interior vertices need the load
   mass :math:`B_a\lambda_a` they had; the difference :math:`\Delta_a =
   \int(\chi - \lambda_a)\psi_a` (over the layer and closed triangles of the
   patch) is taken up by global P1 corrections :math:`z_1, z_2` with
   :math:`\mu_1 A z_1 = \Delta`, :math:`\mu_2 A z_2 = -\Delta` (interior
   vertices): the patch problems are solved for :math:`u_{ih} + z_i`, which
   restores every compatibility condition, and the flux is still measured
   against :math:`u_{ih}`.  :math:`z_i` is the response of the membranes to
   the load the lumped pressure misplaced, which is also what the error holds.
3. **Comparison function.**  On every layer triangle K with a positive gap the
   soft membrane is squeezed onto the stiff one:
   :math:`\tilde u_{soft} = u_{soft,h} \mp w` with :math:`w = \mathrm{gap}_h\,\varphi_t`,
   :math:`\varphi_t = \min(1, \min_j \lambda_j / t)` (:math:`\lambda_j` the
   barycentric coordinates of K): w vanishes on the edges of K, so
   :math:`\tilde u` is continuous, keeps its boundary values and the gap
   :math:`\mathrm{gap}_h (1 - \varphi_t) \ge 0` lives in a band of relative
   width t along the edges.  *Connected squeeze* (:func:`band_sets`): w need only
   vanish on the rim of a connected set of squeezed triangles (edges to a
   triangle that does not squeeze the same membrane, or on the boundary, with a
   positive gap at an end; and the ends of those edges), not on the edges the
   set shares inside: with one t per set, :math:`\varphi = \min(1,
   \min_{e\ free}\lambda_e/t, \min_{v\ free}(1 - \lambda_v)/t)` (:func:`band_phi`)
   restricts to :math:`\min(1, (1-\lambda_p)/t, (1-\lambda_q)/t)` over the free
   ends of a shared edge pq from both sides, so w is continuous.  The band then
   follows the lines that hold the soft membrane up, where the true solution
   drapes.  Checkerboard 1e-3, f = (-1, 1), n = 16: :math:`\eta` 0.210 -> 0.172.

4. **Cross points.**  Where a membrane's tension is checkerboard-like around a
   vertex a (:func:`fastmem.estimators.flux.cross_point_vertices`; isolated ones only),
   its z is *broken* at a: one unknown per run of high or low triangles around
   a (a sector), so that every sector's data balances on its own.  Nothing
   in the proof needs z continuous: z enters only the split of the data over
   the patches, :math:`g_a = \Pi f\psi_a \pm \ell_a - \mu\nabla(u_h +
   z)\cdot\nabla\psi_a - \rho\psi_a`, and :math:`\sum_a\nabla\psi_a = 0`
   on every triangle for any z that is P1 there, so the divergence of
   :math:`\sum_a\sigma_a` is the same; z is solved from the broken stiffness
   (the mesh cut at a), with the patch sums per sector as data.  A stiff
   sector's data is O(h) while its load is O(h^2) (its flux ends on the
   interfaces, where the true pressure has a line measure), so the stiff
   material's net load must move to the other membrane: the contact load of
   every closed component k (closed triangles joined by edges of equal
   tensions) is :math:`(1 + \alpha_k)\chi`, with :math:`\alpha_k \ge -1`
   (the load stays :math:`\ge 0`; P1, so the oscillation is unchanged, and the
   gap vanishes there, so c does not change) chosen to minimise
   :math:`\sum_i b_i^T(\mu_i A_i)^{-1}b_i` of the z data (per membrane one solve
   with K + 1 right-hand sides, K <= :data:`ALPHA_MAX_COMPONENTS`).  Any
   :math:`\alpha \ge -1` keeps the bound.  Checkerboard, f = (-4, 2), n = 16:
   :math:`\eta` 93.7 -> 0.387 (c = 1e-6), 3.01 -> 0.525 (c = 1e-3).

Bound.  With :math:`\tilde u = (u_{1h} - w_1, u_{2h} - \delta + w_2) \in K_g`
(:math:`w_1, w_2` on the triangles where membrane 1, resp. 2, is the soft one;
:math:`\delta = (u_{2h} - u_{1h})^+` vanishes there), the contact load
:math:`\ell = \chi + \lambda^-` on the layer and closed triangles and
:math:`\hat\lambda` elsewhere (:math:`\ell \ge 0`), and fluxes with
:math:`\nabla\cdot\sigma_{1h} = \Pi f_1 + \ell - \lambda^- - \rho_1`,
:math:`\nabla\cdot\sigma_{2h} = \Pi f_2 - \ell + \lambda^- - \rho_2`, the
proof of docs/method.md §5 runs unchanged: :math:`|||u - u_h||| \le |||u -
\tilde u||| + |||\tilde u - u_h|||`, the residuals :math:`r_i` are the same
functions (oscillation, :math:`\rho_i`, :math:`\lambda^-`), the flux part is
bounded triangle by triangle by :math:`\eta_{F,K,i} + \mu_{i,K}^{1/2}\|\nabla
w_i\|_K` and the contact part by :math:`c = (\ell, \tilde u_1 - \tilde u_2) =
(\ell, (u_{1h} - u_{2h})^+ - w_1 - w_2)`.  Hence

.. math::

    \eta = \tfrac12\big(a + \sqrt{a^2 + 4c}\big) + \Big(\sum_K \eta_{nc,K}^2
    + \eta_{w,K,1}^2 + \eta_{w,K,2}^2\Big)^{1/2},

with :math:`\eta_{w,K,i} = \mu_{i,K}^{1/2}\|\nabla w_i\|_K` added to membrane
i's term of a.  All integrals of w are exact (polynomials on the pieces of K
where :math:`\varphi` is linear, degree-4 rule).  The band parameter t
is chosen per triangle, or per connected set (any choice keeps the bound; it
only trades c against :math:`\eta_w`).  A second form of the same bound,
:func:`fastmem.estimators.terms.split_form`, tests the error equation of
:math:`u - u_h` with :math:`u - \tilde u` and charges the squeeze about half
as much where c dominates; :func:`fastmem.estimators.terms.combine` takes the
smaller, and the choice of t minimises the smaller.
:func:`fastmem.estimators.bound.evaluate` returns the smaller of this bound and the
standard one.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import LinearOperator, cg

from ..fem.loaddata import integrals
from ..fem.quadrature import quadrature_points, triangle_rule
from ..fem.residual import residuals
from ..linalg.amg import amg_preconditioner
from ..linalg.direct import factorize
from ..memory import meminfo_bytes, memory_limit, rss_bytes
from .flux import _T3, _load_values, _oscillation_at_points, cross_point_vertices, load_moments
from .terms import _lambda_parts, split_form

__all__ = [
    "BAND_T",
    "CONNECTED_BAND",
    "LAYER_BETA",
    "LAYER_BOUND",
    "LAYER_RATIO",
    "LayerLoad",
    "band_phi",
    "band_sets",
    "layer_load",
    "layer_terms",
    "squeeze_terms",
]

#: evaluate the layer bound at all (the benchmarks switch it off for the comparison)
LAYER_BOUND = True
#: a triangle is floppy when the softer tension is at most this fraction of the stiffer
LAYER_RATIO = 0.1
#: ... and a layer triangle when the drape width delta_K is at most this fraction of h_K
LAYER_BETA = 0.5
#: band parameters t tried on every squeezed triangle (0 stands for "no squeeze")
SQUEEZE_T = (0.0, 1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3)
#: squeeze connected sets of layer triangles with a band along their rims only (band_sets)
CONNECTED_BAND = True
#: band parameters of the connected squeeze, one per connected set
BAND_T = (1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3, 0.5, 1.0)
#: vertices of the direct z solves (above: AMG-preconditioned CG) ...
LAYER_DIRECT_VERTICES = 1_100_000
#: ... as long as two factors (one per membrane) fit in this fraction of the memory the
#: process can still use (a factor's peak estimated at LAYER_FACTOR_BYTES per vertex times
#: log2(n) / 20, nested dissection on a 2-d mesh; measured peaks 2.3, 2.4 and 2.5 KB per
#: vertex at 66k, 263k and 1.05M vertices, 1.8, 2.0 and 2.4 KB kept).
#: Checkerboard 1e-3, f = (-4, 2), n = 1024 (1.05M vertices, two factors): the layer bound
#: in 11.9 s warm, 30.8 s first call, 8.0 GB peak; by AMG-CG 67.7 s, 70.4 s, 3.6 GB
LAYER_DIRECT_MEMORY_FRACTION = 0.35
LAYER_FACTOR_BYTES = 2600
#: relative residual of the z solves by CG (the rest is carried by rho, so the bound holds)
LAYER_CG_TOL = 1e-10
_CHUNK = 20_000
#: break the z solves at the cross points of a membrane's tension (one unknown per run of
#: high or low triangles around the point) and rescale the pressure of the closed
#: components there (see "Cross points" in the module docstring)
CUT_CROSS_POINTS = True
#: the cut is skipped when more vertices than this qualify (random per-triangle tensions)
CUT_MAX_VERTICES = 5000
#: closed components whose pressure scale alpha_k is optimised (the largest by load) ...
ALPHA_MAX_COMPONENTS = 64
#: ... and at most as many as fit their responses (one vector per membrane) in these bytes
ALPHA_MEMORY = 256 * 2**20
#: relative residual and iteration cap of the responses by CG above LAYER_DIRECT_VERTICES
#: (they only choose alpha, and any alpha keeps the bound; 1e-2 and 10 iterations lost the
#: whole gain on the checkerboard 1e-3, f = (-4, 2), n = 1024: eta 0.261 instead of 0.200)
ALPHA_CG_TOL = 1e-4
ALPHA_CG_MAXITER = 200


@dataclass
class LayerLoad:
    r"""The contact load, patch-mass corrections and squeeze set of the layer bound.

    Attributes
    ----------
    tri : int32 (S,)
        Triangles where the contact load is :math:`\\chi` (layer and closed).
    chi : float64 (S, 3)
        Nodal values of :math:`\\chi \\ge 0` on them.
    moments : float64 (S, 3, 3)
        ``((chi - lam_a) psi_a, lambda_j)_K`` for the vertex a in row i: what the
        flux kernel adds to membrane 1's patch loads (and takes from membrane 2's).
    z1, z2 : float64 (N,)
        The global P1 corrections (0 on the boundary).
    eps1, eps2 : float64 (N,)
        What the z solves leave: ``Delta - mu_1 A z_1`` and ``-Delta - mu_2 A z_2``
        (added to the residuals R_1, R_2: rho carries them).
    squeeze : int32 (Q,)
        Triangles squeezed (rows of ``tri`` with a positive gap, no negative one).
    soft : int8 (Q,)
        The membrane squeezed there (1 or 2).
    osc_rows, osc1, osc2 : ndarray or None
        Callable loads: the closed triangles whose pressure is the pointwise glued
        one, and there the oscillations of ``f1 + chi`` and ``f2 - chi``.
    extra1, extra2 : (rows, add) or None
        Membrane i's z is broken at cross points: ``z_i`` holds its continuous
        part and ``add`` (R, 3, 3) the load moments ``-(mu_i grad e . grad psi_a,
        lambda_j)_K`` of the rest e on the triangles ``rows`` (added to membrane
        i's load moments by :func:`fastmem.estimators.flux.reconstruct`).
    alpha : ndarray or None
        The pressure scales of the closed components at cross points (diagnostic).
    """

    tri: np.ndarray
    chi: np.ndarray
    moments: np.ndarray
    z1: np.ndarray
    z2: np.ndarray
    eps1: np.ndarray
    eps2: np.ndarray
    squeeze: np.ndarray
    soft: np.ndarray
    osc_rows: np.ndarray | None = None
    osc1: np.ndarray | None = None
    osc2: np.ndarray | None = None
    extra1: tuple | None = None
    extra2: tuple | None = None
    alpha: np.ndarray | None = None


def _projected_load(scene, i):
    r"""Nodal values per triangle (M, 3) of :math:`\\Pi_K f_i`."""
    mesh = scene.mesh
    f = scene.f1 if i == 1 else scene.f2
    kind = scene.data_kind(f"f{i}")
    if kind == "constant":
        return np.full((mesh.n_triangles, 3), float(f))
    if kind != "callable":
        return np.asarray(f, dtype=np.float64)[mesh.triangles]
    mom = integrals(scene, i, moments=True)["moments"]
    b = mom.sum(axis=2)  # (f, lambda_j)_K
    return (3.0 / mesh.areas)[:, None] * (4.0 * b - b.sum(axis=1, keepdims=True))


def _per_triangle(mu, m):
    return np.broadcast_to(np.asarray(mu, dtype=np.float64), (m,))


def layer_load(scene, u1, u2, lam, r1=None, r2=None) -> LayerLoad | None:
    """Layer contact load of a triple, or None when no triangle is a layer triangle.

    Only for per-triangle tensions (constant tensions: None).  ``lam`` is 0 on
    the boundary; ``r1``, ``r2`` are the algebraic residuals of the triple
    (computed when omitted and needed: at cross points, see :func:`_cross_points`).
    """
    if scene.constant_mu:
        return None
    mesh = scene.mesh
    t = mesh.triangles
    m = mesh.n_triangles
    mu1 = _per_triangle(scene.mu1, m)
    mu2 = _per_triangle(scene.mu2, m)
    gap = u1 - u2
    gk = gap[t]
    open_k = gk > 0.0
    n_open = open_k.sum(axis=1)
    soft = np.minimum(mu1, mu2)
    floppy = soft <= LAYER_RATIO * np.maximum(mu1, mu2)
    if not floppy.any():
        return None
    chi = (mu1[:, None] * _projected_load(scene, 2) - mu2[:, None] * _projected_load(scene, 1)) / (
        mu1 + mu2
    )[:, None]
    chi = np.maximum(chi, 0.0)
    chi_min = chi.min(axis=1)
    gmax = np.maximum(gk.max(axis=1), 0.0)
    width = np.sqrt(2.0 * soft * gmax / np.maximum(chi_min, 1e-300))
    layer = floppy & (n_open > 0) & (chi_min > 0.0) & (width <= LAYER_BETA * mesh.diameters)
    layer &= ~(gk < 0.0).any(axis=1)  # squeezing needs gap >= 0 on K
    if not layer.any():
        return None
    closed = (n_open == 0) & (chi.max(axis=1) > 0.0)
    sel = np.flatnonzero(layer | closed).astype(np.int32)
    area = mesh.areas[sel]
    chi_s = chi[sel]
    lam_k = lam[t[sel]]  # (S, 3)
    # ((chi - lam_a) psi_a, psi_j)_K = |K| (sum_k chi_k T3[a,k,j] - lam_a (1 + d_aj) / 12)

    mom = np.einsum("sk,ikj->sij", chi_s, _T3) - lam_k[:, :, None] * ((np.eye(3) + 1.0) / 12.0)
    mom *= area[:, None, None]
    osc1 = osc2 = None
    closed_rows = np.flatnonzero(closed[sel])
    if closed_rows.size and "callable" in (scene.data_kind("f1"), scene.data_kind("f2")):
        # callable loads: on the closed triangles (where c vanishes whatever the load's
        # form) the pressure is the glued one pointwise, not its P1 projection, so that
        # f1 + chi = mu1 (f1 + f2) / (mu1 + mu2) is what the soft membrane's oscillation
        # (weight mu_soft^-1/2) measures; moments and oscillation at the load rule's points
        mom[closed_rows], osc1, osc2, points = _pointwise_closed(
            scene, sel[closed_rows], mu1, mu2, lam_k[closed_rows]
        )
    delta = np.bincount(t[sel].ravel(), weights=mom.sum(axis=2).ravel(), minlength=mesh.n_vertices)
    bnd = mesh.boundary_vertex_mask
    delta[bnd] = 0.0
    cuts = [_cut(scene, i) for i in (1, 2)] if CUT_CROSS_POINTS else [None, None]
    extra = [None, None]
    alpha = None
    if cuts[0] is None and cuts[1] is None:
        z1, eps1 = _solve(scene, 1, delta)
        z2, eps2 = _solve(scene, 2, -delta)
    else:
        if r1 is None or r2 is None:

            r1, r2 = residuals(scene, u1, u2, lam)
        cp = _cross_points(scene, u1, u2, lam, r1, r2, sel, mom, delta, closed, cuts)
        alpha, scale, zs, epss, extra = cp
        if alpha is not None and np.any(alpha != 0.0):
            # the closed components' pressure (1 + alpha_k) chi: moments (the chi part of
            # the moments scaled, pointwise ones included), nodal values and (callable
            # loads) the pointwise pressure's oscillation
            part = mom + lam_k[:, :, None] * ((np.eye(3) + 1.0) / 12.0) * area[:, None, None]
            mom += (scale - 1.0)[:, None, None] * part
            chi_s = chi_s * scale[:, None]
            if osc1 is not None:
                osc1, osc2 = _closed_oscillation(
                    scene, sel[closed_rows], mu1, mu2, points, scale[closed_rows]
                )
        (z1, z2), (eps1, eps2) = zs, epss
    squeeze_rows = np.flatnonzero(layer[sel])
    squeeze = sel[squeeze_rows]
    soft_id = np.where(mu1[squeeze] <= mu2[squeeze], 1, 2).astype(np.int8)
    return LayerLoad(
        tri=sel,
        chi=chi_s,
        moments=np.ascontiguousarray(mom),
        z1=z1,
        z2=z2,
        eps1=eps1,
        eps2=eps2,
        squeeze=squeeze.astype(np.int32),
        soft=soft_id,
        osc_rows=None if osc1 is None else sel[closed_rows],
        osc1=osc1,
        osc2=osc2,
        extra1=extra[0],
        extra2=extra[1],
        alpha=alpha,
    )


def _pointwise_closed(scene, tri, mu1, mu2, lam_k):
    """Moments ``((chi - lam_a) psi_a, psi_j)_K`` and oscillations of ``f1 + chi``, ``f2 - chi``.

    With the pointwise glued pressure ``chi = (mu1 f2 - mu2 f1)^+ / (mu1 + mu2)`` at the
    points of the load rule (degree ``scene.load_degree``) of the triangles ``tri``.
    Returns ``(mom, osc1, osc2, points)``; ``points`` (the loads and chi there) lets
    :func:`_closed_oscillation` rescale the pressure without evaluating the loads again.
    """
    mesh = scene.mesh
    bary, w = triangle_rule(scene.load_degree)
    x, y = quadrature_points(mesh.vertices, mesh.triangles[tri], bary)
    f1 = _load_values(scene, 1, tri, x, y, bary)
    f2 = _load_values(scene, 2, tri, x, y, bary)
    m1, m2 = mu1[tri, None], mu2[tri, None]
    chi = np.maximum(m1 * f2 - m2 * f1, 0.0) / (m1 + m2)
    area = mesh.areas[tri]
    # (chi psi_i, psi_j)_K = |K| sum_q w_q chi_q b_qi b_qj
    mom = np.einsum("sq,qi,qj->sij", chi * w, bary, bary) * area[:, None, None]
    mom -= lam_k[:, :, None] * ((np.eye(3) + 1.0) / 12.0) * area[:, None, None]
    points = (f1, f2, chi)
    osc1, osc2 = _closed_oscillation(scene, tri, mu1, mu2, points)
    return mom, osc1, osc2, points


def _closed_oscillation(scene, tri, mu1, mu2, points, scale=None):
    """Oscillations of ``f1 + s chi`` and ``f2 - s chi`` on ``tri`` (s: ``scale`` or 1)."""
    mesh = scene.mesh
    f1, f2, chi = points
    if scale is not None:
        chi = chi * scale[:, None]
    bary, w = triangle_rule(scene.load_degree)
    area = mesh.areas[tri]
    h = mesh.diameters[tri] / np.pi
    osc1 = h / np.sqrt(mu1[tri]) * _oscillation_at_points(f1 + chi, bary, w, area)
    osc2 = h / np.sqrt(mu2[tri]) * _oscillation_at_points(f2 - chi, bary, w, area)
    return osc1, osc2


def _solve(scene, i, rhs):
    """Solve ``mu_i A z = rhs`` on the interior vertices (z = 0 on the boundary).

    Returns z and what the solve leaves, ``rhs - mu_i A z``.
    """
    mesh = scene.mesh
    inner = mesh.interior_vertices
    z = np.zeros(mesh.n_vertices)
    if not np.any(rhs):
        return z, np.zeros(mesh.n_vertices)
    solve = _solver(scene, i)
    z[inner] = solve(rhs[inner])
    eps = rhs - scene.weighted_stiffness(i) @ z
    eps[mesh.boundary_vertex_mask] = 0.0
    return z, eps


def _solver(scene, i):
    """Return the cached solver of the interior block of ``mu_i A`` (LU, or AMG-CG)."""
    key = ("layer_solver", i)
    cache = scene._cache
    if key not in cache:
        mesh = scene.mesh
        inner = mesh.interior_vertices
        a = scene.weighted_stiffness(i).tocsr()[inner][:, inner].tocsr()
        cache[key] = _factor(a, mesh.n_vertices, mesh.vertices[inner])
    return cache[key]


def _direct_fits(n_vertices):
    """Return whether two factors of ``n_vertices`` unknowns fit in memory.

    They may take :data:`LAYER_DIRECT_MEMORY_FRACTION` of the memory limit
    (:func:`fastmem.memory.memory_limit`) and of what the process can still reach
    (resident memory plus ``MemAvailable``, Linux).
    """
    need = 2 * LAYER_FACTOR_BYTES * n_vertices * max(1.0, math.log2(max(n_vertices, 2)) / 20.0)
    room = [memory_limit()[0]]
    avail = meminfo_bytes("MemAvailable")
    if avail is not None:
        room.append(avail + rss_bytes())
    room = [r for r in room if r]
    return not room or need <= LAYER_DIRECT_MEMORY_FRACTION * min(room)


def _factor(a, n_vertices, coordinates):
    """Return a solver of the SPD matrix a (vector or (n, k) right-hand sides).

    Nested-dissection LU (:func:`fastmem.linalg.direct.factorize`, a point per unknown in
    ``coordinates``) up to :data:`LAYER_DIRECT_VERTICES` when it fits in memory
    (:func:`_direct_fits`), else AMG-preconditioned CG.
    """
    if n_vertices <= LAYER_DIRECT_VERTICES and _direct_fits(n_vertices):

        lu = factorize(a, coordinates)

        def solve(b, rtol=None, maxiter=None):
            return lu.solve(b)

        solve.exact = True
        return solve


    ml = amg_preconditioner(a)
    pre = LinearOperator(a.shape, matvec=ml, dtype=np.float64)

    def solve(b, rtol=LAYER_CG_TOL, maxiter=200):
        if b.ndim == 2:
            return np.stack([solve(col, rtol, maxiter) for col in b.T], axis=1)
        x, _ = cg(a, b, rtol=rtol, maxiter=maxiter, M=pre)
        return x

    solve.exact = False
    return solve


# --- cross points: z broken per sector, pressure rescaled per closed component ---------


def _cut(scene, i):
    """Sector unknowns of membrane i at the cross points of its tension, cached on the scene.

    Only isolated cross points (no neighbour is one) are cut.  Returns None
    (constant tension, no such point, or more than :data:`CUT_MAX_VERTICES`),
    else a dict: ``n`` the number of unknowns (N + the sectors), ``cut`` the
    cut vertices, and for the patch entries of the cut vertices
    ``owner``/``tri``/``loc`` (vertex, triangle, local index) and ``sector``: that
    corner's unknown is ``N + sector`` (the vertex itself elsewhere; :func:`_unknowns`).
    """
    key = ("layer_cut", i)
    cache = scene._cache
    if key in cache:
        return cache[key]

    mu = scene.mu1 if i == 1 else scene.mu2
    out = None
    if np.ndim(mu) == 1:
        mesh = scene.mesh
        cut = cross_point_vertices(mesh, mu)
        # isolated cross points only: with two cut neighbours a sector can be an island
        # without boundary values (random tensions), and the broken stiffness singular
        ev = mesh.edges
        both = cut[ev[:, 0]] & cut[ev[:, 1]]
        cut[ev[both].ravel()] = False
        if 0 < int(cut.sum()) <= CUT_MAX_VERTICES:
            out = _sectors(mesh, np.asarray(mu, dtype=np.float64), cut)
    cache[key] = out
    return out


def _sectors(mesh, mu, cut):
    """Find the runs of high / low triangles around the vertices ``cut`` (see :func:`_cut`).

    Two triangles of the patch of a cut vertex a lie in one sector when they share
    an edge at a and both are high or both low (threshold ``(max mu min mu)^1/2``
    over the patch, as :func:`fastmem.estimators.flux.cross_point_vertices`).  Vectorised:
    one union of the patch entries over the edges at cut vertices.
    """
    n = mesh.n_vertices
    m = mesh.n_triangles
    ptr = mesh.patch_ptr
    verts = np.flatnonzero(cut)
    counts = ptr[verts + 1] - ptr[verts]
    owner = np.repeat(verts, counts)
    pos = np.repeat(ptr[verts] - np.cumsum(counts) + counts, counts) + np.arange(counts.sum())
    tri = mesh.patch_triangles[pos]
    loc = mesh.patch_local[pos]
    mus = mu[tri]
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    th = np.sqrt(np.maximum.reduceat(mus, starts) * np.minimum.reduceat(mus, starts))
    high = mus >= np.repeat(th, counts)
    keys = owner.astype(np.int64) * m + tri
    order = np.argsort(keys)
    et = mesh.edge_triangles
    ev = mesh.edges
    rows = []
    cols = []
    for end in (0, 1):
        v = ev[:, end]
        sel = np.flatnonzero(cut[v] & (et[:, 1] >= 0))
        p0 = order[np.searchsorted(keys, v[sel].astype(np.int64) * m + et[sel, 0], sorter=order)]
        p1 = order[np.searchsorted(keys, v[sel].astype(np.int64) * m + et[sel, 1], sorter=order)]
        same = high[p0] == high[p1]
        rows.append(p0[same])
        cols.append(p1[same])
    rows = np.concatenate(rows)
    cols = np.concatenate(cols)
    k = len(pos)
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(k, k))
    n_sec, sector = connected_components(graph, directed=False)
    return {
        "n": n + n_sec,
        "cut": cut,
        "owner": owner,
        "tri": tri,
        "loc": loc,
        "sector": sector,
    }


def _unknowns(mesh, cutinfo, rows):
    """Return the unknowns of the corners of the triangles ``rows`` (sorted, unique): (R, 3)."""
    out = mesh.triangles[rows].astype(np.int64)
    if len(rows) == 0:
        return out
    tri = cutinfo["tri"]
    pos = np.minimum(np.searchsorted(rows, tri), len(rows) - 1)
    hit = rows[pos] == tri
    out[pos[hit], cutinfo["loc"][hit]] = mesh.n_vertices + cutinfo["sector"][hit]
    return out


def _cut_solver(scene, i, cutinfo):
    """Return the cached solver of the broken ``mu_i A`` on the free unknowns of :func:`_cut`.

    The matrix is ``mu_i A`` with the triangles of the cross points' patches
    assembled again on their sector unknowns.  Returns ``(solve, matrix, free)``.
    """
    key = ("layer_cut_solver", i)
    cache = scene._cache
    if key in cache:
        return cache[key]
    mesh = scene.mesh
    n, nd = mesh.n_vertices, cutinfo["n"]
    tri = np.unique(cutinfo["tri"])
    mu = np.asarray(scene.mu1 if i == 1 else scene.mu2, dtype=np.float64)[tri]
    grad = mesh.gradients[tri]
    loc = np.einsum("tik,tjk->tij", grad, grad) * (mu * mesh.areas[tri])[:, None, None]
    old = mesh.triangles[tri].astype(np.int64)
    new = _unknowns(mesh, cutinfo, tri)
    r = np.concatenate([np.repeat(old, 3, axis=1).ravel(), np.repeat(new, 3, axis=1).ravel()])
    c = np.concatenate([np.tile(old, (1, 3)).ravel(), np.tile(new, (1, 3)).ravel()])
    v = np.concatenate([-loc.ravel(), loc.ravel()])
    a = scene.weighted_stiffness(i).tocoo()
    full = sp.coo_matrix(
        (np.concatenate([a.data, v]), (np.concatenate([a.row, r]), np.concatenate([a.col, c]))),
        shape=(nd, nd),
    ).tocsr()
    free = np.ones(nd, dtype=bool)
    free[:n] = ~mesh.boundary_vertex_mask
    free[np.flatnonzero(cutinfo["cut"])] = False  # replaced by their sector unknowns
    free = np.flatnonzero(free)
    block = full[free][:, free].tocsr()
    owner = np.arange(nd)
    owner[cutinfo["sector"] + n] = cutinfo["owner"]  # a sector sits at its vertex
    out = (_factor(block, n, mesh.vertices[owner[free]]), full, free)
    cache[key] = out
    return out


def _cross_points(scene, u1, u2, lam, r1, r2, sel, mom, delta, closed, cuts):
    r"""Solve for z broken at cross points and the closed components' pressure scales.

    Returns ``(alpha, scale, (z1, z2), (eps1, eps2), (extra1, extra2))``: scale
    (S,) per row of ``sel`` (1 + alpha_k on component k), the continuous parts
    of z and what the solves leave (nodal), and the load moments of the broken
    rest (see :class:`LayerLoad`).
    """
    mesh = scene.mesh
    n = mesh.n_vertices
    t = mesh.triangles
    area = mesh.areas
    bnd = mesh.boundary_vertex_mask
    lam_k = lam[t[sel]]
    # the chi part of the layer moments per (row, vertex): int_K chi psi_a
    chimom = mom.sum(axis=2) + lam_k * area[sel, None] / 3.0
    row_of = np.full(mesh.n_triangles, -1, dtype=np.int64)
    row_of[sel] = np.arange(len(sel))
    spaces = []
    for i, cutinfo in zip((1, 2), cuts, strict=True):
        sign = 1.0 if i == 1 else -1.0
        if cutinfo is None:
            solve = _solver(scene, i)
            spaces.append((None, solve, None, np.flatnonzero(~bnd), sign * delta))
            continue
        solve, matrix, free = _cut_solver(scene, i, cutinfo)
        b = np.zeros(cutinfo["n"])
        b[:n] = sign * delta
        b[np.flatnonzero(cutinfo["cut"])] = 0.0
        b[n:] = np.bincount(
            cutinfo["sector"],
            weights=_sector_data(
                scene, i, u1 if i == 1 else u2, lam, r1 if i == 1 else r2, cutinfo, row_of, mom
            ),
            minlength=cutinfo["n"] - n,
        )
        spaces.append((cutinfo, solve, matrix, free, b))
    # closed components (equal tensions, edge-connected) holding a high sector's triangle
    comp, kc = _components(scene, sel, closed, chimom)
    on = np.flatnonzero(comp >= 0)
    cmat = []  # per membrane: sparse (kc, n_unknowns), the load of chi on each component
    for cutinfo, _, _, _, b in spaces:
        idx = t[sel[on]] if cutinfo is None else _unknowns(mesh, cutinfo, sel[on])
        ck = coo_matrix(
            (chimom[on].ravel(), (np.repeat(comp[on], 3), idx.ravel())), shape=(kc, b.size)
        ).tocsr()
        cmat.append(ck)
    z = []
    w = []
    for (_, solve, _, free, b), ck, sign in zip(spaces, cmat, (1.0, -1.0), strict=True):
        # one solve with the data and the kc component loads as columns (by CG: the
        # loads only choose alpha, any alpha keeps the bound; z is solved again below,
        # also when direct)
        cols = np.column_stack([b[free], sign * ck[:, free].T.toarray()])
        sol = solve(cols, ALPHA_CG_TOL, ALPHA_CG_MAXITER)
        z.append(sol[:, 0])
        w.append(np.ascontiguousarray(sol[:, 1:].T))
    alpha = np.zeros(kc)
    if kc:
        # minimise sum_i b_i(alpha)^T (mu_i A_i)^-1 b_i(alpha), b_1 + C alpha, b_2 - C alpha,
        # over alpha_k >= -1 (the pressure stays >= 0): a few active-set passes
        h = sum(
            c[:, sp[3]] @ wi.T * s
            for sp, c, wi, s in zip(spaces, cmat, w, (1.0, -1.0), strict=True)
        )
        g = sum(
            s * c[:, sp[3]] @ zi for sp, c, zi, s in zip(spaces, cmat, z, (1.0, -1.0), strict=True)
        )
        fixed = np.zeros(kc, dtype=bool)
        for _ in range(kc):
            fr = ~fixed
            alpha[fixed] = -1.0
            rhs = -g[fr] - h[np.ix_(fr, fixed)] @ alpha[fixed]
            alpha[fr] = np.linalg.lstsq(h[np.ix_(fr, fr)], rhs, rcond=None)[0]
            low = fr & (alpha < -1.0)
            if not low.any():
                break
            fixed |= low
        alpha = np.maximum(alpha, -1.0)
    scale = np.ones(len(sel))
    scale[on] += alpha[comp[on]]
    zs, epss, extra = [], [], []
    for sp_, ck, i in zip(spaces, cmat, (1, 2), strict=True):
        cutinfo, _, matrix, free, b = sp_
        sign = 1.0 if i == 1 else -1.0
        full = np.zeros(b.size)
        rhs = b + sign * (ck.T @ alpha) if kc else b
        solve = sp_[1]
        # solved again, also when direct: the combination zi + alpha @ wi cancels large
        # responses (mu = 1e-6) and leaves round-off that rho carries at the price 1/h
        # (checkerboard 1e-6 refined 44 times at a cross point, h = 4e-8: eps 8e-12 per
        # vertex, eta_glob1 0.17 against 6e-6 by the standard bound)
        full[free] = solve(rhs[free])
        if cutinfo is None:
            eps = rhs - scene.weighted_stiffness(i) @ full
            eps[bnd] = 0.0
            zs.append(full)
            epss.append(eps)
            extra.append(None)
            continue
        eps_d = np.zeros(b.size)
        eps_d[free] = rhs[free] - (matrix @ full)[free]
        owner = cutinfo["owner"]
        first = np.zeros(cutinfo["n"] - n, dtype=np.int64)
        first[cutinfo["sector"]] = owner  # the vertex of each sector
        eps = eps_d[:n] + np.bincount(first, weights=eps_d[n:], minlength=n)
        # continuous part: z at the uncut vertices, the sectors' mean at the cut ones
        cnt = np.bincount(first, minlength=n)
        zc = full[:n].copy()
        cut = cnt > 0
        zc[cut] = np.bincount(first, weights=full[n:], minlength=n)[cut] / cnt[cut]
        zs.append(zc)
        epss.append(eps)
        extra.append(_broken_moments(scene, i, cutinfo, full, zc))
    return alpha, scale, tuple(zs), tuple(epss), tuple(extra)


def _sector_data(scene, i, u, lam, r, cutinfo, row_of, mom):
    """Per patch entry of the cross points: the total of membrane i's patch data on it.

    ``int_K (Pi f_i psi_a +- ell_a - mu_i grad u . grad psi_a - rho_a psi_a)`` with
    the layer contact load (z = 0): the sector sums are what the broken z must carry.
    """
    mesh = scene.mesh
    tri, loc, owner = cutinfo["tri"], cutinfo["loc"], cutinfo["owner"]
    area = mesh.areas[tri]
    f = scene.f1 if i == 1 else scene.f2
    lm = load_moments(scene, i)
    load = float(f) * area / 3.0 if lm is None else lm[tri, loc].sum(axis=1)
    rows = row_of[tri]
    contact = lam[owner] * area / 3.0
    has = rows >= 0
    contact[has] += mom[rows[has], loc[has]].sum(axis=1)
    mu = np.asarray(scene.mu1 if i == 1 else scene.mu2, dtype=np.float64)
    mu = mu[tri] if mu.ndim else np.full(tri.size, float(mu))
    grad = mesh.gradients[tri]
    du = np.einsum("tjk,tj->tk", grad, u[mesh.triangles[tri]])
    dot = mu * np.einsum("tk,tk->t", grad[np.arange(tri.size), loc], du) * area
    rho = r[owner] / mesh.lumped_mass[owner] * area / 3.0
    sign = 1.0 if i == 1 else -1.0
    return load + sign * contact - dot - rho


def _broken_moments(scene, i, cutinfo, z, zc):
    """Load moments of the broken rest ``e = z - zc`` on the cross points' patches.

    e is ``z_sector - zc_a`` at the corners of the cut vertices, 0 elsewhere, so it
    lives on the triangles of their patches: ``(rows, add)`` with ``add[r, a, j] =
    -(mu_i grad e . grad psi_a, lambda_j)_K`` (the same for every j).
    """
    mesh = scene.mesh
    n = mesh.n_vertices
    tri = cutinfo["tri"]
    e = z[n + cutinfo["sector"]] - zc[cutinfo["owner"]]
    rows, inv = np.unique(tri, return_inverse=True)
    ge = np.zeros((rows.size, 2))
    np.add.at(ge, inv, e[:, None] * mesh.gradients[tri, cutinfo["loc"]])
    mu = _per_triangle(scene.mu1 if i == 1 else scene.mu2, mesh.n_triangles)[rows]
    per = (
        -np.einsum("tjk,tk->tj", mesh.gradients[rows], ge) * (mu * mesh.areas[rows] / 3.0)[:, None]
    )
    return rows, np.ascontiguousarray(np.repeat(per[:, :, None], 3, axis=2))


def _components(scene, sel, closed, chimom):
    """Return the component of every row of ``sel`` (-1: none) and their number K.

    Components: closed triangles (rows of sel) connected through edges whose two
    triangles have equal tensions; the :data:`ALPHA_MAX_COMPONENTS` largest by
    their chi load.  (Restricting them to those that hold a high sector of a
    cross point gave eta 0.359 instead of 0.329 on the checkerboard 1e-6,
    f = (-4, 2), n = 32: components whose cross points are open gain too.)
    """
    mesh = scene.mesh
    m = mesh.n_triangles
    rows_c = np.flatnonzero(closed[sel])
    if rows_c.size == 0:
        return np.full(len(sel), -1, dtype=np.int64), 0
    is_c = np.zeros(m, dtype=bool)
    is_c[sel[rows_c]] = True
    mu1 = _per_triangle(scene.mu1, m)
    mu2 = _per_triangle(scene.mu2, m)
    et = mesh.edge_triangles
    e = et[(et[:, 1] >= 0)]
    e = e[is_c[e[:, 0]] & is_c[e[:, 1]]]
    e = e[(mu1[e[:, 0]] == mu1[e[:, 1]]) & (mu2[e[:, 0]] == mu2[e[:, 1]])]
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(m, m))
    _, label = connected_components(graph, directed=False)
    row_lab = label[sel[rows_c]]
    mass = chimom[rows_c].sum(axis=1)
    uniq, inv = np.unique(row_lab, return_inverse=True)
    load = np.bincount(inv, weights=mass)
    cap = max(1, min(ALPHA_MAX_COMPONENTS, ALPHA_MEMORY // (16 * mesh.n_vertices)))
    best = np.argsort(-load)[:cap]
    best = best[load[best] > 0.0]
    rank = np.full(uniq.size, -1, dtype=np.int64)
    rank[best] = np.arange(best.size)
    comp = np.full(len(sel), -1, dtype=np.int64)
    comp[rows_c] = rank[inv]
    return comp, best.size


# --- the squeeze integrals -------------------------------------------------------------


def _clip(poly, a, b):
    """Clip a convex polygon (list of 2-d points) to the half-plane ``a . p + b <= 0``."""
    out = []
    for k in range(len(poly)):
        p, q = poly[k], poly[(k + 1) % len(poly)]
        fp, fq = float(a @ p + b), float(a @ q + b)
        if fp <= 0.0:
            out.append(p)
        if (fp < 0.0 < fq) or (fq < 0.0 < fp):
            out.append(p + fp / (fp - fq) * (q - p))
    return out


def _band_functions(fmask, vmask, t):
    r"""List the affine functions ``(coef (3,), const)`` of barycentric coordinates.

    Their minimum is t phi: ``t`` itself (phi = 1), :math:`\lambda_j` for every edge j
    (opposite vertex j) in ``fmask`` and :math:`1 - \lambda_v` for every vertex v in
    ``vmask`` (bit j, v).
    """
    e = np.eye(3)
    funcs = [(np.zeros(3), float(t))]
    funcs += [(e[j], 0.0) for j in range(3) if fmask >> j & 1]
    funcs += [(-e[v], 1.0) for v in range(3) if vmask >> v & 1]
    return funcs


def band_phi(bary, fmask, vmask, t):
    r"""Evaluate the band function :math:`\varphi` at barycentric points ``bary`` (P, 3).

    :math:`\varphi = \min(1, \min_{j \in F}\lambda_j / t, \min_{v \in V}(1 - \lambda_v) / t)`:
    0 on the edges in F and at the vertices in V, 1 at distance (relative) t from them.
    F = all edges, V = none is the band of :func:`squeeze_terms`' default.
    """
    funcs = _band_functions(int(fmask), int(vmask), float(t))
    vals = np.stack([np.asarray(bary) @ c + d for c, d in funcs], axis=-1)
    return vals.min(axis=-1) / t


@functools.lru_cache(maxsize=1024)
def _band_rule(fmask, vmask, t):
    r"""Quadrature on the pieces of K where :math:`\varphi` is linear (exact to degree 4).

    Each piece is the convex polygon where one of :func:`_band_functions` is the
    smallest (clipped from the reference triangle, fan-triangulated).  Returns the
    barycentric points (Q, 3), the weights (Q,) summing to 1, the gradient of
    :math:`\varphi` as coefficients of :math:`\nabla\lambda_j` (Q, 3), and
    :math:`\varphi` there (Q,).  Cached: a handful of masks and t per call.
    """
    funcs = _band_functions(fmask, vmask, t)
    # 2-d coordinates (x, y) = (lambda_1, lambda_2); lambda_0 = 1 - x - y
    flat = [(np.array([c[1] - c[0], c[2] - c[0]]), d + c[0]) for c, d in funcs]
    ref = [np.array([0.0, 0.0]), np.array([1.0, 0.0]), np.array([0.0, 1.0])]
    bary, w = triangle_rule(4)
    pts, wts, coef, phi = [], [], [], []
    for m, (am, bm) in enumerate(flat):
        poly = ref
        for n, (an, bn) in enumerate(flat):
            if n != m and len(poly) >= 3:
                poly = _clip(poly, am - an, bm - bn)
        for k in range(1, len(poly) - 1):  # fan of the piece
            p0, p1, p2 = poly[0], poly[k], poly[k + 1]
            frac = abs((p1[0] - p0[0]) * (p2[1] - p0[1]) - (p1[1] - p0[1]) * (p2[0] - p0[0]))
            if frac <= 1e-15:
                continue
            xy = bary[:, :1] * p0 + bary[:, 1:2] * p1 + bary[:, 2:3] * p2
            lam = np.column_stack([1.0 - xy.sum(axis=1), xy])
            c, d = funcs[m]
            pts.append(lam)
            wts.append(w * frac)
            coef.append(np.tile(c / t, (lam.shape[0], 1)))
            phi.append((lam @ c + d) / t)
    out = tuple(np.concatenate(v) for v in (pts, wts, coef, phi))
    for v in out:
        v.flags.writeable = False
    return out


def squeeze_terms(mesh, tri, gap_k, ell_k, mu_k, t, fmask=None, vmask=None):
    r"""Squeeze integrals of triangles ``tri`` for one band parameter t.

    Parameters
    ----------
    mesh : Mesh
    tri : int (Q,)
    gap_k, ell_k : float (Q, 3)
        Nodal values on each triangle of the gap (>= 0) and of the contact load.
    mu_k : float (Q,)
        Tension of the squeezed membrane.
    t : float
        Band parameter, > 0; 0: no squeeze (w = 0).
    fmask, vmask : int (Q,), optional
        The edges (bit j: the edge opposite vertex j) and vertices where
        :math:`\varphi` vanishes (:func:`band_phi`); default all edges, no vertex:
        :math:`\varphi_t = \min(1, \min_j\lambda_j / t)`, w = 0 on :math:`\partial K`.

    Returns
    -------
    eta_w : float (Q,)
        :math:`\mu_K^{1/2}\|\nabla w\|_K`, :math:`w = \mathrm{gap}_h\varphi`.
    c : float (Q,)
        :math:`(\ell, \mathrm{gap}_h - w)_K`.

    All integrands are polynomials of degree <= 3 on the pieces where
    :math:`\varphi` is linear: exact.
    """
    area = mesh.areas[tri]
    if t == 0.0:
        c = area / 12.0 * ((ell_k * gap_k).sum(axis=1) + ell_k.sum(axis=1) * gap_k.sum(axis=1))
        return np.zeros(tri.size), c
    key = np.full(tri.size, 7 * 8) if fmask is None else fmask * 8 + vmask
    eta_w = np.empty(tri.size)
    c = np.empty(tri.size)
    for kk in np.unique(key):  # at most 64 masks
        group = np.flatnonzero(key == kk)
        pts, wts, coef, phi = _band_rule(int(kk) // 8, int(kk) % 8, float(t))
        for lo in range(0, group.size, _CHUNK):  # chunks of triangles (memory)
            sl = group[lo : lo + _CHUNK]
            gr = mesh.gradients[tri[sl]]  # (q, 3, 2)
            g = gap_k[sl]
            gq = g @ pts.T  # (q, Q)
            grad_g = np.einsum("sb,sbd->sd", g, gr)
            grad_phi = np.einsum("pj,sjd->spd", coef, gr)
            grad_w = grad_g[:, None, :] * phi[None, :, None] + gq[..., None] * grad_phi
            eta_w[sl] = np.sqrt(mu_k[sl] * area[sl] * ((grad_w**2).sum(axis=2) @ wts))
            c[sl] = area[sl] * (((ell_k[sl] @ pts.T) * gq * (1.0 - phi)[None, :]) @ wts)
    return eta_w, c


def band_sets(mesh, tri, soft, gap):
    r"""Rims of the connected sets of squeezed triangles (the connected squeeze).

    Parameters
    ----------
    mesh : Mesh
    tri : int (Q,)
        The squeezed triangles.
    soft : int (Q,)
        The membrane squeezed on each (1 or 2).
    gap : float (N,)
        Nodal gap :math:`u_{1h} - u_{2h}` (>= 0 on ``tri``).

    Returns
    -------
    fmask, vmask : int64 (Q,)
        Per triangle, the *free* edges (bit j: the edge opposite vertex j) and the
        free vertices not on a free edge of the triangle.  An edge is free when
        the triangle across it does not squeeze the same membrane (or it lies on
        the boundary) and the gap is positive at one of its ends; a vertex is free
        when it ends a free edge of any triangle.
    comp : int64 (Q,)
        Connected set of each triangle (triangles joined by edges that both
        squeeze, same membrane).
    n_comp : int

    With one t per connected set, :math:`w = \mathrm{gap}_h\varphi` (:func:`band_phi`)
    is continuous: on a free edge it vanishes (:math:`\varphi = 0`, or the gap is 0
    at both ends); on an edge shared by two squeezed triangles,
    :math:`\varphi = \min(1, (1 - \lambda_p)/t, (1 - \lambda_q)/t)` over its free
    ends p, q, from both sides.
    """
    m = mesh.n_triangles
    t = mesh.triangles
    soft = np.asarray(soft, dtype=np.int8)
    et = mesh.edge_triangles[mesh.triangle_edges[tri]]  # (Q, 3, 2)
    other = np.where(et[..., 0] == tri[:, None], et[..., 1], et[..., 0])
    owner = np.zeros(m, dtype=np.int8)
    owner[tri] = soft
    same = (other >= 0) & (owner[np.maximum(other, 0)] == soft[:, None])
    gk = gap[t[tri]]
    nxt, prv = [1, 2, 0], [2, 0, 1]  # the ends of local edge j
    positive = np.maximum(gk[:, nxt], gk[:, prv]) > 0.0
    free = ~same & positive  # (Q, 3)
    free_v = np.zeros((2, mesh.n_vertices), dtype=bool)
    rows, j = np.nonzero(free)
    for ends in (nxt, prv):
        free_v[soft[rows] - 1, t[tri[rows], np.asarray(ends)[j]]] = True
    on_free_edge = free[:, prv] | free[:, nxt]  # vertex v ends local edges v+1 and v+2
    vin = free_v[soft[:, None] - 1, t[tri]] & ~on_free_edge
    bits = np.array([1, 2, 4])
    fmask = (free * bits).sum(axis=1).astype(np.int64)
    vmask = (vin * bits).sum(axis=1).astype(np.int64)
    row_of = np.full(m, -1, dtype=np.int64)
    row_of[tri] = np.arange(tri.size)
    r, j = np.nonzero(same)
    graph = coo_matrix((np.ones(r.size), (r, row_of[other[r, j]])), shape=(tri.size, tri.size))
    n_comp, comp = connected_components(graph, directed=False)
    return fmask, vmask, comp.astype(np.int64), int(n_comp)


def layer_terms(scene, layer: LayerLoad, u1, u2, lam, eta_f1, eta_f2, local, glob):
    """Squeeze terms and c of the layer bound, with the band chosen per triangle or per set.

    Returns ``local`` with ``eta_C`` replaced (c of the layer contact load and
    the squeezed gap) and ``eta_w1``, ``eta_w2`` added (zeros off the squeezed
    triangles).  Two kinds of band, each valid where it is used:

    * per triangle, w = 0 on the triangle's edges, t in :data:`SQUEEZE_T` chosen
      per triangle;
    * per connected set of squeezed triangles (:func:`band_sets`, with
      :data:`CONNECTED_BAND`), w = 0 on the set's rim only, one t in
      :data:`BAND_T` per set.

    Every connected set takes the per-triangle choice or one of the set's bands.
    The choices minimise a linearisation of the bound around the current one, a
    few sweeps, keeping the best bound met.
    """
    mesh = scene.mesh
    m = mesh.n_triangles
    gap = u1 - u2
    _, lam_minus = _lambda_parts(mesh, lam)
    eta_c = np.array(local["eta_C"], dtype=np.float64)
    eta_c[layer.tri] = 0.0  # closed triangles: the gap is <= 0 on K, the product vanishes
    q = layer.squeeze
    rows = np.searchsorted(layer.tri, q)
    ell = layer.chi[rows] + lam_minus[mesh.triangles[q]]
    gk = gap[mesh.triangles[q]]
    mu = np.where(layer.soft == 1, _per_triangle(scene.mu1, m)[q], _per_triangle(scene.mu2, m)[q])
    cols = [squeeze_terms(mesh, q, gk, ell, mu, t) for t in SQUEEZE_T]
    w_all = np.stack([cw[0] for cw in cols], axis=1)  # (Q, nt)
    c_all = np.stack([cw[1] for cw in cols], axis=1)
    base1 = np.asarray(local["eta_osc1"]) + eta_f1
    base2 = np.asarray(local["eta_osc2"]) + eta_f2 + np.asarray(local["eta_nc"])
    nc2 = float(np.asarray(local["eta_nc"]) @ np.asarray(local["eta_nc"]))
    glob_sum = math.hypot(float(glob["eta_glob1"]), float(glob["eta_glob2"]))
    on1 = layer.soft == 1
    base_q = np.where(on1, base1[q], base2[q])
    c_rest = float(eta_c.sum())
    d1 = base1.copy()
    d2 = base2.copy()
    # the split form's a: fluxes against u_h, without eta_nc and eta_w (split_form)
    plain2 = np.asarray(local["eta_osc2"]) + eta_f2
    a0 = math.sqrt(float(base1 @ base1) + float(plain2 @ plain2)) + glob_sum

    def bound(wk, ck):
        """(eta, linearisation data) of both forms for the squeeze terms wk, ck (Q,)."""
        d1[q] = np.where(on1, base1[q] + wk, base1[q])
        d2[q] = np.where(on1, base2[q], base2[q] + wk)
        big = math.sqrt(float(d1 @ d1) + float(d2 @ d2))
        a = big + glob_sum
        c = c_rest + float(ck.sum())
        s = math.sqrt(a * a + 4.0 * c)
        p = math.sqrt(nc2 + float(wk @ wk))
        joint = 0.5 * (a + s) + p
        split = split_form(a0, p, c)
        return min(joint, split), (big, a, s, p, c, joint, split)

    def costs(info, w_opt, c_opt):
        """Per-triangle cost of each option: the linearised eta of the form that is smaller."""
        big, a, s, p, c, joint, split = info
        if joint <= split:
            alpha = 0.5 * (1.0 + a / s) / (2.0 * big)  # d eta / d (d_K^2)
            beta = 1.0 / s  # d eta / d c
            gamma = 1.0 / (2.0 * p) if p > 0.0 else 0.0  # d eta / d (w_K^2)
            return alpha * (base_q[:, None] + w_opt) ** 2 + gamma * w_opt**2 + beta * c_opt
        big_a = a0 + p
        root = math.sqrt(big_a * big_a + 4.0 * (a0 * p + c))
        gamma = 0.5 * (1.0 + (big_a + 2.0 * a0) / root) / (2.0 * p) if p > 0.0 else 0.0
        return gamma * w_opt**2 + c_opt / root

    k = _choose(bound, costs, w_all, c_all)
    idx = np.arange(q.size)
    wk, ck = w_all[idx, k], c_all[idx, k]
    if CONNECTED_BAND and q.size:
        fmask, vmask, comp, n_comp = band_sets(mesh, q, layer.soft, gap)
        cols = [squeeze_terms(mesh, q, gk, ell, mu, t, fmask, vmask) for t in BAND_T]
        w_set = np.column_stack([wk] + [cw[0] for cw in cols])  # option 0: per triangle
        c_set = np.column_stack([ck] + [cw[1] for cw in cols])
        k = _choose(bound, costs, w_set, c_set, comp, n_comp)
        wk, ck = w_set[idx, k], c_set[idx, k]
    eta_w1 = np.zeros(m)
    eta_w2 = np.zeros(m)
    eta_w1[q[on1]] = wk[on1]
    eta_w2[q[~on1]] = wk[~on1]
    eta_c[q] = ck
    return {**local, "eta_C": eta_c, "eta_w1": eta_w1, "eta_w2": eta_w2}


def _choose(bound, costs, w_opt, c_opt, unit=None, n_units=0):
    """Option (column of ``w_opt``, ``c_opt``) per row, one per unit when ``unit`` is given.

    The best uniform option first, then sweeps that give every unit the option of
    least linearised cost (summed over its rows), kept while the bound decreases.
    """
    rows = np.arange(w_opt.shape[0])
    best, best_k = math.inf, None
    for j in range(w_opt.shape[1]):
        k = np.full(rows.size, j)
        val, _ = bound(w_opt[rows, k], c_opt[rows, k])
        if val < best:
            best, best_k = val, k
    k = best_k
    for _ in range(4):
        _, info = bound(w_opt[rows, k], c_opt[rows, k])
        cost = costs(info, w_opt, c_opt)
        if unit is None:
            k_new = cost.argmin(axis=1)
        else:
            per = np.stack([np.bincount(unit, col, n_units) for col in cost.T], axis=1)
            k_new = per.argmin(axis=1)[unit]
        val, _ = bound(w_opt[rows, k_new], c_opt[rows, k_new])
        if not val < best:
            break
        best, best_k, k = val, k_new, k_new
    return best_k
