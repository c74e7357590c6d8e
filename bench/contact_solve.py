"""The contact solve in Poisson units: inexact vs exact-amg vs exact (BENCHMARKS.md #3).

For each mesh size and scene (the default scene of MATH.md section 8 and the
default manufactured solution of section 7): one pyamg smoothed-aggregation
Poisson solve (setup + CG to 1e-8 on the interior Laplacian, BLAS limited to
one thread) measured in the same run as the unit, then each method with its
Newton steps (per nested level and in total), CG iterations, time, time in
Poisson units, the bound eta and, for the manufactured scene, the true energy
error.  Runs without nested iteration are included up to ``--plain-max``.

    python -m bench.contact_solve [--quick] [--sizes 256 512 1024 2048]
"""

import argparse
import time

import numpy as np

from bench._common import peak_rss_mb, progress, timed, write_json


def poisson_unit(scene, repeat):
    import pyamg

    from fastmem.config import blas_limits

    mesh = scene.mesh
    ii = mesh.interior_vertices
    a_ii = scene.stiffness[ii][:, ii].tocsr()
    b = mesh.lumped_mass[ii]
    with blas_limits(1):
        _, t = timed(
            lambda: pyamg.smoothed_aggregation_solver(a_ii).solve(b, tol=1e-8, accel="cg"),
            repeat,
            0,
        )
    return t["median"]


def run_one(scene, method, nested, ms=None):
    import fastmem as fm

    t0 = time.perf_counter()
    r = fm.solve(scene, method=method, nested=nested, estimate=True)
    seconds = time.perf_counter() - t0
    solver = r.parameters["solver"]
    row = {
        "method": method,
        "nested": nested,
        "converged": bool(r.converged),
        "seconds": seconds,
        "timings": r.timings,
        "eta": r.eta,
        "eta_disc": r.estimate.totals["eta_disc"],
        "eta_lin": r.estimate.totals["eta_lin"],
        "eta_alg": r.estimate.totals["eta_alg"],
        "contact_fraction": r.contact_fraction,
    }
    if method == "exact":
        row["newton_total"] = row["newton_finest"] = r.n_newton
        row["inner_total"] = None
    else:
        levels = solver["levels"]
        row["levels"] = levels
        row["newton_per_level"] = [lv["newton"] for lv in levels]
        row["newton_total"] = int(sum(row["newton_per_level"]))
        row["newton_finest"] = r.n_newton
        row["inner_total"] = int(r.history["inner_total"][-1])
        row["flux_evaluations"] = int(sum(lv["flux_evaluations"] for lv in levels))
        row["amg_setups"] = int(sum(lv["amg_setups"] for lv in levels))
    if ms is not None:
        row["energy_error"] = ms.energy_error(scene.mesh, r.u1, r.u2)
        row["effectivity"] = r.eta / row["energy_error"]
    return row, r


def run(sizes, repeat, exact_max, plain_max):
    import fastmem as fm

    fm.solve(fm.Scene(fm.Mesh.square(16), f=(-1.0, 1.0), g=0.1))  # compile / load caches
    rows = []
    for n in sizes:
        mesh = fm.Mesh.square(n)
        ms = fm.Manufactured()
        scenes = {
            "default": (fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1), None),
            "manufactured": (ms.scene(mesh), ms),
        }
        for name, (scene, man) in scenes.items():
            unit = poisson_unit(scene, repeat)
            progress(f"contact_solve: n = {n} {name}: Poisson unit {unit:.3f} s")
            runs = [("inexact", "auto"), ("exact-amg", "auto")]
            if n <= plain_max:
                runs += [("inexact", False), ("exact-amg", False)]
            if n <= exact_max:
                runs.append(("exact", False))
            results = {}
            for method, nested in runs:
                row, res = run_one(scene, method, nested, man)
                row.update(n=n, scene=name, vertices=mesh.n_vertices, poisson_s=unit)
                row["poisson_units"] = row["seconds"] / unit
                row["peak_rss_mb"] = peak_rss_mb()
                results[(method, nested)] = res
                rows.append(row)
                err = f" err {row['energy_error']:.3e}" if man is not None else ""
                progress(
                    f"  {method:9s} nested={str(nested):5s} steps {row['newton_total']:4d} "
                    f"(finest {row['newton_finest']}) inner {row['inner_total']} "
                    f"{row['seconds']:.2f}s = {row['poisson_units']:.2f} PU  eta {row['eta']:.3e}"
                    + err
                )
            ref = results[("exact-amg", "auto")]
            for row in rows[-len(runs) :]:
                r = results[(row["method"], row["nested"])]
                row["max_abs_diff_u_vs_exact_amg"] = float(
                    max(np.abs(r.u1 - ref.u1).max(), np.abs(r.u2 - ref.u2).max())
                )
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--sizes", type=int, nargs="*", default=None)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--exact-max", type=int, default=512)
    p.add_argument("--plain-max", type=int, default=512)
    args = p.parse_args(argv)
    sizes = args.sizes or ([16, 32] if args.quick else [256, 512, 1024, 2048])
    repeat = 1 if args.quick else args.repeat
    payload = {
        "parameters": {
            "sizes": sizes,
            "repeat": repeat,
            "exact_max": args.exact_max,
            "plain_max": args.plain_max,
        },
        "rows": run(sizes, repeat, args.exact_max, args.plain_max),
    }
    path = write_json("contact_solve_quick" if args.quick else "contact_solve", payload)
    progress(f"wrote {path}")


if __name__ == "__main__":
    main()
