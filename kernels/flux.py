"""Equilibrated flux reconstruction: RT1 mixed problems on vertex patches, in parallel.

For vertex a the patch system (MATH.md section 4) in the dof basis of
:mod:`.rt1` is the symmetric saddle-point matrix

    [  M   -D^T   0 ] [sigma]   [ -T_i ]
    [ -D    0     c ] [  r  ] = [ -G_i ]          (c: only for interior vertices)
    [  0    c^T   0 ] [  s  ]   [  0   ]

with M the RT1 mass on the patch, D the divergence-P1 coupling, c_q = (1, q)
(the multiplier s enforces mean-zero r for interior vertices; it vanishes for
compatible data), T_i = (tau_i^a, v) and G_i = (g_i^a, q).  Both membranes
share the matrix: one factorisation, two right-hand sides.  The system is
solved by block elimination (:func:`_saddle_solve`): Cholesky of the SPD RT1
mass, then Cholesky of the Schur complement on the multipliers, in place in a
per-thread workspace (no LAPACK call, no allocation per patch).

Factorisation reuse policy: none, deliberately.  The factors of an interior
patch of a structured mesh (24 flux and 18 multiplier dofs) take about 900
doubles (7 KB) per vertex, i.e. 7.6 GB at n = 1024 and 30 GB at n = 2048,
while the factorisation is only 38 % of the per-patch time (6.5 of 17 us,
measured at n = 512 on one thread); the rest (the RT1 locals and the
right-hand side) would have to be recomputed anyway.  Re-estimating the same
mesh therefore costs the same as the first estimate, minus the colouring and
the load moments, which are cached on the mesh and the scene.

Patch edges: an edge containing a carries two dofs (shared by its two patch
triangles, or free when it lies on the boundary of the domain); the edge
opposite a carries none (zero normal flux) unless a is a boundary vertex and
the edge lies on the boundary (free).  Interior vertices have zero normal flux
on their whole patch boundary and the mean-zero multiplier space.

Threading: vertices are processed by colour classes of a proper colouring of
the vertex graph; no two vertices of one class share a triangle, so each
patch adds its sigma^a straight into the rows of its own triangles without
races, and the result does not depend on the number of threads.
"""

import numpy as np
from numba import prange

from ._jit import jit, pjit
from .rt1 import SCRATCH_SIZE, rt1_local

__all__ = ["color_vertices", "flux_estimators", "reconstruct_colored"]


@jit
def color_vertices(n, indptr, indices):
    """Greedy proper colouring of the vertex graph (CSR adjacency, diagonal included).

    Returns
    -------
    colors : int64 (n,)
    n_colors : int
    """
    colors = np.full(n, -1, dtype=np.int64)
    n_colors = 0
    used = np.full(64, -1, dtype=np.int64)
    for a in range(n):
        for k in range(indptr[a], indptr[a + 1]):
            b = indices[k]
            if b != a and colors[b] >= 0 and colors[b] < 64:
                used[colors[b]] = a
        c = 0
        while c < 64 and used[c] == a:
            c += 1
        colors[a] = c
        if c + 1 > n_colors:
            n_colors = c + 1
    return colors, n_colors


@jit
def _cholesky(a, n):
    """In-place lower Cholesky factor of the leading n x n block of a (upper part untouched).

    Returns False if a pivot is not positive (the block is not SPD).
    """
    for j in range(n):
        d = a[j, j]
        for k in range(j):
            d -= a[j, k] * a[j, k]
        if not d > 0.0:
            return False
        d = np.sqrt(d)
        a[j, j] = d
        inv = 1.0 / d
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s -= a[i, k] * a[j, k]
            a[i, j] = s * inv
    return True


@jit
def _lower_solve2(lo, b, n):
    """In place ``b <- L^-1 b`` for the lower factor in ``lo`` and two columns of b."""
    for k in range(n):
        s0 = b[k, 0]
        s1 = b[k, 1]
        for m in range(k):
            s0 -= lo[k, m] * b[m, 0]
            s1 -= lo[k, m] * b[m, 1]
        b[k, 0] = s0 / lo[k, k]
        b[k, 1] = s1 / lo[k, k]


