"""Tests of fastmem/estimators/terms.py and kernels/cut.py (MATH.md sections 5 and 6).

The cut kernels are checked against two independent references defined here:
an exact one (Sutherland-Hodgman clipping of K to {w > 0} in barycentric
coordinates, in rational arithmetic with ``fractions.Fraction``) and a brute
force one (six uniform refinements and a high-degree rule on every sub-triangle).
"""

import math
from fractions import Fraction

import numba
import numpy as np
import pytest
from fastmem.kernels.cut import positive_area, positive_product
from meshes import perturbed_square
from numpy.testing import assert_allclose

import fastmem as fm
from fastmem.errors import DataError
from fastmem.estimators.terms import combine, friedrichs_constant, global_terms, local_terms
from fastmem.fem.assembly import assemble_mass
from fastmem.fem.quadrature import triangle_rule
from fastmem.fem.residual import residuals

# --------------------------------------------------------------------------- references


def exact_cut(w, v):
    """``(|{w>0} ∩ K| / |K|, (v, w⁺)_K / |K|)`` in exact rational arithmetic.

    Clip K to {w > 0} (Sutherland-Hodgman, points in barycentric coordinates),
    fan-triangulate and integrate v w on each piece with the edge-midpoint rule
    (exact for quadratics).
    """
    w = [Fraction(float(x)) for x in w]
    v = [Fraction(float(x)) for x in v]

    def val(f, p):
        return sum(fi * pi for fi, pi in zip(f, p, strict=True))

    def lerp(s, e, t):
        return tuple(si + t * (ei - si) for si, ei in zip(s, e, strict=True))

    poly = [tuple(Fraction(int(i == k)) for i in range(3)) for k in range(3)]
    clipped = []
    for k in range(3):
        s, e = poly[k - 1], poly[k]
        ws, we = val(w, s), val(w, e)
        if we > 0:
            if ws <= 0:
                clipped.append(lerp(s, e, ws / (ws - we)))
            clipped.append(e)
        elif ws > 0:
            clipped.append(lerp(s, e, ws / (ws - we)))
    area = Fraction(0)
    moment = Fraction(0)
    for k in range(1, len(clipped) - 1):
        tri = (clipped[0], clipped[k], clipped[k + 1])
        (a0, a1, a2), (b0, b1, b2), (c0, c1, c2) = tri
        det = abs(a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0))
        mids = [lerp(tri[i], tri[(i + 1) % 3], Fraction(1, 2)) for i in range(3)]
        area += det
        moment += det * sum(val(v, m) * val(w, m) for m in mids) / 3
    return float(area), float(moment)


def exact_kernels(mesh, w, v):
    """Per-triangle exact positive area and product."""
    res = np.array([exact_cut(w[t], v[t]) for t in mesh.triangles])
    return res[:, 0] * mesh.areas, res[:, 1] * mesh.areas


def brute_force(mesh, w, v, levels=6, degree=12):
    """Refine ``levels`` times and integrate 1{w>0} and v w⁺ with a degree-``degree`` rule."""
    fine = mesh
    for _ in range(levels):
        e = fine.edges
        w = np.concatenate([w, 0.5 * (w[e[:, 0]] + w[e[:, 1]])])  # exact for P1
        v = np.concatenate([v, 0.5 * (v[e[:, 0]] + v[e[:, 1]])])
        fine = fine.refine()
    bary, weights = triangle_rule(degree)
    wq = w[fine.triangles] @ bary.T  # (Mf, nq)
    vq = v[fine.triangles] @ bary.T
    area = ((wq > 0) @ weights) * fine.areas
    prod = ((vq * np.maximum(wq, 0.0)) @ weights) * fine.areas
    parent = np.arange(fine.n_triangles) // 4**levels  # children of t are 4t .. 4t+3
    m = mesh.n_triangles
    return np.bincount(parent, area, m), np.bincount(parent, prod, m)


def random_p1(rng, n, zero_fraction=0.3, integers=False):
    """Random nodal values with exact zeros (cuts through vertices, w = 0 on whole triangles)."""
    x = rng.integers(-2, 3, n).astype(float) if integers else rng.standard_normal(n)
    x[rng.random(n) < zero_fraction] = 0.0
    return x


def assert_close(actual, desired, atol):
    """``|actual - desired| <= atol`` elementwise, ``atol`` an array (one scale per triangle)."""
    actual, desired = np.asarray(actual), np.asarray(desired)
    err = np.abs(actual - desired)
    bad = ~(err <= atol)
    assert not bad.any(), f"{int(bad.sum())} mismatches, worst error/atol {np.max(err / atol):.3g}"


def unit_triangle():
    return fm.Mesh([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], [[0, 1, 2]])


# --------------------------------------------------------------------------- cut kernels


