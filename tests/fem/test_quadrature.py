"""Tests of fastmem.quadrature: exactness, sharpness, positivity and validation."""

from __future__ import annotations

import functools
import itertools
from fractions import Fraction
from math import factorial

import numpy as np
import pytest
from numpy.testing import assert_allclose

from fastmem.errors import DataError, FastmemError, ParameterError
from fastmem.fem.quadrature import MAX_DEGREE, quadrature_points, triangle_rule

DEGREES = range(13)  # 0..12

# Physical triangles with dyadic (exactly representable) vertices, counter-clockwise.
# The first lies in the positive quadrant (no cancellation: relative error is meaningful);
# the second straddles the axes (errors measured against the size of |x|^a |y|^b).
TRI_POSITIVE = ((0.5, 0.25), (1.75, 0.5), (0.25, 1.25))
TRI_MIXED = ((-0.75, -0.5), (1.25, -0.25), (0.5, 1.5))


def monomials(degree):
    """All exponent pairs (a, b) with a + b <= degree."""
    return [(a, b) for a in range(degree + 1) for b in range(degree + 1 - a)]


def reference_exact(a, b):
    """Integral of x^a y^b over the reference triangle (0,0), (1,0), (0,1)."""
    return factorial(a) * factorial(b) / factorial(a + b + 2)


def _compositions(n):
    """Triples (i, j, k) of non-negative integers with i + j + k = n."""
    return [(i, j, n - i - j) for i in range(n + 1) for j in range(n + 1 - i)]


def _multinomial(n, idx):
    out = factorial(n)
    for i in idx:
        out //= factorial(i)
    return out


@functools.cache
def physical_exact(tri, a, b):
    """Exact integral of x^a y^b over triangle ``tri`` in rational arithmetic.

    Writes x = sum_k l_k x_k, y = sum_k l_k y_k in barycentrics l_k, expands
    with the multinomial theorem and integrates each term with
    int_K l0^p l1^q l2^r = 2 |K| p! q! r! / (p + q + r + 2)!.
    """
    xs = [Fraction(v[0]) for v in tri]
    ys = [Fraction(v[1]) for v in tri]
    area = abs((xs[1] - xs[0]) * (ys[2] - ys[0]) - (xs[2] - xs[0]) * (ys[1] - ys[0])) / 2
    total = Fraction(0)
    for i in _compositions(a):
        ci = _multinomial(a, i) * xs[0] ** i[0] * xs[1] ** i[1] * xs[2] ** i[2]
        for j in _compositions(b):
            cj = _multinomial(b, j) * ys[0] ** j[0] * ys[1] ** j[1] * ys[2] ** j[2]
            p = [i[k] + j[k] for k in range(3)]
            moment = Fraction(
                2 * factorial(p[0]) * factorial(p[1]) * factorial(p[2]), factorial(a + b + 2)
            )
            total += ci * cj * moment * area
    return total


def integrate_on(tri, degree, a, b):
    bary, weights = triangle_rule(degree)
    vertices = np.array(tri, dtype=np.float64)
    x, y = quadrature_points(vertices, np.array([[0, 1, 2]]), bary)
    e1 = vertices[1] - vertices[0]
    e2 = vertices[2] - vertices[0]
    area = 0.5 * abs(e1[0] * e2[1] - e1[1] * e2[0])
    return area * float(np.sum(weights * x[0] ** a * y[0] ** b))


# ------------------------------------------------------------------ exactness


@pytest.mark.parametrize("degree", DEGREES)
def test_reference_triangle_monomials_exact(degree):
    bary, weights = triangle_rule(degree)
    x, y = bary[:, 1], bary[:, 2]
    for a, b in monomials(degree):
        approx = 0.5 * np.sum(weights * x**a * y**b)
        assert_allclose(approx, reference_exact(a, b), rtol=1e-13, atol=0, err_msg=f"x^{a} y^{b}")


