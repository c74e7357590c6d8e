"""Slow, plain NumPy/SciPy reference of the equilibrated flux reconstruction (MATH.md section 4).

Written independently of :mod:`fastmem.estimators.flux` (small meshes only, Python loops over
patches).  Each patch triangle carries the 8 coefficients of the canonical RT1
representation used by the package: on K with centroid (xc, yc), diameter h,
xi = (x - xc) / h, eta = (y - yc) / h,

    sigma_x = a0 + a1 xi + a2 eta + xi (c1 xi + c2 eta)
    sigma_y = b0 + b1 xi + b2 eta + eta (c1 xi + c2 eta)
    coef[K] = [a0, a1, a2, b0, b1, b2, c1, c2]

so the unknowns of a patch are 8 per triangle with no H(div) structure built in.
Normal continuity across patch-interior edges and zero normal flux on the
zero-flux part of the patch boundary are explicit linear constraints (sigma.n is
linear along an edge: its values at the two endpoints are equated / zeroed);
their null space (scipy.linalg.null_space) parametrises V^a.  Then

    min ||mu^(-1/2) (tau + sigma)||^2_{omega_a}  s.t.  (div sigma, q) = (g, q)  for all q in Q^a

(the mu-weighted norm of MATH.md section 4: ``(sigma, v)`` and ``(tau, v)`` carry
the factor 1 / mu_K triangle by triangle; ``weighted=False`` gives the unweighted
problem of earlier versions) is solved with a dense KKT system.  Integrals use a
collapsed (Duffy) Gauss rule written here, exact to degree 8, except integrals
of a callable load, which use the package's load rule
(``fastmem.fem.quadrature.triangle_rule(scene.load_degree)``) so that
the discrete compatibility (g, 1) = 0 of interior patches holds exactly
as for the load vector F.  Edge topology and P1 gradients are recomputed here
from ``mesh.vertices`` / ``mesh.triangles`` (not read from the package's mesh
topology).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from fastmem.fem.quadrature import triangle_rule
from fastmem.fem.residual import residuals


# --------------------------------------------------------------------- quadrature
def _duffy_rule(n=5):
    """Barycentric points and weights (sum 1) of a collapsed Gauss rule, exact to 2n - 2."""
    x, w = np.polynomial.legendre.leggauss(n)
    s, ws = 0.5 * (x + 1.0), 0.5 * w
    pts, wts = [], []
    for si, wsi in zip(s, ws, strict=False):
        for ti, wti in zip(s, ws, strict=False):
            px, py = si, ti * (1.0 - si)
            pts.append([1.0 - px - py, px, py])
            wts.append(2.0 * wsi * wti * (1.0 - si))  # reference area 1/2 -> weights sum to 1
    return np.array(pts), np.array(wts)


QUAD_BARY, QUAD_W = _duffy_rule(5)  # exact for degree <= 8


# --------------------------------------------------------------------- geometry
def _tri_geometry(vertices, tri):
    """Corners p (3, 2), area, centroid, diameter and barycentric map of one triangle."""
    p = vertices[tri]
    vand = np.column_stack([np.ones(3), p])
    area = 0.5 * abs(np.linalg.det(vand))
    inv = np.linalg.inv(vand)  # column i: coefficients (c, cx, cy) of phi_i = c + cx x + cy y
    grads = inv[1:, :].T  # (3, 2)
    cen = p.mean(axis=0)
    h = max(np.linalg.norm(p[i] - p[j]) for i in range(3) for j in range(i + 1, 3))
    return p, area, cen, h, inv, grads


def _basis(xi, eta):
    """Canonical RT1 basis values, shape (P, 8, 2)."""
    z = np.zeros_like(xi)
    o = np.ones_like(xi)
    bx = np.stack([o, xi, eta, z, z, z, xi * xi, xi * eta], axis=1)
    by = np.stack([z, z, z, o, xi, eta, xi * eta, eta * eta], axis=1)
    return np.stack([bx, by], axis=2)


def _basis_div(xi, eta, h):
    """Divergence of the canonical basis, shape (P, 8)."""
    z = np.zeros_like(xi)
    o = np.ones_like(xi)
    return np.stack([z, o, z, z, z, o, 3.0 * xi, 3.0 * eta], axis=1) / h


def _local(p, cen, h, bary):
    x = bary @ p
    return x, (x[:, 0] - cen[0]) / h, (x[:, 1] - cen[1]) / h


def _find_edges(triangles):
    """Dict (lo, hi) -> list of triangles containing that edge (whole mesh)."""
    owners = {}
    for k, t in enumerate(triangles):
        for i in range(3):
            a, b = int(t[(i + 1) % 3]), int(t[(i + 2) % 3])
            owners.setdefault((min(a, b), max(a, b)), []).append(k)
    return owners


def _eval_load(f, x, y):
    val = f(x, y)
    return np.broadcast_to(np.asarray(val, dtype=float), x.shape)


def _f_psi_q(f, tri, p, area, la, load_degree):
    """(f psi_a, phi_l)_K, l = 0..2, with psi_a = phi_la (local index la)."""
    if callable(f):
        bary, w = triangle_rule(load_degree)
        x = bary @ p
        fv = _eval_load(f, x[:, 0], x[:, 1])
    else:
        bary, w = QUAD_BARY, QUAD_W
        arr = np.asarray(f, dtype=float)
        fv = np.full(len(w), float(arr)) if arr.ndim == 0 else bary @ arr[tri]
    return area * (w * fv * bary[:, la]) @ bary


def _mu_on(mu, k):
    return float(mu) if np.ndim(mu) == 0 else float(np.asarray(mu)[k])


# --------------------------------------------------------------------- patch problem
def patch_problem(
    scene, a, u, lam_a, r_a, f, mu, owners=None, boundary=None, weighted=True, contact=None
):
    """Solve the RT1 patch problem of vertex ``a`` for one membrane.

    Parameters
    ----------
    u : nodal values of u_ih; lam_a : the signed contact term (+lam_a for membrane 1,
    -lam_a for membrane 2, 0 at boundary vertices); r_a : R_i,a (0 at boundary
    vertices); f, mu : the membrane's load and tension; weighted : minimise
    ``||mu^(-1/2) (tau + sigma)||`` (default) or ``||tau + sigma||``; contact :
    optional callable ``(k) -> (3,)`` giving the signed contact load of the
    patch on triangle k as values at its three vertices (a P1 function),
    used instead of ``lam_a psi_a``.

    Returns
    -------
    tris : list of triangle indices of the patch
    coef : ndarray (len(tris), 8) canonical coefficients of sigma_i^a
    zero_edges : list of (lo, hi) vertex pairs of the zero-flux edges
    """
    mesh = scene.mesh
    vertices, triangles = mesh.vertices, mesh.triangles
    if owners is None:
        owners = _find_edges(triangles)
    if boundary is None:
        boundary = _boundary_vertices(owners, mesh.n_vertices)
    tris = [k for k in range(len(triangles)) if a in triangles[k]]
    n = len(tris)
    idx = {k: j for j, k in enumerate(tris)}
    geo = {k: _tri_geometry(vertices, triangles[k]) for k in tris}
    b_a = sum(geo[k][1] for k in tris) / 3.0
    interior = not boundary[a]

    mass = np.zeros((8 * n, 8 * n))
    lin = np.zeros(8 * n)  # (tau, phi_j)
    div = np.zeros((3 * n, 8 * n))  # (div phi_j, q_l)
    rhs = np.zeros(3 * n)  # (g, q_l)
    qmean = np.zeros(3 * n)  # (q_l, 1)
    for k in tris:
        j = idx[k]
        p, area, cen, h, inv, grads = geo[k]
        tri = triangles[k]
        la = int(np.flatnonzero(tri == a)[0])
        mu_k = _mu_on(mu, k)
        grad_u = grads.T @ u[tri]
        x, xi, eta = _local(p, cen, h, QUAD_BARY)
        phi = _basis(xi, eta)  # (P, 8, 2)
        dphi = _basis_div(xi, eta, h)  # (P, 8)
        psi = QUAD_BARY[:, la]
        w = area * QUAD_W
        sl = slice(8 * j, 8 * j + 8)
        wk = 1.0 / mu_k if weighted else 1.0  # weight of the patch norm on K
        mass[sl, sl] = wk * np.einsum("p,pic,pjc->ij", w, phi, phi)
        tau = mu_k * psi[:, None] * grad_u[None, :]  # (P, 2)
        lin[sl] = wk * np.einsum("p,pic,pc->i", w, phi, tau)
        ql = slice(3 * j, 3 * j + 3)
        div[ql, sl] = np.einsum("p,pl,pi->li", w, QUAD_BARY, dphi)
        # g = psi_a f - mu grad psi_a . grad u + (lam_a - R_a / B_a) psi_a
        if contact is None:
            gp = -mu_k * grads[la] @ grad_u + (lam_a - r_a / b_a) * psi
        else:
            gp = -mu_k * grads[la] @ grad_u - r_a / b_a * psi + QUAD_BARY @ contact(k)
        rhs[ql] = np.einsum("p,pl,p->l", w, QUAD_BARY, gp)
        rhs[ql] += _f_psi_q(f, tri, p, area, la, scene.load_degree)
        qmean[ql] = area / 3.0

    # Constraints on the 8n coefficients: continuity / zero flux of sigma.n at edge endpoints.
    rows = []
    zero_edges = []
    patch_edges = {}
    for k in tris:
        t = triangles[k]
        for i in range(3):
            e = (
                min(int(t[(i + 1) % 3]), int(t[(i + 2) % 3])),
                max(int(t[(i + 1) % 3]), int(t[(i + 2) % 3])),
            )
            patch_edges.setdefault(e, []).append(k)
    for e, ks in patch_edges.items():
        on_domain_boundary = len(owners[e]) == 1
        if len(ks) == 1 and on_domain_boundary and not interior:
            continue  # free normal flux on the domain boundary (boundary vertex only)
        if len(ks) == 1:
            zero_edges.append(e)
        tvec = vertices[e[1]] - vertices[e[0]]
        normal = np.array([tvec[1], -tvec[0]]) / np.linalg.norm(tvec)
        for v in e:
            row = np.zeros(8 * n)
            for sign, k in zip((1.0, -1.0), ks, strict=False):
                p, area, cen, h, inv, grads = geo[k]
                xi = np.array([(vertices[v, 0] - cen[0]) / h])
                eta = np.array([(vertices[v, 1] - cen[1]) / h])
                row[8 * idx[k] : 8 * idx[k] + 8] = sign * (_basis(xi, eta)[0] @ normal)
            rows.append(row)
    cons = np.array(rows)
    null = sla.null_space(cons) if len(rows) else np.eye(8 * n)

    if interior:
        wq = sla.null_space(qmean[None, :])  # mean-zero test functions
        e_mat = wq.T @ div @ null
        g_vec = wq.T @ rhs
    else:
        e_mat = div @ null
        g_vec = rhs
    m_red = null.T @ mass @ null
    nv, nq = m_red.shape[0], e_mat.shape[0]
    kkt = np.zeros((nv + nq, nv + nq))
    kkt[:nv, :nv] = m_red
    kkt[:nv, nv:] = e_mat.T
    kkt[nv:, :nv] = e_mat
    sol = np.linalg.solve(kkt, np.concatenate([-null.T @ lin, g_vec]))
    coef = (null @ sol[:nv]).reshape(n, 8)
    return tris, coef, zero_edges


def _boundary_vertices(owners, n_vertices):
    bnd = np.zeros(n_vertices, dtype=bool)
    for e, ks in owners.items():
        if len(ks) == 1:
            bnd[list(e)] = True
    return bnd


def naive_reconstruct(
    scene, u1, u2, lam, r1=None, r2=None, return_patches=False, weighted=True, contact=None
):
    """Equilibrated fluxes sigma_1h, sigma_2h in the canonical representation.

    ``weighted``: patch problems in the mu-weighted norm (default) or unweighted.
    ``contact``: optional dict ``a -> (k -> (3,))``: the contact load of the patch
    of a on triangle k (vertex values, membrane 1's sign; membrane 2 gets its
    negative) instead of ``lam_a psi_a``; vertices not in the dict keep it.

    Returns ``(coef1, coef2)``, each of shape (M, 8); with ``return_patches=True``
    also a list ``patches`` of ``(a, i, tris, coef_a, zero_edges)`` (i = 0, 1).
    """
    mesh = scene.mesh
    u1, u2, lam = (np.asarray(v, dtype=float) for v in (u1, u2, lam))
    if r1 is None or r2 is None:
        rr1, rr2 = residuals(scene, u1, u2, lam)
        r1 = rr1 if r1 is None else r1
        r2 = rr2 if r2 is None else r2
    owners = _find_edges(mesh.triangles)
    boundary = _boundary_vertices(owners, mesh.n_vertices)
    out = [np.zeros((mesh.n_triangles, 8)) for _ in range(2)]
    patches = []
    data = ((u1, 1.0, r1, scene.f1, scene.mu1), (u2, -1.0, r2, scene.f2, scene.mu2))
    for a in range(mesh.n_vertices):
        for i, (u, sgn, r, f, mu) in enumerate(data):
            lam_a = 0.0 if boundary[a] else sgn * lam[a]
            piece = None if contact is None else contact.get(a)
            hook = None if piece is None else (lambda k, piece=piece, sgn=sgn: sgn * piece(k))
            r_a = 0.0 if boundary[a] else r[a]
            tris, coef, zero_edges = patch_problem(
                scene, a, u, lam_a, r_a, f, mu, owners, boundary, weighted, hook
            )
            out[i][tris] += coef
            if return_patches:
                patches.append((a, i, tris, coef, zero_edges))
    if return_patches:
        return out[0], out[1], patches
    return out[0], out[1]


# --------------------------------------------------------------------- evaluation
def _local_coords(mesh, tri, x, y):
    tri = np.asarray(tri)
    p = mesh.vertices[mesh.triangles[tri]]  # (P, 3, 2)
    cen = p.mean(axis=1)
    d = np.stack([p[:, 1] - p[:, 2], p[:, 2] - p[:, 0], p[:, 0] - p[:, 1]], axis=1)
    h = np.sqrt((d**2).sum(axis=2)).max(axis=1)
    xi = (np.asarray(x, dtype=float) - cen[:, 0]) / h
    eta = (np.asarray(y, dtype=float) - cen[:, 1]) / h
    return xi, eta, h


def evaluate(mesh, coef, tri, x, y):
    """sigma at points (x, y) of triangles tri (arrays of equal length P): shape (P, 2)."""
    tri = np.atleast_1d(tri)
    xi, eta, _ = _local_coords(mesh, tri, np.atleast_1d(x), np.atleast_1d(y))
    return np.einsum("pic,pi->pc", _basis(xi, eta), coef[tri])


def divergence(mesh, coef, tri, x, y):
    """div sigma at points (x, y) of triangles tri: shape (P,)."""
    tri = np.atleast_1d(tri)
    xi, eta, h = _local_coords(mesh, tri, np.atleast_1d(x), np.atleast_1d(y))
    c = coef[tri]
    return (c[:, 1] + c[:, 5] + 3.0 * c[:, 6] * xi + 3.0 * c[:, 7] * eta) / h