def test_exact_reference_on_closed_forms():
    # the reference itself: half-area cut through a vertex, corner cut, whole, nothing
    assert exact_cut([0, 1, -1], [1, 1, 1]) == (0.5, 1 / 6)
    assert exact_cut([1, -1, -1], [1, 1, 1]) == (0.25, 0.25 / 3)
    assert exact_cut([0, 0, 0], [1, 2, 3]) == (0.0, 0.0)
    assert exact_cut([1, 2, 3], [1, 1, 1]) == (1.0, 2.0)


@pytest.mark.parametrize("integers", [False, True])
def test_kernels_match_exact_reference(rng, integers):
    mesh = perturbed_square(10, 0.3)
    w = random_p1(rng, mesh.n_vertices, zero_fraction=0.2, integers=integers)
    v = rng.standard_normal(mesh.n_vertices)
    w_signs = np.sign(w[mesh.triangles])
    n_pos = (w_signs > 0).sum(1)
    n_zero = (w_signs == 0).sum(1)
    # the data cover every case: all signs, zeros at 1, 2 and 3 vertices
    assert set(n_pos) == {0, 1, 2, 3}
    assert {1, 2} <= set(n_zero)
    area_ref, prod_ref = exact_kernels(mesh, w, v)
    scale = mesh.areas * np.abs(w).max() * np.abs(v).max()
    assert_allclose(positive_area(mesh.vertices, mesh.triangles, w), area_ref, rtol=1e-13, atol=0)
    assert_close(positive_product(mesh.vertices, mesh.triangles, w, v), prod_ref, 1e-14 * scale)


def test_kernels_match_brute_force(rng):
    mesh = perturbed_square(2, 0.3)
    w = random_p1(rng, mesh.n_vertices, zero_fraction=0.2)
    v = rng.standard_normal(mesh.n_vertices)
    assert 0 < (w > 0).sum() < mesh.n_vertices
    area_bf, prod_bf = brute_force(mesh, w, v)
    area = positive_area(mesh.vertices, mesh.triangles, w)
    prod = positive_product(mesh.vertices, mesh.triangles, w, v)
    scale = mesh.areas * np.abs(w).max() * np.abs(v).max()
    # Quadrature of a discontinuous (area) or kinked (product) integrand on 4^6
    # sub-triangles: errors ~2e-4 |K| and ~1e-8 on the cut triangles (measured).
    assert_close(area, area_bf, 1e-3 * mesh.areas)
    assert_close(prod, prod_bf, 1e-6 * scale)
    cut = (area > 0) & (area < mesh.areas)
    assert cut.sum() >= 2  # some triangles are really cut


@pytest.mark.parametrize(
    ("w", "area", "moment"),
    [
        # w = x - y: zero at vertex 0, cut from vertex 0 to the midpoint of edge 12
        ([0.0, 1.0, -1.0], 0.25, 1.0 / 12.0),
        # w = x + y - 1/2 (two positive vertices): K minus the corner triangle of area 1/8
        ([-0.5, 0.5, 0.5], 0.375, 5.0 / 48.0),
        # w = (1 - x - y) - 1/2: the similar triangle of ratio 1/2 at vertex 0
        ([0.5, -0.5, -0.5], 0.125, 0.125 * 0.5 / 3.0),
        # zero on an edge, positive at the third vertex: w = y
        ([0.0, 0.0, 1.0], 0.5, 1.0 / 6.0),
        # zero on an edge, negative at the third vertex
        ([0.0, 0.0, -1.0], 0.0, 0.0),
        # w = 0 at one vertex, positive at the others: all of K
        ([0.0, 1.0, 1.0], 0.5, 1.0 / 3.0),
        ([0.0, 0.0, 0.0], 0.0, 0.0),
        ([-1.0, -2.0, -3.0], 0.0, 0.0),
        ([2.0, 2.0, 2.0], 0.5, 1.0),
    ],
)
def test_closed_forms_on_unit_triangle(w, area, moment):
    """v = 1 on the unit triangle (|K| = 1/2): area of {w > 0} and the integral of w⁺."""
    mesh = unit_triangle()
    w = np.array(w)
    assert_allclose(positive_area(mesh.vertices, mesh.triangles, w), [area], rtol=1e-15, atol=0)
    got = positive_product(mesh.vertices, mesh.triangles, w, np.ones(3))
    assert_allclose(got, [moment], rtol=1e-15, atol=0)


