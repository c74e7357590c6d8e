"""Flux reconstruction and estimators in Poisson units (BENCHMARKS.md #4).

For each mesh size: one pyamg smoothed-aggregation Poisson solve (setup + CG
to 1e-8, BLAS limited to one thread) as the unit, then the flux
reconstruction (first and repeated evaluation) and the whole estimate, with
patches per second.  The estimate is taken at the exact discrete solution up
to ``--solve-max`` and at the Dirichlet lifting beyond.

    python -m bench.estimate [--quick] [--sizes 256 1024 2048]
"""

import argparse
import time

import numpy as np

from bench._common import peak_rss_mb, progress, timed, write_json


def run(sizes, repeat, solve_max):
    import pyamg

    import fastmem as fm
    from fastmem.config import blas_limits
    from fastmem.flux import reconstruct

    rows = []
    for n in sizes:
        progress(f"estimate: n = {n}")
        mesh = fm.Mesh.square(n)
        scene = fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
        a = scene.stiffness
        ii = mesh.interior_vertices
        a_ii = a[ii][:, ii].tocsr()
        b = scene.loads[0][ii]
        with blas_limits(1):
            _, t_poisson = timed(
                lambda: pyamg.smoothed_aggregation_solver(a_ii).solve(b, tol=1e-8, accel="cg"),
                repeat,
                0,
            )
        if n <= solve_max:
            r = fm.solve(scene)
            u1, u2, lam = r.u1, r.u2, r.lam
        else:
            u1 = scene.boundary_values.copy()
            u2 = np.zeros(mesh.n_vertices)
            lam = np.zeros(mesh.n_vertices)
        t0 = time.perf_counter()
        reconstruct(scene, u1, u2, lam)
        t_first = time.perf_counter() - t0
        _, t_flux = timed(lambda: reconstruct(scene, u1, u2, lam), repeat, 0)
        est, t_est = timed(lambda: fm.estimate(scene, u1, u2, lam), repeat, 0)
        unit = t_poisson["median"]
        row = {
            "n": n,
            "vertices": mesh.n_vertices,
            "triangles": mesh.n_triangles,
            "poisson_s": t_poisson,
            "flux_first_s": t_first,
            "flux_repeat_s": t_flux,
            "estimate_s": t_est,
            "patches_per_s": mesh.n_vertices / t_flux["median"],
            "estimate_poisson_units": t_est["median"] / unit,
            "eta": est.eta,
            "peak_rss_mb": peak_rss_mb(),
        }
        rows.append(row)
        progress(
            f"  poisson {unit:.3f}s flux {t_flux['median']:.3f}s "
            f"({row['patches_per_s']:.0f} patches/s) estimate {t_est['median']:.3f}s "
            f"= {row['estimate_poisson_units']:.1f} Poisson units"
        )
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--sizes", type=int, nargs="*", default=None)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--solve-max", type=int, default=512)
    args = p.parse_args(argv)
    sizes = args.sizes or ([16, 32] if args.quick else [256, 1024, 2048])
    repeat = 1 if args.quick else args.repeat
    payload = {
        "parameters": {"sizes": sizes, "repeat": repeat, "solve_max": args.solve_max},
        "rows": run(sizes, repeat, args.solve_max),
    }
    path = write_json("estimate_quick" if args.quick else "estimate", payload)
    progress(f"wrote {path}")


if __name__ == "__main__":
    main()
