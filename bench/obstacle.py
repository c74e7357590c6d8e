"""The obstacle family against exact solutions, adaptivity and speed (issue 35).

Sections (``--only`` picks some; the others are kept from the earlier JSON):

* ``ball``: the ball problem of PETSc ex9/ex34 (docs/obstacle.md §8.1) on
  uniform ``n x n`` meshes of (-2, 2)², solved by ``fm.solve(problem,
  method="exact-amg")`` (the discrete solution to round-off, its guaranteed
  bound): the energy error against the exact solution (edge integrals split at
  the free boundary, ``ball_energy_error``), the bound, the effectivity, the
  observed rate in h, the discrete contact area against pi a², the max-norm
  nodal error (PETSc ex9 publishes 9.34e-5 on its 257 x 257 grid, n = 256).
* ``ball_adaptive``: ``fm.solve(ball(--adapt-start), tol=...)`` to the bound of
  uniform n = ``--adapt-uniform``; per mesh the bound, the exact error (the
  per-mesh solve is wrapped to keep its iterate) and the effectivity; the rate
  in N (eta ~ N^-p) over the meshes with N >= 2000.
* ``twosided``: the manufactured two-sided case (§8.3), both signs of s0.
* ``step41``: deal.II's step-41 (§8.2): the active set at 128 x 128 cells
  (fastmem's majorant convention and the pointwise one deal.II uses), the
  Newton steps on the finest level; uniform n against a reference three
  refinements finer (effectivity); the adaptive loop against uniform
  refinement at the bound of uniform n = ``--step41-uniform`` (vertices, time).
* ``speed``: the ball at n = ``--speed-n`` (default 1024): the first
  ``fm.solve(problem)`` after ``fm.warm_up()`` and the median of ``--repeat``
  more, in Poisson units measured in the same process (the zero-free unit of
  bench/_common.py on the same mesh).

Times are wall seconds on this machine; nothing here is asserted.
"""

from __future__ import annotations

import time

import numpy as np

import fastmem as fm
from bench._common import finish, keep_sections, parse, poisson_unit, progress, sectioned_parser
from fastmem.problems.ball import CONTACT_AREA, ball_solution
from fastmem.problems.obstacles import ball, exact_error, step41, twosided
from fastmem.problems.step41 import StairObstacle
from fastmem.solver.nested import interpolation_matrix

SECTIONS = ("ball", "ball_adaptive", "twosided", "step41", "speed")
PETSC_EX9_MAX_ERROR_256 = 9.34e-5


def _rates(ns, errors):
    ns, errors = np.asarray(ns, float), np.asarray(errors, float)
    return (np.log(errors[:-1] / errors[1:]) / np.log(ns[1:] / ns[:-1])).tolist()


def run_ball(sizes):
    rows = []
    for n in sizes:
        problem = ball(n)
        t0 = time.perf_counter()
        res = fm.solve(problem, method="exact-amg")
        seconds = time.perf_counter() - t0
        err = exact_error(problem, res.u)
        nodal = float(np.abs(res.u - ball_solution(*problem.mesh.vertices.T)).max())
        totals = res.estimate.totals
        rows.append(
            {
                "n": n,
                "vertices": problem.mesh.n_vertices,
                "error": err,
                "eta": res.eta,
                "effectivity": res.eta / err,
                "eta_disc": totals["eta_disc"],
                "c_over_error2": totals["c"] / err**2,
                "flux_over_error": totals["flux"] / err,
                "contact_area": res.contact_area,
                "contact_area_error": res.contact_area - CONTACT_AREA,
                "max_nodal_error": nodal,
                "newton_finest": res.n_newton,
                "guaranteed": bool(totals["guaranteed"]),
                "seconds": seconds,
            }
        )
        progress(
            f"ball n={n}: error {err:.4e} eta {res.eta:.4e} eff {res.eta / err:.3f} "
            f"area {res.contact_area:.5f} max nodal {nodal:.3e} ({seconds:.1f} s)"
        )
    rates = _rates([r["n"] for r in rows], [r["error"] for r in rows])
    for r, p in zip(rows[1:], rates, strict=True):
        r["rate_h"] = p
    at256 = [r["max_nodal_error"] for r in rows if r["n"] == 256]
    eff = [r["effectivity"] for r in rows]
    return {
        "rows": rows,
        "max_nodal_error_256": at256[0] if at256 else None,
        "petsc_ex9_max_error_256": PETSC_EX9_MAX_ERROR_256,
        "effectivity_range": [min(eff), max(eff)],
        "min_rate_h": min(rates) if rates else None,
    }


