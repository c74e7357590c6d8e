"""Work-precision on the manufactured solution: time against error and eta.

The default manufactured solution of docs/method.md §7 on the structured
square meshes n x n, n doubling.  For every mesh and method (``exact``:
sparse direct Newton-min, up to ``--exact-max``; ``exact-amg``: AMG solves to
round-off; ``inexact``: adaptive stopping by the estimators) the wall time of
``fm.solve(scene, method=..., estimate=True)`` on a fresh scene (assembly,
mesh topology and the final bound included; mesh generation and JIT
compilation excluded), the true energy error (quadrature of degree 7), the
guaranteed bound eta with its components, and the effectivity eta / error.

Checks recorded per row: ``bound_holds`` (eta >= error), the error relative
to the exact-amg error of the same mesh, and max |u - u_exact-amg|.  The
headline figure: error (solid) and eta (dashed) against time, one curve per
method.

    python -m bench.work_precision [--quick] [--sizes 32 64 128 256 512 1024]
"""

import time

import numpy as np

from bench._common import finish, parse, parser, peak_rss_mb, progress, summary

FULL_SIZES = [32, 64, 128, 256, 512, 1024]
QUICK_SIZES = [8, 16]
METHODS = ("exact", "exact-amg", "inexact")


def solve_timed(ms, n, method, repeat, budget):
    """Median wall time of the solve on a fresh mesh and scene per repetition."""
    import fastmem as fm

    times = []
    r = mesh = None
    while len(times) < max(1, repeat):
        mesh = fm.Mesh.square(n)
        scene = ms.scene(mesh)
        t0 = time.perf_counter()
        r = fm.solve(scene, method=method, estimate=True)
        times.append(time.perf_counter() - t0)
        if sum(times) > budget:
            break
    return r, mesh, summary(times)


def run(sizes, methods, exact_max, repeat, budget):
    import fastmem as fm

    ms = fm.Manufactured()
    for method in methods:  # compile / load the JIT caches on a tiny mesh
        fm.solve(ms.scene(fm.Mesh.square(8)), method=method, estimate=True)
    rows = []
    for n in sizes:
        results = {}
        first = len(rows)
        for method in methods:
            if method == "exact" and n > exact_max:
                continue
            r, mesh, t = solve_timed(ms, n, method, repeat, budget)
            err = ms.energy_error(mesh, r.u1, r.u2)
            totals = r.estimate.totals
            row = {
                "n": n,
                "vertices": mesh.n_vertices,
                "h": mesh.h,
                "method": method,
                "path": r.path,
                "converged": bool(r.converged),
                "seconds": t,
                "timings": r.timings,
                "newton_finest": r.n_newton,
                "energy_error": err,
                "error_quadrature_degree": ms.quadrature_degree,
                "eta": r.eta,
                "eta_disc": totals["eta_disc"],
                "eta_lin": totals["eta_lin"],
                "eta_alg": totals["eta_alg"],
                "effectivity": r.eta / err,
                "bound_holds": bool(r.eta >= err),
                "contact_fraction": r.contact_fraction,
                "peak_rss_mb": peak_rss_mb(),
            }
            if "inner_total" in r.history:
                row["inner_total"] = int(r.history["inner_total"][-1])
            results[method] = r
            rows.append(row)
            progress(
                f"work_precision: n = {n:5d} {method:9s} {t['median']:8.3f}s "
                f"err {err:.4e} eta {r.eta:.4e} eff {row['effectivity']:.3f}"
            )
        _compare(rows[first:], results)
    return rows


def _compare(rows, results):
    """Same-mesh checks and ratios against exact-amg (and exact where it ran)."""
    by = {r["method"]: r for r in rows}
    ref = results.get("exact-amg")
    for row in rows:
        r = results[row["method"]]
        for base in ("exact-amg", "exact"):
            if base not in by:
                continue
            tag = base.replace("-", "_")
            row[f"error_over_{tag}_error"] = row["energy_error"] / by[base]["energy_error"]
            row[f"time_over_{tag}_time"] = row["seconds"]["median"] / by[base]["seconds"]["median"]
        if ref is not None:
            row["max_abs_diff_u_vs_exact_amg"] = float(
                max(np.abs(r.u1 - ref.u1).max(), np.abs(r.u2 - ref.u2).max())
            )


def rates(rows):
    """Fitted convergence rate of error and eta in h per method (log-log least squares)."""
    out = {}
    for method in dict.fromkeys(r["method"] for r in rows):
        sub = [r for r in rows if r["method"] == method]
        if len(sub) < 2:
            continue
        h = np.log([r["h"] for r in sub])
        out[method] = {
            "error_rate_in_h": float(np.polyfit(h, np.log([r["energy_error"] for r in sub]), 1)[0]),
            "eta_rate_in_h": float(np.polyfit(h, np.log([r["eta"] for r in sub]), 1)[0]),
        }
    return out


def main(argv=None):
    p = parser(__doc__)
    p.add_argument("--methods", nargs="*", default=list(METHODS), choices=METHODS)
    p.add_argument("--exact-max", type=int, default=256)
    p.add_argument("--budget", type=float, default=60.0, help="stop repeating a run after this")
    args = parse(p, argv)
    sizes = args.sizes or (QUICK_SIZES if args.quick else FULL_SIZES)
    if args.quick and args.repeat == p.get_default("repeat"):
        args.repeat = 1
    rows = run(sizes, args.methods, args.exact_max, args.repeat, args.budget)
    import fastmem as fm

    payload = {
        "parameters": {
            "sizes": sizes,
            "methods": args.methods,
            "exact_max": args.exact_max,
            "repeat": args.repeat,
            "budget_s": args.budget,
            "quick": args.quick,
            "manufactured": fm.Manufactured().to_dict(),
            "timed": "fm.solve(scene, method, estimate=True) on a fresh Mesh.square(n) scene",
        },
        "rows": rows,
        "rates": rates(rows),
    }
    finish("work_precision", payload, args.quick)


if __name__ == "__main__":
    main()
