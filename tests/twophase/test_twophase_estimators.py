"""The two-phase estimators: equilibration, and the algebraic and linearisation parts vanishing."""

import numpy as np
import pytest
import scipy.sparse as sp

from fastmem.twophase import YEAR, Estimator, benchmark, section, simulate
from fastmem.twophase.linear import gmres, preconditioner
from fastmem.twophase.newton import _ORDER


@pytest.fixture(scope="module")
def state():
    prob = benchmark("momas", n_cells=80)
    run = simulate(prob, t_end=5 * 5000 * YEAR, linear_solver="direct", estimate=False)
    return prob, run.final


def test_dual_flux_has_the_divergence_it_is_built_from(state):
    prob, _ = state
    est = Estimator(prob)
    s = np.random.default_rng(0).standard_normal((prob.grid.n, 2))
    fi, fb = est.flux(s)
    div = prob.divergence(fi, fb)
    assert np.abs(div - s).max() <= 1e-11 * np.abs(s).max()
    # its norm is the dual norm s . L^-1 s
    assert est.face_norm2(fi, fb) == pytest.approx(est.dual_norm2(s), rel=1e-10)


def test_equilibrated_fluxes_balance_every_cell(state):
    """storage change / dt + div sigma = source in every cell, for a non-converged iterate."""
    prob, x_old = state
    dt, t = 5000 * YEAR, 6 * 5000 * YEAR
    x = x_old.copy()
    x[:, 1] *= 1 + 1e-3 * np.sin(np.arange(prob.grid.n))
    gas = prob.gas(x)
    est = Estimator(prob)
    si, sb = est.equilibrated(x, x_old, gas, dt, t)
    qw, qh = prob.sources(t)
    balance = (prob.storage(x) - prob.storage(x_old)) / dt + prob.divergence(si, sb)
    balance -= np.column_stack([qw, qh])
    size = np.abs(prob.divergence(*prob.fluxes(x))).max(axis=0)
    assert np.all(np.abs(balance).max(axis=0) <= 1e-10 * size)


def _linear_system(prob, x, x_old, dt, t):
    gas = prob.gas(x)
    r = prob.residual(x, x_old, dt, t, gas)
    jac = prob.jacobian(x, gas, dt)
    rows = 1.0 / prob.row_scales(dt, gas).ravel()
    cols = np.tile(prob.units(), prob.grid.n)
    perm = (3 * np.arange(prob.grid.n)[:, None] + _ORDER).ravel()
    a = (sp.diags(rows) @ jac @ sp.diags(cols)).tocsr()[perm]
    return gas, r, jac, a, -(r.ravel() * rows)[perm], cols


def test_eta_alg_vanishes_as_gmres_converges():
    """On the 2D section (in 1D the block ILU is exact and GMRES stops after one step)."""
    prob = section(120, 12)
    dt = 5000 * YEAR
    x_old = simulate(prob, t_end=4 * dt, linear_solver="direct", estimate=False).final
    t = 5 * dt
    gas, r, jac, a, b, cols = _linear_system(prob, x_old, x_old, dt, t)
    est = Estimator(prob)
    m = preconditioner("cpr", a, prob.grid.n)
    etas = []
    for its in (1, 4, 12, 30):
        y, _ = gmres(a, b, m, rtol=1e-14, maxiter=its, restart=100)
        x = prob.admissible(x_old + (y * cols).reshape(-1, 3))
        r_alg = r.ravel() + jac @ (y * cols)
        e, _ = est.estimate(x, x_old, r_alg, gas, dt, t)
        etas.append(e.alg)
    assert etas[-1] <= 1e-6 * etas[0], etas
    assert all(b_ <= a_ * 1.0001 for a_, b_ in zip(etas, etas[1:], strict=False)), etas


def test_eta_lin_vanishes_as_newton_converges(state):
    prob, x_old = state
    dt, t = 5000 * YEAR, 6 * 5000 * YEAR
    est = Estimator(prob)
    x = x_old.copy()
    lins = []
    for _ in range(8):
        gas, r, jac, a, b, cols = _linear_system(prob, x, x_old, dt, t)
        y = sp.linalg.spsolve(a.tocsc(), b)
        d = (y * cols).reshape(-1, 3)
        alpha = min(1.0, 0.1 / max(np.abs(d[:, 0]).max(), 1e-300))
        x = prob.admissible(x + alpha * d)
        r_alg = alpha * (r.ravel() + jac @ (y * cols))
        e, _ = est.estimate(x, x_old, r_alg, gas, dt, t)
        lins.append(e.lin)
        assert e.alg <= 1e-8 * max(e.disc, e.lin, 1e-300) + 1e-30
    assert lins[-1] <= 1e-8 * max(lins)
    assert lins[-1] <= 1e-6 * e.disc


def test_adaptive_strategy_stops_by_the_estimators(state):
    prob, _ = state
    run = simulate(prob, t_end=5 * 5000 * YEAR, strategy="adaptive", gamma_lin=1e-3)
    disc, lin, alg = np.array(run.eta).T
    assert np.all(lin <= 1e-3 * disc)
    assert np.all(alg <= 1e-3 * np.maximum(disc, lin) + 1e-300)
    assert np.abs(run.balance).max() <= 1e-6 * max(run.injected)
    # the equilibrated flux balances to round-off although Newton-min stopped early
    assert np.abs(run.balance_equilibrated).max() <= 1e-13 * max(run.injected)
