"""Exact Newton-min on the default scene and the manufactured solution (sparse direct solves).

Reports Newton steps, factorisations, seconds per phase and, for the
manufactured solution, the energy error, for both linear-step paths, and
checks that the two paths give the same solution.

    python -m bench.exact_solve [--quick] [--sizes 32 64 128 256 512] [--general-max 256]
"""

import time

import numpy as np

from bench._common import finish, parse, parser, peak_rss_mb, progress


def run(sizes, general_max):
    import fastmem as fm

    ms = fm.Manufactured()
    for path in ("decoupled", "general"):  # load the JIT caches outside the timings
        fm.solve(ms.scene(fm.Mesh.square(4)), method="exact", path=path, estimate=False)
    rows = []
    for n in sizes:
        mesh = fm.Mesh.square(n)
        for scene_name in ("default", "manufactured"):
            for path in ("decoupled", "general"):
                if path == "general" and n > general_max:
                    continue
                if scene_name == "default":
                    scene = fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
                else:
                    scene = ms.scene(mesh)
                t0 = time.perf_counter()
                r = fm.solve(scene, method="exact", path=path, estimate=False)
                wall = time.perf_counter() - t0
                row = {
                    "n": n,
                    "vertices": mesh.n_vertices,
                    "scene": scene_name,
                    "path": path,
                    "newton_steps": r.n_newton,
                    "converged": r.converged,
                    "factorizations": r.parameters["solver"]["factorizations"],
                    "contact_fraction": r.contact_fraction,
                    "wall_s": wall,
                    "timings": r.timings,
                    "final_res_norm": float(r.history["res_norm"][-1]),
                }
                if path == "decoupled":
                    ref = r
                else:  # with exact solves both paths give the same iterates (docs/method.md §3.3)
                    row["max_abs_diff_u_vs_decoupled"] = float(
                        max(np.abs(r.u1 - ref.u1).max(), np.abs(r.u2 - ref.u2).max())
                    )
                    row["max_abs_diff_lam_vs_decoupled"] = float(np.abs(r.lam - ref.lam).max())
                if scene_name == "manufactured":
                    row["energy_error"] = ms.energy_error(mesh, r.u1, r.u2)
                    row["error_quadrature_degree"] = 7
                row["peak_rss_mb"] = peak_rss_mb()
                rows.append(row)
                progress(
                    f"n={n:4d} {scene_name:12s} {path:9s} steps={r.n_newton:3d} "
                    f"time={wall:7.2f}s"
                    + (f" err={row['energy_error']:.4e}" if "energy_error" in row else "")
                )
    return rows


def main(argv=None):
    p = parser(__doc__)
    p.add_argument("--general-max", type=int, default=256)
    args = parse(p, argv)
    sizes = args.sizes or ([8, 16] if args.quick else [32, 64, 128, 256, 512])
    payload = {
        "parameters": {"sizes": sizes, "general_max": args.general_max, "quick": args.quick},
        "rows": run(sizes, args.general_max),
    }
    finish("exact_solve", payload, args.quick)


if __name__ == "__main__":
    main()
