"""Flux reconstruction and estimators in Poisson units (BENCHMARKS.md #4).

For each mesh size: one pyamg smoothed-aggregation Poisson solve (setup + CG
to 1e-8, BLAS limited to one thread; ``bench._common.poisson_unit``) as the
unit, then the flux
reconstruction (first evaluation on a fresh mesh object, which builds the
cached topology and vertex colouring, and repeated evaluation) and the whole
estimate, with patches per second.  Numba compilation is done on a tiny mesh
beforehand and is not in any timing.  The estimate is taken at the exact discrete solution up
to ``--solve-max`` and at the Dirichlet lifting beyond.

    python -m bench.estimate [--quick] [--sizes 256 1024 2048] [--results DIR]
"""

import time

import numpy as np

from bench._common import finish, parse, parser, peak_rss_mb, poisson_unit, progress, timed


def run(sizes, repeat, solve_max):
    import fastmem as fm
    from fastmem.flux import reconstruct

    fm.estimate(*_lifting(fm.Scene(fm.Mesh.square(8), f=(-1.0, 1.0), g=0.1)))  # JIT caches
    rows = []
    for n in sizes:
        progress(f"estimate: n = {n}")
        mesh = fm.Mesh.square(n)
        scene = fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
        unit_info = poisson_unit(mesh, repeat)
        if n <= solve_max:
            r = fm.solve(scene)
            u1, u2, lam = r.u1, r.u2, r.lam
        else:
            _, u1, u2, lam = _lifting(scene)
        # first evaluation: a fresh mesh object, so its cached topology and colouring are
        # built inside the timing (JIT compilation was done on a tiny mesh above)
        fresh = fm.Scene(fm.Mesh.square(n), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
        t0 = time.perf_counter()
        reconstruct(fresh, u1, u2, lam)
        t_first = time.perf_counter() - t0
        est_first = fm.estimate(fresh, u1, u2, lam)
        del fresh
        _, t_flux = timed(lambda: reconstruct(scene, u1, u2, lam), repeat, 0)
        est, t_est = timed(lambda: fm.estimate(scene, u1, u2, lam), repeat, 0)
        unit = unit_info["seconds"]
        row = {
            "n": n,
            "vertices": mesh.n_vertices,
            "triangles": mesh.n_triangles,
            "poisson_s": unit_info["total_s"],
            "poisson": unit_info,
            "triple": "exact solution" if n <= solve_max else "Dirichlet lifting",
            "flux_first_s": t_first,
            "flux_repeat_s": t_flux,
            "estimate_s": t_est,
            "patches_per_s": mesh.n_vertices / t_flux["median"],
            "estimate_poisson_units": t_est["median"] / unit,
            "eta": est.eta,
            "eta_first_minus_repeat": abs(est.eta - est_first.eta),
            "peak_rss_mb": peak_rss_mb(),
        }
        rows.append(row)
        progress(
            f"  poisson {unit:.3f}s flux {t_flux['median']:.3f}s "
            f"({row['patches_per_s']:.0f} patches/s) estimate {t_est['median']:.3f}s "
            f"= {row['estimate_poisson_units']:.1f} Poisson units"
        )
    return rows


def _lifting(scene):
    """The Dirichlet lifting (u1 = g on the boundary, zero elsewhere) as a triple."""
    n = scene.mesh.n_vertices
    return scene, scene.boundary_values.copy(), np.zeros(n), np.zeros(n)


def main(argv=None):
    p = parser(__doc__)
    p.add_argument("--solve-max", type=int, default=512)
    args = parse(p, argv)
    sizes = args.sizes or ([16, 32] if args.quick else [256, 1024, 2048])
    repeat = 1 if args.quick else args.repeat
    payload = {
        "parameters": {
            "sizes": sizes,
            "repeat": repeat,
            "solve_max": args.solve_max,
            "quick": args.quick,
        },
        "rows": run(sizes, repeat, args.solve_max),
    }
    finish("estimate", payload, args.quick)


if __name__ == "__main__":
    main()
