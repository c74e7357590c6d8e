"""The obstacle bound against exact solutions: the ball, the two-sided case, step-41, the CLI."""

import numpy as np
import pytest

import fastmem as fm
from fastmem.cli.main import main
from fastmem.estimators import obstacle as est
from fastmem.problems.ball import CONTACT_AREA, ball_solution
from fastmem.problems.obstacles import ball, exact_error, step41, twosided


def _rate(errors, ns):
    return np.log(errors[:-1] / errors[1:]) / np.log(np.asarray(ns[1:]) / np.asarray(ns[:-1]))


def test_ball_converges_with_effectivity_in_range():
    ns = (32, 64, 128)
    errors, etas, areas = [], [], []
    for n in ns:
        problem = ball(n)
        res = fm.solve(problem, method="exact")
        errors.append(exact_error(problem, res.u))
        etas.append(res.eta)
        areas.append(res.contact_area)
        assert res.estimate.totals["guaranteed"] == 1.0
    errors, etas = np.array(errors), np.array(etas)
    eff = etas / errors
    assert np.all(eff >= 1.0), eff
    assert np.all(eff <= 1.3), eff  # measured 1.29, 1.18, 1.11
    assert np.all(np.diff(eff) < 0)  # the obstacle terms fade like h
    assert _rate(errors, ns)[-1] >= 0.95  # measured 0.96, 0.98
    # the contact area tends to pi a^2 (O(h), not monotone)
    assert abs(areas[-1] - CONTACT_AREA) < abs(areas[0] - CONTACT_AREA)
    assert abs(areas[-1] - CONTACT_AREA) < 0.05


def test_ball_max_nodal_error_matches_petsc_ex9_on_a_coarse_grid():
    # the P1 stiffness of the structured mesh is the 5-point Laplacian and f = 0: the
    # discrete solution is ex9's finite-difference one (docs/obstacle.md §8.1); on the
    # 65 x 65 grid the small NumPy check of the derivation gave 5.991e-4
    problem = ball(64)
    res = fm.solve(problem, method="exact", estimate=False)
    exact = ball_solution(*problem.mesh.vertices.T)
    assert np.abs(res.u - exact).max() == pytest.approx(5.991e-4, rel=1e-3)


@pytest.mark.parametrize("s0", [1.0, -1.0])
def test_two_sided_manufactured_solution(s0):
    ns = (16, 32, 64)
    errors, etas = [], []
    for n in ns:
        problem = twosided(n, s0=s0)
        res = fm.solve(problem, method="exact")
        errors.append(exact_error(problem, res.u))
        etas.append(res.eta)
        assert res.active_lower.sum() > 0
        assert res.active_upper.sum() > 0
    errors, etas = np.array(errors), np.array(etas)
    assert np.all(etas >= errors)
    assert np.all(etas <= 1.15 * errors)  # measured 1.04-1.09
    assert np.all(_rate(errors, ns) >= 0.98)


@pytest.mark.parametrize("make", [ball, twosided])
def test_bound_holds_for_inexact_and_perturbed_iterates(make):
    problem = make(32)
    res = fm.solve(problem, method="inexact")
    assert res.eta >= exact_error(problem, res.u)
    rng = np.random.default_rng(3)
    bnd = problem.mesh.boundary_vertex_mask
    for scale in (1e-3, 1e-2, 1e-1):
        u = res.u + np.where(bnd, 0.0, scale * rng.standard_normal(res.u.size))
        lam = res.lam + np.where(bnd, 0.0, 10 * scale * rng.standard_normal(res.u.size))
        e = est.estimate(problem, u, lam)
        assert e.eta >= exact_error(problem, u), scale
        assert e.eta_I <= e.eta_disc + e.eta_lin + e.eta_alg + 1e-12