def test_half_area_cuts_and_similar_triangles(rng):
    """Cuts through a vertex and the midpoint of the opposite edge halve |K|; w = phi_0 - s
    leaves the similar triangle of ratio (1 - s), with (w⁺, 1) = (1 - s)^3 |K| / 3."""
    mesh = perturbed_square(5, 0.3)
    t = mesh.triangles
    m = mesh.n_triangles
    areas = mesh.areas
    for k in range(3):  # one triangle at a time: every vertex value is set per triangle
        for sign in (1.0, -1.0):
            a_half, a_sim, p_sim = np.empty(m), np.empty(m), np.empty(m)
            s = rng.uniform(0.05, 0.95, m)
            for j in range(m):
                single = fm.Mesh(mesh.vertices[t[j]], [[0, 1, 2]])
                w = np.zeros(3)
                w[(k + 1) % 3], w[(k + 2) % 3] = sign, -sign
                a_half[j] = positive_area(single.vertices, single.triangles, w)[0]
                w = -np.full(3, s[j])
                w[k] += 1.0
                a_sim[j] = positive_area(single.vertices, single.triangles, w)[0]
                p_sim[j] = positive_product(single.vertices, single.triangles, w, np.ones(3))[0]
            assert_allclose(a_half, 0.5 * areas, rtol=1e-14, atol=0)
            assert_allclose(a_sim, (1 - s) ** 2 * areas, rtol=1e-13, atol=0)
            assert_allclose(p_sim, (1 - s) ** 3 * areas / 3.0, rtol=1e-13, atol=0)


def test_positivity_and_bounds(rng):
    mesh = perturbed_square(10, 0.3)
    w = random_p1(rng, mesh.n_vertices)
    v = np.abs(rng.standard_normal(mesh.n_vertices))
    v[rng.random(v.size) < 0.3] = 0.0
    area = positive_area(mesh.vertices, mesh.triangles, w)
    prod = positive_product(mesh.vertices, mesh.triangles, w, v)
    assert (area >= 0).all()
    assert (area <= mesh.areas * (1 + 1e-15)).all()  # |K| recomputed in the kernel
    assert (prod >= 0).all()
    # (v, w⁺)_K <= max(w⁺) (v, 1)_K
    wmax = np.maximum(w[mesh.triangles].max(1), 0.0)
    assert (prod <= wmax * v[mesh.triangles].mean(1) * mesh.areas * (1 + 1e-14)).all()
    # complementary sets: area{w > 0} + area{-w > 0} + area{w = 0} = |K|, and w⁺ - (-w)⁺ = w
    area_neg = positive_area(mesh.vertices, mesh.triangles, -w)
    zero_tri = (w[mesh.triangles] == 0).all(1)
    assert_allclose(area + area_neg + zero_tri * mesh.areas, mesh.areas, rtol=1e-14, atol=0)
    v2 = rng.standard_normal(mesh.n_vertices)
    full = (mesh.areas / 12.0) * (
        (w[mesh.triangles] * v2[mesh.triangles]).sum(1)
        + w[mesh.triangles].sum(1) * v2[mesh.triangles].sum(1)
    )
    diff = positive_product(mesh.vertices, mesh.triangles, w, v2) - positive_product(
        mesh.vertices, mesh.triangles, -w, v2
    )
    scale = mesh.areas * np.abs(w).max() * np.abs(v2).max()
    assert_close(diff, full, 1e-14 * scale)


@pytest.mark.parametrize("magnitude", [1e-12, 1e-6, 1.0, 1e6, 1e12])
def test_scaling(rng, magnitude):
    """positive_area is invariant and positive_product linear under w -> t w, t > 0."""
    mesh = perturbed_square(8, 0.3)
    w = random_p1(rng, mesh.n_vertices)
    v = rng.standard_normal(mesh.n_vertices)
    vt, tr = mesh.vertices, mesh.triangles
    area = positive_area(vt, tr, w)
    prod = positive_product(vt, tr, w, v)
    scale = mesh.areas * np.abs(w).max() * np.abs(v).max()
    t = magnitude * 1.2345  # not a power of two: rounding may differ in the last bits
    assert_allclose(positive_area(vt, tr, t * w), area, rtol=1e-14, atol=0)
    assert_close(positive_product(vt, tr, t * w, v), t * prod, 1e-14 * t * scale)
    assert_close(positive_product(vt, tr, w, t * v), t * prod, 1e-14 * t * scale)
    p2 = 2.0 ** round(math.log2(magnitude))  # power of two: exact scaling, bitwise
    assert np.array_equal(positive_area(vt, tr, p2 * w), area)
    assert np.array_equal(positive_product(vt, tr, p2 * w, v), p2 * prod)


def test_mixed_magnitudes_in_one_triangle(rng):
    """Values from 1e-12 to 1e12 within a triangle: no overflow, no cancellation."""
    mags = 10.0 ** rng.uniform(-12, 12, (200, 3))
    signs = rng.choice([-1.0, 1.0], (200, 3))
    signs[rng.random((200, 3)) < 0.15] = 0.0
    tri = unit_triangle()
    for wk, vk in zip(mags * signs, 10.0 ** rng.uniform(-12, 12, (200, 3)), strict=True):
        ref_area, ref_mom = exact_cut(wk, vk)
        area = positive_area(tri.vertices, tri.triangles, wk)[0]
        prod = positive_product(tri.vertices, tri.triangles, wk, vk)[0]
        assert math.isclose(area, 0.5 * ref_area, rel_tol=1e-13, abs_tol=0)
        # v >= 0: a sum of non-negative terms, so relative accuracy even for tiny parts
        assert math.isclose(prod, 0.5 * ref_mom, rel_tol=1e-13, abs_tol=0)


