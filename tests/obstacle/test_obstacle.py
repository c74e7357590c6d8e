"""The obstacle family: input checks, the three methods, symmetry, the bound, archives."""

import numpy as np
import pytest

import fastmem as fm
from fastmem.errors import DataError, InputTypeError, ParameterError
from fastmem.estimators import obstacle as est
from fastmem.solver.nested import interpolation_matrix


def _energy(problem, v):
    return float(np.sqrt(v @ (problem.weighted @ v)))


def _step41_like(n, **kw):
    """A P1 two-sided problem with a large contact set on both obstacles."""
    mesh = fm.Mesh.square(n)
    x, y = mesh.vertices.T
    lower = -0.3 + 0.2 * x  # nodal data: a P1 obstacle
    return fm.Obstacle(
        mesh, mu=1.0, f=lambda x, y: -10.0 * np.cos(3 * x), lower=lower, upper=0.05, **kw
    )


# ----------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("kw", "error", "words"),
    [
        ({}, ParameterError, "lower=..., upper=..."),
        ({"lower": 0.2, "g": 0.0}, DataError, "lower obstacle is above the boundary value"),
        ({"upper": -0.2, "g": 0.0}, DataError, "upper obstacle is below the boundary value"),
        ({"lower": -0.1, "upper": -0.2, "g": -0.15}, DataError, "lower > upper"),
        ({"lower": np.full(25, np.nan)}, DataError, "lower is NaN or infinite"),
        (
            {"upper": lambda x, y: np.where(x > 0.5, np.inf, 1.0)},
            DataError,
            r"upper\(x, y\) returned NaN",
        ),
        ({"lower": "high"}, InputTypeError, "lower must be None"),
        ({"lower": np.zeros(7)}, DataError, "one value per vertex"),
        ({"lower": -1.0, "mu": -1.0}, ParameterError, "mu must be positive"),
    ],
)
def test_bad_input_is_refused_naming_the_place(kw, error, words):
    with pytest.raises(error, match=words):
        fm.Obstacle(fm.Mesh.square(4), **kw)


def test_infeasible_boundary_names_the_vertex():
    mesh = fm.Mesh.square(4)
    lower = np.full(mesh.n_vertices, -1.0)
    k = int(mesh.boundary_vertices[3])
    lower[k] = 0.5
    with pytest.raises(DataError, match=f"vertex {k} at"):
        fm.Obstacle(mesh, lower=lower)


@pytest.mark.parametrize(
    ("kw", "words"),
    [({"path": "decoupled"}, "path='decoupled'"), ({"safeguard": False}, "safeguard=False")],
)
def test_two_membrane_options_are_refused(kw, words):
    problem = fm.Obstacle(fm.Mesh.square(4), lower=-0.1)
    with pytest.raises(ParameterError, match=words):
        fm.solve(problem, **kw)


def test_problem_is_read_only_and_typos_are_named():
    problem = fm.Obstacle(fm.Mesh.square(4), lower=-0.1)
    with pytest.raises(AttributeError, match="immutable"):
        problem.lower = 0.0
    with pytest.raises(ParameterError, match="lower"):
        fm.Obstacle(fm.Mesh.square(4), lowr=-0.1)


# ----------------------------------------------------------------- solving
def test_methods_agree_and_discrete_complementarity_holds():
    problem = _step41_like(32)
    out = {m: fm.solve(problem, method=m) for m in ("exact", "exact-amg", "inexact")}
    ex = out["exact"]
    assert ex.converged
    assert ex.eta_components["eta_lin"] == 0.0
    ii = problem.mesh.interior_vertices
    u, lam = ex.u[ii], ex.lam[ii]
    psi, chi = problem.psi[ii], problem.chi[ii]
    # discrete complementarity: both sets non-empty, signs and contact exact
    assert (lam > 0).sum() > 20
    assert (lam < 0).sum() > 20
    assert np.all(u >= psi - 1e-12)
    assert np.all(u <= chi + 1e-12)
    assert np.all(np.abs(u[lam > 0] - psi[lam > 0]) <= 1e-14)
    assert np.all(np.abs(u[lam < 0] - chi[lam < 0]) <= 1e-14)
    # the residual is zero on every interior vertex of the exact solution
    r = est.residual(problem, ex.u, ex.lam)
    assert np.abs(r).max() <= 1e-10 * np.abs(problem.load).max()
    assert np.abs(out["exact-amg"].u - ex.u).max() <= 1e-9
    inexact = out["inexact"]
    assert inexact.converged
    c = inexact.eta_components
    assert c["eta_alg"] <= 0.1 * c["eta_disc"]
    assert c["eta_lin"] <= 0.1 * c["eta_disc"]
    # the inexact solution is as accurate as the estimate says
    assert _energy(problem, inexact.u - ex.u) <= inexact.eta


