"""RT1 local matrices by the Piola map (kernels/rt1.py) vs the quadrature path and exact arithmetic.

``rt1_local`` (reference matrices under the contravariant Piola map) and
``rt1_coefficient_matrix`` / ``rt1_dofs_to_coefficients`` (dofs -> canonical
coefficients) must reproduce what the original quadrature algorithm computes
(``_quadrature`` here, plain NumPy: a degree-5 rule for the canonical monomials
and an 8 x 8 inverse of their dof matrix) on random, obtuse, stretched (aspect 1e3) and tiny
(area 1e-12) triangles, for every orientation pattern of the three edges.

A third, independent reference is the quadrature algorithm carried out in
exact rational arithmetic (the float vertices taken as exact rationals,
monomials integrated exactly, the dof matrix inverted exactly).  It shows
where a discrepancy comes from: on stretched triangles the quadrature path
loses about eps * aspect^2 to the conditioning of its dof matrix (~3e-10 at
aspect 1e3) while the Piola path stays at round-off.
"""

import itertools
from fractions import Fraction

import numpy as np
import pytest
from fastmem.kernels import rt1

from fastmem.fem.quadrature import triangle_rule

CLASSES = ["random", "obtuse", "stretched", "tiny", "tiny-offset"]
#: classes on which the quadrature path itself is accurate to round-off
WELL_CONDITIONED = ["random", "obtuse", "tiny"]
N_PER_CLASS = 4  # x 6 vertex numberings (all realisable edge-orientation patterns)


def _rotation(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s], [s, c]])


def _ccw(p):
    d = (p[1, 0] - p[0, 0]) * (p[2, 1] - p[0, 1]) - (p[2, 0] - p[0, 0]) * (p[1, 1] - p[0, 1])
    return np.ascontiguousarray(p if d > 0 else p[[0, 2, 1]])


def _triangle(kind, rng):
    """One counter-clockwise triangle of the given class, (3, 2)."""
    rot = _rotation(rng.uniform(0.0, 2.0 * np.pi))
    if kind == "random":
        while True:  # random vertices, not degenerate (area >= 5 % of the unit square)
            p = rng.uniform(-1.0, 1.0, (3, 2))
            d1, d2 = p[1] - p[0], p[2] - p[0]
            area = 0.5 * abs(d1[0] * d2[1] - d1[1] * d2[0])
            if area >= 0.2:
                return _ccw(p)
    if kind == "obtuse":  # largest angle about 170 degrees
        base = np.array([[0.0, 0.0], [1.0, 0.0], [rng.uniform(0.3, 0.7), 0.04]])
        return _ccw(base @ rot.T + rng.uniform(-1.0, 1.0, 2))
    if kind == "stretched":  # aspect ratio 1e3
        base = np.array([[0.0, 0.0], [1.0, 0.0], [rng.uniform(0.0, 1.0), 1e-3]])
        return _ccw(base @ rot.T + rng.uniform(-1.0, 1.0, 2))
    scale = np.sqrt(2e-12)  # unit right triangle scaled to area 1e-12
    base = scale * np.array([[0.0, 0.0], [1.0, 0.0], [rng.uniform(0.0, 1.0), 1.0]])
    shift = rng.uniform(-1.0, 1.0, 2) * (scale if kind == "tiny" else 1.0)
    return _ccw(base @ rot.T + shift)


def _diameter(p):
    return max(float(np.hypot(*(p[i] - p[j]))) for i in range(3) for j in range(i))


def _cases(kind, seed):
    rng = np.random.default_rng(seed)
    for _ in range(N_PER_CLASS):
        p = _triangle(kind, rng)
        base = rng.integers(0, 1000)
        for perm in itertools.permutations(range(3)):
            yield p, np.array(perm, dtype=np.int64) + base


# ------------------------------------------------------------------ the three paths


def _monomials(xi, eta):
    """The 8 canonical monomial fields at scaled points: (..., 8, 2)."""
    z, o = np.zeros_like(xi), np.ones_like(xi)
    fx = [o, xi, eta, z, z, z, xi * xi, xi * eta]
    fy = [z, z, z, o, xi, eta, xi * eta, eta * eta]
    return np.stack([np.stack(fx, -1), np.stack(fy, -1)], -1)