def test_serial_and_parallel_agree_bitwise(rng):
    mesh = perturbed_square(40, 0.3)
    w = random_p1(rng, mesh.n_vertices)
    v = rng.standard_normal(mesh.n_vertices)
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        a1 = positive_area(mesh.vertices, mesh.triangles, w)
        p1 = positive_product(mesh.vertices, mesh.triangles, w, v)
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        a2 = positive_area(mesh.vertices, mesh.triangles, w)
        p2 = positive_product(mesh.vertices, mesh.triangles, w, v)
    finally:
        numba.set_num_threads(old)
    assert np.array_equal(a1, a2)
    assert np.array_equal(p1, p2)


# --------------------------------------------------------------------------- estimators


def test_friedrichs_constant():
    assert_allclose(friedrichs_constant(fm.Mesh.square(4)), 2 / (np.pi * np.sqrt(2)), rtol=1e-15)
    rect = fm.Mesh.rectangle(3, 2, (0.0, 3.0, 1.0, 2.0))
    assert_allclose(friedrichs_constant(rect), 1 / (np.pi * np.sqrt(1 / 9 + 1)), rtol=1e-15)
    # the L-shape lies in the same box as the square
    assert friedrichs_constant(fm.Mesh.lshape(4)) == friedrichs_constant(fm.Mesh.square(4))


