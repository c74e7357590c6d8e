"""The liquid–gas hydrogen benchmark (issue 34; docs/twophase.md §benchmark).

Sections (``--only`` picks some; the others are kept from the earlier JSON):

* ``viscosities``: the 1D column (200 m, ``--cells`` cells, 100 steps of 5000
  years) with both viscosity sets, exact strategy: the step where gas first
  appears, and at 1.05e5 and 3.5e5 years the gas saturation, pressure and
  dissolved fraction at x = 0 and the front (the farthest gas cell), beside
  the values docs/twophase.md reads off the paper's figures.
* ``strategies``: MoMaS viscosities, ``exact`` / ``inexact`` / ``adaptive``
  with GMRES-ILU and GMRES-CPR (and ``exact`` with SuperLU): cumulated
  Newton-min steps and linear iterations, wall time of the whole run, the
  largest hydrogen mass-balance defect, the largest profile difference to the
  exact strategy (scaled unknowns) against eta_disc.
* ``section``: the 2D section (200 m x 20 m, hydrogen through 2 m of the left
  edge, vertex-centred on ``nx x ny`` rectangles), ``--section-steps`` steps of
  5000 years with GMRES-CPR, exact strategy: seconds per step (the first
  step left out: it compiles the block-ILU kernel), Newton-min steps and
  linear iterations per Newton step, cells holding gas; the exponent of the
  time per step in the number of cells.  At the last state of the largest
  mesh, one Newton-min system solved by GMRES-ILU and by GMRES-CPR to 1e-8
  (iterations, seconds; ILU capped at 1000 iterations).  On the middle mesh,
  the adaptive strategy against the exact one (both GMRES-CPR): Newton-min
  steps, linear iterations, seconds (the exact run's include its first,
  compiling step), the largest profile difference.
* ``variant``: injection stopped at 5e5 years (after ``--steps`` steps), run to
  twice that (adaptive,
  ILU): when the gas phase vanishes, the Newton-min steps around it, the
  largest balance defect.

Times are wall seconds of one run on this machine (no JIT is involved:
the model is NumPy/SciPy), each run started after one untimed 3-step run;
nothing here is asserted.
"""

from __future__ import annotations

import math
import time

import numpy as np
import scipy.sparse as sp

from bench._common import finish, keep_sections, parse, progress, sectioned_parser
from fastmem.twophase import YEAR, benchmark, section, simulate
from fastmem.twophase.linear import gmres, preconditioner
from fastmem.twophase.newton import _ORDER

SECTIONS = ("viscosities", "strategies", "variant", "section")
STEP = 5000 * YEAR
#: Values docs/twophase.md reads off the reference paper's figures (approximate).
PAPER = {
    1.05e5: {"s_gas0": 0.011, "p0": 1.165e6, "chi0": 1.04e-4, "front": (95.0, 100.0)},
    3.5e5: {"s_gas0": 0.017, "front": (160.0, 160.0)},
}


def _profile_row(run, years):
    i = run.at(years)
    return {
        "t_years": run.times[i] / YEAR,
        "s_gas0": run.s_gas0[i],
        "p0": run.p0[i],
        "chi0": run.chi0[i],
        "front_m": run.front[i],
        "gas_cells": run.gas_cells[i],
    }


def run_viscosities(cells, steps):
    out = []
    for visc in ("momas", "paper"):
        t0 = time.perf_counter()
        run = simulate(benchmark(visc, cells), t_end=steps * STEP, estimate=False)
        row = {
            "viscosity": visc,
            "cells": cells,
            "steps": steps,
            "first_gas_step": run.first_gas_step,
            "seconds": time.perf_counter() - t0,
            **run.totals(),
        }
        for years in PAPER:
            if run.times[-1] >= years * YEAR * (1 - 1e-9):
                row[f"at_{years:.3g}"] = _profile_row(run, years)
        progress(f"viscosities {visc}: {row}")
        out.append(row)
    return out