def _quadrature(p, tri, h):
    """The original algorithm (plain NumPy): monomial integrals by a degree-5 rule and an
    8 x 8 inverse of the dof matrix of the canonical monomials about the centroid / h."""
    bary, w = triangle_rule(5)
    d1, d2 = p[1] - p[0], p[2] - p[0]
    area = 0.5 * (d1[0] * d2[1] - d2[0] * d1[1])
    c = p.mean(axis=0)
    g = np.zeros((8, 8))
    for k in range(3):  # edge k: vertices k+1, k+2, oriented low -> high global index
        ia, ib = (k + 1) % 3, (k + 2) % 3
        lo, hi = (ia, ib) if tri[ia] < tri[ib] else (ib, ia)
        t = p[hi] - p[lo]
        for end, v in enumerate((lo, hi)):
            mv = _monomials(*((p[v] - c) / h))  # (8, 2)
            g[2 * k + end] = mv[:, 0] * t[1] - mv[:, 1] * t[0]
    xq = bary @ p  # (nq, 2)
    sc = (xq - c) / h
    mq = _monomials(sc[:, 0], sc[:, 1])  # (nq, 8, 2)
    wq = w * area
    g[6] = np.einsum("q,qm->m", wq, mq[..., 0]) * h / area
    g[7] = np.einsum("q,qm->m", wq, mq[..., 1]) * h / area
    mass_m = np.einsum("q,qmc,qnc->mn", wq, mq, mq)
    # divergence of the monomials (physical): (1/h) [0, 1, 0, 0, 0, 1, 3 xi, 3 eta]
    dv = np.zeros((bary.shape[0], 8))
    dv[:, 1] = dv[:, 5] = 1.0 / h
    dv[:, 6], dv[:, 7] = 3.0 * sc[:, 0] / h, 3.0 * sc[:, 1] / h
    div_m = np.einsum("q,qa,qm->am", wq, bary, dv)
    tau_m = np.einsum("q,qa,qmc->acm", wq, bary, mq)
    coef = np.linalg.inv(g)
    return {
        "area": area,
        "coef": coef,
        "mass": coef.T @ mass_m @ coef,
        "div": div_m @ coef,
        "tau": tau_m @ coef,
    }


def _piola(p, tri, h):
    coef, mass = np.zeros((8, 8)), np.zeros((8, 8))
    div, tau = np.zeros((3, 8)), np.zeros((3, 2, 8))
    area = rt1.rt1_local(p, tri, h, mass, div, tau)
    rt1.rt1_coefficient_matrix(p, tri, h, coef)
    return {"area": area, "coef": coef, "mass": mass, "div": div, "tau": tau}


# exact polynomial arithmetic on the reference triangle ({(i, j): Fraction} for x^i y^j)
_pmul, _pint, _pdiff = rt1._pmul, rt1._pint, rt1._pdiff
_pval = rt1._peval


def _plin(*terms):
    out = {}
    for c, poly in terms:
        for k, v in poly.items():
            out[k] = out.get(k, 0) + c * v
    return out