@pytest.fixture(scope="module")
def solved():
    scene = fm.Scene(fm.Mesh.square(16), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    result = fm.solve(scene, method="exact")
    assert result.converged
    return scene, result


def test_terms_at_the_discrete_solution(solved):
    scene, res = solved
    mesh = scene.mesh
    u1, u2, lam = res.u1, res.u2, res.lam
    gap = u1 - u2
    assert lam.min() >= 0  # complementary, feasible triple
    assert gap.min() >= 0
    assert 0 < (lam > 0).sum() < mesh.interior_vertices.size
    loc = local_terms(scene, u1, u2, lam)
    assert set(loc) == {"eta_nc", "eta_C", "eta_osc1", "eta_osc2"}
    for value in loc.values():
        assert value.shape == (mesh.n_triangles,)
    assert np.all(loc["eta_nc"] == 0.0)  # gap >= 0 nodally => gap >= 0 on every K
    assert np.all(loc["eta_osc1"] == 0.0)
    assert np.all(loc["eta_osc2"] == 0.0)
    # Nodal complementarity is not pointwise: on triangles that meet both a contact
    # vertex (lam > 0, gap = 0) and a free vertex (lam = 0, gap > 0) the P1
    # product lam_h gap_h is positive.  With gap >= 0 and lam_a gap_a = 0 the
    # exact value is (lam, gap)_K = |K|/12 (sum lam)(sum gap).
    lt, gt = lam[mesh.triangles], gap[mesh.triangles]
    expected = mesh.areas / 12.0 * lt.sum(1) * gt.sum(1)
    assert_allclose(loc["eta_C"], expected, rtol=1e-13, atol=0)
    zero = (lt.sum(1) == 0) | (gt.sum(1) == 0)
    assert np.all(loc["eta_C"][zero] == 0.0)
    assert np.all(loc["eta_C"][~zero] > 0.0)
    assert zero.mean() > 0.8  # only the free-boundary layer contributes

    r1, r2 = residuals(scene, u1, u2, lam)
    glob = global_terms(scene, u1, u2, lam, r1, r2)
    assert glob["lam_minus_norm"] == 0.0
    # at the exact discrete solution R is round-off: compare with the load scale
    f1, f2 = scene.loads
    b = mesh.lumped_mass
    mass = assemble_mass(mesh)
    c_f = friedrichs_constant(mesh)
    load_scale = c_f * max(
        np.sqrt((f1 / b) @ (mass @ (f1 / b))), np.sqrt((f2 / b) @ (mass @ (f2 / b)))
    )
    assert glob["eta_glob1"] < 1e-12 * load_scale
    assert glob["eta_glob2"] < 1e-12 * load_scale
    assert glob["C_F"] == c_f


def test_complementary_triple_has_no_contact_or_nonconformity_term():
    """gap = 0 on a set S, lam > 0 only at vertices whose whole patch lies in S."""
    mesh = fm.Mesh.square(12)
    x, y = mesh.vertices.T
    in_s = (np.abs(x) <= 0.5) & (np.abs(y) <= 0.5)
    gap = np.where(in_s, 0.0, 1.0 + x**2)
    # vertices all of whose neighbours are in S
    e = mesh.edges
    bad = np.zeros(mesh.n_vertices, dtype=bool)
    bad[e[~in_s[e[:, 1]], 0]] = True
    bad[e[~in_s[e[:, 0]], 1]] = True
    inner = in_s & ~bad
    assert inner.sum() > 0
    lam = np.where(inner, 1.0 + y**2, 0.0)
    u2 = 0.3 * np.sin(x)
    scene = fm.Scene(mesh, f=(lambda x, y: np.cos(x), 0.0))
    loc = local_terms(scene, u2 + gap, u2, lam)
    assert np.all(loc["eta_C"] == 0.0)
    assert np.all(loc["eta_nc"] == 0.0)


def test_nonconformity_closed_form(rng):
    """u2 - u1 = x - 0.3 on (-1, 1)^2: ||grad delta||^2 = |{x > 0.3}| = 1.4 (also per-K mu)."""
    mesh = perturbed_square(9, 0.3)
    x = mesh.vertices[:, 0]
    mu2 = rng.uniform(0.5, 2.0, mesh.n_triangles)
    for mu in (2.5, mu2):
        scene = fm.Scene(mesh, mu=(1.0, mu))
        loc = local_terms(scene, np.zeros_like(x), x - 0.3, np.zeros_like(x))
        area = positive_area(mesh.vertices, mesh.triangles, x - 0.3)
        assert_allclose(area.sum(), 1.4, rtol=1e-13)
        assert_allclose(loc["eta_nc"] ** 2, mu * area, rtol=1e-12, atol=1e-15)
        assert np.all(loc["eta_C"] == 0.0)  # lam = 0


def test_contact_term_ignores_negative_and_boundary_multiplier(rng):
    mesh = perturbed_square(8, 0.3)
    scene = fm.Scene(mesh)
    n = mesh.n_vertices
    u1, u2 = rng.standard_normal(n), rng.standard_normal(n)
    lam = rng.standard_normal(n)
    lam_int = np.where(mesh.boundary_vertex_mask, 0.0, lam)
    loc = local_terms(scene, u1, u2, lam)
    ref = positive_product(mesh.vertices, mesh.triangles, u1 - u2, np.maximum(lam_int, 0.0))
    assert np.array_equal(loc["eta_C"], ref)
    assert (loc["eta_C"] >= 0).all()
    assert loc["eta_C"].sum() > 0
    assert loc["eta_nc"].sum() > 0  # the random iterate is infeasible
    assert np.array_equal(local_terms(scene, u1, u2, lam_int)["eta_C"], loc["eta_C"])


def test_global_terms_formulas(rng):
    mesh = perturbed_square(8, 0.3)
    n = mesh.n_vertices
    mu1 = rng.uniform(0.5, 4.0, mesh.n_triangles)
    scene = fm.Scene(mesh, mu=(mu1, 0.25))
    b = mesh.lumped_mass
    interior = ~mesh.boundary_vertex_mask
    q1, q2, lam = rng.standard_normal((3, n))
    r1, r2 = b * q1, b * q2  # rho_i = q_i at interior vertices
    z = np.zeros(n)
    glob = global_terms(scene, z, z, lam, r1, r2)
    mass = assemble_mass(mesh).toarray()
    rho1, rho2 = np.where(interior, q1, 0), np.where(interior, q2, 0)
    lam_minus = np.where(interior, np.maximum(-lam, 0), 0)
    c_f = 2 / (np.pi * np.sqrt(2))
    norm = lambda x: np.sqrt(x @ mass @ x)  # noqa: E731
    assert glob["mu1"] == mu1.min()  # per-triangle mu: the minimum keeps the bound guaranteed
    assert glob["mu2"] == 0.25
    expected = {
        "rho_norm1": norm(rho1),
        "rho_norm2": norm(rho2),
        "lam_minus_norm": norm(lam_minus),
        "eta_glob1": c_f / np.sqrt(mu1.min()) * norm(rho1 + lam_minus),
        "eta_glob2": c_f / np.sqrt(0.25) * norm(rho2 - lam_minus),
        "C_F": c_f,
    }
    for key, value in expected.items():
        assert_allclose(glob[key], value, rtol=1e-13, err_msg=key)
    # the mass matrix is assembled once and cached on the scene
    cached = scene._cache["M"]
    global_terms(scene, z, z, lam, r1, r2)
    assert scene._cache["M"] is cached


def test_oscillation_is_zero_for_p1_data(rng):
    mesh = perturbed_square(6, 0.3)
    n = mesh.n_vertices
    x, y = mesh.vertices.T
    z = np.zeros(n)
    for f in ((-1.0, 2.0), (rng.standard_normal(n), 3.0 * x - y)):
        loc = local_terms(fm.Scene(mesh, f=f), z, z, z)
        assert np.all(loc["eta_osc1"] == 0.0)
        assert np.all(loc["eta_osc2"] == 0.0)
    # a P1 callable goes through the quadrature path and gives round-off only
    loc = local_terms(fm.Scene(mesh, f=(lambda x, y: 1 + 2 * x - 3 * y, 0.0)), z, z, z)
    assert loc["eta_osc1"].max() < 1e-14
    assert np.all(loc["eta_osc2"] == 0.0)


def _f_smooth(x, y):
    return np.sin(np.pi * x) * np.cos(2 * y) + x * x


def test_oscillation_of_smooth_data_converges():
    """||f - Pi f||_Omega = O(h^2), hence (sum_K eta_osc,K^2)^(1/2) = O(h^3) (one more h_K)."""
    hs, osc, proj = [], [], []
    for n in (8, 16, 32):
        mesh = fm.Mesh.square(n)
        scene = fm.Scene(mesh, mu=(2.0, 0.5), f=(_f_smooth, 1.0))
        z = np.zeros(mesh.n_vertices)
        loc = local_terms(scene, z, z, z)
        eta = loc["eta_osc1"]
        assert (eta > 0).all()
        assert np.all(loc["eta_osc2"] == 0.0)
        hs.append(mesh.h)
        osc.append(np.sqrt(eta @ eta))
        proj.append(np.sqrt((((np.pi / mesh.diameters) * np.sqrt(2.0) * eta) ** 2).sum()))
    rate_proj = np.polyfit(np.log(hs), np.log(proj), 1)[0]
    rate_osc = np.polyfit(np.log(hs), np.log(osc), 1)[0]
    assert 1.8 < rate_proj < 2.2
    assert 2.8 < rate_osc < 3.2


def test_oscillation_with_per_triangle_mu_and_reference(rng):
    mesh = perturbed_square(6, 0.3)
    mu = rng.uniform(0.5, 2.0, mesh.n_triangles)
    z = np.zeros(mesh.n_vertices)
    one = local_terms(fm.Scene(mesh, f=(0.0, _f_smooth)), z, z, z)["eta_osc2"]
    var = local_terms(fm.Scene(mesh, mu=(1.0, mu), f=(0.0, _f_smooth)), z, z, z)["eta_osc2"]
    assert_allclose(var, one / np.sqrt(mu), rtol=1e-14)
    # reference: brute L2 projection per triangle with a degree-12 rule
    bary, wq = triangle_rule(12)
    ref = np.empty(mesh.n_triangles)
    for k, tri in enumerate(mesh.triangles):
        p = mesh.vertices[tri]
        xq, yq = (bary @ p).T
        fq = _f_smooth(xq, yq)
        loc_mass = (bary.T * wq) @ bary
        coef = np.linalg.solve(loc_mass, (bary.T * wq) @ fq)
        ref[k] = np.sqrt(mesh.areas[k] * wq @ (fq - bary @ coef) ** 2)
    ref *= mesh.diameters / np.pi
    # with the scene's rule (degree 5) the projection residual is only approximated on
    # this coarse mesh; with the reference's rule the two agree to round-off
    fine = local_terms(fm.Scene(mesh, f=(0.0, _f_smooth), load_degree=12), z, z, z)["eta_osc2"]
    assert_allclose(fine, ref, rtol=1e-10)


def test_input_validation():
    mesh = fm.Mesh.square(3)
    scene = fm.Scene(mesh)
    z = np.zeros(mesh.n_vertices)
    with pytest.raises(DataError, match="u1"):
        local_terms(scene, z[:-1], z, z)
    with pytest.raises(DataError, match="lam"):
        local_terms(scene, z, z, np.full_like(z, np.nan))
    with pytest.raises(DataError, match="r2"):
        global_terms(scene, z, z, z, z, np.ones((2, 2)))
    loc = local_terms(scene, z, z, z)
    glob = global_terms(scene, z, z, z, z, z)
    m = mesh.n_triangles
    with pytest.raises(DataError, match="eta_F1"):
        combine(-np.ones(m), np.zeros(m), loc, glob)
    with pytest.raises(DataError, match="eta_F2"):
        combine(np.zeros(m), np.zeros(m + 1), loc, glob)
    with pytest.raises(DataError, match="glob"):
        combine(np.zeros(m), np.zeros(m), loc, {"eta_glob1": 0.0})


# --------------------------------------------------------------------------- combine


def _inputs(f1, f2, osc1, osc2, nc, eta_c, g1=0.0, g2=0.0, rho1=0.0, rho2=0.0, lm=0.0, mu=(1, 1)):
    local = {
        "eta_osc1": np.array(osc1, float),
        "eta_osc2": np.array(osc2, float),
        "eta_nc": np.array(nc, float),
        "eta_C": np.array(eta_c, float),
    }
    glob = {
        "eta_glob1": g1,
        "eta_glob2": g2,
        "rho_norm1": rho1,
        "rho_norm2": rho2,
        "lam_minus_norm": lm,
        "C_F": 0.5,
        "mu1": float(mu[0]),
        "mu2": float(mu[1]),
    }
    return np.array(f1, float), np.array(f2, float), local, glob


def test_combine_by_hand():
    # Two triangles.  Membrane 1: osc + F = (1 + 2, 0) = (3, 0); membrane 2:
    # osc + F = (0, 3), plus nc = (0, 1) in a: (0, 4).  So
    # a = sqrt(9 + 16) + sqrt(3^2 + 4^2) = 5 + 5 = 10, c = 2 + 4 = 6,
    # eta = (10 + sqrt(100 + 24)) / 2 + 1 = 6 + sqrt(31),
    # eta_alg = 0.5 sqrt(0.6^2 / 1 + 0.8^2 / 4) = 0.5 sqrt(0.52),
    # eta_lin = 0.5 sqrt(1 + 1/4) * 2 + 2 * 1 = sqrt(1.25) + 2,
    # eta_disc = sqrt(9 + 9) + sqrt(6).
    args = _inputs(
        f1=[2, 0], f2=[0, 2], osc1=[1, 0], osc2=[0, 1], nc=[0, 1], eta_c=[2, 4],
        g1=3.0, g2=4.0, rho1=0.6, rho2=0.8, lm=2.0, mu=(1.0, 4.0),
    )  # fmt: skip
    out = combine(*args)
    tot = out["totals"]
    assert_allclose(tot["a"], 10.0, rtol=1e-15)
    assert_allclose(tot["c"], 6.0, rtol=1e-15)
    assert_allclose(tot["eta"], 6.0 + np.sqrt(31.0), rtol=1e-15)
    assert_allclose(tot["eta_alg"], 0.5 * np.sqrt(0.52), rtol=1e-15)
    assert_allclose(tot["eta_lin"], np.sqrt(1.25) + 2.0, rtol=1e-15)
    assert_allclose(tot["eta_disc"], np.sqrt(18.0) + np.sqrt(6.0), rtol=1e-15)
    assert_allclose(tot["eta_nc"], 1.0, rtol=1e-15)
    assert_allclose(tot["eta_unguaranteed_slides"], np.sqrt(18.0 + 6.0), rtol=1e-15)
    assert set(out["maps"]) == {"eta_F1", "eta_F2", "eta_osc1", "eta_osc2", "eta_nc", "eta_C"}
    assert_allclose(out["maps"]["eta_F1"], [2, 0])


def test_slides_variant_is_not_an_upper_bound():
    """MATH.md section 5: a = c = 1 admits x = (1 + sqrt 5)/2 > sqrt(a^2 + c) = sqrt 2."""
    out = combine(*_inputs(f1=[1], f2=[0], osc1=[0], osc2=[0], nc=[0], eta_c=[1]))["totals"]
    assert out["a"] == 1.0
    assert out["c"] == 1.0
    x = out["eta"]  # eta_nc = 0 here, so eta is the root itself
    assert_allclose(x, (1 + np.sqrt(5)) / 2, rtol=1e-15)
    assert_allclose(x * x, out["a"] * x + out["c"], rtol=1e-15)  # an admissible error value
    assert out["eta_unguaranteed_slides"] == np.sqrt(2.0)
    assert out["eta_unguaranteed_slides"] < x


def test_combine_monotone_and_root_property(rng):
    m = 7
    base = _inputs(
        *(rng.uniform(0, 1, m) for _ in range(6)), g1=0.3, g2=0.2, rho1=0.1, rho2=0.2, lm=0.3,
        mu=(0.5, 2.0),
    )  # fmt: skip
    f1, f2, local, glob = base
    ref = combine(f1, f2, local, glob)["totals"]
    a, c, nc_total = ref["a"], ref["c"], ref["eta_nc"]
    x = ref["eta"] - nc_total
    assert x * x <= a * x + c + 1e-14 * (a * x + c)
    assert x * x >= (a * x + c) * (1 - 1e-14)  # x is the root, not just any bound
    for k in range(m):
        for which in ("f1", "f2", "eta_osc1", "eta_osc2", "eta_nc", "eta_C"):
            g1, g2, loc = f1.copy(), f2.copy(), {key: v.copy() for key, v in local.items()}
            arr = {"f1": g1, "f2": g2}.get(which, loc.get(which))
            arr[k] += 0.1
            assert combine(g1, g2, loc, glob)["totals"]["eta"] > ref["eta"], (which, k)
    for key in ("eta_glob1", "eta_glob2"):
        assert combine(f1, f2, local, {**glob, key: glob[key] + 0.1})["totals"]["eta"] > ref["eta"]
    # zero inputs give zero
    zero = combine(*_inputs(*([0.0] * m for _ in range(6))))["totals"]
    assert all(zero[k] == 0.0 for k in ("eta", "eta_disc", "eta_lin", "eta_alg", "a", "c"))


def test_components_react_to_the_right_defects(solved):
    """eta_lin > 0 for an infeasible iterate, eta_alg > 0 for a non-zero residual."""
    scene, res = solved
    mesh = scene.mesh
    n = mesh.n_triangles
    bumped = res.lam.copy()
    inner = mesh.interior_vertices
    bumped[inner[::7]] -= 0.5  # negative multiplier somewhere
    u2 = res.u2.copy()
    u2[inner[::5]] += 0.01  # membrane 2 above membrane 1 somewhere
    r1, r2 = residuals(scene, res.u1, u2, bumped)
    loc = local_terms(scene, res.u1, u2, bumped)
    glob = global_terms(scene, res.u1, u2, bumped, r1, r2)
    tot = combine(np.zeros(n), np.zeros(n), loc, glob)["totals"]
    assert tot["eta_lin"] > 0
    assert tot["eta_alg"] > 0
    assert tot["eta_nc"] > 0
    # with consistent global terms the components dominate the bound
    flux = np.random.default_rng(20261121).uniform(0, 1e-3, (2, n))
    tot = combine(*flux, loc, glob)["totals"]
    assert tot["eta"] <= tot["eta_disc"] + tot["eta_lin"] + tot["eta_alg"]
    exact = combine(
        np.zeros(n),
        np.zeros(n),
        local_terms(scene, res.u1, res.u2, res.lam),
        global_terms(scene, res.u1, res.u2, res.lam, res.r1, res.r2),
    )["totals"]
    assert exact["eta_lin"] == 0.0
    assert exact["eta_alg"] < 1e-12 * tot["eta_alg"]


@pytest.mark.parametrize("per_triangle", [False, True])
def test_fused_contact_terms_match_separate_path(per_triangle):
    """kernels.cut.contact_terms vs NumPy gradients + positive_area/positive_product."""
    from fastmem.kernels.cut import contact_terms

    rng = np.random.default_rng(3)
    base = fm.Mesh.square(10)
    v = base.vertices.copy()
    interior = base.interior_vertices
    v[interior] += rng.uniform(-0.03, 0.03, (interior.size, 2))
    mesh = fm.Mesh(v, base.triangles)
    gap = rng.standard_normal(mesh.n_vertices)
    lam_hat = np.abs(rng.standard_normal(mesh.n_vertices))
    mu2 = rng.uniform(0.1, 10.0, mesh.n_triangles) if per_triangle else np.array([2.5])
    nc, c = contact_terms(mesh.vertices, mesh.triangles, gap, lam_hat, mu2)
    grad = np.einsum("mij,mi->mj", mesh.gradients, gap[mesh.triangles])
    neg = positive_area(mesh.vertices, mesh.triangles, -gap)
    ref_nc = np.sqrt((mu2 if per_triangle else mu2[0]) * (grad**2).sum(axis=1) * neg)
    ref_c = positive_product(mesh.vertices, mesh.triangles, gap, lam_hat)
    assert ((neg > 0) & (neg < 0.999 * mesh.areas)).any()  # cut triangles are exercised
    assert_allclose(nc, ref_nc, rtol=1e-12, atol=1e-15)
    assert_allclose(c, ref_c, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize(
    "gap", [[5e-324, 0.0, 0.0], [5e-324, 0.0, -1.0], [0.0, 5e-324, -5e-324], [-5e-324, 0.0, 1e-320]]
)
def test_cut_terms_finite_for_subnormal_gaps(gap):
    """Subnormal gaps (g = 5e-324, found by test_hostile) give finite terms, scaled exactly."""
    from fastmem.kernels import cut

    vertices = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    triangles = np.array([[0, 1, 2]])
    lam_hat, mu2 = np.array([1.0, 2.0, 3.0]), np.ones(1)
    gap = np.array(gap)
    nc, c = cut.contact_terms(vertices, triangles, gap, lam_hat, mu2)
    assert np.isfinite(nc).all()
    assert np.isfinite(c).all()
    assert (nc >= 0).all()
    assert (c >= 0).all()
    # eta_C is linear in the gap: the same cut on the gap scaled by 2**600 (all normal),
    # scaled back, agrees to the few digits a subnormal result carries
    _, c_big = cut.contact_terms(vertices, triangles, gap * 2.0**600, lam_hat, mu2)
    assert c[0] == pytest.approx(c_big[0] * 2.0**-600, rel=1e-2, abs=1e-321)
