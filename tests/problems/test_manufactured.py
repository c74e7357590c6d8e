"""Tests of fastmem.manufactured: the exact solutions of docs/method.md §7 and the error routine."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from fastmem.errors import DataError, MeshError, ParameterError
from fastmem.problems.manufactured import Manufactured, energy_error, energy_error_parts

SEED = 731_905

PARAMETER_SETS = [
    {},
    {"kappa": 0.0},
    {"discontinuous": True},
    {"mu": (1.0, 10.0)},
    {"mu": (3.0, 0.2), "g": 0.2, "beta": 0.5, "s0": -0.7, "kappa": 2.5},
    {"mu": (0.5, 2.0), "discontinuous": True, "kappa": 3.0},
]
IDS = ["default", "kappa0", "discontinuous", "mu1-10", "mixed", "mixed-disc"]


def square_mesh(n):
    """Structured mesh of (-1, 1)^2: n x n cells, two counter-clockwise triangles each."""
    t = np.linspace(-1.0, 1.0, n + 1)
    X, Y = np.meshgrid(t, t)  # X varies along axis 1
    vertices = np.column_stack([X.ravel(), Y.ravel()])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    triangles = np.vstack([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    boundary = (np.abs(vertices[:, 0]) == 1.0) | (np.abs(vertices[:, 1]) == 1.0)
    return SimpleNamespace(
        vertices=vertices,
        triangles=triangles.astype(np.int64),
        boundary_vertex_mask=boundary,
        areas=np.full(len(triangles), 2.0 / n**2),
    )


def grid(n=201, lo=-1.0, hi=1.0):
    t = np.linspace(lo, hi, n)
    return np.meshgrid(t, t)


def bubble(x, y):
    return (1 - x**2) * (1 - y**2)


# ------------------------------------------------------------------ validation


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"mu": (0.0, 1.0)}, "mu1"),
        ({"mu": (1.0, -2.0)}, "mu2"),
        ({"mu": (math.nan, 1.0)}, "mu1"),
        ({"mu": (1.0, math.inf)}, "mu2"),
        ({"mu": (1.0,)}, "mu"),
        ({"mu": (1.0, 1.0, 1.0)}, "mu"),
        ({"mu": 1.0}, "mu"),
        ({"mu": "ab"}, "mu"),
        ({"mu": ("1", 1.0)}, "mu1"),
        ({"g": 0.0}, "g"),
        ({"g": -0.1}, "g"),
        ({"g": math.nan}, "g"),
        ({"beta": 0.0}, "beta"),
        ({"beta": -1.0}, "beta"),
        ({"beta": math.inf}, "beta"),
        ({"kappa": -1e-3}, "kappa"),
        ({"kappa": math.nan}, "kappa"),
        ({"s0": math.nan}, "s0"),
        ({"s0": "1"}, "s0"),
        ({"discontinuous": "yes"}, "discontinuous"),
    ],
)
def test_invalid_parameters(kwargs, field):
    with pytest.raises(ParameterError, match=field):
        Manufactured(**kwargs)


def test_parameter_error_is_value_error_and_names_value():
    with pytest.raises(ValueError, match=r"g must be positive, got -0\.5"):
        Manufactured(g=-0.5)


def test_properties_and_repr():
    m = Manufactured(mu=(2.0, 3.0), g=0.2, beta=0.5, s0=0.5, kappa=0.0, discontinuous=True)
    assert (m.mu1, m.mu2) == (2.0, 3.0)
    assert m.mu == (2.0, 3.0)
    assert (m.g, m.beta, m.s0, m.kappa, m.discontinuous) == (0.2, 0.5, 0.5, 0.0, True)
    assert m.contact_threshold == pytest.approx(0.4)
    assert "mu=(2.0, 3.0)" in repr(m)
    assert m.to_dict()["mu"] == [2.0, 3.0]
    assert m.quadrature_degree == 7
    Manufactured(mu=np.array([1.0, 2.0]), kappa=0)  # arrays and ints are accepted


# ------------------------------------------------------------------ shapes


def test_fields_are_vectorised_over_any_shape():
    m = Manufactured()
    rng = np.random.default_rng(SEED)
    x = rng.uniform(-1, 1, size=(4, 5, 3))
    y = rng.uniform(-1, 1, size=(4, 5, 3))
    for name in ("u1", "u2", "lam", "gap", "f1", "f2", "q"):
        out = getattr(m, name)(x, y)
        assert out.shape == x.shape, name
        assert out.dtype == np.float64, name
        flat = getattr(m, name)(x.ravel(), y.ravel())
        assert_allclose(out.ravel(), flat, rtol=0, atol=0)
    for name in ("grad_u1", "grad_u2"):
        dx, dy = getattr(m, name)(x, y)
        assert dx.shape == dy.shape == x.shape
    assert m.contact_indicator(x, y).dtype == np.bool_
    assert np.ndim(m.u1(0.1, 0.2)) == 0


def test_mismatched_shapes_raise():
    with pytest.raises(DataError, match="shape"):
        Manufactured().u1(np.zeros(3), np.zeros(4))


# ------------------------------------------------------------------ exact solution


@pytest.mark.parametrize("params", PARAMETER_SETS, ids=IDS)
def test_boundary_values(params):
    m = Manufactured(**params)
    t = np.linspace(-1.0, 1.0, 101)
    one = np.ones_like(t)
    for x, y in ((t, one), (t, -one), (one, t), (-one, t)):
        assert_allclose(m.u1(x, y), m.g, rtol=1e-15, atol=0)
        assert_allclose(m.u2(x, y), 0.0, rtol=0, atol=1e-15 * m.g)
        assert_allclose(m.gap(x, y), m.g, rtol=1e-15, atol=0)
        assert np.all(m.lam(x, y) == 0.0)


@pytest.mark.parametrize("params", PARAMETER_SETS, ids=IDS)
def test_complementarity(params):
    m = Manufactured(**params)
    x, y = grid(301)
    gap, lam = m.gap(x, y), m.lam(x, y)
    assert np.all(gap >= 0.0)
    assert np.all(lam >= 0.0)
    assert np.all(gap * lam == 0.0)
    assert_allclose(m.u1(x, y) - m.u2(x, y), gap, rtol=0, atol=1e-14)
    contact = m.contact_indicator(x, y)
    assert np.all(gap[contact] == 0.0)
    assert np.all(gap[~contact] > 0.0)
    if m.kappa > 0:
        # the pressure is active somewhere (not only on the free boundary)
        assert np.any(lam > 0.0)
    else:
        assert np.all(lam == 0.0)
        assert np.any(contact)


def test_lambda_variants():
    x, y = grid(101)
    q = 0.1 - 0.25 * bubble(x, y)
    assert_allclose(Manufactured(kappa=2.0).lam(x, y), 2.0 * np.maximum(-q, 0), atol=1e-15)
    assert_allclose(Manufactured(kappa=2.0, discontinuous=True).lam(x, y), 2.0 * (q < 0), atol=0)


@settings(max_examples=60, deadline=None)
@given(
    mu1=st.floats(0.05, 20.0),
    mu2=st.floats(0.05, 20.0),
    g=st.floats(0.01, 1.0),
    beta=st.floats(0.01, 5.0),
    s0=st.floats(-3.0, 3.0),
    kappa=st.floats(0.0, 5.0),
    discontinuous=st.booleans(),
    x=st.floats(-1.0, 1.0),
    y=st.floats(-1.0, 1.0),
)
def test_complementarity_property(mu1, mu2, g, beta, s0, kappa, discontinuous, x, y):
    m = Manufactured((mu1, mu2), g, beta, s0, kappa, discontinuous)
    gap, lam = m.gap(x, y), m.lam(x, y)
    assert gap >= 0.0
    assert lam >= 0.0
    assert gap * lam == 0.0
    assert bool(m.contact_indicator(x, y)) == (g - beta * bubble(x, y) <= 0.0)
    assert m.u1(x, 1.0) == pytest.approx(g, rel=1e-14)
    assert m.u2(-1.0, y) == pytest.approx(0.0, abs=1e-14 * g)


@pytest.mark.parametrize(
    ("params", "threshold"),
    [({}, 0.4), ({"g": 0.05, "beta": 0.5}, 0.1), ({"g": 0.3, "beta": 0.5}, 0.6)],
)
def test_contact_set(params, threshold):
    m = Manufactured(**params)
    assert m.contact_threshold == pytest.approx(threshold, rel=1e-15)
    x, y = grid(401)
    b = bubble(x, y)
    away = np.abs(b - threshold) > 1e-12
    contact = m.contact_indicator(x, y)
    assert np.array_equal(contact[away], (b >= threshold)[away])
    assert np.any(contact)
    assert not np.all(contact)


def test_default_contact_set_is_b_at_least_04():
    m = Manufactured()
    x, y = grid(201)
    b = bubble(x, y)
    away = np.abs(b - 0.4) > 1e-12
    assert np.array_equal(m.contact_indicator(x, y)[away], (b >= 0.4)[away])
    assert m.contact_indicator(0.0, 0.0)
    assert not m.contact_indicator(0.9, 0.0)


def _away_from_free_boundary(m, x, y, margin):
    return np.abs(m.q(x, y)) > margin


@pytest.mark.parametrize("params", PARAMETER_SETS, ids=IDS)
def test_gradients_match_finite_differences(params):
    m = Manufactured(**params)
    x, y = grid(61, -0.99, 0.99)
    keep = _away_from_free_boundary(m, x, y, 1e-4)
    x, y = x[keep], y[keep]
    h = 1e-6
    for u, grad in ((m.u1, m.grad_u1), (m.u2, m.grad_u2)):
        dx, dy = grad(x, y)
        fdx = (u(x + h, y) - u(x - h, y)) / (2 * h)
        fdy = (u(x, y + h) - u(x, y - h)) / (2 * h)
        scale = 1.0 + np.max(np.abs(dx)) + np.max(np.abs(dy))
        assert_allclose(dx, fdx, rtol=0, atol=1e-8 * scale)
        assert_allclose(dy, fdy, rtol=0, atol=1e-8 * scale)


def _five_point_laplacian(u, x, y, h):
    return (u(x + h, y) + u(x - h, y) + u(x, y + h) + u(x, y - h) - 4.0 * u(x, y)) / h**2


@pytest.mark.parametrize("mu", [(1.0, 1.0), (1.0, 10.0), (3.0, 0.2)])
@pytest.mark.parametrize(
    "extra", [{}, {"discontinuous": True}, {"kappa": 0.0}, {"s0": -2.0, "g": 0.2, "beta": 0.4}]
)
def test_loads_match_finite_difference_laplacian(mu, extra):
    m = Manufactured(mu=mu, **extra)
    h = 1e-3
    x, y = grid(81, -0.98, 0.98)
    # |grad q| <= beta |grad b| <= 2 beta, so the 5-point stencil stays on one side
    keep = _away_from_free_boundary(m, x, y, 4.0 * m.beta * h + 1e-3)
    x, y = x[keep], y[keep]
    f1_fd = -m.mu1 * _five_point_laplacian(m.u1, x, y, h) - m.lam(x, y)
    f2_fd = -m.mu2 * _five_point_laplacian(m.u2, x, y, h) + m.lam(x, y)
    # truncation error h^2/12 |u_xxxx + u_yyyy|: w = q^2/g has 4th derivatives <= 24 beta^2/g
    tol = h**2 * (5.0 + 24.0 * m.beta**2 / m.g) * max(mu) + 1e-8
    assert_allclose(m.f1(x, y), f1_fd, rtol=0, atol=tol)
    assert_allclose(m.f2(x, y), f2_fd, rtol=0, atol=tol)


def test_loads_match_symbolic_derivation():
    r"""Independent derivation with sympy, region by region.

    On {q > 0}: w = q^2/g, lam = 0; on {q < 0}: w = 0, lam = kappa (-q) (or kappa).
    f1 = -mu1 lap u1 - lam, f2 = -mu2 lap u2 + lam, with
    u1 = (s + mu2 w)/(mu1 + mu2), u2 = (s - mu1 w)/(mu1 + mu2), s = mu1 g + s0 b.
    """
    sp = pytest.importorskip("sympy")
    X, Y = sp.symbols("x y", real=True)
    mu1, mu2, g, beta, s0, kappa = 3.0, 0.2, 0.15, 0.3, 0.8, 1.7
    b = (1 - X**2) * (1 - Y**2)
    q = g - beta * b
    s = mu1 * g + s0 * b
    rng = np.random.default_rng(SEED)
    x, y = rng.uniform(-1, 1, size=(2, 4000))
    for discontinuous in (False, True):
        m = Manufactured((mu1, mu2), g, beta, s0, kappa, discontinuous)
        for w, lam, region in (
            (q**2 / g, sp.Integer(0), m.q(x, y) > 1e-12),
            (sp.Integer(0), kappa if discontinuous else -kappa * q, m.q(x, y) < -1e-12),
        ):
            u1 = (s + mu2 * w) / (mu1 + mu2)
            u2 = (s - mu1 * w) / (mu1 + mu2)
            f1 = -mu1 * (sp.diff(u1, X, 2) + sp.diff(u1, Y, 2)) - lam
            f2 = -mu2 * (sp.diff(u2, X, 2) + sp.diff(u2, Y, 2)) + lam
            xr, yr = x[region], y[region]
            assert xr.size > 100
            for expr, got in ((f1, m.f1(xr, yr)), (f2, m.f2(xr, yr))):
                want = sp.lambdify((X, Y), expr, "numpy")(xr, yr) + np.zeros_like(xr)
                assert_allclose(got, want, rtol=1e-12, atol=1e-12)
            for expr, (gx, gy) in ((u1, m.grad_u1(xr, yr)), (u2, m.grad_u2(xr, yr))):
                wx = sp.lambdify((X, Y), sp.diff(expr, X), "numpy")(xr, yr)
                wy = sp.lambdify((X, Y), sp.diff(expr, Y), "numpy")(xr, yr)
                assert_allclose(gx, wx, rtol=1e-12, atol=1e-13)
                assert_allclose(gy, wy, rtol=1e-12, atol=1e-13)


# ------------------------------------------------------------------ meshes


def test_interpolate():
    m = Manufactured(mu=(1.0, 10.0), discontinuous=True)
    mesh = square_mesh(8)
    u1h, u2h, lamh = m.interpolate(mesh)
    n = mesh.vertices.shape[0]
    assert u1h.shape == u2h.shape == lamh.shape == (n,)
    bnd = mesh.boundary_vertex_mask
    assert np.all(u1h[bnd] == m.g)
    assert np.all(u2h[bnd] == 0.0)
    assert np.all(lamh[bnd] == 0.0)
    x, y = mesh.vertices[~bnd].T
    assert_allclose(u1h[~bnd], m.u1(x, y), rtol=0, atol=0)
    assert_allclose(u2h[~bnd], m.u2(x, y), rtol=0, atol=0)
    assert_allclose(lamh[~bnd], m.lam(x, y), rtol=0, atol=0)
    assert np.any(lamh > 0)


def test_interpolate_rejects_other_domains():
    mesh = square_mesh(4)
    shifted = SimpleNamespace(**vars(mesh))
    shifted.vertices = mesh.vertices * 0.5
    with pytest.raises(MeshError, match=r"\(-1, 1\)\^2"):
        Manufactured().interpolate(shifted)
    shifted.vertices = mesh.vertices * 2.0
    with pytest.raises(MeshError, match=r"\(-1, 1\)\^2"):
        Manufactured().interpolate(shifted)


def _interpolant_errors(m, ns=(8, 16, 32, 64)):
    errors = []
    for n in ns:
        mesh = square_mesh(n)
        u1h, u2h, _ = m.interpolate(mesh)
        errors.append(m.energy_error(mesh, u1h, u2h))
    return 2.0 / np.array(ns), np.array(errors)


@pytest.mark.parametrize("params", PARAMETER_SETS, ids=IDS)
def test_energy_error_of_interpolant_is_first_order(params):
    m = Manufactured(**params)
    h, errors = _interpolant_errors(m)
    assert np.all(np.diff(errors) < 0)
    rate = np.polyfit(np.log(h), np.log(errors), 1)[0]
    assert 0.9 <= rate <= 1.1, (rate, errors)
    assert m.quadrature_degree == 7


def test_energy_error_parts_combine():
    m = Manufactured(mu=(3.0, 0.2))
    mesh = square_mesh(16)
    u1h, u2h, _ = m.interpolate(mesh)
    e1, e2 = m.energy_error_parts(mesh, u1h, u2h, degree=9)
    assert m.quadrature_degree == 9
    assert e1 > 0
    assert e2 > 0
    assert m.energy_error(mesh, u1h, u2h, degree=9) == pytest.approx(math.hypot(e1, e2))
    # doubling mu2 multiplies e2 by sqrt(2): the weights are applied per membrane
    f1, f2 = energy_error_parts(
        mesh.vertices, mesh.triangles, (3.0, 0.4), (m.grad_u1, m.grad_u2), u1h, u2h, 9
    )
    assert f1 == pytest.approx(e1, rel=1e-14)
    assert f2 == pytest.approx(math.sqrt(2.0) * e2, rel=1e-14)


def test_energy_error_independent_of_degree_on_uncut_meshes():
    """Without contact (beta < g b everywhere) u is polynomial of degree <= 8,
    |grad(u - u_h)|^2 of degree <= 14: every rule of degree >= 14 gives the same value."""
    m = Manufactured(mu=(1.0, 2.0), g=0.5, beta=0.25)
    assert not np.any(m.contact_indicator(*grid(51)))
    mesh = square_mesh(6)
    u1h, u2h, _ = m.interpolate(mesh)
    values = [m.energy_error(mesh, u1h, u2h, degree=d) for d in (14, 16, 21, 30)]
    assert_allclose(values, values[0], rtol=1e-13)


def _jittered_mesh(n, seed, clockwise=False):
    mesh = square_mesh(n)
    rng = np.random.default_rng(seed)
    interior = ~mesh.boundary_vertex_mask
    mesh.vertices[interior] += rng.uniform(-0.2, 0.2, size=(interior.sum(), 2)) * (2.0 / n)
    if clockwise:
        mesh.triangles = mesh.triangles[:, ::-1].copy()
    return mesh


@pytest.mark.parametrize("clockwise", [False, True])
def test_energy_error_of_linear_function_is_zero(clockwise):
    mesh = _jittered_mesh(10, SEED, clockwise)
    x, y = mesh.vertices.T
    u1h = 0.3 + 2.0 * x - 1.5 * y
    u2h = -0.7 * x + 4.0 * y

    def grad1(x, y):
        return np.full_like(x, 2.0), np.full_like(x, -1.5)

    def grad2(x, y):
        return -0.7, 4.0  # scalars are broadcast

    err = energy_error(mesh.vertices, mesh.triangles, (2.0, 5.0), (grad1, grad2), u1h, u2h)
    assert err < 1e-12
    # and a wrong nodal field is detected
    err = energy_error(mesh.vertices, mesh.triangles, (2.0, 5.0), (grad1, grad2), u1h + x**2, u2h)
    assert err > 1e-2


def test_energy_error_matches_exact_formula_for_quadratic():
    """u = x^2 + 3 x y: grad(u - I u) is linear on each triangle, and for a linear
    function phi with vertex values p_k, int_K phi^2 = |K|/6 (sum p_k^2 + sum_{j<k} p_j p_k)."""
    mesh = _jittered_mesh(7, SEED + 1)
    v, t = mesh.vertices, mesh.triangles
    x, y = v.T
    mu = (1.3, 0.4)

    def grad(x, y):
        return 2.0 * x + 3.0 * y, 3.0 * x

    uh = x**2 + 3.0 * x * y
    # independent exact value
    p = v[t]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    area = 0.5 * np.abs(det)
    d1, d2 = uh[t[:, 1]] - uh[t[:, 0]], uh[t[:, 2]] - uh[t[:, 0]]
    ghx = (e2[:, 1] * d1 - e1[:, 1] * d2) / det
    ghy = (e1[:, 0] * d2 - e2[:, 0] * d1) / det
    total = 0.0
    for comp, gh in ((0, ghx), (1, ghy)):
        vals = grad(p[..., 0], p[..., 1])[comp] - gh[:, None]  # (M, 3) vertex values
        sq = (vals**2).sum(axis=1) + vals[:, 0] * vals[:, 1] + vals[:, 1] * vals[:, 2]
        sq += vals[:, 0] * vals[:, 2]
        total += np.sum(area / 6.0 * sq)
    expected = math.sqrt((mu[0] + mu[1]) * total)
    got = energy_error(v, t, mu, (grad, grad), uh, uh, degree=6)
    assert got == pytest.approx(expected, rel=1e-13)


@pytest.mark.parametrize("degree", [0, 2, 5, -1, 31, 6.5, "7"])
def test_energy_error_degree_validation(degree):
    m = Manufactured()
    mesh = square_mesh(4)
    u1h, u2h, _ = m.interpolate(mesh)
    with pytest.raises(ParameterError, match="degree"):
        m.energy_error(mesh, u1h, u2h, degree=degree)
    assert m.quadrature_degree == 7


def test_energy_error_bad_data():
    m = Manufactured()
    mesh = square_mesh(4)
    u1h, u2h, _ = m.interpolate(mesh)
    with pytest.raises(DataError, match="u1h"):
        m.energy_error(mesh, u1h[:-1], u2h)
    bad = u2h.copy()
    bad[3] = np.nan
    with pytest.raises(DataError, match="u2h"):
        m.energy_error(mesh, u1h, bad)
    with pytest.raises(ParameterError, match="mu1"):
        energy_error(mesh.vertices, mesh.triangles, (0.0, 1.0), (m.grad_u1, m.grad_u2), u1h, u2h)
    flat = SimpleNamespace(**vars(mesh))
    flat.triangles = np.vstack([mesh.triangles, [[0, 1, 2]]])  # collinear boundary vertices
    with pytest.raises(MeshError, match="degenerate"):
        m.energy_error(flat, u1h, u2h)


def test_with_fastmem_mesh():
    """The real Mesh class works through the same interface as plain arrays."""
    import fastmem.mesh.mesh as mesh_module

    m = Manufactured(mu=(1.0, 10.0))
    errors = []
    ns = (8, 16, 32, 64)
    for n in ns:
        mesh = mesh_module.Mesh.square(n)
        u1h, u2h, lamh = m.interpolate(mesh)
        plain = SimpleNamespace(
            vertices=np.array(mesh.vertices),
            triangles=np.array(mesh.triangles),
            boundary_vertex_mask=np.array(mesh.boundary_vertex_mask),
        )
        v1, v2, vl = m.interpolate(plain)
        assert np.array_equal(u1h, v1)
        assert np.array_equal(lamh, vl)
        errors.append(m.energy_error(mesh, u1h, u2h))
        assert errors[-1] == m.energy_error(plain, v1, v2)
    rate = np.polyfit(np.log(2.0 / np.array(ns)), np.log(errors), 1)[0]
    assert 0.9 <= rate <= 1.1, (rate, errors)