def _exact(p, tri, h):
    """The quadrature algorithm in exact rational arithmetic (polynomials in reference coords)."""
    pf = [[Fraction(float(v)) for v in row] for row in p]
    hf = Fraction(float(h))
    j00, j10 = pf[1][0] - pf[0][0], pf[1][1] - pf[0][1]
    j01, j11 = pf[2][0] - pf[0][0], pf[2][1] - pf[0][1]
    det = j00 * j11 - j01 * j10
    xc = sum(r[0] for r in pf) / 3
    yc = sum(r[1] for r in pf) / 3
    one = {(0, 0): Fraction(1)}
    xi = {(0, 0): (pf[0][0] - xc) / hf, (1, 0): j00 / hf, (0, 1): j01 / hf}
    eta = {(0, 0): (pf[0][1] - yc) / hf, (1, 0): j10 / hf, (0, 1): j11 / hf}
    mono = [
        (one, {}),
        (xi, {}),
        (eta, {}),
        ({}, one),
        ({}, xi),
        ({}, eta),
        (_pmul(xi, xi), _pmul(xi, eta)),
        (_pmul(xi, eta), _pmul(eta, eta)),
    ]
    ref = [(Fraction(0), Fraction(0)), (Fraction(1), Fraction(0)), (Fraction(0), Fraction(1))]
    g = [[Fraction(0)] * 8 for _ in range(8)]
    for k in range(3):
        ia, ib = (k + 1) % 3, (k + 2) % 3
        lo, hi = (ia, ib) if tri[ia] < tri[ib] else (ib, ia)
        tx, ty = pf[hi][0] - pf[lo][0], pf[hi][1] - pf[lo][1]
        for end, v in enumerate((lo, hi)):
            for m, (cx, cy) in enumerate(mono):
                g[2 * k + end][m] = _pval(cx, *ref[v]) * ty - _pval(cy, *ref[v]) * tx
    for m, (cx, cy) in enumerate(mono):  # (h / |K|) int_K = 2 h int_ref
        g[6][m] = 2 * hf * _pint(cx)
        g[7][m] = 2 * hf * _pint(cy)
    aug = [row + [Fraction(int(i == j)) for j in range(8)] for i, row in enumerate(g)]
    for c in range(8):
        piv = max(range(c, 8), key=lambda r: abs(aug[r][c]))
        aug[c], aug[piv] = aug[piv], aug[c]
        aug[c] = [v / aug[c][c] for v in aug[c]]
        for r in range(8):
            if r != c and aug[r][c]:
                f = aug[r][c]
                aug[r] = [v - f * w for v, w in zip(aug[r], aug[c], strict=True)]
    coef = [row[8:] for row in aug]
    basis = [
        tuple(_plin(*[(coef[m][j], mono[m][comp]) for m in range(8)]) for comp in range(2))
        for j in range(8)
    ]
    lam = [
        {(0, 0): Fraction(1), (1, 0): Fraction(-1), (0, 1): Fraction(-1)},
        {(1, 0): Fraction(1)},
        {(0, 1): Fraction(1)},
    ]
    adet = abs(det)
    mass = [
        [adet * _pint(_plin((1, _pmul(bi[0], bj[0])), (1, _pmul(bi[1], bj[1])))) for bj in basis]
        for bi in basis
    ]
    # physical derivatives: d/dx = (j11 d/dx^ - j10 d/dy^) / det,
    # d/dy = (-j01 d/dx^ + j00 d/dy^) / det
    divs = [
        _plin(
            (j11 / det, _pdiff(bx, 0)),
            (-j10 / det, _pdiff(bx, 1)),
            (-j01 / det, _pdiff(by, 0)),
            (j00 / det, _pdiff(by, 1)),
        )
        for bx, by in basis
    ]
    div = [[adet * _pint(_pmul(d, lam[q])) for d in divs] for q in range(3)]
    tau = [[[adet * _pint(_pmul(b[c], lam[q])) for b in basis] for c in range(2)] for q in range(3)]

    def arr(v):
        return np.array(v, dtype=object).astype(np.float64)

    return {
        "area": float(det / 2),
        "coef": arr(coef),
        "mass": arr(mass),
        "div": arr(div),
        "tau": arr(tau),
    }


def _rel(a, b):
    return float(np.abs(a - b).max() / np.abs(b).max())


KEYS = ["coef", "mass", "div", "tau"]


# ------------------------------------------------------------------------- tests


@pytest.mark.parametrize("kind", CLASSES)
def test_piola_matches_exact_arithmetic(kind):
    """The Piola path agrees with the exact-arithmetic reference to 1e-12 on every class."""
    worst = dict.fromkeys(KEYS, 0.0)
    for k, (p, tri) in enumerate(_cases(kind, seed=11)):
        if k % 3:  # three numberings per triangle are enough here (exact arithmetic is slow)
            continue
        h = _diameter(p)
        new, ref = _piola(p, tri, h), _exact(p, tri, h)
        assert abs(new["area"] - ref["area"]) <= 1e-14 * abs(ref["area"])
        for key in KEYS:
            worst[key] = max(worst[key], _rel(new[key], ref[key]))
    assert max(worst.values()) <= 1e-12, worst