@jit
def _upper_solve2(lo, b, n):
    """In place ``b <- L^-T b`` for the lower factor in ``lo`` and two columns of b."""
    for k in range(n - 1, -1, -1):
        s0 = b[k, 0]
        s1 = b[k, 1]
        for m in range(k + 1, n):
            s0 -= lo[m, k] * b[m, 0]
            s1 -= lo[m, k] * b[m, 1]
        b[k, 0] = s0 / lo[k, k]
        b[k, 1] = s1 / lo[k, k]


@jit
def _saddle_solve(mat, dmat, smat, rs, rq, cvec, n_sig, n_q, interior):
    """Solve the symmetric patch saddle-point system by block elimination, in place.

    System (both membranes, two right-hand-side columns)::

        M sigma - D^T r = rs        (rs = -T)
        D sigma         = rq        (rq = G, plus c s for interior patches)

    with M (n_sig x n_sig) SPD.  With M = L L^T, Y = L^-1 D^T and t = L^-1 rs:
    S r = rq - Y^T t with S = Y^T Y, then sigma = L^-T (Y r + t).  For an
    interior patch S has the constants in its kernel (zero normal flux on the
    whole patch boundary) and the data are compatible (sum of rq = 0), so the
    mean-zero multiplier solves (S + alpha c c^T) r = rq - Y^T t.

    On return ``rs`` holds sigma and ``rq`` the multiplier r.
    """
    _cholesky(mat, n_sig)
    # Y^T rows: solve L y = D[q, :]^T for each q, skipping the leading zeros
    for q in range(n_q):
        row = dmat[q]
        k0 = 0
        while k0 < n_sig and row[k0] == 0.0:
            k0 += 1
        for k in range(k0, n_sig):
            s = row[k]
            for m in range(k0, k):
                s -= mat[k, m] * row[m]
            row[k] = s / mat[k, k]
    _lower_solve2(mat, rs, n_sig)  # t = L^-1 rs
    # Schur complement (lower triangle) and reduced right-hand side
    for q1 in range(n_q):
        y1 = dmat[q1]
        for q2 in range(q1 + 1):
            y2 = dmat[q2]
            s = 0.0
            for k in range(n_sig):
                s += y1[k] * y2[k]
            smat[q1, q2] = s
        b0 = 0.0
        b1 = 0.0
        for k in range(n_sig):
            b0 += y1[k] * rs[k, 0]
            b1 += y1[k] * rs[k, 1]
        rq[q1, 0] -= b0
        rq[q1, 1] -= b1
    if interior:
        tr = 0.0
        cc = 0.0
        for q in range(n_q):
            tr += smat[q, q]
            cc += cvec[q] * cvec[q]
        alpha = tr / cc
        for q1 in range(n_q):
            for q2 in range(q1 + 1):
                smat[q1, q2] += alpha * cvec[q1] * cvec[q2]
    _cholesky(smat, n_q)
    _lower_solve2(smat, rq, n_q)  # r = S^-1 b
    _upper_solve2(smat, rq, n_q)
    # sigma = L^-T (Y r + t)
    for q in range(n_q):
        y = dmat[q]
        r0 = rq[q, 0]
        r1 = rq[q, 1]
        for k in range(n_sig):
            rs[k, 0] += y[k] * r0
            rs[k, 1] += y[k] * r1
    _upper_solve2(mat, rs, n_sig)


