"""The liquid–gas model: laws, Jacobian, Newton-min, mass balance, complementarity, bad input."""

import numpy as np
import pytest

import fastmem as fm
from fastmem.errors import ParameterError
from fastmem.twophase import (
    YEAR,
    Grid,
    Physics,
    Problem,
    benchmark,
    newton_min,
    simulate,
)
from fastmem.twophase.laws import CHORD


def small(n=60, **kw):
    """The benchmark column with fewer cells (same physics, 200 m)."""
    return benchmark("momas", n_cells=n, **kw)


@pytest.fixture(scope="module")
def gas_state():
    """A small column after 6 steps of 5000 years: gas in the first cells."""
    prob = small()
    run = simulate(prob, t_end=6 * 5000 * YEAR, linear_solver="direct", estimate=False)
    assert run.gas_cells[-1] > 0
    return prob, run.final


def test_laws_van_genuchten_values():
    laws = Physics().laws()
    s = np.array([0.5, 0.8, 0.99])
    se = (s - 0.4) / 0.6
    m = 1 - 1 / 1.49
    pc = 2e6 * (se ** (-1 / m) - 1) ** (1 / 1.49)
    krl = np.sqrt(se) * (1 - (1 - se ** (1 / m)) ** m) ** 2
    krg = np.sqrt(1 - se) * (1 - se ** (1 / m)) ** (2 * m)
    assert np.allclose(laws.capillary(s), pc, rtol=1e-13)
    assert np.allclose(laws.k_liquid(s), krl, rtol=1e-13)
    assert np.allclose(laws.k_gas(s), krg, rtol=1e-13)
    # the chord on the last CHORD of S_e: continuous, zero capillary pressure at S = 1
    top = 0.4 + 0.6 * (1 - CHORD)
    assert laws.capillary(np.array([1.0]))[0] == 0.0
    assert laws.k_liquid(np.array([1.0]))[0] == pytest.approx(1.0)
    below, above = laws.capillary(np.array([top - 1e-12, top + 1e-12]))
    assert above == pytest.approx(below, rel=1e-6)


def test_jacobian_matches_finite_differences(gas_state):
    """Every column of the complex-step Jacobian against finite differences.

    Central differences, one-sided (backward) in S where S = 1 (the model is
    not defined above): the laws' S-derivatives in gas cells, chained into
    the face fluxes, are all checked.
    """
    prob, x = gas_state
    dt, t = 5000 * YEAR, 7 * 5000 * YEAR
    x_old = x.copy()
    x = x.copy()
    x[:, 1] *= 1.001  # off the solution, so every term is active
    gas = prob.gas(x)
    assert gas.sum() >= 3
    jac = prob.jacobian(x, gas, dt).toarray()
    units = prob.units()
    checked_gas_s = 0
    for col in range(3 * prob.grid.n):
        i, k = divmod(col, 3)
        h = 1e-7 * units[k]
        xp, xm = x.copy(), x.copy()
        if k == 0 and x[i, 0] >= 1.0 - 2 * h:
            xm[i, k] -= h  # backward difference at S = 1
            fd = (prob.residual(x, x_old, dt, t, gas) - prob.residual(xm, x_old, dt, t, gas)) / h
            tol = 1e-4
        else:
            xp[i, k] += h
            xm[i, k] -= h
            fd = (prob.residual(xp, x_old, dt, t, gas) - prob.residual(xm, x_old, dt, t, gas)) / (
                2 * h
            )
            tol = 1e-5
            checked_gas_s += int(k == 0 and gas[i])
        scale = np.abs(jac[:, col]).max() + 1e-300
        assert np.abs(fd.ravel() - jac[:, col]).max() <= tol * scale, (i, k)
    assert checked_gas_s >= 3


def test_newton_min_converges_quadratically(gas_state):
    """Once the residual is small, each Newton-min step squares it (up to a constant)."""
    prob, x = gas_state
    dt = 5000 * YEAR
    _, stats = newton_min(prob, x, dt, 7 * dt, linear_solver="direct", tol=1e-13)
    assert stats.converged
    r = np.array(stats.residuals)
    # above the round-off floor of the residual (the last steps stagnate there: about
    # 1e-12 on one machine, below it on another); 100x the smallest one reached
    floor = max(1e-12, 100.0 * r.min())
    tail = r[(r < 1e-3) & (r > floor)]
    assert tail.size >= 2, stats.residuals
    # r_{k+1} <= C r_k^2 with a modest C on every pair of the tail
    assert np.all(tail[1:] <= 1e2 * tail[:-1] ** 2), stats.residuals
    orders = np.log(tail[1:]) / np.log(tail[:-1])
    assert orders.min() >= 1.8, (stats.residuals, orders)


