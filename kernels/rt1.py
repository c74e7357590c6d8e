"""Raviart-Thomas RT1 on a triangle: canonical coefficients and the dof-based local basis.

Canonical representation (shared by every fastmem module that touches fluxes).
On triangle K with centroid (xc, yc) and diameter h, with scaled coordinates
xi = (x - xc) / h, eta = (y - yc) / h, a field of RT1(K) = P1(K)^2 + x P1(K)
is written

    sigma_x = a0 + a1 xi + a2 eta + xi  (c1 xi + c2 eta)
    sigma_y = b0 + b1 xi + b2 eta + eta (c1 xi + c2 eta)

with coefficients ``[a0, a1, a2, b0, b1, b2, c1, c2]``, so that
``div sigma = (a1 + b2 + 3 c1 xi + 3 c2 eta) / h``.  The monomial fields of this
basis are numbered 0..7 in that order.

Local degrees of freedom (H(div)-conforming through the global edge
orientation): for local edge k (opposite local vertex k) with global end
points lo < hi and t = p_hi - p_lo, the two dofs are ``sigma(p_lo) . (t_y, -t_x)``
and ``sigma(p_hi) . (t_y, -t_x)`` (|E| times the normal component at each end,
normal to the right of lo -> hi); the two interior dofs are
``(h / |K|) int_K sigma``.  Both triangles sharing an edge compute the same
functionals, so equal dof values give equal (linear) normal traces.
"""


from ._jit import jit

__all__ = ["SCRATCH_SIZE", "monomial_values", "rt1_local"]

#: Length of the scratch array :func:`rt1_local` needs.
SCRATCH_SIZE = 264


@jit
def monomial_values(xi, eta, out):
    """Values of the 8 canonical monomial fields at one scaled point: out (8, 2)."""
    out[:, :] = 0.0
    out[0, 0] = 1.0
    out[1, 0] = xi
    out[2, 0] = eta
    out[3, 1] = 1.0
    out[4, 1] = xi
    out[5, 1] = eta
    out[6, 0] = xi * xi
    out[6, 1] = xi * eta
    out[7, 0] = xi * eta
    out[7, 1] = eta * eta