def run_strategies(cells, steps):
    # (strategy, linear solver, complementarity, estimator weights, gamma)
    cases = [
        ("exact", "direct", "min", "volume", 1e-3),
        ("exact", "ilu", "min", "volume", 1e-3),
        ("inexact", "ilu", "min", "volume", 1e-3),
        ("adaptive", "ilu", "min", "volume", 1e-3),
        ("exact", "cpr", "min", "volume", 1e-3),
        ("adaptive", "cpr", "min", "volume", 1e-3),
        ("exact", "ilu", "fb", "volume", 1e-3),
        ("adaptive", "ilu", "fb", "volume", 1e-3),
        ("adaptive", "ilu", "min", "mass", 1e-3),
        ("adaptive", "ilu", "min", "volume", 1e-1),
    ]
    simulate(benchmark("momas", cells), t_end=3 * STEP)  # untimed: imports, caches
    rows, finals = [], {}
    for strategy, solver, comp, weights, gamma in cases:
        prob = benchmark("momas", cells, complementarity=comp)
        t0 = time.perf_counter()
        run = simulate(
            prob,
            t_end=steps * STEP,
            strategy=strategy,
            linear_solver=solver,
            weights=weights,
            gamma_alg=gamma,
            gamma_lin=gamma,
        )
        seconds = time.perf_counter() - t0
        key = (strategy, solver, comp, weights, gamma)
        finals[key] = (prob, run)
        eta = np.array(run.eta)
        rows.append(
            {
                "strategy": strategy,
                "linear_solver": solver,
                "complementarity": comp,
                "weights": weights,
                "gamma": gamma,
                "cells": cells,
                "steps": len(run.times),
                "retries": len(run.retries),
                "seconds": seconds,
                **run.totals(),
                "balance_max_kg": float(np.abs(run.balance).max()),
                "balance_equilibrated_max_kg": float(np.abs(run.balance_equilibrated).max()),
                "injected_kg": run.injected[-1],
                "eta_disc_max": float(eta[:, 0].max()),
                "eta_lin_max": float(eta[:, 1].max()),
                "eta_alg_max": float(eta[:, 2].max()),
                "cumulative_newton": np.cumsum(run.newton).tolist(),
                "cumulative_linear": np.cumsum(run.linear).tolist(),
            }
        )
        progress(f"strategies {key}: {run.totals()} in {seconds:.2f} s")
    prob, ref = finals[cases[0]]
    units = prob.units()
    for row, key in zip(rows, cases, strict=True):
        run = finals[key][1]
        row["max_scaled_difference_to_exact"] = float(np.abs((run.final - ref.final) / units).max())
    exact, adaptive = rows[1], rows[3]  # exact and adaptive with GMRES-ILU, Newton-min
    summary = {
        "newton_ratio_exact_over_adaptive": exact["newton"] / adaptive["newton"],
        "linear_ratio_exact_over_adaptive": exact["linear"] / adaptive["linear"],
        "paper": {
            "exact": {"newton": 550, "linear": 6000},
            "adaptive": {"newton": 113, "linear": 427},
        },
    }
    kept = simulate(
        benchmark("momas", cells),
        t_end=steps * STEP,
        keep=[t for t in (1.05e5 * YEAR, 3.5e5 * YEAR) if t < steps * STEP] + [steps * STEP],
    )
    profiles = [
        {
            "t_years": t / YEAR,
            "x": kept.problem.grid.centres[:, 0].tolist(),
            "s_gas": (1 - s[:, 0]).tolist(),
            "p": s[:, 1].tolist(),
            "chi": s[:, 2].tolist(),
        }
        for t, s in zip(kept.kept_times, kept.states, strict=True)
    ]
    return rows, summary, profiles


def run_variant(cells, steps):
    stop = steps * STEP / YEAR  # 5e5 years for the 100 steps of the benchmark
    prob = benchmark("momas", cells, stop_injection=stop)
    t0 = time.perf_counter()
    run = simulate(prob, t_end=2 * steps * STEP, strategy="adaptive")
    seconds = time.perf_counter() - t0
    g = np.array(run.gas_cells)
    gone = [i for i in range(1, len(g)) if g[i] == 0 and g[i - 1] > 0]
    vanish = run.times[gone[0]] / YEAR if gone else math.nan
    around = slice(max(gone[0] - 3, 0), gone[0] + 3) if gone else slice(0, 0)
    row = {
        "cells": cells,
        "stop_injection_years": stop,
        "t_end_years": run.times[-1] / YEAR,
        "vanishes_at_years": vanish,
        "gas_cells_at_stop": int(g[run.at(stop)]),
        "newton_around_vanishing": run.newton[around],
        "times_around_vanishing": [t / YEAR for t in run.times[around]],
        "gas_cells_around_vanishing": g[around].tolist(),
        "retries": len(run.retries),
        "balance_max_kg": float(np.abs(run.balance).max()),
        "seconds": seconds,
        **run.totals(),
        "gas_cells": g.tolist(),
        "times_years": (np.array(run.times) / YEAR).tolist(),
    }
    progress(f"variant: gas vanishes at {vanish} years, {run.totals()}")
    return row


