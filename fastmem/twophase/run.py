"""Time stepping and the Couplex-Gas / MoMaS hydrogen benchmark.

:func:`benchmark` builds the column of docs/twophase.md (200 m,
1000 cells, hydrogen injected into the first cell, Dirichlet data at the
right end) with either viscosity set; :func:`simulate` runs backward Euler
with Newton-min per step (:func:`fastmem.twophase.newton.newton_min`) and
records, per accepted step, the iterations, the estimators, the key values of
the profiles and the hydrogen mass balance.

A step is retried with half the length, and the run says so on its logger,
when Newton-min fails or when more than ``max_front_cells`` cells change
phase in it; the steps grow back by doubling after two steps without a
retry.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import ConvergenceError, ParameterError
from ..mesh.mesh import Mesh
from .estimators import Estimator
from .linear import LINEAR_SOLVERS
from .model import YEAR, Grid, Physics, Problem, mesh_grid
from .newton import STRATEGIES, newton_min

__all__ = ["INJECTION_PER_YEAR", "VISCOSITIES", "Run", "benchmark", "section", "simulate"]

logger = logging.getLogger(__name__)

#: The two viscosity sets of docs/twophase.md, ``(mu_l, mu_g)`` in Pa s: as printed in
#: the reference paper, and as specified by MoMaS (and used by the other codes).
VISCOSITIES = {"paper": (1e-9, 9e-9), "momas": (1e-3, 9e-6)}

#: The benchmark's hydrogen injection, kg m^-2 per year.
INJECTION_PER_YEAR = 5.57e-6


_STATE = (1.0, 1e6, 0.0)


def _hydrogen_problem(
    grid,
    viscosity,
    hydrogen,
    stop_injection,
    monitor=None,
    complementarity="min",
    physics=None,
    boundary=_STATE,
    initial=_STATE,
) -> Problem:
    """Build the benchmark's rock, fluids and states on ``grid`` with the given injection.

    ``physics``, when given, replaces the benchmark's (and ``viscosity``).
    """
    if physics is None:
        mu_l, mu_g = VISCOSITIES[viscosity]
        physics = Physics(mu_l=mu_l, mu_g=mu_g)
    return Problem(
        grid,
        physics,
        boundary=boundary,
        initial=initial,
        hydrogen=hydrogen,
        stop_injection=None if stop_injection is None else stop_injection * YEAR,
        monitor=monitor,
        complementarity=complementarity,
    )


def benchmark(
    viscosity: str = "momas",
    n_cells: int = 1000,
    *,
    stop_injection=None,
    complementarity="min",
    length: float = 200.0,
    injection: float | None = None,
    physics: Physics | None = None,
    boundary=_STATE,
    initial=_STATE,
) -> Problem:
    """Build the hydrogen-injection column of docs/twophase.md.

    Parameters
    ----------
    viscosity : {"momas", "paper"}
    n_cells : int
    stop_injection : float, optional
        Years after which the injection stops (the MoMaS variant: 5e5).
    complementarity : {"min", "fb"}
        Newton-min or Newton on Fischer-Burmeister (:class:`Problem`).
    length, injection, physics, boundary, initial : optional
        Another column (m), rate (kg m^-2 per year), rock and fluids
        (replacing ``viscosity``), Dirichlet and initial ``(S, P, chi)``:
        scene files (:mod:`fastmem.twophase.scene`) change them.
    """
    if viscosity not in VISCOSITIES:
        raise ParameterError(
            f"viscosity must be one of {', '.join(VISCOSITIES)}, got {viscosity!r}"
        )
    grid = Grid.column(length, n_cells)
    rate = INJECTION_PER_YEAR if injection is None else float(injection)
    if not (math.isfinite(rate) and rate >= 0):
        raise ParameterError(
            f"injection must be a rate >= 0 in kg m^-2 per year, got {injection!r}"
        )
    hydrogen = np.zeros(grid.n)
    hydrogen[0] = rate / YEAR
    prob = _hydrogen_problem(
        grid, viscosity, hydrogen, stop_injection, None, complementarity, physics, boundary, initial
    )
    prob.scene = {
        "name": "benchmark",
        "viscosity": viscosity,
        "cells": n_cells,
        "length": length,
        "injection_per_year": rate,
        "stop_injection_years": stop_injection,
    }
    return prob


def section(
    nx: int = 1000,
    ny: int = 100,
    viscosity: str = "momas",
    *,
    length: float = 200.0,
    height: float = 20.0,
    stretch=(9.0, 11.0),
    injection: float | None = None,
    stop_injection=None,
    complementarity: str = "min",
    physics: Physics | None = None,
    boundary=_STATE,
    initial=_STATE,
) -> Problem:
    """Build the 2D section: ``length x height`` m, hydrogen injected along ``stretch`` of x = 0.

    The benchmark's rock and fluids, vertex-centred on the structured mesh of
    ``nx x ny`` rectangles (``(nx + 1) (ny + 1)`` vertices, the right edge
    Dirichlet: ``nx (ny + 1)`` cells), no flow on the other edges.
    ``injection`` is the rate on the stretch, kg m^-2 per year; by default the
    column's hydrogen per metre of height, all of it through the stretch
    (``5.57e-6 * height / (y1 - y0)``: with the benchmark's rate spread over
    the whole edge the dissolved hydrogen spreads in 2D and gas would not
    appear for about a million years).  It is shared among the left-edge
    vertices by the length of their dual boundary within the stretch (per
    metre of depth).  The monitor cell is the left-edge vertex nearest the
    stretch's middle.  ``physics``, ``boundary``, ``initial``: as for
    :func:`benchmark`.
    """
    if viscosity not in VISCOSITIES:
        raise ParameterError(
            f"viscosity must be one of {', '.join(VISCOSITIES)}, got {viscosity!r}"
        )
    y0, y1 = (float(v) for v in stretch)
    if not 0 <= y0 < y1 <= height:
        raise ParameterError(f"stretch must satisfy 0 <= y0 < y1 <= height, got {stretch!r}")
    mesh = Mesh.rectangle(nx, ny, (0.0, length, 0.0, height))
    x, y = mesh.vertices[:, 0], mesh.vertices[:, 1]
    grid, free, boundary_vertex = mesh_grid(mesh, np.isclose(x, length))
    dy = height / ny
    lo = np.clip(y - dy / 2, 0.0, height)
    hi = np.clip(y + dy / 2, 0.0, height)
    share = np.clip(np.minimum(hi, y1) - np.maximum(lo, y0), 0.0, None) * np.isclose(x, 0.0)
    rate = INJECTION_PER_YEAR * height / (y1 - y0) if injection is None else float(injection)
    if not (math.isfinite(rate) and rate >= 0):
        raise ParameterError(
            f"injection must be a rate >= 0 in kg m^-2 per year, got {injection!r}"
        )
    hydrogen = share[free] * rate / YEAR
    left = np.flatnonzero(np.isclose(grid.centres[:, 0], 0.0))
    monitor = int(left[np.argmin(np.abs(grid.centres[left, 1] - 0.5 * (y0 + y1)))])
    prob = _hydrogen_problem(
        grid,
        viscosity,
        hydrogen,
        stop_injection,
        monitor,
        complementarity,
        physics,
        boundary,
        initial,
    )
    prob.scene = {
        "name": "section",
        "viscosity": viscosity,
        "nx": nx,
        "ny": ny,
        "length": length,
        "height": height,
        "stretch": [y0, y1],
        "injection_per_year": rate,
        "stop_injection_years": stop_injection,
    }
    prob.mesh, prob.cell_vertex, prob.boundary_vertex = mesh, free, boundary_vertex
    return prob


@dataclass
class Run:
    """The record of a simulation: one entry per accepted time step (SI units)."""

    problem: Problem
    strategy: str = "exact"
    linear_solver: str = "ilu"
    times: list = field(default_factory=list)
    dts: list = field(default_factory=list)
    newton: list = field(default_factory=list)
    linear: list = field(default_factory=list)
    converged: list = field(default_factory=list)
    gas_cells: list = field(default_factory=list)
    front: list = field(default_factory=list)  # largest x of a gas cell (nan: none)
    s_gas0: list = field(default_factory=list)  # at the problem's monitor cell
    p0: list = field(default_factory=list)
    chi0: list = field(default_factory=list)
    eta: list = field(default_factory=list)  # (disc, lin, alg) per step
    in_place: list = field(default_factory=list)
    injected: list = field(default_factory=list)
    outflow: list = field(default_factory=list)
    #: cumulated hydrogen outflow of the equilibrated flux (kg; with the estimators)
    outflow_equilibrated: list = field(default_factory=list)
    kept_times: list = field(default_factory=list)
    states: list = field(default_factory=list)
    retries: list = field(default_factory=list)  # (time, dt, reason)
    residuals: list = field(default_factory=list)  # Newton-min residual history per step
    initial_in_place: float = 0.0  # hydrogen in the domain at t = 0 (kg)
    final: np.ndarray | None = None
    seconds: float = 0.0

    @property
    def balance(self) -> np.ndarray:
        """``in place - initially in place + outflow - injected`` per step (kg).

        With the two-point fluxes of the state: round-off when every step's
        Newton-min converged; a strategy that stops early leaves its residual
        here (docs/twophase.md §6).
        """
        return (
            np.array(self.in_place)
            - self.initial_in_place
            + np.array(self.outflow)
            - np.array(self.injected)
        )

    @property
    def balance_equilibrated(self) -> np.ndarray:
        """The same with the equilibrated flux's outflow: round-off by construction.

        The equilibrated flux (:meth:`Estimator.equilibrated`) balances every
        cell's storage change exactly whatever the state, the residual moved
        into the flux (and into the estimators): this says the flux handed out
        is conservative, it does not check the solver (:attr:`balance` does).
        Empty without estimators.
        """
        if not self.outflow_equilibrated:
            return np.zeros(0)
        return (
            np.array(self.in_place) + np.array(self.outflow_equilibrated) - np.array(self.injected)
        )

    @property
    def first_gas_step(self) -> int | None:
        """The first accepted step (1-based) that ends with gas in some cell."""
        for k, g in enumerate(self.gas_cells):
            if g > 0:
                return k + 1
        return None

    def totals(self) -> dict:
        """Cumulated Newton-min steps and linear iterations."""
        return {"newton": int(np.sum(self.newton)), "linear": int(np.sum(self.linear))}

    def at(self, years: float) -> int:
        """Index of the accepted step ending nearest to ``years``."""
        return int(np.argmin(np.abs(np.array(self.times) / YEAR - years)))


def simulate(
    problem: Problem,
    dt: float = 5000 * YEAR,
    t_end: float = 5e5 * YEAR,
    *,
    strategy: str = "exact",
    linear_solver: str = "ilu",
    gamma_alg: float = 1e-3,
    gamma_lin: float = 1e-3,
    nu: int = 1,
    keep=(),
    max_newton: int = 40,
    max_front_cells: int | None = None,
    min_dt: float | None = None,
    estimate: bool = True,
    extrapolate: bool = True,
    weights: str = "volume",
    check_drop: float = 1.0,
    progress=None,
) -> Run:
    """Run backward Euler from the problem's initial state to ``t_end``.

    Parameters
    ----------
    problem : Problem
    dt, t_end : float
        Time step and final time, seconds (``dt`` is the largest step).
    strategy : {"exact", "inexact", "adaptive"}
    linear_solver : {"ilu", "cpr", "direct"}
    gamma_alg, gamma_lin, nu : float, float, int
        Adaptive stopping parameters (docs/twophase.md §5).
    keep : sequence of float, int or "all"
        Which profiles are kept: the step ending nearest to each given time
        (s, in (0, t_end]), every step (``"all"``), or every k-th step and the
        last (an int k).  A step never crosses the time the injection stops.
    max_front_cells : int, optional
        Retry a step with half its length when more cells change phase in it.
    min_dt : float, optional
        Smallest step (default ``dt / 1024``); below it ConvergenceError.
    estimate : bool
        Evaluate the estimators at the end of every step (``adaptive`` always does).
    extrapolate : bool
        Start Newton-min from the linear extrapolation of the last two states
        (projected on the admissible box) instead of the last state.
    weights : {"volume", "mass"}
        How the estimators weigh the components (:data:`~fastmem.twophase.estimators.WEIGHTS`).
    check_drop : float
        Adaptive strategy: evaluate the estimators inside GMRES only once its
        residual has fallen below ``check_drop`` times its value at the last
        evaluation (1: every ``nu`` iterations, the paper's rule; 0.5: after
        each halving).
    progress : callable, optional
        Called with a dict after every accepted step.
    """
    for name, value in (("dt", dt), ("t_end", t_end)):
        if isinstance(value, bool) or not (
            isinstance(value, (int, float)) and math.isfinite(value) and value > 0
        ):
            raise ParameterError(f"{name} must be a positive time in seconds, got {value!r}")
    if not (isinstance(check_drop, (int, float)) and 0 < check_drop <= 1):
        raise ParameterError(f"check_drop must be in (0, 1], got {check_drop!r}")
    if isinstance(nu, bool) or not (isinstance(nu, int) and nu >= 1):
        raise ParameterError(f"nu must be an integer >= 1, got {nu!r}")
    for name, value in (("gamma_alg", gamma_alg), ("gamma_lin", gamma_lin)):
        if not (isinstance(value, (int, float)) and 0 < value < 1):
            raise ParameterError(f"{name} must be in (0, 1), got {value!r}")
    if strategy not in STRATEGIES:
        raise ParameterError(f"strategy must be one of {', '.join(STRATEGIES)}, got {strategy!r}")
    if linear_solver not in LINEAR_SOLVERS:
        raise ParameterError(
            f"linear_solver must be one of {', '.join(LINEAR_SOLVERS)}, got {linear_solver!r}"
        )
    if max_front_cells is not None and not (
        isinstance(max_front_cells, (int, np.integer)) and max_front_cells >= 1
    ):
        raise ParameterError(f"max_front_cells must be an integer >= 1, got {max_front_cells!r}")
    min_dt = dt / 1024 if min_dt is None else min_dt
    if not (isinstance(min_dt, (int, float)) and 0 < min_dt <= dt):
        raise ParameterError(f"min_dt must be in (0, dt], got {min_dt!r}")
    estimator = Estimator(problem, weights) if (estimate or strategy == "adaptive") else None
    x = problem.initial.copy()
    run = Run(problem, strategy=strategy, linear_solver=linear_solver)
    t = 0.0
    injected = 0.0
    outflow = 0.0
    outflow_eq = 0.0
    every = None
    if isinstance(keep, str):
        if keep != "all":
            raise ParameterError(f"keep must be 'all', an int or a sequence of times, got {keep!r}")
        every, keep = 1, []
    elif isinstance(keep, (int, np.integer)) and not isinstance(keep, bool):
        if keep < 1:
            raise ParameterError(f"keep must be >= 1 when an int (every k-th step), got {keep!r}")
        every, keep = int(keep), []
    else:
        keep = sorted(float(v) for v in keep)
        bad = [k for k in keep if not 0 < k <= t_end * (1 + 1e-12)]
        if bad:
            raise ParameterError(
                f"keep times must lie in (0, t_end] = (0, {t_end:.6g}] s, got {bad[0]!r}"
            )
    pending = list(keep)  # requested times not yet served
    flux_old = None
    if estimator is not None:
        fi, fb = problem.fluxes(x)
        flux_old = (fi / estimator.scale, fb / estimator.scale)
    t0 = time.perf_counter()
    step = dt
    x_prev = None  # the state one step back, for the extrapolated first guess
    calm = 2  # accepted steps since the last retry: the step grows back after two
    stop = problem.stop_injection
    run.initial_in_place = problem.hydrogen_in_place(x)
    while t < t_end * (1 - 1e-12):
        step = min(step, t_end - t)
        if stop is not None and t < stop * (1 - 1e-12) and t + step > stop * (1 + 1e-12):
            step = stop - t  # a step ends where the injection stops: none is lost or added
        retried = False
        while True:
            guess = None
            if extrapolate and x_prev is not None:
                guess = problem.admissible(x + (step / run.dts[-1]) * (x - x_prev))
            new, stats = newton_min(
                problem,
                x,
                step,
                t + step,
                strategy=strategy,
                linear_solver=linear_solver,
                estimator=estimator,
                flux_old=flux_old,
                gamma_alg=gamma_alg,
                gamma_lin=gamma_lin,
                nu=nu,
                max_newton=max_newton,
                x0=guess,
                check_drop=check_drop,
            )
            reason = None
            if not stats.converged:
                reason = f"Newton-min did not converge in {max_newton} steps"
            elif max_front_cells is not None:
                changed = int(np.count_nonzero(problem.gas(new) != problem.gas(x)))
                if changed > max_front_cells:
                    reason = f"{changed} cells changed phase (max_front_cells={max_front_cells})"
            if reason is None:
                break
            run.retries.append((t, step, reason))
            retried = True
            logger.warning(
                "t = %.6g years, dt = %.4g years: %s; retrying with dt = %.4g years",
                t / YEAR,
                step / YEAR,
                reason,
                step / 2 / YEAR,
            )
            step *= 0.5
            if step < min_dt:
                raise ConvergenceError(
                    f"the time step fell below min_dt = {min_dt / YEAR:.4g} years at t = "
                    f"{t / YEAR:.6g} years: {reason}. Lower min_dt or dt, or use "
                    "linear_solver='direct'"
                )
        qw, qh = problem.sources(t + step)
        fw_out, fh_out = problem.outflow(new)
        outflow += fh_out * step
        if estimator is not None:
            _, sigma_b = estimator.equilibrated(new, x, problem.gas(new), step, t + step)
            outflow_eq += float(np.sum(sigma_b[:, 1])) * step
        injected += float(np.sum(qh)) * step
        x_prev, x = x, new
        t += step
        gas = problem.gas(x)
        run.times.append(t)
        run.dts.append(step)
        run.newton.append(stats.newton)
        run.linear.append(stats.linear)
        run.converged.append(stats.converged)
        run.residuals.append(stats.residuals)
        run.gas_cells.append(int(gas.sum()))
        run.front.append(float(problem.grid.centres[gas, 0].max()) if gas.any() else math.nan)
        m = problem.monitor
        run.s_gas0.append(float(1.0 - x[m, 0]))
        run.p0.append(float(x[m, 1]))
        run.chi0.append(float(x[m, 2]))
        run.in_place.append(problem.hydrogen_in_place(x))
        run.injected.append(injected)
        run.outflow.append(outflow)
        if estimator is not None:
            run.outflow_equilibrated.append(outflow_eq)
        if stats.estimate is not None:
            e = stats.estimate
            run.eta.append((e.disc, e.lin, e.alg))
            flux_old = stats.fluxes  # the scaled fluxes the estimate computed at x
        last = t >= t_end * (1 - 1e-12)
        wanted = every is not None and (len(run.times) % every == 0 or last)
        while pending and pending[0] <= t * (1 + 1e-12):
            k = pending.pop(0)  # the nearer of the two step ends around k
            t_before = run.times[-2] if len(run.times) > 1 else None
            if t_before is not None and abs(t_before - k) < abs(t - k):
                if not run.kept_times or run.kept_times[-1] != t_before:
                    run.states.append(x_prev.copy())
                    run.kept_times.append(t_before)
            else:
                wanted = True
        if wanted:
            run.states.append(x.copy())
            run.kept_times.append(t)
        if progress is not None:
            row = {
                "step": len(run.times),
                "t_years": t / YEAR,
                "dt_years": step / YEAR,
                "newton": stats.newton,
                "linear": stats.linear,
                "gas_cells": int(gas.sum()),
                "front": run.front[-1],
            }
            if stats.estimate is not None:
                row.update(eta_disc=e.disc, eta_lin=e.lin, eta_alg=e.alg)
            progress(row)
        calm = 0 if retried else calm + 1
        if calm >= 2:  # not straight back to the length that just failed
            step = min(dt, 2 * step)
    run.final = x
    run.seconds = time.perf_counter() - t0
    return run