@jit
def rt1_local(p, tri, h, bary, weights, coef_out, mass_out, div_out, tau_out, work, scratch):
    """Local RT1 quantities of one triangle in its dof basis.

    Parameters
    ----------
    p : float64 (3, 2)
        Vertex coordinates (counter-clockwise).
    tri : int64 (3,)
        Global vertex indices (for the edge orientation).
    h : float
        Diameter of the triangle (the scaling of the canonical coordinates).
    bary, weights : float64 (nq, 3), (nq,)
        A quadrature rule exact for degree 4 (weights sum to 1).
    coef_out : float64 (8, 8)
        Out: column j = canonical coefficients of local basis function j.
    mass_out : float64 (8, 8)
        Out: ``int_K phi_i . phi_j``.
    div_out : float64 (3, 8)
        Out: ``int_K div(phi_j) lambda_q`` for the barycentric P1 basis lambda_q.
    tau_out : float64 (3, 2, 8)
        Out: ``int_K lambda_q phi_j`` (vector), for the flux target terms.
    work : float64 (8, 2)
        Scratch.
    scratch : float64 (SCRATCH_SIZE,)
        Scratch (no allocation happens inside this function).

    Returns
    -------
    area : float
    """
    x0, y0 = p[0, 0], p[0, 1]
    x1, y1 = p[1, 0], p[1, 1]
    x2, y2 = p[2, 0], p[2, 1]
    area = 0.5 * ((x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0))
    xc = (x0 + x1 + x2) / 3.0
    yc = (y0 + y1 + y2) / 3.0
    g = scratch[0:64].reshape((8, 8))
    mass_m = scratch[64:128].reshape((8, 8))
    div_m = scratch[128:152].reshape((3, 8))
    tau_m = scratch[152:200].reshape((3, 2, 8))
    tmp = scratch[200:264].reshape((8, 8))
    scratch[:264] = 0.0
    # edge dofs
    for k in range(3):
        ia = (k + 1) % 3
        ib = (k + 2) % 3
        if tri[ia] < tri[ib]:
            lo, hi = ia, ib
        else:
            lo, hi = ib, ia
        tx = p[hi, 0] - p[lo, 0]
        ty = p[hi, 1] - p[lo, 1]
        for end in range(2):
            v = lo if end == 0 else hi
            monomial_values((p[v, 0] - xc) / h, (p[v, 1] - yc) / h, work)
            for m in range(8):
                g[2 * k + end, m] = work[m, 0] * ty - work[m, 1] * tx
    # interior dofs and all quadrature-based integrals
    for q in range(weights.shape[0]):
        b0, b1, b2 = bary[q, 0], bary[q, 1], bary[q, 2]
        xq = b0 * x0 + b1 * x1 + b2 * x2
        yq = b0 * y0 + b1 * y1 + b2 * y2
        xi = (xq - xc) / h
        eta = (yq - yc) / h
        monomial_values(xi, eta, work)
        wq = weights[q] * area
        for m in range(8):
            g[6, m] += wq * work[m, 0] * h / area
            g[7, m] += wq * work[m, 1] * h / area
            for n in range(m, 8):
                mass_m[m, n] += wq * (work[m, 0] * work[n, 0] + work[m, 1] * work[n, 1])
        # divergence of the monomials (physical): (1/h) * [0, 1, 0, 0, 0, 1, 3 xi, 3 eta]
        for qq in range(3):
            lam = bary[q, qq]
            wl = wq * lam / h
            div_m[qq, 1] += wl
            div_m[qq, 5] += wl
            div_m[qq, 6] += 3.0 * xi * wl
            div_m[qq, 7] += 3.0 * eta * wl
            for m in range(8):
                tau_m[qq, 0, m] += wq * lam * work[m, 0]
                tau_m[qq, 1, m] += wq * lam * work[m, 1]
    for m in range(8):
        for n in range(m):
            mass_m[m, n] = mass_m[n, m]
    _invert8(g, coef_out)
    c = coef_out
    # transform to the dof basis: M = C^T Mm C, D = Dm C, T = Tm C (explicit loops:
    # BLAS call overhead dominates at this size)
    for m in range(8):
        for k in range(8):
            mk = mass_m[m, k]
            if mk != 0.0:
                for j in range(8):
                    tmp[m, j] += mk * c[k, j]
    for i in range(8):
        for j in range(i, 8):
            s = 0.0
            for m in range(8):
                s += c[m, i] * tmp[m, j]
            mass_out[i, j] = s
            mass_out[j, i] = s
    for j in range(8):
        for qq in range(3):
            sd = 0.0
            s0 = 0.0
            s1 = 0.0
            for m in range(8):
                cmj = c[m, j]
                sd += div_m[qq, m] * cmj
                s0 += tau_m[qq, 0, m] * cmj
                s1 += tau_m[qq, 1, m] * cmj
            div_out[qq, j] = sd
            tau_out[qq, 0, j] = s0
            tau_out[qq, 1, j] = s1
    return area


@jit
def _invert8(a, out):
    """Inverse of a small dense matrix by Gauss-Jordan elimination with partial pivoting.

    ``a`` is overwritten; ``out`` receives the inverse.
    """
    n = a.shape[0]
    for i in range(n):
        for j in range(n):
            out[i, j] = 1.0 if i == j else 0.0
    for col in range(n):
        piv = col
        best = abs(a[col, col])
        for r in range(col + 1, n):
            v = abs(a[r, col])
            if v > best:
                best = v
                piv = r
        if piv != col:
            for j in range(n):
                a[col, j], a[piv, j] = a[piv, j], a[col, j]
                out[col, j], out[piv, j] = out[piv, j], out[col, j]
        inv_p = 1.0 / a[col, col]
        for j in range(n):
            a[col, j] *= inv_p
            out[col, j] *= inv_p
        for r in range(n):
            if r != col:
                f = a[r, col]
                if f != 0.0:
                    for j in range(n):
                        a[r, j] -= f * a[col, j]
                        out[r, j] -= f * out[col, j]
