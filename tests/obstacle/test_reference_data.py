"""Reference data of the obstacle family: the ball (docs/obstacle.md §8.1) and the
manufactured two-sided case (§8.3), with their guaranteed envelopes (§5.1-5.3).

Every check compares with an independent computation: SymPy derivatives, scipy
quadrature of the closed-form pieces, direct 2D quadrature of the energy error, and
dense sampling of random triangles for the envelope bounds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import sympy as sp
from numpy.testing import assert_allclose
from scipy import optimize
from scipy.special import roots_legendre

from fastmem.errors import DataError, MeshError, ParameterError
from fastmem.fem.quadrature import triangle_rule
from fastmem.mesh.mesh import Mesh
from fastmem.problems import ball, twosided
from fastmem.problems.ball import enclosing_radius
from fastmem.problems.twosided import TwoSided

SEED = 604_913

#: Random triangles per envelope test and sample points per triangle.
N_TRIANGLES = 20_000
N_SAMPLES = 40


# --------------------------------------------------------------------------- helpers


def gauss(f, a, b, n=60):
    """Gauss-Legendre quadrature of an analytic ``f`` on ``[a, b]`` (machine accuracy)."""
    t, w = roots_legendre(n)
    return float(0.5 * (b - a) * (w @ f(a + 0.5 * (b - a) * (t + 1.0))))


def ball_mesh(n):
    return Mesh.rectangle(n, n, (-2.0, 2.0, -2.0, 2.0), diagonal="symmetric")


def random_triangles(rng, centres, sizes):
    """Random triangles (any shape, slivers included) around ``centres``, shape (P, 3)."""
    offsets = rng.standard_normal((centres.shape[0], 3, 2)) * sizes[:, None, None]
    p = centres[:, None, :] + offsets
    return p[..., 0].copy(), p[..., 1].copy()


def sample_points(rng, px, py, k=N_SAMPLES):
    """Barycentric coordinates (P, S, 3) of random points, vertices and edge points."""
    n = px.shape[0]
    beta = rng.dirichlet(np.ones(3), size=(n, k))
    fixed = np.array(
        [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0.5, 0.5, 0], [0, 0.5, 0.5], [0.5, 0, 0.5]],
        dtype=float,
    )
    beta = np.concatenate([beta, np.broadcast_to(fixed, (n, 6, 3))], axis=1)
    x = np.einsum("psi,pi->ps", beta, px)
    y = np.einsum("psi,pi->ps", beta, py)
    return beta, x, y


def q_t(beta, px, py, x, y):
    """``q_T(x) = sum_i beta_i |x_i - x|^2`` of Lemma 5.1."""
    dx = px[:, None, :] - x[..., None]
    dy = py[:, None, :] - y[..., None]
    return np.einsum("psi,psi->ps", beta, dx * dx + dy * dy)


def check_envelope(name, v, lam_true, hessian, px, py, envelope, rng):
    """Check the envelope of ``v`` on the pieces by dense sampling; return the ratios.

    ``hessian(x, y)`` returns the entries (h11, h12, h22) of D^2 v; ``lam_true`` is
    the pressure bound Lambda of v, computed independently of the code under test.
    """
    m_minus, m_plus, lam = envelope(px, py)
    assert m_minus.shape == m_plus.shape == (px.shape[0],)
    assert lam.shape == px.shape
    assert np.all(m_minus >= 0.0)
    assert np.all(m_plus >= 0.0)
    beta, x, y = sample_points(rng, px, py)
    vals = v(x, y)
    interp = np.einsum("psi,pi->ps", beta, v(px, py))
    q = q_t(beta, px, py, x, y)
    diff = vals - interp
    scale = 1e-13 * (1.0 + np.abs(vals))
    upper = 0.5 * m_minus[:, None] * q
    lower = 0.5 * m_plus[:, None] * q
    assert np.all(diff <= upper + scale), f"{name}: v - I_T v above 1/2 M^- q_T"
    assert np.all(-diff <= lower + scale), f"{name}: I_T v - v above 1/2 M^+ q_T"
    # Hessian eigenvalues at the sample points
    h11, h12, h22 = hessian(x, y)
    half = 0.5 * (h11 - h22)
    root = np.sqrt(half * half + h12 * h12)
    lam_max = 0.5 * (h11 + h22) + root
    lam_max_neg = -0.5 * (h11 + h22) + root
    tol = 1e-12 * (1.0 + np.abs(h11) + np.abs(h22) + np.abs(h12))
    assert np.all(lam_max_neg <= m_minus[:, None] + tol), f"{name}: M^- below the Hessian"
    assert np.all(lam_max <= m_plus[:, None] + tol), f"{name}: M^+ below the Hessian"
    # the affine majorant of Lambda
    big_lam = lam_true(x, y)
    u_t = np.einsum("psi,pi->ps", beta, lam)
    assert np.all(big_lam <= u_t + 1e-12 * (1.0 + big_lam)), f"{name}: U_T below Lambda"
    small = 2.0 * enclosing_radius(px, py) < 1e-2
    return {
        "v-Iv / (M- q/2)": _max_ratio(diff, upper),
        "Iv-v / (M+ q/2)": _max_ratio(-diff, lower),
        "Lambda / U_T": _max_ratio(big_lam, u_t),
        "lam_max(-H) / M-": _max_ratio(lam_max_neg, np.broadcast_to(m_minus[:, None], x.shape)),
        "lam_max(H) / M+": _max_ratio(lam_max, np.broadcast_to(m_plus[:, None], x.shape)),
        "sharpness M-": _sharpness(lam_max_neg, m_minus, small),
        "sharpness M+": _sharpness(lam_max, m_plus, small),
    }


def _max_ratio(num, den, floor=1e-8):
    """Largest ``num / den`` where ``den > floor`` (None if there is no such point)."""
    sig = den > floor
    return float(np.max(num[sig] / den[sig])) if np.any(sig) else None


def _sharpness(sampled, bound, small):
    """Median over small pieces with a bound above 0.5 of (sampled sup) / bound."""
    sel = small & (bound > 0.5)
    if np.count_nonzero(sel) < 100:
        return None
    return float(np.median(np.max(sampled[sel], axis=1) / bound[sel]))


# --------------------------------------------------------------------------- the ball: data


def test_ball_constants_match_their_definitions():
    assert ball.PSI0 == pytest.approx(0.435889894354067, abs=1e-15)
    assert ball.DPSI0 == pytest.approx(-2.06474160483506, abs=1e-14)
    exact = optimize.brentq(
        lambda r: r * r * math.log(2.0 / r) - (1.0 - r * r), 0.5, 0.9, xtol=1e-16
    )
    assert abs(ball.RSTAR - exact) < 1e-15
    assert ball.ASTAR == pytest.approx(ball.RSTAR**2 / math.sqrt(1 - ball.RSTAR**2), abs=5e-15)
    assert ball.BSTAR == pytest.approx(ball.ASTAR * math.log(2.0), abs=5e-15)
    assert ball.CONTACT_AREA == pytest.approx(1.530443662856247, abs=5e-15)
    assert ball.DOMAIN == (-2.0, 2.0)


def test_energy_sq_closed_form_and_quadrature():
    # the value of docs/obstacle.md §8.1 (closed form with the exact r_*); the
    # module's closed form uses the rounded constants: 5e-15 relative apart
    assert ball.ENERGY_SQ == pytest.approx(3.948249232793262, rel=1e-14)
    # Catalan's constant: G = int_0^1 arctan(t)/t dt
    assert ball.CATALAN == pytest.approx(gauss(lambda t: np.arctan(t) / t, 0.0, 1.0), rel=1e-15)
    # |||u|||^2 by 1D quadratures of its three parts (disc, annulus, square minus disc)
    rs, a = ball.RSTAR, ball.ASTAR
    disc = gauss(lambda r: 2 * np.pi * r**3 / (1 - r * r), 0.0, rs)
    corners = gauss(lambda t: -8.0 * np.log(np.cos(t)), 0.0, np.pi / 4)
    assert corners == pytest.approx(2 * np.pi * np.log(2) - 4 * ball.CATALAN, rel=1e-14)
    total = disc + a * a * (2 * math.pi * math.log(2.0 / rs) + corners)
    assert ball.ENERGY_SQ == pytest.approx(total, rel=2e-15)


@pytest.fixture(scope="module")
def ball_sympy():
    """Laplacian and Hessian of the two branches of the ball obstacle, by SymPy."""
    x, y = sp.symbols("x y", real=True)
    r = sp.sqrt(x * x + y * y)
    inner = sp.sqrt(1 - x * x - y * y)
    outer = sp.Float(ball.PSI0, 30) + sp.Float(ball.DPSI0, 30) * (r - sp.Float(ball.R0, 30))
    out = {}
    for key, expr in (("inner", inner), ("outer", outer)):
        hess = [sp.diff(expr, x, x), sp.diff(expr, x, y), sp.diff(expr, y, y)]
        out[key] = (
            sp.lambdify((x, y), expr, "numpy"),
            sp.lambdify((x, y), sp.diff(expr, x, 2) + sp.diff(expr, y, 2), "numpy"),
            [sp.lambdify((x, y), h, "numpy") for h in hess],
        )
    return out


def test_ball_solution_contact_and_multiplier(ball_sympy):
    rng = np.random.default_rng(SEED)
    x, y = rng.uniform(-2.0, 2.0, (2, 200_000))
    r = np.hypot(x, y)
    psi, u, lam = ball.ball_obstacle(x, y), ball.ball_solution(x, y), ball.ball_multiplier(x, y)
    inner_f, inner_lap, _ = ball_sympy["inner"]
    outer_f, outer_lap, _ = ball_sympy["outer"]
    with np.errstate(invalid="ignore"):
        psi_ref = np.where(r <= ball.R0, inner_f(x, y), outer_f(x, y))
        lap_ref = np.where(r <= ball.R0, inner_lap(x, y), outer_lap(x, y))
    assert_allclose(psi, psi_ref, rtol=0, atol=1e-14)
    assert_allclose(ball.ball_obstacle.laplacian(x, y), lap_ref, rtol=1e-12, atol=0)
    assert_allclose(ball.ball_obstacle.pressure_bound(x, y), -lap_ref, rtol=1e-12, atol=0)
    # u >= psi with equality exactly on the contact disc; lambda (u - psi) = 0
    assert np.all(u - psi >= -1e-15)
    assert np.all(u[r <= ball.RSTAR] == psi[r <= ball.RSTAR])
    assert np.all(u[r > ball.RSTAR + 1e-3] - psi[r > ball.RSTAR + 1e-3] > 2e-6)
    assert np.all(lam >= 0)
    assert np.all(lam * (u - psi) == 0)
    assert_allclose(lam[r < ball.RSTAR], -lap_ref[r < ball.RSTAR], rtol=1e-12)
    assert np.all(lam[r >= ball.RSTAR] == 0)
    # C^1 across r_*: values and radial derivatives of both branches agree
    rs = ball.RSTAR
    assert abs(math.sqrt(1 - rs * rs) - (-ball.ASTAR * math.log(rs) + ball.BSTAR)) < 1e-14
    assert abs(-rs / math.sqrt(1 - rs * rs) - (-ball.ASTAR / rs)) < 1e-14
    # u = 0 on the circle r = 2; g is u; the gradient matches central differences
    assert abs(float(ball.ball_solution(0.0, 2.0))) < 1e-15
    assert ball.ball_g is ball.ball_solution
    h = 1e-6
    gx, gy = ball.ball_gradient(x, y)
    fd_x = (ball.ball_solution(x + h, y) - ball.ball_solution(x - h, y)) / (2 * h)
    fd_y = (ball.ball_solution(x, y + h) - ball.ball_solution(x, y - h)) / (2 * h)
    assert_allclose(gx, fd_x, atol=1e-7)
    assert_allclose(gy, fd_y, atol=1e-7)


# --------------------------------------------------------------------------- the ball: error


@pytest.mark.parametrize("n", [8, 16])
def test_ball_energy_error_edge_integrals_match_2d_quadrature(n):
    mesh = ball_mesh(n)
    xv, yv = mesh.vertices.T
    u_i = ball.ball_solution(xv, yv)
    rng = np.random.default_rng(SEED + n)
    for u_h in (u_i, u_i + 0.05 * rng.standard_normal(u_i.size), np.zeros_like(u_i)):
        way1 = ball.ball_energy_error(mesh, u_h)
        way2 = ball._energy_error_2d(mesh, u_h)
        assert way1 == pytest.approx(way2, rel=1e-11)
    # the 2D reference is converged
    assert ball._energy_error_2d(mesh, u_i) == pytest.approx(
        ball._energy_error_2d(mesh, u_i, n_angle=36, n_radius=36), rel=1e-13
    )


def test_ball_energy_error_of_interpolant_is_first_order():
    ns = np.array([32, 64, 128])
    errors = []
    for n in ns:
        mesh = ball_mesh(n)
        errors.append(ball.ball_energy_error(mesh, ball.ball_solution(*mesh.vertices.T)))
    errors = np.array(errors)
    h = 4.0 / ns
    rate = np.polyfit(np.log(h), np.log(errors), 1)[0]
    assert 0.93 < rate < 1.05
    assert np.all(np.diff(errors) < 0)
    assert np.all((errors / h > 1.0) & (errors / h < 1.2))  # about 1.08 ... 1.15


def test_ball_energy_error_input_checks():
    mesh = ball_mesh(4)
    with pytest.raises(DataError, match="u_h"):
        ball.ball_energy_error(mesh, np.zeros(3))
    with pytest.raises(DataError, match="NaN"):
        ball.ball_energy_error(mesh, np.full(mesh.n_vertices, np.nan))
    with pytest.raises(MeshError, match="square"):
        ball.ball_energy_error(Mesh.square(4), np.zeros(25))


# --------------------------------------------------------------------------- the ball: envelope


def test_ball_envelope_is_guaranteed(ball_sympy):
    rng = np.random.default_rng(SEED + 1)
    n = N_TRIANGLES
    kind = rng.integers(0, 4, n)
    angle = rng.uniform(0.0, 2.0 * np.pi, n)
    radius = np.choose(
        kind,
        [
            rng.uniform(0.0, 2.0, n),
            ball.R0 + 0.05 * rng.standard_normal(n),
            ball.RSTAR + 0.05 * rng.standard_normal(n),
            0.05 * rng.random(n),
        ],
    )
    centres = np.column_stack([radius * np.cos(angle), radius * np.sin(angle)])
    sizes = 10.0 ** rng.uniform(-3.0, 0.0, n)
    px, py = random_triangles(rng, centres, sizes)
    # a few special pieces: a vertex at the origin, pieces around the origin and r0
    px[:3] = [[0.0, 0.1, 0.0], [-0.1, 0.1, 0.0], [0.85, 0.95, 0.9]]
    py[:3] = [[0.0, 0.0, 0.1], [-0.1, -0.1, 0.1], [0.0, 0.0, 0.05]]
    inner_f, inner_lap, inner_h = ball_sympy["inner"]
    _, outer_lap, outer_h = ball_sympy["outer"]

    def lam_true(x, y):
        r = np.hypot(x, y)
        with np.errstate(invalid="ignore", divide="ignore"):
            return -np.where(r <= ball.R0, inner_lap(x, y), outer_lap(x, y))

    def hessian(x, y):
        inside = np.hypot(x, y) <= ball.R0
        with np.errstate(invalid="ignore", divide="ignore"):
            return [
                np.where(inside, hi(x, y), ho(x, y))
                for hi, ho in zip(inner_h, outer_h, strict=True)
            ]

    ratios = check_envelope(
        "ball", ball.ball_obstacle, lam_true, hessian, px, py, ball.ball_obstacle.envelope, rng
    )
    m_minus, m_plus, _ = ball.ball_obstacle.envelope(px, py)
    assert np.all(m_plus == 0.0)
    # sharp for small pieces: the lemma's bound is nearly attained somewhere
    assert ratios["v-Iv / (M- q/2)"] > 0.9
    assert ratios["lam_max(-H) / M-"] > 0.999
    assert ratios["sharpness M-"] > 0.95


# --------------------------------------------------------------------------- two-sided: data


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"s0": 0.0}, "s0"),
        ({"s0": float("nan")}, "s0"),
        ({"alpha": 0.0}, "alpha"),
        ({"alpha": -1.0}, "alpha"),
        ({"kappa": -0.5}, "kappa"),
        ({"rc": 0.0}, "rc"),
        ({"rc": float("inf")}, "rc"),
        ({"mu": 0.0}, "mu"),
        ({"mu": True}, "mu"),
        ({"m": "0.5"}, "m"),
        ({"m": 0.3}, "m must exceed rc"),
        ({"m": 0.2, "rc": 0.25}, "m must exceed rc"),
        ({"m": 0.75, "rc": 0.3}, "m \\+ rc"),
    ],
)
def test_twosided_parameter_checks(kwargs, name):
    with pytest.raises(ParameterError, match=name):
        TwoSided(**kwargs)


@pytest.fixture(scope="module")
def twosided_sympy():
    """u, its Laplacian and Hessian, and the Hessian of p^2, by SymPy (for parameters)."""
    x, y, s0, cx, rc = sp.symbols("x y s0 cx rc", real=True)
    u = s0 * x * (1 - x**2) * (1 - y**2)
    p = (x - cx) ** 2 + y**2 - rc**2
    args = (x, y, s0, cx, rc)
    return {
        "u": sp.lambdify(args, u, "numpy"),
        "lap_u": sp.lambdify(args, sp.diff(u, x, 2) + sp.diff(u, y, 2), "numpy"),
        "hess_u": [
            sp.lambdify(args, h, "numpy")
            for h in (sp.diff(u, x, x), sp.diff(u, x, y), sp.diff(u, y, y))
        ],
        "hess_p2": [
            sp.lambdify(args, h, "numpy")
            for h in (sp.diff(p**2, x, x), sp.diff(p**2, x, y), sp.diff(p**2, y, y))
        ],
        "energy_sq": sp.integrate(sp.diff(u, x) ** 2 + sp.diff(u, y) ** 2, (x, -1, 1), (y, -1, 1)),
        "s0": s0,
    }


PARAMS = [
    {},
    {"s0": -1.0},
    {"s0": 0.7, "alpha": 3.0, "kappa": 0.0, "m": 0.45, "rc": 0.4, "mu": 2.5},
]


def lambda_psi_reference(pr, x, y):
    """Lambda_psi of docs/obstacle.md §8.3, piecewise, written out here."""
    pm = (x + pr.m) ** 2 + y**2 - pr.rc**2
    pp = (x - pr.m) ** 2 + y**2 - pr.rc**2
    q = pr.mu * pr.alpha * (16 * pm + 8 * pr.rc**2)
    return np.where(pm <= 0, pr.kappa * -pm, np.where(pp < 0, np.maximum(q - pr.kappa * -pp, 0), q))


@pytest.mark.parametrize("params", PARAMS)
def test_twosided_solution_obstacles_and_multiplier(params, twosided_sympy):
    pr = TwoSided(**params)
    rng = np.random.default_rng(SEED + 2)
    t = np.linspace(-1.0, 1.0, 401)
    gx, gy = np.meshgrid(t, t)
    x = np.concatenate([gx.ravel(), rng.uniform(-1, 1, 100_000)])
    y = np.concatenate([gy.ravel(), rng.uniform(-1, 1, 100_000)])
    u, psi, chi = pr.solution(x, y), pr.lower(x, y), pr.upper(x, y)
    lam_p, lam_m = pr.multiplier_plus(x, y), pr.multiplier_minus(x, y)
    pm = (x + pr.m) ** 2 + y**2 - pr.rc**2
    pp = (x - pr.m) ** 2 + y**2 - pr.rc**2
    sym = twosided_sympy
    assert_allclose(u, sym["u"](x, y, pr.s0, 0.0, 0.0), atol=1e-15)
    # ordering, equality exactly on the discs, strict elsewhere
    assert np.all(psi <= u)
    assert np.all(u <= chi)
    assert np.all(psi < chi)
    assert np.all(psi[pm <= 0] == u[pm <= 0])
    assert np.all(chi[pp <= 0] == u[pp <= 0])
    assert np.all(psi[pm > 1e-6] < u[pm > 1e-6])
    assert np.all(chi[pp > 1e-6] > u[pp > 1e-6])
    # complementarity and signs
    assert np.all(lam_p >= 0)
    assert np.all(lam_m >= 0)
    assert np.all(lam_p * (u - psi) == 0)
    assert np.all(lam_m * (chi - u) == 0)
    assert_allclose(pr.multiplier(x, y), lam_p - lam_m, atol=0)
    # the load from an independent Laplacian
    lap = sym["lap_u"](x, y, pr.s0, 0.0, 0.0)
    assert_allclose(pr.laplacian(x, y), lap, atol=1e-13)
    assert_allclose(pr.load(x, y), -pr.mu * lap - lam_p + lam_m, atol=1e-13)
    # boundary: u = 0 = g, psi < 0 < chi
    edge = (np.abs(x) == 1.0) | (np.abs(y) == 1.0)
    assert np.all(u[edge] == 0)
    assert pr.g == 0.0
    assert np.all(psi[edge] < 0)
    assert np.all(chi[edge] > 0)
    # symmetry: S combined with x -> -x
    assert np.all(pr.load(-x, y) == -pr.load(x, y))
    assert np.all(pr.lower(-x, y) == -pr.upper(x, y))
    # pressure bounds: the piecewise formula, symmetry, and lambda^+ <= Lambda_psi
    lam_psi = pr.lower.pressure_bound(x, y)
    lam_chi = pr.upper.pressure_bound(x, y)
    scale = 1e-12 * (1 + pr.kappa + pr.mu * pr.alpha)
    assert_allclose(lam_psi, lambda_psi_reference(pr, x, y), atol=scale)
    assert_allclose(lam_chi, lambda_psi_reference(pr, -x, y), atol=scale)
    assert np.all(lam_p <= lam_psi + scale)
    assert np.all(lam_m <= lam_chi + scale)
    assert_allclose(lam_p[pm < 0], lam_psi[pm < 0], atol=scale)


def test_twosided_default_values_of_the_design_note():
    pr = TwoSided()
    assert float(pr.load(-0.5, 0.0)) == pytest.approx(-4.65, abs=1e-14)
    assert float(pr.multiplier_plus(-0.5, 0.0)) == pytest.approx(0.9, abs=1e-14)
    t = np.linspace(-1.0, 1.0, 2001)
    x, y = np.meshgrid(t, t)
    assert np.max(np.abs(pr.solution(x, y))) == pytest.approx(0.385, abs=1e-3)
    edge = np.concatenate(
        [pr.lower(t, -1.0), pr.lower(t, 1.0), pr.lower(1.0, t), pr.lower(-1.0, t)]
    )
    assert np.max(edge) == pytest.approx(-0.0256, abs=1e-4)
    assert np.min(pr.load(x, y)) == pytest.approx(-6.0, abs=0.05)


# --------------------------------------------------------------------------- two-sided: error


@pytest.mark.parametrize("params", PARAMS)
def test_twosided_energy_error_is_exact(params, twosided_sympy):
    pr = TwoSided(**params)
    mesh = Mesh.square(8)
    xv, yv = mesh.vertices.T
    rng = np.random.default_rng(SEED + 3)
    u_h = pr.solution(xv, yv) + 0.01 * rng.standard_normal(xv.size)
    # against a rule of much higher degree
    bary, weights = triangle_rule(24)
    p = mesh.vertices[mesh.triangles]
    x, y = p[..., 0] @ bary.T, p[..., 1] @ bary.T
    gh = np.einsum("mi,mij->mj", u_h[mesh.triangles], mesh.gradients)
    gx, gy = pr.gradient(x, y)
    ref = math.sqrt(
        pr.mu * float(mesh.areas @ (((gx - gh[:, :1]) ** 2 + (gy - gh[:, 1:]) ** 2) @ weights))
    )
    assert pr.energy_error(mesh, u_h) == pytest.approx(ref, rel=1e-13)
    # |||u|||^2 in closed form (SymPy), from u_h = 0
    exact = float(twosided_sympy["energy_sq"].subs(twosided_sympy["s0"], pr.s0)) * pr.mu
    assert pr.energy_error(mesh, np.zeros_like(xv)) ** 2 == pytest.approx(exact, rel=1e-14)
    with pytest.raises(DataError, match="u_h"):
        pr.energy_error(mesh, np.zeros(3))


def test_twosided_interpolant_error_is_first_order():
    pr = TwoSided()
    ns = np.array([8, 16, 32, 64])
    errors = np.array(
        [pr.energy_error(Mesh.square(n), pr.solution(*Mesh.square(n).vertices.T)) for n in ns]
    )
    rate = np.polyfit(np.log(2.0 / ns), np.log(errors), 1)[0]
    assert 0.95 < rate < 1.05


# --------------------------------------------------------------------------- two-sided: envelopes


def test_interval_helpers_give_exact_ranges():
    rng = np.random.default_rng(SEED + 5)
    a = rng.uniform(-1.5, 1.5, (2, 500))
    lo, hi = a.min(axis=0), a.max(axis=0)
    b = rng.uniform(-1.5, 1.5, (2, 500))
    blo, bhi = b.min(axis=0), b.max(axis=0)
    t = lo[:, None] + (hi - lo)[:, None] * np.linspace(0.0, 1.0, 2001)
    s = blo[:, None] + (bhi - blo)[:, None] * np.linspace(0.0, 1.0, 41)
    for (rlo, rhi), vals in (
        (twosided._square_range(lo, hi), t * t),
        (twosided._cubic_range(lo, hi), t - t**3),
        (twosided._product_range(lo, hi, blo, bhi), t[:, ::50, None] * s[:, None, :]),
    ):
        vals = vals.reshape(vals.shape[0], -1)
        assert np.all(rlo <= vals.min(axis=1) + 1e-14)
        assert np.all(rhi >= vals.max(axis=1) - 1e-14)
        assert_allclose(rlo, vals.min(axis=1), atol=1e-6)  # sharp
        assert_allclose(rhi, vals.max(axis=1), atol=1e-6)
    # sup of lambda_max over a box of symmetric matrices is attained at the corner
    a_hi, c_hi, b_abs = rng.normal(size=(3, 200))
    b_abs = np.abs(b_abs)
    best = _lam_max_brute(a_hi, c_hi, b_abs)
    assert_allclose(twosided._lam_max_sup(a_hi, c_hi, b_abs), best, rtol=1e-12, atol=1e-12)


def _lam_max_brute(a_hi, c_hi, b_abs):
    """Largest eigenvalue over a grid of matrices with a <= a_hi, c <= c_hi, |b| <= b_abs."""
    g = np.linspace(0.0, 1.0, 21)
    a = a_hi[:, None, None, None] - 2.0 * g[None, :, None, None]
    c = c_hi[:, None, None, None] - 2.0 * g[None, None, :, None]
    b = b_abs[:, None, None, None] * (2.0 * g[None, None, None, :] - 1.0)
    a, b, c = np.broadcast_arrays(a, b, c)
    lam = np.linalg.eigvalsh(np.stack([np.stack([a, b], -1), np.stack([b, c], -1)], -2))
    return lam[..., -1].reshape(a_hi.size, -1).max(axis=1)


@pytest.mark.parametrize("params", PARAMS)
def test_twosided_envelopes_are_guaranteed(params, twosided_sympy):
    pr = TwoSided(**params)
    rng = np.random.default_rng(SEED + 4)
    n = N_TRIANGLES // 2
    kind = rng.integers(0, 3, n)
    angle = rng.uniform(0.0, 2.0 * np.pi, n)
    centre_x = rng.choice([-pr.m, pr.m], n)
    radius = np.where(kind == 1, pr.rc + 0.03 * rng.standard_normal(n), pr.rc * rng.random(n))
    centres = np.where(
        (kind == 0)[:, None],
        rng.uniform(-1.0, 1.0, (n, 2)),
        np.column_stack([centre_x + radius * np.cos(angle), radius * np.sin(angle)]),
    )
    sizes = 10.0 ** rng.uniform(-3.0, np.log10(0.5), n)
    px, py = random_triangles(rng, centres, sizes)
    sym = twosided_sympy

    def hessian(side):
        sign, cx = (-1.0, -pr.m) if side == "lower" else (1.0, pr.m)

        def h(x, y):
            p = (x - cx) ** 2 + y**2 - pr.rc**2
            return [
                hu(x, y, pr.s0, cx, pr.rc)
                + sign * pr.alpha * np.where(p > 0, hp(x, y, pr.s0, cx, pr.rc), 0.0)
                for hu, hp in zip(sym["hess_u"], sym["hess_p2"], strict=True)
            ]

        return h

    results = {}
    for side, obstacle in (("lower", pr.lower), ("upper", pr.upper)):
        sign = 1.0 if side == "lower" else -1.0

        def lam_true(x, y, sign=sign):
            return lambda_psi_reference(pr, sign * x, y)

        results[side] = check_envelope(
            f"two-sided {side} {params}",
            obstacle,
            lam_true,
            hessian(side),
            px,
            py,
            obstacle.envelope,
            rng,
        )
        # sharp: on small pieces the Hessian bounds are nearly attained
        for key in ("sharpness M-", "sharpness M+"):
            assert results[side][key] is None or results[side][key] > 0.95, key
        assert results[side]["sharpness M-"] or results[side]["sharpness M+"]
    # mirror images: the upper envelope on reflected pieces is the lower one, exchanged
    lo = pr.lower.envelope(px, py)
    up = pr.upper.envelope(-px, py)
    assert_allclose(up[0], lo[1])
    assert_allclose(up[1], lo[0])
    assert_allclose(up[2], lo[2])