class _Levels:
    """Wrap the per-mesh solves of the obstacle loop to keep each mesh's iterate."""

    def __init__(self):
        import fastmem.adapt.obstacle as loop

        self.loop = loop
        self.kept = []
        self._first = loop.solve_obstacle_levels
        self._next = loop.newton_min_obstacle

    def __enter__(self):
        kept = self.kept

        def first(problem, options, initial=None):
            levels = self._first(problem, options, initial)
            kept.append((problem, levels[-1].u, levels[-1].estimate.eta))
            return levels

        def nxt(problem, options, u, lam, **kw):
            out = self._next(problem, options, u, lam, **kw)
            kept.append((problem, out.u, out.estimate.eta))
            return out

        self.loop.solve_obstacle_levels = first
        self.loop.newton_min_obstacle = nxt
        return self

    def __exit__(self, *exc):
        self.loop.solve_obstacle_levels = self._first
        self.loop.newton_min_obstacle = self._next


def run_ball_adaptive(start, uniform_n):
    uniform = fm.solve(ball(uniform_n))
    tol = uniform.eta * (1 + 1e-6)
    t0 = time.perf_counter()
    res = fm.solve(ball(start), tol=tol)
    seconds = time.perf_counter() - t0
    with _Levels() as levels:
        fm.solve(ball(start), tol=tol)
    rows = []
    for problem, u, eta in levels.kept:
        err = exact_error(problem, u)
        rows.append(
            {
                "vertices": problem.mesh.n_vertices,
                "eta": eta,
                "error": err,
                "effectivity": eta / err,
            }
        )
    n = np.array([r["vertices"] for r in rows], float)
    eta = np.array([r["eta"] for r in rows])
    err = np.array([r["error"] for r in rows])
    fit = n >= 2000
    rate_eta = -np.polyfit(np.log(n[fit]), np.log(eta[fit]), 1)[0] if fit.sum() >= 2 else None
    rate_err = -np.polyfit(np.log(n[fit]), np.log(err[fit]), 1)[0] if fit.sum() >= 2 else None
    progress(
        f"ball adaptive to tol {tol:.3e} (uniform n={uniform_n}, {uniform.mesh.n_vertices} "
        f"vertices): {res.mesh.n_vertices} vertices, {len(rows)} meshes, {seconds:.1f} s; rate "
        f"eta {rate_eta}, error {rate_err}; effectivity {min(r['effectivity'] for r in rows):.3f}"
        f"-{max(r['effectivity'] for r in rows):.3f}"
    )
    return {
        "rows": rows,
        "tol": tol,
        "uniform_n": uniform_n,
        "uniform_vertices": uniform.mesh.n_vertices,
        "adaptive_vertices": res.mesh.n_vertices,
        "seconds": seconds,
        "rate_eta_N": rate_eta,
        "rate_error_N": rate_err,
        "effectivity_max": max(r["effectivity"] for r in rows),
        "effectivity_min": min(r["effectivity"] for r in rows),
    }


def run_twosided(sizes):
    out = {}
    for s0 in (1.0, -1.0):
        rows = []
        for n in sizes:
            problem = twosided(n, s0=s0)
            res = fm.solve(problem, method="exact-amg")
            err = exact_error(problem, res.u)
            rows.append(
                {
                    "n": n,
                    "error": err,
                    "eta": res.eta,
                    "effectivity": res.eta / err,
                    "lower_contact": int(res.active_lower.sum()),
                    "upper_contact": int(res.active_upper.sum()),
                }
            )
        rates = _rates([r["n"] for r in rows], [r["error"] for r in rows])
        for r, p in zip(rows[1:], rates, strict=True):
            r["rate_h"] = p
        out[f"s0={s0:+g}"] = rows
        progress(
            f"twosided s0={s0:+g}: effectivity "
            f"{[round(r['effectivity'], 3) for r in rows]}, rates {np.round(rates, 3)}"
        )
    return out


def _energy(problem, v):
    return float(np.sqrt(v @ (problem.weighted @ v)))


