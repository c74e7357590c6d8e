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

Local matrices by the contravariant Piola map (:func:`rt1_local`).  With the
reference triangle ``K^ = {(0,0), (1,0), (0,1)}``, ``F(x^) = p0 + J x^``,
``J = [p1 - p0, p2 - p0]`` and ``P(v^) = J v^ / det J``, the point normal-flux
dofs are invariant (``J^T R J = det(J) R`` for the rotation R), so the
physical dof basis is ``phi_j = sum_i P(psi^_i) T_ij`` with psi^ the reference
basis (edge k oriented from vertex k+1 to k+2, interior dofs ``int_K^ psi^``)
and T a signed swap of the two dofs of every edge whose global orientation is
reversed, plus ``adj(J) / (2h)`` on the interior pair.  Then, exactly,

    mass = T^T [ (G00 A00 + G01 (A01 + A10) + G11 A11) / |det J| ] T,  G = J^T J
    div  = sign(det J) D^ T,       tau[q] = sign(det J) J H^[q] T

with A_ab, D^, H^ fixed reference matrices computed once, in exact rational
arithmetic, when this module is imported: no quadrature and no 8 x 8
inverse per triangle.  The quadrature path of earlier versions is the
reference of tests/test_rt1_reference.py.
"""

from fractions import Fraction
from math import factorial

import numpy as np

from ._jit import jit

__all__ = [
    "rt1_coefficient_matrix",
    "rt1_dofs_to_coefficients",
    "rt1_local",
    "rt1_local_xy",
]

# ------------------------------------------------------------------ reference data
# Polynomials on the reference triangle as {(i, j): Fraction} for x^i y^j.


def _pmul(a, b):
    out = {}
    for (i1, j1), c1 in a.items():
        for (i2, j2), c2 in b.items():
            key = (i1 + i2, j1 + j2)
            out[key] = out.get(key, 0) + c1 * c2
    return out


def _padd(a, b, s=1):
    out = dict(a)
    for key, c in b.items():
        out[key] = out.get(key, 0) + s * c
    return out


def _pint(a):
    """Exact integral over the reference triangle: int x^i y^j = i! j! / (i + j + 2)!."""
    return sum(
        (
            c * Fraction(factorial(i) * factorial(j), factorial(i + j + 2))
            for (i, j), c in a.items()
        ),
        Fraction(0),
    )


def _peval(a, x, y):
    return sum((c * x**i * y**j for (i, j), c in a.items()), Fraction(0))


def _pdiff(a, var):
    out = {}
    for (i, j), c in a.items():
        if var == 0 and i > 0:
            out[(i - 1, j)] = out.get((i - 1, j), 0) + c * i
        if var == 1 and j > 0:
            out[(i, j - 1)] = out.get((i, j - 1), 0) + c * j
    return out


def _inverse(mat):
    """Exact inverse of a small Fraction matrix (Gauss-Jordan)."""
    n = len(mat)
    a = [list(row) + [Fraction(int(i == j)) for j in range(n)] for i, row in enumerate(mat)]
    for col in range(n):
        piv = next(r for r in range(col, n) if a[r][col] != 0)
        a[col], a[piv] = a[piv], a[col]
        inv = 1 / a[col][col]
        a[col] = [v * inv for v in a[col]]
        for r in range(n):
            if r != col and a[r][col] != 0:
                f = a[r][col]
                a[r] = [v - f * w for v, w in zip(a[r], a[col], strict=True)]
    return [row[n:] for row in a]


def _reference_data():
    """Compute the reference RT1 basis and its matrices (exactly, then rounded to float64).

    Returns ``coef`` (8, 8): column j = coefficients of psi^_j in the monomials of
    the canonical fields ``(1, 0), (x, 0), (y, 0), (0, 1), (0, x), (0, y),
    (x^2, xy), (xy, y^2)`` taken about the origin without scaling; ``a00``,
    ``s01``, ``a11`` (8, 8): ``int psi^_i,a psi^_j,b`` for (a, b) = (0, 0),
    (0, 1) + (1, 0), (1, 1); ``div`` (3, 8): ``int div(psi^_j) lambda^_q``;
    ``tau`` (3, 2, 8): ``int lambda^_q psi^_j``.
    """
    one, x, y = {(0, 0): Fraction(1)}, {(1, 0): Fraction(1)}, {(0, 1): Fraction(1)}
    zero = {}
    mono = [
        (one, zero),
        (x, zero),
        (y, zero),
        (zero, one),
        (zero, x),
        (zero, y),
        (_pmul(x, x), _pmul(x, y)),
        (_pmul(x, y), _pmul(y, y)),
    ]
    verts = [(Fraction(0), Fraction(0)), (Fraction(1), Fraction(0)), (Fraction(0), Fraction(1))]
    dofmat = [[Fraction(0)] * 8 for _ in range(8)]
    for k in range(3):
        pa, pb = verts[(k + 1) % 3], verts[(k + 2) % 3]
        tx, ty = pb[0] - pa[0], pb[1] - pa[1]
        for end, pt in enumerate((pa, pb)):
            for m, (cx, cy) in enumerate(mono):
                dofmat[2 * k + end][m] = _peval(cx, *pt) * ty - _peval(cy, *pt) * tx
    for m, (cx, cy) in enumerate(mono):
        dofmat[6][m] = _pint(cx)
        dofmat[7][m] = _pint(cy)
    coef = _inverse(dofmat)
    basis = []
    for j in range(8):
        bx, by = {}, {}
        for m, (cx, cy) in enumerate(mono):
            if coef[m][j] != 0:
                bx = _padd(bx, cx, coef[m][j])
                by = _padd(by, cy, coef[m][j])
        basis.append((bx, by))
    lam = [_padd(one, _padd(x, y), -1), x, y]
    a00 = [[_pint(_pmul(basis[i][0], basis[j][0])) for j in range(8)] for i in range(8)]
    a11 = [[_pint(_pmul(basis[i][1], basis[j][1])) for j in range(8)] for i in range(8)]
    s01 = [
        [
            _pint(_pmul(basis[i][0], basis[j][1])) + _pint(_pmul(basis[i][1], basis[j][0]))
            for j in range(8)
        ]
        for i in range(8)
    ]
    div = [
        [
            _pint(_pmul(_padd(_pdiff(basis[j][0], 0), _pdiff(basis[j][1], 1)), lam[q]))
            for j in range(8)
        ]
        for q in range(3)
    ]
    tau = [
        [[_pint(_pmul(lam[q], basis[j][c])) for j in range(8)] for c in range(2)] for q in range(3)
    ]

    def arr(v):
        return np.array(v, dtype=object).astype(np.float64)

    return arr(coef), arr(a00), arr(s01), arr(a11), arr(div), arr(tau)


# Module constants (frozen into the compiled kernels).
REF_COEF, REF_A00, REF_S01, REF_A11, REF_DIV, REF_TAU = _reference_data()


def _flipped_tables():
    """Multiply the reference matrices by the edge part of T, for the 8 reversal patterns.

    Pattern bit k set: the two dofs of edge k are swapped and negated (exact).
    """
    a00, s01, a11 = np.empty((8, 8, 8)), np.empty((8, 8, 8)), np.empty((8, 8, 8))
    div, tau = np.empty((8, 3, 8)), np.empty((8, 3, 2, 8))
    for f in range(8):
        t = np.eye(8)
        for k in range(3):
            if f >> k & 1:
                t[2 * k : 2 * k + 2, 2 * k : 2 * k + 2] = [[0.0, -1.0], [-1.0, 0.0]]
        a00[f], s01[f], a11[f] = t.T @ REF_A00 @ t, t.T @ REF_S01 @ t, t.T @ REF_A11 @ t
        div[f] = REF_DIV @ t
        tau[f] = REF_TAU @ t
    return a00, s01, a11, div, tau


_A00, _S01, _A11, _DIV, _TAU = _flipped_tables()


@jit
def rt1_local(p, tri, h, mass_out, div_out, tau_out):
    """Local RT1 matrices of one triangle in its dof basis (Piola map, no quadrature).

    Parameters
    ----------
    p : float64 (3, 2)
        Vertex coordinates (counter-clockwise).
    tri : int64 (3,)
        Global vertex indices (for the edge orientation).
    h : float
        Diameter of the triangle (the scaling of the interior dofs).
    mass_out : float64 (8, 8)
        Out: ``int_K phi_i . phi_j``.
    div_out : float64 (3, 8)
        Out: ``int_K div(phi_j) lambda_q`` for the barycentric P1 basis lambda_q.
    tau_out : float64 (3, 2, 8)
        Out: ``int_K lambda_q phi_j`` (vector), for the flux target terms.

    Returns
    -------
    area : float
        Signed area (positive for counter-clockwise vertices).

    The same quantities as the quadrature path of tests/test_rt1_reference.py (up to round-off),
    from the reference matrices of the module docstring: the edge part of T
    is folded into the tables (one per pattern of reversed edges), the
    interior block ``adj(J) / (2h)`` is applied here.
    """
    return rt1_local_xy(
        p[0, 0],
        p[0, 1],
        p[1, 0],
        p[1, 1],
        p[2, 0],
        p[2, 1],
        tri[0],
        tri[1],
        tri[2],
        h,
        mass_out,
        div_out,
        tau_out,
    )


@jit
def rt1_local_xy(x0, y0, x1, y1, x2, y2, i0, i1, i2, h, mass_out, div_out, tau_out):
    """:func:`rt1_local` with the vertices and their global indices as scalars."""
    j00 = x1 - x0
    j10 = y1 - y0
    j01 = x2 - x0
    j11 = y2 - y0
    det = j00 * j11 - j01 * j10
    adet = abs(det)
    sg = 1.0 if det > 0.0 else -1.0
    w00 = (j00 * j00 + j10 * j10) / adet
    w01 = (j00 * j01 + j10 * j11) / adet
    w11 = (j01 * j01 + j11 * j11) / adet
    inv2h = 0.5 / h
    q00 = j11 * inv2h
    q01 = -j01 * inv2h
    q10 = -j10 * inv2h
    q11 = j00 * inv2h
    f = _flip_pattern(i0, i1, i2)
    for i in range(8):
        for j in range(8):
            mass_out[i, j] = w00 * _A00[f, i, j] + w01 * _S01[f, i, j] + w11 * _A11[f, i, j]
    # interior block of T: columns, then rows
    for r in range(8):
        c6 = mass_out[r, 6]
        c7 = mass_out[r, 7]
        mass_out[r, 6] = c6 * q00 + c7 * q10
        mass_out[r, 7] = c6 * q01 + c7 * q11
    for c in range(8):
        r6 = mass_out[6, c]
        r7 = mass_out[7, c]
        mass_out[6, c] = q00 * r6 + q10 * r7
        mass_out[7, c] = q01 * r6 + q11 * r7
    # The column and row passes round the two off-diagonal copies differently (by an
    # ulp or so once LLVM no longer reassociates): mirror the upper triangle so that
    # the mass matrix is symmetric bit for bit, as the patch Cholesky assumes.
    for i in range(8):
        for j in range(i + 1, 8):
            mass_out[j, i] = mass_out[i, j]
    for q in range(3):
        for j in range(6):
            div_out[q, j] = sg * _DIV[f, q, j]
            t0 = _TAU[f, q, 0, j]
            t1 = _TAU[f, q, 1, j]
            tau_out[q, 0, j] = sg * (j00 * t0 + j01 * t1)
            tau_out[q, 1, j] = sg * (j10 * t0 + j11 * t1)
        d6 = sg * _DIV[f, q, 6]
        d7 = sg * _DIV[f, q, 7]
        div_out[q, 6] = d6 * q00 + d7 * q10
        div_out[q, 7] = d6 * q01 + d7 * q11
        for c in range(2):
            jc0 = j00 if c == 0 else j10
            jc1 = j01 if c == 0 else j11
            t6 = sg * (jc0 * _TAU[f, q, 0, 6] + jc1 * _TAU[f, q, 1, 6])
            t7 = sg * (jc0 * _TAU[f, q, 0, 7] + jc1 * _TAU[f, q, 1, 7])
            tau_out[q, c, 6] = t6 * q00 + t7 * q10
            tau_out[q, c, 7] = t6 * q01 + t7 * q11
    return 0.5 * det


@jit
def _flip_pattern(i0, i1, i2):
    """Bit k set when local edge k (from local vertex k+1 to k+2) is globally reversed."""
    f = 0
    if i1 > i2:
        f += 1
    if i2 > i0:
        f += 2
    if i0 > i1:
        f += 4
    return f


@jit
def rt1_dofs_to_coefficients(x0, y0, x1, y1, x2, y2, i0, i1, i2, h, v, k):
    """In place: dof values ``v[k]`` (v: (n, 8)) of a field of RT1(K) -> canonical coefficients.

    ``(x0, y0) .. (x2, y2)`` are the vertices, ``i0, i1, i2`` their global
    indices (edge orientation), h the diameter.  Piola map of the reference
    field ``sum_i (T v)_i psi^_i``: with ``x^ = x^_c + h J^-1 xi`` (x^_c the
    reference centroid) and the reference field ``a^ + B^ x^ + x^ (c^ . x^)``,

        a = J (a^ + B^ x^_c + x^_c (c^ . x^_c)) / det J
        B = h J (B^ + x^_c c^^T + (c^ . x^_c) I) J^-1 / det J
        c = h^2 J^-T c^ / det J
    """
    j00 = x1 - x0
    j10 = y1 - y0
    j01 = x2 - x0
    j11 = y2 - y0
    det = j00 * j11 - j01 * j10
    inv2h = 0.5 / h
    # reference-basis coefficients e = T v
    if i1 > i2:
        e0, e1 = -v[k, 1], -v[k, 0]
    else:
        e0, e1 = v[k, 0], v[k, 1]
    if i2 > i0:
        e2, e3 = -v[k, 3], -v[k, 2]
    else:
        e2, e3 = v[k, 2], v[k, 3]
    if i0 > i1:
        e4, e5 = -v[k, 5], -v[k, 4]
    else:
        e4, e5 = v[k, 4], v[k, 5]
    e6 = (j11 * v[k, 6] - j01 * v[k, 7]) * inv2h
    e7 = (-j10 * v[k, 6] + j00 * v[k, 7]) * inv2h
    # reference monomial coefficients
    c = REF_COEF
    for m in range(8):  # (the input now lives in e0..e7; v[k] is reused as scratch)
        v[k, m] = (
            c[m, 0] * e0
            + c[m, 1] * e1
            + c[m, 2] * e2
            + c[m, 3] * e3
            + c[m, 4] * e4
            + c[m, 5] * e5
            + c[m, 6] * e6
            + c[m, 7] * e7
        )
    ra0 = v[k, 0]
    rb00 = v[k, 1]
    rb01 = v[k, 2]
    ra1 = v[k, 3]
    rb10 = v[k, 4]
    rb11 = v[k, 5]
    rc0 = v[k, 6]
    rc1 = v[k, 7]
    third = 1.0 / 3.0
    s = (rc0 + rc1) * third
    v0 = ra0 + (rb00 + rb01 + s) * third
    v1 = ra1 + (rb10 + rb11 + s) * third
    n00 = rb00 + rc0 * third + s
    n01 = rb01 + rc1 * third
    n10 = rb10 + rc0 * third
    n11 = rb11 + rc1 * third + s
    inv_det = 1.0 / det
    # B = (h / det^2) J N adj(J),  adj(J) = [[j11, -j01], [-j10, j00]]
    jn00 = j00 * n00 + j01 * n10
    jn01 = j00 * n01 + j01 * n11
    jn10 = j10 * n00 + j11 * n10
    jn11 = j10 * n01 + j11 * n11
    fb = h * inv_det * inv_det
    fc = h * fb
    v[k, 0] = (j00 * v0 + j01 * v1) * inv_det
    v[k, 3] = (j10 * v0 + j11 * v1) * inv_det
    v[k, 1] = (jn00 * j11 - jn01 * j10) * fb
    v[k, 2] = (-jn00 * j01 + jn01 * j00) * fb
    v[k, 4] = (jn10 * j11 - jn11 * j10) * fb
    v[k, 5] = (-jn10 * j01 + jn11 * j00) * fb
    # c = (h^2 / det^2) adj(J)^T c^
    v[k, 6] = (j11 * rc0 - j10 * rc1) * fc
    v[k, 7] = (-j01 * rc0 + j00 * rc1) * fc


@jit
def rt1_coefficient_matrix(p, tri, h, out):
    """Column j of ``out`` (8, 8) = canonical coefficients of local basis function j."""
    for j in range(8):
        for m in range(8):
            out[m, j] = 1.0 if m == j else 0.0
    col = np.empty((1, 8))
    for j in range(8):
        for m in range(8):
            col[0, m] = out[m, j]
        rt1_dofs_to_coefficients(
            p[0, 0], p[0, 1], p[1, 0], p[1, 1], p[2, 0], p[2, 1], tri[0], tri[1], tri[2], h, col, 0
        )
        for m in range(8):
            out[m, j] = col[0, m]