def test_complementarity_and_mass_balance_every_step():
    prob = small()
    run = simulate(prob, t_end=10 * 5000 * YEAR, linear_solver="direct")
    x = run.final
    one, two = prob.branches(x)
    assert np.abs(np.minimum(one, two)).max() <= 1e-12
    assert one.min() >= -1e-15
    assert two.min() >= -1e-12 * prob.physics.henry_mass * 1e6
    gas = prob.gas(x)
    assert gas.any()
    assert (~gas).any()
    assert np.all(x[gas, 0] < 1)
    assert np.all(x[~gas, 0] == 1.0)
    injected = np.array(run.injected)
    assert np.abs(run.balance).max() <= 1e-12 * injected.max()
    assert injected[-1] == pytest.approx(10 * 5000 * 5.57e-6)


def test_linear_solvers_and_strategies_agree():
    prob = small()
    runs = {
        (s, ls): simulate(prob, t_end=6 * 5000 * YEAR, strategy=s, linear_solver=ls)
        for s, ls in (("exact", "direct"), ("exact", "ilu"), ("exact", "cpr"), ("inexact", "ilu"))
    }
    ref = runs["exact", "direct"].final
    units = prob.units()
    for key, run in runs.items():
        assert np.abs((run.final - ref) / units).max() <= 1e-8, key
    adaptive = simulate(prob, t_end=6 * 5000 * YEAR, strategy="adaptive")
    # adaptive stops early: its profiles differ from exact by much less than eta_disc's size
    diff = np.abs((adaptive.final - ref) / units).max()
    assert diff <= 1e-4
    # in 1D block ILU(0) is exact (one GMRES iteration per Newton step): the saving is
    # in Newton-min steps, stopped once eta_lin <= gamma_lin eta_disc
    assert adaptive.totals()["newton"] < runs["exact", "ilu"].totals()["newton"]
    exact = runs["exact", "ilu"].totals()
    assert exact["linear"] == exact["newton"]


def test_gas_appears_in_the_third_step_of_the_benchmark():
    prob = benchmark("momas")
    run = simulate(prob, t_end=3 * 5000 * YEAR, linear_solver="direct", estimate=False)
    assert run.first_gas_step == 3
    gas = prob.gas(run.final)
    assert gas[0]
    assert prob.grid.centres[gas, 0].max() < 5.0


def test_gas_disappears_after_injection_stops():
    """The MoMaS variant on a coarse column, shortened: injection until 1e5 years."""
    prob = benchmark("momas", n_cells=50, stop_injection=1e5)
    run = simulate(prob, t_end=3e5 * YEAR, linear_solver="direct", estimate=False)
    g = np.array(run.gas_cells)
    peak = int(np.argmax(g))
    assert g[peak] > 0
    assert g[-1] == 0
    assert np.abs(run.balance).max() <= 1e-12 * max(run.injected)


def test_bad_input_is_refused_with_the_field_named():
    grid = Grid.column(10.0, 5)
    with pytest.raises(ParameterError, match=r"S outside \[S_lr, 1\].*cell 0"):
        Problem(grid, initial=(0.2, 1e6, 0.0))
    with pytest.raises(ParameterError, match="nonpositive pressure.*cell 0"):
        Problem(grid, initial=(1.0, -5.0, 0.0))
    with pytest.raises(ParameterError, match="negative dissolved"):
        Problem(grid, boundary=(1.0, 1e6, -1e-3))
    with pytest.raises(ParameterError, match="dt must be a positive"):
        simulate(Problem(grid), dt=0.0)
    with pytest.raises(ParameterError, match="Physics.porosity"):
        Physics(porosity=-0.1)
    with pytest.raises(ParameterError, match="Physics.n must exceed 1"):
        Physics(n=0.9)
    with pytest.raises(ParameterError, match="strategy must be one of"):
        simulate(Problem(grid), strategy="fast")
    with pytest.raises(ParameterError, match="viscosity must be one of"):
        benchmark("water")
    with pytest.raises(ParameterError, match="no Dirichlet face"):
        Problem(Grid.column(10.0, 5, right_dirichlet=False))
    with pytest.raises(ParameterError, match=r"boundary_cells must name cells 0\.\.4, got 7"):
        Grid(np.ones(5), np.arange(5), [[0, 1]], [1.0], [7], [1.0])
    with pytest.raises(ParameterError, match="boundary_geometry must be positive, got -1.0"):
        Grid(np.ones(5), np.arange(5), [[0, 1]], [1.0], [4], [-1.0])
    with pytest.raises(ParameterError, match=r"S outside \[S_lr, 1\]"):
        Problem(grid, initial=(1.2, 1e6, 0.0))
    with pytest.raises(ParameterError, match="t_end must be a positive"):
        simulate(Problem(grid), t_end=-1.0)
    with pytest.raises(ParameterError, match="dt must be a positive"):
        simulate(Problem(grid), dt=-5.0)
    with pytest.raises(ParameterError, match="linear_solver must be one of"):
        simulate(Problem(grid), linear_solver="jacobi")
    with pytest.raises(ParameterError, match="max_front_cells must be an integer"):
        simulate(Problem(grid), max_front_cells=-1)
    with pytest.raises(ParameterError, match=r"keep times must lie in \(0, t_end\]"):
        simulate(Problem(grid), t_end=10.0, dt=5.0, keep=[20.0])