def run_section(sizes, steps):
    rows = []
    finals = {}
    for nx, ny in sizes:
        prob = section(nx, ny)
        per_step = []
        t_last = [time.perf_counter()]

        def tick(row, per_step=per_step, t_last=t_last):
            now = time.perf_counter()
            per_step.append(now - t_last[0])
            t_last[0] = now

        run = simulate(prob, t_end=steps * STEP, linear_solver="cpr", progress=tick)
        rows.append(
            {
                "nx": nx,
                "ny": ny,
                "cells": prob.grid.n,
                "unknowns": 3 * prob.grid.n,
                "steps": len(run.times),
                "seconds_per_step": float(np.mean(per_step[1:])),
                "seconds_first_step": per_step[0],
                **run.totals(),
                "linear_per_newton": run.totals()["linear"] / run.totals()["newton"],
                "gas_cells_end": run.gas_cells[-1],
                "balance_max_kg": float(np.abs(run.balance).max()),
                "injected_kg": run.injected[-1],
            }
        )
        progress(f"section {nx}x{ny}: {rows[-1]}")
        last = (prob, run)
        finals[nx, ny] = (prob, run, float(np.sum(per_step)))
    cells = np.array([r["cells"] for r in rows], float)
    secs = np.array([r["seconds_per_step"] for r in rows])
    exponent = float(np.polyfit(np.log(cells), np.log(secs), 1)[0]) if len(rows) > 1 else None
    prob, run = last
    dt = STEP
    x = run.final
    gas = prob.gas(x)
    r = prob.residual(x, x, dt, run.times[-1] + dt, gas)
    jac = prob.jacobian(x, gas, dt)
    scales = prob.row_scales(dt, gas).ravel()
    perm = (3 * np.arange(prob.grid.n)[:, None] + _ORDER).ravel()
    a = (sp.diags(1 / scales) @ jac @ sp.diags(np.tile(prob.units(), prob.grid.n))).tocsr()
    a = a[perm].tocsr()
    b = -(r.ravel() / scales)[perm]
    solves = {}
    for kind in ("ilu", "cpr"):
        t0 = time.perf_counter()
        m = preconditioner(kind, a, prob.grid.n, scales[perm])
        setup = time.perf_counter() - t0
        _, stats = gmres(a, b, m, rtol=1e-8, maxiter=1000, restart=100)
        solves[kind] = {
            "iterations": stats.iterations,
            "residual": stats.residual,
            "setup_s": setup,
            "seconds": time.perf_counter() - t0,
        }
        progress(f"section solve {kind}: {solves[kind]}")
    # adaptive against exact on the middle mesh (GMRES-CPR both)
    nx, ny = sizes[len(sizes) // 2]
    prob_e, exact, exact_s = finals[nx, ny]
    prob_a = section(nx, ny)
    t0 = time.perf_counter()
    adaptive = simulate(prob_a, t_end=steps * STEP, linear_solver="cpr", strategy="adaptive")
    adaptive_s = time.perf_counter() - t0
    strategies = [
        {"strategy": "exact", **exact.totals(), "seconds": exact_s},
        {
            "strategy": "adaptive",
            **adaptive.totals(),
            "seconds": adaptive_s,
            "max_scaled_difference_to_exact": float(
                np.abs((adaptive.final - exact.final) / prob_e.units()).max()
            ),
            "balance_max_kg": float(np.abs(adaptive.balance).max()),
            "balance_equilibrated_max_kg": float(np.abs(adaptive.balance_equilibrated).max()),
        },
    ]
    progress(f"section strategies {nx}x{ny}: {strategies}")
    return {
        "rows": rows,
        "time_exponent": exponent,
        "one_solve": solves,
        "cells": prob.grid.n,
        "strategies": {"nx": nx, "ny": ny, "cells": prob_a.grid.n, "rows": strategies},
    }


def main(argv=None):
    p = sectioned_parser(__doc__, SECTIONS, repeat=1)
    p.add_argument("--cells", type=int, default=1000)
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--section-steps", type=int, default=6)
    args = parse(p, argv)
    only = {args.only} if args.only else set(SECTIONS)
    quick = args.quick
    cells = 100 if quick else args.cells
    steps = 12 if quick else args.steps
    payload = {"parameters": vars(args) | {"results": None, "cells": cells, "steps": steps}}
    if "viscosities" in only:
        payload["viscosities"] = run_viscosities(cells, steps)
        payload["paper_figures"] = {f"{k:.3g}": v for k, v in PAPER.items()}
    if "strategies" in only:
        rows, summary, profiles = run_strategies(cells, steps)
        payload["rows"] = rows
        payload["summary"] = summary
        payload["profiles"] = profiles
    if "variant" in only:
        payload["variant"] = run_variant(cells, steps)
    if "section" in only:
        sizes = [(50, 5), (100, 10)] if quick else [(250, 25), (500, 50), (1000, 100)]
        payload["section"] = run_section(sizes, 3 if quick else args.section_steps)
    payload = keep_sections("twophase", args.only, quick, payload)
    finish("twophase", payload, quick)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