@jit
def _patch_solve(
    a,
    vertices,
    triangles,
    diameters,
    tri_edges,
    edge_tris,
    boundary,
    patch_ptr,
    patch_triangles,
    patch_local,
    u1,
    u2,
    lam,
    rho1,
    rho2,
    mu1,
    mu2,
    f1c,
    f2c,
    load1,
    load2,
    bary,
    weights,
    out,
    iwork,
    fwork,
):
    pstart = patch_ptr[a]
    nt = patch_ptr[a + 1] - pstart
    interior = not boundary[a]
    # --- workspace views (no allocation per patch)
    edge_ids = iwork[0 : 3 * nt]
    loc2patch = iwork[3 * nt : 11 * nt].reshape((nt, 8))
    loc2patch[:, :] = -1
    ne = 0
    for p in range(nt):
        t = patch_triangles[pstart + p]
        i = patch_local[pstart + p]
        for k in range(3):
            e = tri_edges[t, k]
            on_bnd = edge_tris[e, 1] < 0
            if k == i and not (on_bnd and not interior):
                continue  # zero normal flux on this patch-boundary edge
            s = -1
            for q in range(ne):
                if edge_ids[q] == e:
                    s = q
                    break
            if s < 0:
                edge_ids[ne] = e
                s = ne
                ne += 1
            loc2patch[p, 2 * k] = 2 * s
            loc2patch[p, 2 * k + 1] = 2 * s + 1
    n_sig = 2 * ne + 2 * nt
    for p in range(nt):
        loc2patch[p, 6] = 2 * ne + 2 * p
        loc2patch[p, 7] = 2 * ne + 2 * p + 1
    n_q = 3 * nt
    o = 0
    mat = fwork[o : o + n_sig * n_sig].reshape((n_sig, n_sig))  # RT1 mass, then its Cholesky
    o += n_sig * n_sig
    dmat = fwork[o : o + n_q * n_sig].reshape((n_q, n_sig))  # D, then Y^T = (L^-1 D^T)^T
    o += n_q * n_sig
    smat = fwork[o : o + n_q * n_q].reshape((n_q, n_q))  # Schur complement D M^-1 D^T
    o += n_q * n_q
    rs = fwork[o : o + 2 * n_sig].reshape((n_sig, 2))  # -T, then L^-1 (-T), then sigma
    o += 2 * n_sig
    rq = fwork[o : o + 2 * n_q].reshape((n_q, 2))  # -G, then the multiplier r
    o += 2 * n_q
    cvec = fwork[o : o + n_q]  # mean-value functional (interior patches)
    o += n_q
    mat[:, :] = 0.0
    dmat[:, :] = 0.0
    rs[:, :] = 0.0
    rq[:, :] = 0.0
    coefs = fwork[o : o + 64 * nt].reshape((nt, 8, 8))
    o += 64 * nt
    pts = fwork[o : o + 6].reshape((3, 2))
    mass = fwork[o + 6 : o + 70].reshape((8, 8))
    div = fwork[o + 70 : o + 94].reshape((3, 8))
    tau = fwork[o + 94 : o + 142].reshape((3, 2, 8))
    work = fwork[o + 142 : o + 158].reshape((8, 2))
    gx = fwork[o + 158 : o + 161]
    gy = fwork[o + 161 : o + 164]
    scratch = fwork[o + 164 : o + 164 + SCRATCH_SIZE]
    lam_a = 0.0 if not interior else lam[a]
    r1a = 0.0 if not interior else rho1[a]
    r2a = 0.0 if not interior else rho2[a]
    for p in range(nt):
        t = patch_triangles[pstart + p]
        i = patch_local[pstart + p]
        tri = triangles[t]
        for v in range(3):
            pts[v, 0] = vertices[tri[v], 0]
            pts[v, 1] = vertices[tri[v], 1]
        area = rt1_local(
            pts, tri, diameters[t], bary, weights, coefs[p], mass, div, tau, work, scratch
        )
        # gradients of the hat functions: rot(edge opposite) / (2|K|)
        for v in range(3):
            ia = (v + 1) % 3
            ib = (v + 2) % 3
            gx[v] = -(pts[ib, 1] - pts[ia, 1]) / (2.0 * area)
            gy[v] = (pts[ib, 0] - pts[ia, 0]) / (2.0 * area)
        du1x = u1[tri[0]] * gx[0] + u1[tri[1]] * gx[1] + u1[tri[2]] * gx[2]
        du1y = u1[tri[0]] * gy[0] + u1[tri[1]] * gy[1] + u1[tri[2]] * gy[2]
        du2x = u2[tri[0]] * gx[0] + u2[tri[1]] * gx[1] + u2[tri[2]] * gx[2]
        du2y = u2[tri[0]] * gy[0] + u2[tri[1]] * gy[1] + u2[tri[2]] * gy[2]
        m1 = mu1[0] if mu1.shape[0] == 1 else mu1[t]
        m2 = mu2[0] if mu2.shape[0] == 1 else mu2[t]
        # sigma-sigma block and the flux target -(tau, v), tau = mu psi_a grad u
        for r in range(8):
            pr = loc2patch[p, r]
            if pr < 0:
                continue
            for c in range(8):
                pc = loc2patch[p, c]
                if pc >= 0:
                    mat[pr, pc] += mass[r, c]
            rs[pr, 0] -= m1 * (du1x * tau[i, 0, r] + du1y * tau[i, 1, r])
            rs[pr, 1] -= m2 * (du2x * tau[i, 0, r] + du2y * tau[i, 1, r])
        # divergence coupling (block D, one triangle's rows), data (g, q)
        q0 = 3 * p
        dot1 = m1 * (gx[i] * du1x + gy[i] * du1y)
        dot2 = m2 * (gx[i] * du2x + gy[i] * du2y)
        for j in range(3):
            for c in range(8):
                pc = loc2patch[p, c]
                if pc >= 0:
                    dmat[q0 + j, pc] = div[j, c]
            mij = area / 12.0 * (2.0 if j == i else 1.0)  # int psi_a lambda_j
            if load1.shape[0] == 1:
                l1 = f1c * mij
            else:
                l1 = load1[t, i, j]
            if load2.shape[0] == 1:
                l2 = f2c * mij
            else:
                l2 = load2[t, i, j]
            rq[q0 + j, 0] = l1 - dot1 * area / 3.0 + (lam_a - r1a) * mij
            rq[q0 + j, 1] = l2 - dot2 * area / 3.0 + (-lam_a - r2a) * mij
            cvec[q0 + j] = area / 3.0
    _saddle_solve(mat, dmat, smat, rs, rq, cvec, n_sig, n_q, interior)
    sol = rs
    # add sigma^a to the canonical coefficients of each patch triangle
    for p in range(nt):
        t = patch_triangles[pstart + p]
        for m in range(8):
            s1 = 0.0
            s2 = 0.0
            for r in range(8):
                pr = loc2patch[p, r]
                if pr >= 0:
                    s1 += coefs[p, m, r] * sol[pr, 0]
                    s2 += coefs[p, m, r] * sol[pr, 1]
            out[0, t, m] += s1
            out[1, t, m] += s2


