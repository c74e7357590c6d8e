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
   width t along the edges.

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
i's term of a.  All integrals of w are exact (polynomials on the seven pieces
of K where :math:`\varphi_t` is linear, degree-4 rule).  The band parameter t
is chosen per triangle (any choice keeps the bound; it only trades c against
:math:`\eta_w`).  :func:`fastmem.bound.evaluate` returns the smaller of this
bound and the standard one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .estimators import _lambda_parts
from .quadrature import triangle_rule

__all__ = [
    "LAYER_BETA",
    "LAYER_BOUND",
    "LAYER_RATIO",
    "LayerLoad",
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
#: vertices of the direct z solves (above: AMG-preconditioned CG)
LAYER_DIRECT_VERTICES = 300_000
#: relative residual of the z solves by CG (the rest is carried by rho, so the bound holds)
LAYER_CG_TOL = 1e-10
_CHUNK = 20_000


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


def _projected_load(scene, i):
    r"""Nodal values per triangle (M, 3) of :math:`\\Pi_K f_i`."""
    from .loaddata import integrals

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


def layer_load(scene, u1, u2, lam) -> LayerLoad | None:
    """Layer contact load of a triple, or None when no triangle is a layer triangle.

    Only for per-triangle tensions (constant tensions: None).  ``lam`` is 0 on
    the boundary.
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
    from .flux import _T3

    mom = np.einsum("sk,ikj->sij", chi_s, _T3) - lam_k[:, :, None] * ((np.eye(3) + 1.0) / 12.0)
    mom *= area[:, None, None]
    osc1 = osc2 = None
    closed_rows = np.flatnonzero(closed[sel])
    if closed_rows.size and "callable" in (scene.data_kind("f1"), scene.data_kind("f2")):
        # callable loads: on the closed triangles (where c vanishes whatever the load's
        # form) the pressure is the glued one pointwise, not its P1 projection, so that
        # f1 + chi = mu1 (f1 + f2) / (mu1 + mu2) is what the soft membrane's oscillation
        # (weight mu_soft^-1/2) measures; moments and oscillation at the load rule's points
        mom[closed_rows], osc1, osc2 = _pointwise_closed(
            scene, sel[closed_rows], mu1, mu2, lam_k[closed_rows]
        )
    delta = np.bincount(t[sel].ravel(), weights=mom.sum(axis=2).ravel(), minlength=mesh.n_vertices)
    bnd = mesh.boundary_vertex_mask
    delta[bnd] = 0.0
    z1, eps1 = _solve(scene, 1, delta)
    z2, eps2 = _solve(scene, 2, -delta)
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
    )


def _pointwise_closed(scene, tri, mu1, mu2, lam_k):
    """Moments ``((chi - lam_a) psi_a, psi_j)_K`` and oscillations of ``f1 + chi``, ``f2 - chi``.

    With the pointwise glued pressure ``chi = (mu1 f2 - mu2 f1)^+ / (mu1 + mu2)`` at the
    points of the load rule (degree ``scene.load_degree``) of the triangles ``tri``.
    """
    from .flux import _load_values, _oscillation_at_points
    from .quadrature import quadrature_points

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
    h = mesh.diameters[tri] / np.pi
    osc1 = h / np.sqrt(mu1[tri]) * _oscillation_at_points(f1 + chi, bary, w, area)
    osc2 = h / np.sqrt(mu2[tri]) * _oscillation_at_points(f2 - chi, bary, w, area)
    return mom, osc1, osc2


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
    if key in cache:
        return cache[key]
    from scipy.sparse.linalg import splu

    inner = scene.mesh.interior_vertices
    a = scene.weighted_stiffness(i).tocsr()[inner][:, inner].tocsr()
    if scene.mesh.n_vertices <= LAYER_DIRECT_VERTICES:
        solve = splu(a.tocsc()).solve
    else:
        from scipy.sparse.linalg import cg

        from .amg import amg_preconditioner

        ml = amg_preconditioner(a)

        def solve(b):
            from scipy.sparse.linalg import LinearOperator

            pre = LinearOperator(a.shape, matvec=ml, dtype=np.float64)
            x, _ = cg(a, b, rtol=LAYER_CG_TOL, maxiter=200, M=pre)
            return x

    cache[key] = solve
    return solve


# --- the squeeze integrals -------------------------------------------------------------


def _sub_triangles(t):
    """Return the seven pieces of K where phi_t is linear, in barycentric coordinates (7, 3, 3)."""
    e = np.eye(3)
    p = [e[i] * (1.0 - 3.0 * t) + t for i in range(3)]  # corners of the inner triangle
    subs = [[p[0], p[1], p[2]]]
    for j in range(3):
        k, m = (j + 1) % 3, (j + 2) % 3
        subs.append([e[k], e[m], p[m]])
        subs.append([e[k], p[m], p[k]])
    return np.array(subs)


def _points(t):
    """Barycentric points (Q, 3) and weights (Q,) summing to 1 of the rule on the pieces."""
    bary, w = triangle_rule(4)
    subs = _sub_triangles(t)
    d1 = subs[:, 1, :2] - subs[:, 0, :2]
    d2 = subs[:, 2, :2] - subs[:, 0, :2]
    frac = np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    pts = np.einsum("qv,svb->sqb", bary, subs).reshape(-1, 3)
    wts = (frac[:, None] * w[None, :]).ravel()
    return pts, wts


def squeeze_terms(mesh, tri, gap_k, ell_k, mu_k, t):
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
        Band parameter in [0, 1/3); 0: no squeeze (w = 0).

    Returns
    -------
    eta_w : float (Q,)
        :math:`\mu_K^{1/2}\|\nabla w\|_K`.
    c : float (Q,)
        :math:`(\ell, \mathrm{gap}_h - w)_K`.
    """
    area = mesh.areas[tri]
    if t == 0.0:
        c = area / 12.0 * ((ell_k * gap_k).sum(axis=1) + ell_k.sum(axis=1) * gap_k.sum(axis=1))
        return np.zeros(tri.size), c
    pts, wts = _points(t)
    lmin = pts.min(axis=1)
    jmin = pts.argmin(axis=1)
    phi = np.minimum(1.0, lmin / t)
    band = lmin < t
    eta_w = np.empty(tri.size)
    c = np.empty(tri.size)
    for lo in range(0, tri.size, _CHUNK):  # chunks of triangles (memory), vectorised inside
        sl = slice(lo, lo + _CHUNK)
        gr = mesh.gradients[tri[sl]]  # (q, 3, 2)
        g = gap_k[sl]
        gq = g @ pts.T  # (q, Q)
        grad_g = np.einsum("sb,sbd->sd", g, gr)
        grad_phi = np.where(band[None, :, None], gr[:, jmin, :] / t, 0.0)  # (q, Q, 2)
        grad_w = grad_g[:, None, :] * phi[None, :, None] + gq[..., None] * grad_phi
        eta_w[sl] = np.sqrt(mu_k[sl] * area[sl] * ((grad_w**2).sum(axis=2) @ wts))
        c[sl] = area[sl] * (((ell_k[sl] @ pts.T) * gq * (1.0 - phi)[None, :]) @ wts)
    return eta_w, c


def layer_terms(scene, layer: LayerLoad, u1, u2, lam, eta_f1, eta_f2, local, glob):
    """Squeeze terms and c of the layer bound, with t chosen per triangle.

    Returns ``local`` with ``eta_C`` replaced (c of the layer contact load and
    the squeezed gap) and ``eta_w1``, ``eta_w2`` added (zeros off the squeezed
    triangles).  The choice of t minimises a linearisation of the bound around
    the current choice, a few sweeps, keeping the best bound met.
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

    def bound(k):
        wk = w_all[np.arange(q.size), k]
        d1[q] = np.where(on1, base1[q] + wk, base1[q])
        d2[q] = np.where(on1, base2[q], base2[q] + wk)
        big = math.sqrt(float(d1 @ d1) + float(d2 @ d2))
        a = big + glob_sum
        c = c_rest + float(c_all[np.arange(q.size), k].sum())
        s = math.sqrt(a * a + 4.0 * c)
        p = math.sqrt(nc2 + float(wk @ wk))
        return 0.5 * (a + s) + p, (big, a, s, p)

    # start from the best uniform t, then per-triangle sweeps
    best_k = None
    best = math.inf
    for j in range(len(SQUEEZE_T)):
        k = np.full(q.size, j)
        val, _ = bound(k)
        if val < best:
            best, best_k = val, k
    k = best_k
    for _ in range(4):
        _, (big, a, s, p) = bound(k)
        alpha = 0.5 * (1.0 + a / s) / (2.0 * big)  # d eta / d (d_K^2)
        beta = 1.0 / s  # d eta / d c
        gamma = 1.0 / (2.0 * p) if p > 0.0 else 0.0  # d eta / d (w_K^2)
        cost = alpha * (base_q[:, None] + w_all) ** 2 + gamma * w_all**2 + beta * c_all
        k_new = cost.argmin(axis=1)
        val, _ = bound(k_new)
        if not val < best:
            break
        best, best_k, k = val, k_new, k_new
    k = best_k
    wk = w_all[np.arange(q.size), k]
    eta_w1 = np.zeros(m)
    eta_w2 = np.zeros(m)
    eta_w1[q[on1]] = wk[on1]
    eta_w2[q[~on1]] = wk[~on1]
    eta_c[q] = c_all[np.arange(q.size), k]
    return {**local, "eta_C": eta_c, "eta_w1": eta_w1, "eta_w2": eta_w2}