@pytest.mark.parametrize("kind", CLASSES)
def test_piola_matches_quadrature(kind):
    """Piola vs the original quadrature path: relative error <= 1e-12 (all edge orientations).

    On stretched triangles and on tiny triangles far from the origin the
    quadrature path is itself off by more than 1e-12 (exact reference); there
    the difference must be explained by that error.
    """
    for p, tri in _cases(kind, seed=5):
        h = _diameter(p)
        new, old = _piola(p, tri, h), _quadrature(p, tri, h)
        assert new["area"] == pytest.approx(old["area"], rel=1e-14)
        ref = None if kind in WELL_CONDITIONED else _exact(p, tri, h)
        for key in KEYS:
            err = _rel(new[key], old[key])
            if ref is None:
                assert err <= 1e-12, (key, err)
            else:
                old_err = _rel(old[key], ref[key])
                assert err <= 2.0 * old_err + 1e-12, (key, err, old_err)


@pytest.mark.parametrize("kind", CLASSES)
def test_coefficients_reproduce_dofs(kind):
    """dofs -> canonical coefficients -> dof functionals (exact arithmetic) is the identity.

    The functionals of the float coefficients are evaluated exactly, so only the
    coefficients' own rounding counts; it is amplified by the conditioning of the
    canonical representation (cond of the coefficient matrix, ~2e7 at aspect 1e3).
    """
    rng = np.random.default_rng(3)
    for p, tri in _cases(kind, seed=7):
        h = _diameter(p)
        dofs = rng.standard_normal((1, 8))
        c = dofs.copy()
        rt1.rt1_dofs_to_coefficients(*p.ravel(), *tri, h, c, 0)
        cf = [Fraction(float(v)) for v in c[0]]
        pf = [(Fraction(float(x)), Fraction(float(y))) for x, y in p]
        hf = Fraction(h)
        cen = (sum(q[0] for q in pf) / 3, sum(q[1] for q in pf) / 3)

        def sigma(pt, cf=cf, cen=cen, hf=hf):
            xi, eta = (pt[0] - cen[0]) / hf, (pt[1] - cen[1]) / hf
            quad = cf[6] * xi + cf[7] * eta
            return (
                cf[0] + cf[1] * xi + cf[2] * eta + xi * quad,
                cf[3] + cf[4] * xi + cf[5] * eta + eta * quad,
            )

        back = []
        for k in range(3):
            ia, ib = (k + 1) % 3, (k + 2) % 3
            lo, hi = (ia, ib) if tri[ia] < tri[ib] else (ib, ia)
            tx, ty = pf[hi][0] - pf[lo][0], pf[hi][1] - pf[lo][1]
            for v in (lo, hi):
                sx, sy = sigma(pf[v])
                back.append(sx * ty - sy * tx)
        # (h / |K|) int_K sigma = (h / 3) sum over the edge midpoints (exact for degree 2)
        mids = [
            ((pf[i][0] + pf[j][0]) / 2, (pf[i][1] + pf[j][1]) / 2)
            for i, j in ((0, 1), (1, 2), (2, 0))
        ]
        vals = [sigma(m) for m in mids]
        back += [hf / 3 * sum(v[0] for v in vals), hf / 3 * sum(v[1] for v in vals)]
        back = np.array([float(v) for v in back])
        cond = np.linalg.cond(_piola(p, tri, h)["coef"])
        tol = 1e-12 if kind in WELL_CONDITIONED else max(1e-12, 10.0 * np.finfo(float).eps * cond)
        assert _rel(back, dofs[0]) <= tol


@pytest.mark.parametrize("kind", CLASSES)
def test_mass_symmetric_positive(kind):
    for p, tri in _cases(kind, seed=2):
        new = _piola(p, tri, _diameter(p))
        m = new["mass"]
        assert np.abs(m - m.T).max() <= 1e-15 * np.abs(m).max()
        assert np.linalg.eigvalsh(m).min() > 0.0


def test_flip_tables_are_signed_permutations():
    """Pattern 0 is the reference itself; every pattern only permutes and negates entries."""
    np.testing.assert_array_equal(rt1._A00[0], rt1.REF_A00)
    for f in range(8):
        for tab, ref in ((rt1._A00, rt1.REF_A00), (rt1._S01, rt1.REF_S01), (rt1._DIV, rt1.REF_DIV)):
            assert sorted(np.abs(tab[f]).ravel()) == sorted(np.abs(ref).ravel())