@pytest.mark.parametrize("degree", DEGREES)
def test_physical_triangle_monomials_exact(degree):
    for a, b in monomials(degree):
        exact = float(physical_exact(TRI_POSITIVE, a, b))
        approx = integrate_on(TRI_POSITIVE, degree, a, b)
        assert_allclose(approx, exact, rtol=1e-13, atol=0, err_msg=f"x^{a} y^{b}")


@pytest.mark.parametrize("degree", DEGREES)
def test_straddling_triangle_monomials_exact(degree):
    vertices = np.array(TRI_MIXED)
    area = float(physical_exact(TRI_MIXED, 0, 0))
    rx, ry = np.abs(vertices).max(axis=0)
    for a, b in monomials(degree):
        exact = float(physical_exact(TRI_MIXED, a, b))
        approx = integrate_on(TRI_MIXED, degree, a, b)
        scale = area * rx**a * ry**b  # bounds the integral of |x^a y^b|
        assert abs(approx - exact) <= 1e-13 * scale, f"x^{a} y^{b}: {approx} vs {exact}"


@pytest.mark.parametrize("degree", [0, 1, 2, 5, 7, 9, 11])
def test_rule_is_not_exact_beyond_its_precision(degree):
    """The exactness tests are sharp: some monomial of degree precision + 1 is not
    integrated exactly (precision = degree, except the centroid at degree 0, which is
    exact to degree 1), so a rule labelled with a higher degree than it has fails."""
    precision = max(degree, 1)
    bary, weights = triangle_rule(degree)
    x, y = bary[:, 1], bary[:, 2]
    top = precision + 1
    rel = [
        abs(0.5 * np.sum(weights * x**a * y ** (top - a)) - reference_exact(a, top - a))
        / reference_exact(a, top - a)
        for a in range(top + 1)
    ]
    assert max(rel) > 1e-6


def test_exactness_check_detects_a_mislabelled_rule():
    """The degree-2 rule must fail the exactness test of degree 3."""
    bary, weights = triangle_rule(2)
    x, y = bary[:, 1], bary[:, 2]
    errors = [
        abs(0.5 * np.sum(weights * x**a * y**b) - reference_exact(a, b)) / reference_exact(a, b)
        for a, b in monomials(3)
    ]
    assert max(errors) > 1e-13


# ------------------------------------------------------------------ structure


@pytest.mark.parametrize("degree", range(MAX_DEGREE + 1))
def test_weights_sum_to_one_and_points_inside(degree):
    bary, weights = triangle_rule(degree)
    assert bary.shape == (weights.size, 3)
    assert bary.dtype == np.float64
    assert weights.dtype == np.float64
    assert_allclose(weights.sum(), 1.0, rtol=0, atol=1e-14)
    assert np.all(weights > 0)
    assert np.all(bary >= 0)
    assert_allclose(bary.sum(axis=1), 1.0, rtol=0, atol=1e-15)