def run_step41(sizes, uniform_n, start):
    fine128 = fm.solve(step41(128), method="exact-amg")
    stairs = StairObstacle()
    pointwise = fm.Obstacle(fm.Mesh.square(128), mu=1.0, f=-10.0, lower=lambda x, y: stairs(x, y))
    pw = fm.solve(pointwise, method="exact-amg", estimate=False)
    per_level = fine128.history["k"][fine128.history["level"] == fine128.history["level"].max()]
    out = {
        "n128_vertices": fine128.mesh.n_vertices,
        "n128_active_majorant": int(fine128.active.sum()),
        "n128_active_pointwise": int(pw.active.sum()),
        "dealii_active": 5399,
        "n128_newton_finest": int(per_level.max()),
        "n128_eta": fine128.eta,
    }
    progress(
        f"step41 n=128: active {out['n128_active_majorant']} (majorant), "
        f"{out['n128_active_pointwise']} (pointwise; deal.II 5399), Newton steps on the "
        f"finest level {out['n128_newton_finest']}"
    )
    rows = []
    for n in sizes:
        coarse, fine = step41(n), step41(8 * n)
        res = fm.solve(coarse, method="exact-amg")
        ref = fm.solve(fine, method="exact-amg", estimate=False)
        diff = ref.u - interpolation_matrix(coarse.mesh, fine.mesh) @ res.u
        err = _energy(fine, diff)
        rows.append(
            {
                "n": n,
                "eta": res.eta,
                "error_vs_reference": err,
                "effectivity": res.eta / err,
                "c_disc": res.estimate.totals["c_disc"],
            }
        )
        progress(
            f"step41 n={n}: eta {res.eta:.4e}, error vs n={8 * n} {err:.4e}, "
            f"effectivity {res.eta / err:.3f}"
        )
    out["rows"] = rows
    # adaptive against uniform at the same bound
    t0 = time.perf_counter()
    uni = fm.solve(step41(uniform_n))
    t_uni = time.perf_counter() - t0
    tol = uni.eta * (1 + 1e-6)
    t0 = time.perf_counter()
    ada = fm.solve(step41(start), tol=tol)
    t_ada = time.perf_counter() - t0
    out["adaptive"] = {
        "tol": tol,
        "uniform_n": uniform_n,
        "uniform_vertices": uni.mesh.n_vertices,
        "uniform_seconds": t_uni,
        "adaptive_vertices": ada.mesh.n_vertices,
        "adaptive_seconds": t_ada,
        "adaptive_meshes": len(ada.adaptivity["level"]),
        "adaptive_eta": ada.eta,
        "vertex_ratio": uni.mesh.n_vertices / ada.mesh.n_vertices,
        "time_ratio": t_uni / t_ada,
    }
    progress(
        f"step41 adaptive to eta {tol:.4e}: {ada.mesh.n_vertices} vertices in {t_ada:.2f} s "
        f"against uniform n={uniform_n}: {uni.mesh.n_vertices} vertices in {t_uni:.2f} s"
    )
    return out


def run_speed(n, repeat):
    fm.warm_up()
    problem = ball(n)
    _ = problem.mesh.edges, problem.mesh.patch_ptr  # the mesh's topology, as a user builds it
    t0 = time.perf_counter()
    first = fm.solve(problem)
    t_first = time.perf_counter() - t0
    times = []
    for _ in range(repeat):
        p2 = ball(n)
        _ = p2.mesh.edges, p2.mesh.patch_ptr
        t0 = time.perf_counter()
        fm.solve(p2)
        times.append(time.perf_counter() - t0)
    unit = poisson_unit(problem.mesh, repeat=3)
    err = exact_error(problem, first.u)
    out = {
        "n": n,
        "vertices": problem.mesh.n_vertices,
        "first_seconds": t_first,
        "median_seconds": float(np.median(times)) if times else None,
        "poisson_unit_seconds": unit["seconds"],
        "poisson_unit_iterations": unit["iterations"],
        "first_pu": t_first / unit["seconds"],
        "median_pu": float(np.median(times)) / unit["seconds"] if times else None,
        "eta": first.eta,
        "error": err,
        "effectivity": first.eta / err,
        "newton_finest": first.n_newton,
    }
    progress(
        f"speed ball n={n}: first {t_first:.2f} s = {out['first_pu']:.2f} PU, median "
        f"{out['median_seconds']} s; unit {unit['seconds']:.2f} s; eff {out['effectivity']:.3f}"
    )
    return out


def main(argv=None):
    p = sectioned_parser(__doc__, SECTIONS, repeat=2)
    p.add_argument("--adapt-start", type=int, default=32)
    p.add_argument("--adapt-uniform", type=int, default=512)
    p.add_argument("--step41-uniform", type=int, default=256)
    p.add_argument("--speed-n", type=int, default=1024)
    args = parse(p, argv)
    only = {args.only} if args.only else set(SECTIONS)
    quick = args.quick
    sizes = args.sizes or ([16, 32] if quick else [64, 128, 256, 512, 1024])
    payload = {"parameters": vars(args) | {"results": None}}
    if "ball" in only:
        payload["ball"] = run_ball(sizes)
        payload["rows"] = payload["ball"]["rows"]
    if "ball_adaptive" in only:
        payload["ball_adaptive"] = run_ball_adaptive(
            8 if quick else args.adapt_start, 32 if quick else args.adapt_uniform
        )
    if "twosided" in only:
        payload["twosided"] = run_twosided([8, 16] if quick else [16, 32, 64, 128, 256])
    if "step41" in only:
        payload["step41"] = run_step41(
            [8] if quick else [16, 32, 64], 32 if quick else args.step41_uniform, 8 if quick else 16
        )
    if "speed" in only:
        payload["speed"] = run_speed(64 if quick else args.speed_n, 1 if quick else args.repeat)
    payload = keep_sections("obstacle", args.only, quick, payload)
    finish("obstacle", payload, quick)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