def test_public_face():
    assert fm.twophase.Problem is Problem
    assert set(fm.twophase.STRATEGIES) == {"exact", "inexact", "adaptive"}


def test_fischer_burmeister_reaches_the_newton_min_solution():
    """Both complementarity functions have the same zeros: the same discrete solution."""
    runs = {
        c: simulate(small(complementarity=c), t_end=8 * 5000 * YEAR, linear_solver="direct")
        for c in ("min", "fb")
    }
    prob = small()
    units = prob.units()
    assert runs["fb"].gas_cells[-1] == runs["min"].gas_cells[-1] > 0
    assert np.abs((runs["fb"].final - runs["min"].final) / units).max() <= 1e-8
    assert np.abs(prob.complementarity_residual(runs["fb"].final)).max() <= 1e-10
    with pytest.raises(ParameterError, match="complementarity must be one of"):
        small(complementarity="smooth")


def test_a_step_where_too_many_cells_change_phase_is_halved(caplog):
    prob = small(120)
    with caplog.at_level("WARNING", logger="fastmem.twophase.run"):
        run = simulate(
            prob, t_end=6 * 5000 * YEAR, linear_solver="direct", max_front_cells=2, estimate=False
        )
    assert run.retries
    assert all("changed phase" in reason for _, _, reason in run.retries)
    assert "retrying with dt" in caplog.text
    assert min(run.dts) < 5000 * YEAR
    assert run.times[-1] == pytest.approx(6 * 5000 * YEAR)
    assert np.abs(run.balance).max() <= 1e-12 * run.injected[-1]


def test_a_step_ends_where_the_injection_stops():
    prob = small(40, stop_injection=12_500.0)  # years: inside the third 5000-year step
    run = simulate(prob, t_end=4 * 5000 * YEAR, linear_solver="direct", estimate=False)
    assert any(abs(t / YEAR - 12_500.0) < 1e-6 for t in run.times)
    assert run.injected[-1] == pytest.approx(12_500.0 * 5.57e-6, rel=1e-12)
    assert np.abs(run.balance).max() <= 1e-12 * run.injected[-1]


def test_no_injection_leaves_the_column_at_rest():
    prob = benchmark("momas", n_cells=30)
    prob.hydrogen[:] = 0.0
    run = simulate(prob, t_end=3 * 5000 * YEAR, linear_solver="direct")
    assert np.array_equal(run.final, prob.initial)
    assert run.gas_cells == [0, 0, 0]
    assert np.abs(run.balance).max() == 0.0


def test_balance_counts_the_hydrogen_present_at_the_start():
    grid = Grid.column(20.0, 20)
    chi0 = np.linspace(1e-5, 0.0, 20)
    initial = np.column_stack([np.ones(20), np.full(20, 1e6), chi0])
    prob = Problem(grid, initial=initial, hydrogen=np.r_[1e-12, np.zeros(19)])
    run = simulate(prob, t_end=3 * 5000 * YEAR, linear_solver="direct")
    assert run.initial_in_place > 1e-3
    assert np.abs(run.balance).max() <= 1e-12 * run.initial_in_place


def test_kept_profiles_are_the_steps_nearest_to_the_times_asked():
    prob = small(40, stop_injection=12_500.0)  # the third step is cut at 12,500 years
    wanted = [5000.0 * YEAR, 13_000.0 * YEAR, 20_000.0 * YEAR]
    run = simulate(prob, t_end=4 * 5000 * YEAR, linear_solver="direct", keep=wanted)
    ends = np.array(run.times)
    expected = [ends[np.argmin(np.abs(ends - k))] for k in wanted]
    assert run.kept_times == expected
    for t, state in zip(run.kept_times, run.states, strict=True):
        assert state.shape == (40, 3)
        assert t in run.times


def test_after_a_retry_the_step_does_not_double_straight_back():
    prob = small(120)
    run = simulate(
        prob, t_end=6 * 5000 * YEAR, linear_solver="direct", max_front_cells=2, estimate=False
    )
    starts = np.r_[0.0, np.array(run.times[:-1])]
    retried = {t for t, _, _ in run.retries}
    checked = 0
    for i in range(len(run.dts) - 1):
        if any(abs(starts[i] - t) < 1e-6 * YEAR for t in retried):
            assert run.dts[i + 1] <= run.dts[i] * (1 + 1e-12)  # no doubling right after
            checked += 1
    assert checked >= 1


def test_newton_does_not_accept_a_step_the_projection_swallowed():
    """A state pushed against the box (chi < 0 wanted) is not declared converged on a zero step."""
    prob = small(30)
    x_old = prob.initial.copy()
    dt = 5000 * YEAR
    # a huge negative hydrogen source drives chi below zero: the projection keeps chi >= 0,
    # the update vanishes, the residual does not
    prob.hydrogen[:] = -1e-6
    x, stats = newton_min(prob, x_old, dt, dt, linear_solver="direct", max_newton=6)
    assert not stats.converged
    assert stats.residuals[-1] > 1e-5