def test_known_rules():
    bary, weights = triangle_rule(0)
    assert_allclose(bary, [[1 / 3, 1 / 3, 1 / 3]], rtol=0, atol=1e-16)
    assert triangle_rule(1)[1].size == 1
    bary, weights = triangle_rule(2)
    assert_allclose(np.sort(bary, axis=1), np.tile([1 / 6, 1 / 6, 2 / 3], (3, 1)), atol=1e-16)
    assert_allclose(weights, 1 / 3, rtol=0, atol=1e-16)
    for degree in (3, 4, 5):
        bary, weights = triangle_rule(degree)
        assert weights.size == 7
        assert_allclose(weights[0], 9 / 40, rtol=1e-15)
        r15 = np.sqrt(15.0)
        assert_allclose(np.sort(weights[1:]), [(155 - r15) / 1200] * 3 + [(155 + r15) / 1200] * 3)
    for degree in range(6, MAX_DEGREE + 1):
        n = -(-(degree + 1) // 2)
        assert triangle_rule(degree)[1].size == n * n


def test_rules_are_cached_and_read_only():
    bary, weights = triangle_rule(7)
    again = triangle_rule(np.int64(7))
    assert again[0] is bary
    assert again[1] is weights
    with pytest.raises(ValueError, match="read-only"):
        bary[0, 0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        weights[0] = 1.0


@pytest.mark.parametrize("degree", [-1, MAX_DEGREE + 1, 100, 2.0, 2.5, "3", None, True, [2]])
def test_invalid_degree(degree):
    with pytest.raises(ParameterError, match="degree"):
        triangle_rule(degree)


def test_parameter_error_is_value_error():
    with pytest.raises(ValueError, match="degree"):
        triangle_rule(-3)
    with pytest.raises(FastmemError):
        triangle_rule(31)


# ------------------------------------------------------------------ quadrature_points


def test_quadrature_points_match_per_triangle_mapping():
    rng = np.random.default_rng(731_905)
    vertices = rng.uniform(-2, 2, size=(9, 2))
    triangles = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8], [2, 5, 8]])
    bary, _ = triangle_rule(5)
    x, y = quadrature_points(vertices, triangles, bary)
    assert x.shape == y.shape == (4, 7)
    assert x.dtype == y.dtype == np.float64
    for m, tri in enumerate(triangles):
        expected = bary @ vertices[tri]
        assert_allclose(x[m], expected[:, 0], rtol=0, atol=1e-15)
        assert_allclose(y[m], expected[:, 1], rtol=0, atol=1e-15)


def test_quadrature_points_kernel_matches_numpy_in_chunks():
    """The threaded kernel against the NumPy gather-and-product, serial and in chunks."""
    import fastmem as fm

    mesh = fm.Mesh.square(96)  # 18,432 triangles: several chunks per thread
    rng = np.random.default_rng(5)
    vertices = mesh.vertices + rng.uniform(-1e-3, 1e-3, size=mesh.vertices.shape)
    bary, _ = triangle_rule(7)
    corners = vertices[mesh.triangles]
    for parallel in (True, False):
        x, y = quadrature_points(vertices, mesh.triangles, bary, parallel=parallel)
        assert_allclose(x, corners[:, :, 0] @ bary.T, rtol=0, atol=4e-16)
        assert_allclose(y, corners[:, :, 1] @ bary.T, rtol=0, atol=4e-16)
    # int32 indices and a slice give the same points
    part = mesh.triangles[100:5000].astype(np.int32)
    xs, ys = quadrature_points(vertices, part, bary)
    assert np.array_equal(xs, x[100:5000])
    assert np.array_equal(ys, y[100:5000])


def test_quadrature_points_integrate_over_a_mesh():
    """Sum of the rule over a triangulated square gives the exact monomial integrals."""
    n = 3
    t = np.linspace(0.0, 1.0, n + 1)
    X, Y = np.meshgrid(t, t)
    vertices = np.column_stack([X.ravel(), Y.ravel()])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    triangles = np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    bary, weights = triangle_rule(8)
    x, y = quadrature_points(vertices, triangles, bary)
    areas = np.full(len(triangles), 0.5 / n**2)
    for p, q in itertools.product(range(5), range(5)):
        approx = areas @ ((x**p * y**q) @ weights)
        assert_allclose(approx, 1.0 / ((p + 1) * (q + 1)), rtol=1e-13)


@pytest.mark.parametrize(
    ("vertices", "triangles", "bary"),
    [
        (np.zeros((3, 3)), np.array([[0, 1, 2]]), np.full((1, 3), 1 / 3)),
        (np.zeros((3, 2)), np.array([0, 1, 2]), np.full((1, 3), 1 / 3)),
        (np.zeros((3, 2)), np.array([[0, 1, 2]]), np.full((3,), 1 / 3)),
    ],
)
def test_quadrature_points_bad_shapes(vertices, triangles, bary):
    with pytest.raises(DataError, match="shape"):
        quadrature_points(vertices, triangles, bary)