@pytest.mark.parametrize("make", [ball, twosided])
def test_band_kernel_matches_numpy(make):
    problem = make(16)
    res = fm.solve(problem, method="exact", estimate=False)
    rng = np.random.default_rng(5)
    bnd = problem.mesh.boundary_vertex_mask
    u = res.u + np.where(bnd, 0.0, 0.02 * rng.standard_normal(res.u.size))
    lam = res.lam + np.where(bnd, 0.0, 0.5 * rng.standard_normal(res.u.size))
    cheap = est.cheap_terms(problem, u, lam)
    for side, key in (("lower", "ell_plus"), ("upper", "ell_minus")):
        if problem.obstacle_kind(side) == "none":
            continue
        s = est._Side(problem, side)
        kernel = est._obstacle_terms(problem, s, u, cheap[key])
        numpy = est._obstacle_terms(problem, s, u, cheap[key], reference=True)
        assert kernel[0].max() > 0
        np.testing.assert_allclose(kernel[0], numpy[0], rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(kernel[1], numpy[1], rtol=1e-12, atol=1e-15)


def test_step41_load_shaping_keeps_the_bound_decreasing():
    etas = []
    for n in (16, 32, 64):
        res = fm.solve(step41(n), method="exact")
        assert res.estimate.totals["guaranteed"] == 1.0
        assert res.n_newton <= 5
        etas.append(res.eta)
        # with the default patch load the complementarity term stalls near 0.75
        assert res.estimate.totals["c_disc"] < 0.05
    assert etas[2] < 0.75 * etas[0]


def test_step41_bound_above_a_finer_reference():
    from fastmem.solver.nested import interpolation_matrix

    coarse, fine = step41(16), step41(128)
    res = fm.solve(coarse, method="exact")
    ref = fm.solve(fine, method="exact", estimate=False)
    diff = ref.u - interpolation_matrix(coarse.mesh, fine.mesh) @ res.u
    err = float(np.sqrt(diff @ (fine.weighted @ diff)))
    assert err <= res.eta <= 2.0 * err


def test_cli_runs_a_reference_problem(tmp_path, capsys):
    out = tmp_path / "ball.h5"
    assert main(["run", "--problem", "ball", "--n", "32", "-o", str(out), "-q"]) == 0
    text = capsys.readouterr().out
    assert "exact error" in text
    assert "effectivity" in text
    assert "guaranteed" in text
    back = fm.load(out)
    assert type(back).__name__ == "ObstacleResult"
    assert main(["info", str(out)]) == 0
    assert "BallObstacle" in capsys.readouterr().out
    assert main(["export", str(out), str(tmp_path / "ball.vtu")]) == 0
    assert main(["run", "--problem", "ball", "--n", "8", "--path", "general", "--no-save"]) == 2
    assert "--path general is an option of the two-membrane problem" in capsys.readouterr().err


def test_cli_constant_obstacle_and_typo(capsys):
    argv = ["run", "--problem", "obstacle", "--lower", "-0.1", "--upper", "0.1", "--n", "16"]
    assert main([*argv, "--no-save", "-q"]) == 0
    assert "on the lower obstacle" in capsys.readouterr().out
    assert main(["run", "--problem", "stp41", "--no-save"]) == 2
    assert "did you mean 'step41'" in capsys.readouterr().err
    assert main(["run", "--problem", "ball", "--mu1", "2", "--no-save"]) == 2
    assert "--mu1 is an option of the two-membrane scene" in capsys.readouterr().err
    assert main(["run", "--lower", "0.1", "--no-save"]) == 2
    assert "--lower is an option of --problem obstacle" in capsys.readouterr().err
    assert main(["run", "--problem", "ball", "--g", "1", "--no-save"]) == 2
    assert "cannot change the reference problem ball" in capsys.readouterr().err


def test_callable_obstacle_without_envelope_is_labelled_estimated():
    guaranteed = ball(32)
    plain = fm.Obstacle(guaranteed.mesh, g=ball_solution, lower=lambda x, y: guaranteed.lower(x, y))
    a = fm.solve(guaranteed, method="exact")
    b = fm.solve(plain, method="exact")
    np.testing.assert_array_equal(a.u, b.u)
    assert a.estimate.totals["guaranteed"] == 1.0
    assert b.estimate.totals["guaranteed"] == 0.0
    assert "without envelope" in b.parameters["estimate"]["reason"]
    # the estimated obstacle terms stay close to the guaranteed ones
    assert b.eta == pytest.approx(a.eta, rel=0.1)


def test_per_triangle_mu_with_a_smooth_obstacle_is_not_claimed_guaranteed():
    problem = ball(16)
    mu = np.ones(problem.mesh.n_triangles)
    mu[::2] = 2.0
    res = fm.solve(fm.Obstacle(problem.mesh, mu=mu, g=ball_solution, lower=problem.lower))
    assert res.estimate.totals["guaranteed"] == 0.0
    assert "§10.2" in res.parameters["estimate"]["reason"]
    # a P1 obstacle with per-triangle mu keeps the guarantee (case (i))
    res = fm.solve(fm.Obstacle(problem.mesh, mu=mu, f=-10.0, lower=-0.5, g=0.0))
    assert res.estimate.totals["guaranteed"] == 1.0


def test_obstacle_near_a_callable_boundary_value_is_flagged():
    mesh = fm.Mesh.square(16)
    g = lambda x, y: 0.05 * np.sin(3 * x) * np.cos(2 * y)  # noqa: E731
    near = fm.solve(fm.Obstacle(mesh, f=-10.0, g=g, lower=-0.06))
    assert near.estimate.totals["guaranteed"] == 0.0
    assert "§4.5" in near.parameters["estimate"]["reason"]
    far = fm.solve(fm.Obstacle(mesh, f=-10.0, g=g, lower=-0.5))
    assert far.estimate.totals["guaranteed"] == 1.0


def test_warm_up_of_an_obstacle_covers_its_solve():
    from fastmem.cli import warmup

    fm.warm_up("inexact", obstacle=True, large=True)
    dispatchers = warmup._dispatchers()
    before = {d: sum(d.stats.cache_misses.values()) for d in dispatchers}
    fm.solve(ball(192))  # 37,249 vertices: the threaded active-set matrices
    compiled = [d.__name__ for d in dispatchers if sum(d.stats.cache_misses.values()) != before[d]]
    assert compiled == []


def test_envelopes_and_radii_in_row_blocks_give_the_same_bits(monkeypatch):
    """The obstacle's envelope and the radii, called on slices of rows: same bound, same bits."""
    problem = twosided(24)
    ref = fm.solve(problem)
    rng = np.random.default_rng(3)
    px, py = rng.random((100, 3)), rng.random((100, 3))
    radius = est.enclosing_radius(px, py)
    side = est._Side(problem, "upper")
    whole = side.envelope(px, py)
    monkeypatch.setattr(est, "ENVELOPE_ROWS", 7)
    np.testing.assert_array_equal(est.enclosing_radius(px, py), radius)
    for a, b in zip(side.envelope(px, py), whole, strict=True):
        np.testing.assert_array_equal(a, b)
    got = fm.solve(twosided(24))
    assert got.eta == ref.eta
    np.testing.assert_array_equal(got.u, ref.u)


def test_estimated_obstacle_pieces_in_row_blocks_give_the_same_bits(monkeypatch):
    """A callable obstacle without envelope (terms estimated on pieces), in blocks: same bits."""

    def problem():
        bump = lambda x, y: -0.2 + 0.1 * np.sin(3.0 * x) * np.cos(2.0 * y)  # noqa: E731
        return fm.Obstacle(fm.Mesh.square(16), f=-10.0, lower=bump, parallel_callables=True)

    ref = fm.solve(problem())
    assert ref.estimate is not None
    monkeypatch.setattr(est, "ENVELOPE_ROWS", 7)
    got = fm.solve(problem())
    assert got.eta == ref.eta
    np.testing.assert_array_equal(got.u, ref.u)


def test_envelope_blocks_keep_a_pressure_bound_per_triangle(monkeypatch):
    """An envelope whose pressure bound is one value per triangle: (P, 3) in blocks too."""

    class Flat:
        def __call__(self, x, y):
            return -0.2 + 0.0 * x

        def envelope(self, px, py):
            n = px.shape[0]
            return np.zeros(n), np.zeros(n), px[:, 0] + 2.0 * py[:, 1]

    problem = fm.Obstacle(fm.Mesh.square(8), f=-10.0, lower=Flat())
    side = est._Side(problem, "lower")
    px, py = np.random.default_rng(4).random((2, 20, 3))
    monkeypatch.setattr(est, "ENVELOPE_ROWS", 6)
    mm, mp, lam_up = side.envelope(px, py)
    assert mm.shape == mp.shape == (20,)
    want = px[:, 0] + 2.0 * py[:, 1]
    np.testing.assert_array_equal(lam_up, np.repeat(want[:, None], 3, axis=1))
