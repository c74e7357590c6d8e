"""The Poisson unit on its own: pyamg SA setup + CG to 1e-8.

The unit in which the solver benchmarks express cost: the P1 Laplacian of the
structured n x n square mesh on the interior vertices, f = 1, pyamg's
smoothed-aggregation hierarchy as CG preconditioner, relative residual 1e-8,
BLAS limited to fastmem's setting (1 thread by default).  Setup and solve are
timed apart, with CG iterations, a residual check (recomputed from the
returned solution), and the peak resident memory of one process per size.
The growth exponent of each part in the number of unknowns is fitted.

    python -m bench.poisson_unit [--quick] [--sizes 64 128 256 512 1024 2048]
"""

import argparse
import time

from bench._common import (
    current_rss_mb,
    emit_worker_result,
    finish,
    fit_exponent,
    parse,
    parser,
    peak_rss_mb,
    poisson_unit,
    progress,
    run_worker,
)

FULL_SIZES = [64, 128, 256, 512, 1024, 2048]
QUICK_SIZES = [16, 32]


def measure(n, repeat):
    """One size in this process: the row of the JSON."""
    import fastmem as fm

    rss0 = current_rss_mb()
    t0 = time.perf_counter()
    mesh = fm.Mesh.square(n)
    _ = mesh.interior_vertices, mesh.lumped_mass
    t_mesh = time.perf_counter() - t0
    unit = poisson_unit(mesh, repeat=repeat, warmup=1)
    return {
        "n": n,
        "vertices": mesh.n_vertices,
        "triangles": mesh.n_triangles,
        "mesh_s": t_mesh,
        **unit,
        "rss_before_mb": rss0,
        "peak_rss_mb": peak_rss_mb(),
    }


def run(sizes, repeat, subprocesses=True):
    rows = []
    for n in sizes:
        if subprocesses:
            row = run_worker("bench.poisson_unit", ["--worker", n, "--repeat", repeat])
        else:
            row = measure(n, repeat)
        rows.append(row)
        progress(
            f"poisson_unit: n = {n:5d} ({row['unknowns']} unknowns): setup "
            f"{row['setup_s']['median']:.4f}s solve {row['solve_s']['median']:.4f}s "
            f"({row['iterations']} CG its, rel. res. {row['relative_residual']:.1e}) "
            f"peak {row['peak_rss_mb']:.0f} MB"
        )
    return rows


def fits(rows, min_vertices):
    use = [r for r in rows if r["vertices"] >= min_vertices] or rows
    nn = [r["unknowns"] for r in use]
    return {
        "min_vertices": min_vertices,
        "sizes_used": [r["n"] for r in use],
        **{
            part: fit_exponent(nn, [r[f"{part}_s"]["median"] for r in use])
            for part in ("setup", "solve", "total")
        },
    }


def main(argv=None):
    p = parser(__doc__)
    p.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--in-process", action="store_true", help="no subprocess per size")
    args = parse(p, argv)
    if args.worker is not None:
        emit_worker_result(measure(args.worker, args.repeat))
        return
    sizes = args.sizes or (QUICK_SIZES if args.quick else FULL_SIZES)
    repeat = args.repeat
    rows = run(sizes, repeat, not args.in_process)
    payload = {
        "parameters": {
            "sizes": sizes,
            "repeat": repeat,
            "warmup": 1,
            "quick": args.quick,
            "mesh": "fm.Mesh.square(n): (-1, 1)^2, n x n cells, symmetric diagonals",
            "rhs": "f = 1 (lumped mass), homogeneous Dirichlet",
            "solver": "pyamg.smoothed_aggregation_solver(A_II).solve(b, tol=1e-8, accel='cg')",
            "memory": "subprocess per size" if not args.in_process else "one process",
        },
        "rows": rows,
        "exponents": fits(rows, 1 if args.quick else 10_000),
    }
    finish("poisson_unit", payload, args.quick)


if __name__ == "__main__":
    main()
