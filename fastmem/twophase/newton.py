"""Newton-min for one backward Euler step, with the three stopping strategies.

* ``exact``: linear solves to a relative residual of 1e-10 (or SuperLU),
  Newton-min until the scaled residual is below ``tol`` (or the update is
  below ``tol`` with the branches unchanged);
* ``inexact``: GMRES stopped by the Eisenstat–Walker forcing term (choice 2,
  safeguarded, at most 0.1), Newton-min as ``exact``;
* ``adaptive``: GMRES stopped every ``nu`` iterations once
  ``eta_alg <= gamma_alg max(eta_disc, eta_lin)``, Newton-min once
  ``eta_lin <= gamma_lin eta_disc`` (docs/twophase.md §5).

Every Newton-min update is damped so that no saturation changes by more than
``ds_max`` (a cell entering the gas phase is linearised at ``S = 1``, where
the capillary pressure's slope is that of the chord of
:data:`fastmem.twophase.laws.CHORD`, and the full step overshoots), then
projected on the admissible box ``S in (S_lr, 1]``, ``chi >= 0``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..errors import ParameterError
from .linear import LINEAR_SOLVERS, direct, gmres, preconditioner

__all__ = ["STRATEGIES", "StepStats", "newton_min"]

#: Stopping strategies of the Newton-min and linear loops.
STRATEGIES = ("exact", "inexact", "adaptive")
#: Order of a cell's rows in the linear systems: min, water, hydrogen.
_ORDER = np.array([2, 0, 1])


@dataclass
class StepStats:
    """What Newton-min did in one time step."""

    newton: int = 0
    linear: int = 0
    converged: bool = False
    residuals: list = field(default_factory=list)  # scaled residual before every step
    flips: list = field(default_factory=list)  # cells changing branch at every step
    linear_per_step: list = field(default_factory=list)
    estimate: object = None  # the Estimate of the returned iterate (or None)
    estimates: list = field(default_factory=list)  # per Newton step (adaptive)
    fluxes: tuple | None = None  # the estimator's scaled fluxes at the returned iterate


def _scaled_norm(problem, r, dt, gas):
    return float(np.max(np.abs(r) / problem.row_scales(dt, gas)))


def newton_min(
    problem,
    x_old,
    dt,
    t,
    *,
    strategy="exact",
    linear_solver="ilu",
    estimator=None,
    flux_old=None,
    gamma_alg=1e-3,
    gamma_lin=1e-3,
    nu=1,
    tol=1e-10,
    max_newton=40,
    max_linear=500,
    restart=60,
    ds_max=0.1,
    x0=None,
    check_drop=1.0,
):
    """Solve one backward Euler step from ``x_old`` (N, 3) to ``t`` with step ``dt``.

    Returns ``(x, StepStats)``; ``stats.converged`` is False when
    ``max_newton`` steps did not meet the strategy's criterion.
    """
    if strategy not in STRATEGIES:
        raise ParameterError(f"strategy must be one of {', '.join(STRATEGIES)}, got {strategy!r}")
    if linear_solver not in LINEAR_SOLVERS:
        raise ParameterError(
            f"linear_solver must be one of {', '.join(LINEAR_SOLVERS)}, got {linear_solver!r}"
        )
    if strategy == "adaptive" and estimator is None:
        raise ParameterError("strategy='adaptive' needs an estimator")
    units = problem.units()
    x = np.array(x_old if x0 is None else x0, dtype=float)
    stats = StepStats()
    gas_prev = None
    norm_prev = None
    stages = None  # CPR's AMG hierarchies, built at the first Newton step
    forcing = 0.1
    for k in range(max_newton):
        gas = problem.gas(x)
        r = problem.residual(x, x_old, dt, t, gas)
        scales = problem.row_scales(dt, gas)
        norm = float(np.max(np.abs(r) / scales))
        stats.residuals.append(norm)
        if gas_prev is not None:
            stats.flips.append(int(np.count_nonzero(gas != gas_prev)))
        if strategy != "adaptive" and k > 0 and norm <= tol:
            stats.converged = True
            break
        jac = problem.jacobian(x, gas, dt)
        rows = 1.0 / scales.ravel()
        cols = np.tile(units, problem.grid.n)
        a = sp.diags(rows) @ jac @ sp.diags(cols)
        # rows in the cell order (min, water, hydrogen): every diagonal entry is then
        # nonzero (the min row's S derivative, the water row's P, the hydrogen row's chi),
        # which the ILU without pivoting needs
        perm = (3 * np.arange(problem.grid.n)[:, None] + _ORDER).ravel()
        a = a.tocsr()[perm]
        b = -(r.ravel() * rows)[perm]
        if strategy == "inexact" and norm_prev is not None:
            # Eisenstat-Walker choice 2 with its safeguard
            new = 0.9 * (norm / norm_prev) ** 2
            guard = 0.9 * forcing**2
            if guard > 0.1:
                new = max(new, guard)
            forcing = min(0.1, max(new, 1e-10))
        norm_prev = norm

        def take(y, x=x, cols=cols):
            d = (y * cols).reshape(-1, 3)
            big = float(np.max(np.abs(d[:, 0])))
            alpha = min(1.0, ds_max / big) if big > 0 else 1.0
            return problem.admissible(x + alpha * d), alpha

        def algebraic(y, alpha, jac=jac, r=r, cols=cols):  # unscaled, unpermuted
            return alpha * (r.ravel() + jac @ (y * cols))

        if linear_solver == "direct":
            y = direct(a, b)
            its = 1
        else:
            apply_m = preconditioner(
                linear_solver, a, problem.grid.n, scales.ravel()[perm], stages=stages
            )
            stages = getattr(apply_m, "stages", None)
            check = None
            rtol = 1e-10 if strategy != "inexact" else forcing
            if strategy == "adaptive":

                def check(y, its, x=x, gas=gas):
                    trial, alpha = take(y)
                    est, _ = estimator.estimate(
                        trial, x_old, algebraic(y, alpha), gas, dt, t, flux_old
                    )
                    return est.alg <= gamma_alg * max(est.disc, est.lin)

            y, lin = gmres(
                a,
                b,
                apply_m,
                rtol=rtol,
                maxiter=max_linear,
                restart=restart,
                every=nu,
                check=check,
                drop=check_drop,
            )
            its = lin.iterations
        stats.linear += its
        stats.linear_per_step.append(its)
        x_new, alpha = take(y)
        step = float(np.max(np.abs(x_new - x) / units))
        stats.newton = k + 1
        if estimator is not None and strategy == "adaptive":
            est, fluxes = estimator.estimate(
                x_new, x_old, algebraic(y, alpha), gas, dt, t, flux_old
            )
            stats.fluxes = fluxes
            stats.estimates.append(est)
            stats.estimate = est
            x = x_new
            if est.lin <= gamma_lin * est.disc:
                stats.converged = True
                break
            gas_prev = gas
            continue
        x = x_new
        # a vanishing update with the branches settled is convergence, unless the
        # projection on the admissible box swallowed it: then the residual decides
        settled = gas_prev is not None and np.array_equal(gas, gas_prev)
        if step <= tol and settled and norm <= np.sqrt(tol):
            stats.converged = True
            g_now = problem.gas(x)
            stats.residuals.append(
                _scaled_norm(problem, problem.residual(x, x_old, dt, t, g_now), dt, g_now)
            )
            break
        gas_prev = gas
    if estimator is not None and strategy != "adaptive":
        gas = problem.gas(x)
        r_alg = np.zeros((problem.grid.n, 3))  # the remainder is all linearisation here
        stats.estimate, stats.fluxes = estimator.estimate(x, x_old, r_alg, gas, dt, t, flux_old)
    return x, stats