def test_lower_upper_symmetry_is_exact():
    mesh = fm.Mesh.square(32)
    f = lambda x, y: -8.0 + 4 * x * y  # noqa: E731
    a = fm.solve(fm.Obstacle(mesh, f=f, g=0.05, lower=lambda x, y: -0.1 + 0 * x), method="exact")
    b = fm.solve(
        fm.Obstacle(mesh, f=lambda x, y: -f(x, y), g=-0.05, upper=lambda x, y: 0.1 + 0 * x),
        method="exact",
    )
    np.testing.assert_array_equal(a.u, -b.u)
    np.testing.assert_array_equal(a.lam, -b.lam)
    np.testing.assert_array_equal(a.active_lower, b.active_upper)
    assert a.eta == pytest.approx(b.eta, rel=1e-12)
    for k in ("eta_disc", "eta_lin", "eta_alg"):
        assert a.eta_components[k] == pytest.approx(b.eta_components[k], rel=1e-12, abs=1e-15)


# ----------------------------------------------------------------- the bound
def _reference(problem_of, n, levels=3):
    coarse = problem_of(n)
    fine = problem_of(n * 2**levels)
    ref = fm.solve(fine, method="exact", estimate=False)
    mat = interpolation_matrix(coarse.mesh, fine.mesh)
    return coarse, fine, ref, mat


@pytest.mark.parametrize("n", [8, 16])
def test_bound_above_error_for_every_method_and_perturbed_iterates(n):
    coarse, fine, ref, mat = _reference(_step41_like, n)
    rng = np.random.default_rng(n)
    for method in ("exact", "exact-amg", "inexact"):
        res = fm.solve(coarse, method=method)
        err = _energy(fine, ref.u - mat @ res.u)
        assert res.eta >= err, (method, res.eta, err)
        assert res.eta <= 3.0 * err  # not absurdly large either
    base = fm.solve(coarse, method="exact")
    bnd = coarse.mesh.boundary_vertex_mask
    for scale in (1e-3, 1e-2, 1e-1):
        u = base.u + np.where(bnd, 0.0, scale * rng.standard_normal(coarse.mesh.n_vertices))
        lam = base.lam + np.where(bnd, 0.0, 10 * scale * rng.standard_normal(u.size))
        e = est.estimate(coarse, u, lam)
        err = _energy(fine, ref.u - mat @ u)
        assert e.eta >= err, (scale, e.eta, err)
        assert e.eta_lin > 0.0
        assert e.eta_alg > 0.0
        assert e.eta_I <= e.eta_disc + e.eta_lin + e.eta_alg + 1e-12


def test_archive_round_trip_and_info(tmp_path):
    problem = _step41_like(16)
    res = fm.solve(problem)
    path = tmp_path / "obstacle.h5"
    res.save(path)
    back = fm.load(path)
    assert type(back).__name__ == "ObstacleResult"
    np.testing.assert_array_equal(back.u, res.u)
    np.testing.assert_array_equal(back.lower, problem.psi)
    np.testing.assert_array_equal(back.upper, problem.chi)
    assert back.eta == res.eta
    assert back.contact_area == res.contact_area
    from fastmem.io.archive import info

    summary = info(path)
    assert summary["parameters"]["problem"] == "obstacle"
    assert summary["parameters"]["lower_kind"] == "p1"


def test_solve_to_tolerance_refines_where_needed():
    mesh = fm.Mesh.square(8)
    problem = fm.Obstacle(mesh, mu=1.0, f=-10.0, lower=-0.05)
    first = fm.solve(problem, method="exact")
    res = fm.solve(problem, tol=first.eta / 3)
    table = res.adaptivity
    assert res.converged
    assert res.eta <= first.eta / 3
    assert table["n_vertices"][-1] > mesh.n_vertices
    assert np.all(np.diff(table["n_vertices"]) > 0)
    # adaptive: fewer vertices than the uniform mesh with the same bound would need
    uniform = fm.solve(fm.Obstacle(fm.Mesh.square(32), mu=1.0, f=-10.0, lower=-0.05))
    assert res.eta <= uniform.eta * 1.05 or res.mesh.n_vertices < uniform.mesh.n_vertices