@pjit
def reconstruct_colored(
    order,
    color_ptr,
    vertices,
    triangles,
    diameters,
    tri_edges,
    edge_tris,
    boundary,
    patch_ptr,
    patch_triangles,
    patch_local,
    u1,
    u2,
    lam,
    rho1,
    rho2,
    mu1,
    mu2,
    f1c,
    f2c,
    load1,
    load2,
    bary,
    weights,
    max_nt,
    n_chunks_hint,
):
    """Equilibrated fluxes of both membranes, canonical RT1 coefficients (2, M, 8).

    Parameters
    ----------
    order, color_ptr : int64
        Vertices sorted by colour; class c is ``order[color_ptr[c]:color_ptr[c+1]]``.
    vertices, triangles, diameters, tri_edges, edge_tris, boundary :
        Mesh arrays (boundary: bool mask of boundary vertices).
    patch_ptr, patch_triangles, patch_local : int64
        Vertex patches (CSR).
    u1, u2, lam : float64 (N,)
        Nodal values of the triple.
    rho1, rho2 : float64 (N,)
        Nodal ``R_i,a / B_a`` (zero on the boundary).
    mu1, mu2 : float64 (1,) or (M,)
        Tensions.
    f1c, f2c : float
        Constant loads, used when ``load1``/``load2`` has shape (1, 3, 3).
    load1, load2 : float64 (M, 3, 3) or (1, 3, 3)
        Load moments ``int_K f lambda_i lambda_j`` for non-constant data.
    bary, weights : float64
        Quadrature rule exact for degree 4.
    max_nt : int
        Largest number of triangles in a patch (sizes the workspaces).
    n_chunks_hint : int
        Number of threads; each colour class is cut into 8 chunks per thread,
        each with its own preallocated workspace.

    Threading: parallel over the vertices of one colour class at a time; a
    patch writes only the rows of its own triangles, which no other vertex of
    the class touches.
    """
    m = triangles.shape[0]
    out = np.zeros((2, m, 8))
    n_sig = 6 * max_nt + 2  # bound on the flux dofs (<= 2 nt + 1 dof edges, 2 per triangle)
    n_q = 3 * max_nt
    f_size = (n_sig + n_q) * (n_sig + n_q + 2) + n_q + 64 * max_nt + 164 + SCRATCH_SIZE
    for c in range(color_ptr.shape[0] - 1):
        lo = color_ptr[c]
        count = color_ptr[c + 1] - lo
        n_chunks = min(count, 8 * n_chunks_hint)
        for ch in prange(n_chunks):
            # one workspace per chunk: no allocation inside the patch loop
            iwork = np.empty(11 * max_nt, dtype=np.int64)
            fwork = np.empty(f_size)
            k0 = lo + (count * ch) // n_chunks
            k1 = lo + (count * (ch + 1)) // n_chunks
            for k in range(k0, k1):
                _patch_solve(
                    order[k],
                    vertices,
                    triangles,
                    diameters,
                    tri_edges,
                    edge_tris,
                    boundary,
                    patch_ptr,
                    patch_triangles,
                    patch_local,
                    u1,
                    u2,
                    lam,
                    rho1,
                    rho2,
                    mu1,
                    mu2,
                    f1c,
                    f2c,
                    load1,
                    load2,
                    bary,
                    weights,
                    out,
                    iwork,
                    fwork,
                )
    return out


@pjit
def flux_estimators(vertices, triangles, diameters, coef, u1, u2, mu1, mu2, bary, weights):
    """Per-triangle ``|| mu_i^(1/2) grad u_ih + mu_i^(-1/2) sigma_ih ||_K``, shape (2, M).

    ``coef`` (2, M, 8) holds the canonical RT1 coefficients (see :mod:`.rt1`);
    the rule must be exact for degree 4 (the integrand's degree).

    Threading: parallel over triangles, each writes its own column.
    """
    m = triangles.shape[0]
    out = np.empty((2, m))
    for t in prange(m):
        i0, i1, i2 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        x0, y0 = vertices[i0, 0], vertices[i0, 1]
        x1, y1 = vertices[i1, 0], vertices[i1, 1]
        x2, y2 = vertices[i2, 0], vertices[i2, 1]
        area2 = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        xc = (x0 + x1 + x2) / 3.0
        yc = (y0 + y1 + y2) / 3.0
        h = diameters[t]
        # grad(phi_v) = rot(edge opposite v) / (2|K|)
        g0x, g0y = -(y2 - y1) / area2, (x2 - x1) / area2
        g1x, g1y = -(y0 - y2) / area2, (x0 - x2) / area2
        g2x, g2y = -(y1 - y0) / area2, (x1 - x0) / area2
        for i in range(2):
            u = u1 if i == 0 else u2
            mu_arr = mu1 if i == 0 else mu2
            mu = mu_arr[0] if mu_arr.shape[0] == 1 else mu_arr[t]
            smu = np.sqrt(mu)
            gx = u[i0] * g0x + u[i1] * g1x + u[i2] * g2x
            gy = u[i0] * g0y + u[i1] * g1y + u[i2] * g2y
            c = coef[i, t]
            acc = 0.0
            for q in range(weights.shape[0]):
                xq = bary[q, 0] * x0 + bary[q, 1] * x1 + bary[q, 2] * x2
                yq = bary[q, 0] * y0 + bary[q, 1] * y1 + bary[q, 2] * y2
                xi = (xq - xc) / h
                eta = (yq - yc) / h
                quad = c[6] * xi + c[7] * eta
                sx = c[0] + c[1] * xi + c[2] * eta + xi * quad
                sy = c[3] + c[4] * xi + c[5] * eta + eta * quad
                dx = smu * gx + sx / smu
                dy = smu * gy + sy / smu
                acc += weights[q] * (dx * dx + dy * dy)
            out[i, t] = np.sqrt(0.5 * abs(area2) * acc)
    return out
