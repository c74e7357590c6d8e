"""Thread scaling of the parallel Numba kernels: 1 vs all threads.

For each mesh size (default scene, docs/method.md §8, at its discrete
solution) and each parallel kernel:

* ``assembly``: ``assemble_stiffness`` (fused local-matrix + CSR gather kernel);
* ``flux``: ``fastmem.estimators.flux.reconstruct`` (patch problems, both membranes);
* ``estimate``: ``fm.estimate`` (flux reconstruction and all estimators);
* ``locate``: ``fastmem.solver.nested.interpolation_matrix`` from the next coarser
  mesh (bucket grid + parallel point location).

The Numba thread count is set with ``fm.set_threads(numba=k)``; after one
warm-up per thread count the repetitions alternate between the counts, so
both see the same machine state.  The speed-up is the ratio of medians;
CPU seconds per wall second are recorded too (about k when k threads really
ran: on a shared machine a lower value means the cores were busy).  The
outputs at 1 and k threads are compared (max absolute difference, and
relative to the largest value) and recorded.  BLAS is limited to fastmem's
setting (one thread by default) throughout.

    python -m bench.threads [--quick] [--sizes 256 1024]
"""

import time

import numpy as np

from bench._common import finish, parse, parser, peak_rss_mb, progress, summary

FULL_SIZES = [256, 1024]
QUICK_SIZES = [32]


def _as_arrays(out):
    """Flatten a kernel output into a list of float arrays for comparison."""
    if hasattr(out, "tocsr"):
        out = out.tocsr()
        out.sort_indices()
        return [out.data, out.indices.astype(float), out.indptr.astype(float)]
    if hasattr(out, "coef"):  # Fluxes
        return [out.coef]
    if hasattr(out, "totals"):  # Estimate
        return [np.array([out.totals[k] for k in ("eta", "eta_disc", "eta_lin", "eta_alg")])] + [
            out.maps[k] for k in sorted(out.maps)
        ]
    return [np.asarray(out)]


def _difference(a, b):
    xa, xb = _as_arrays(a), _as_arrays(b)
    if len(xa) != len(xb) or any(x.shape != y.shape for x, y in zip(xa, xb, strict=True)):
        return float("inf"), float("inf")
    diff = max(float(np.abs(x - y).max()) if x.size else 0.0 for x, y in zip(xa, xb, strict=True))
    scale = max(float(np.abs(x).max()) if x.size else 0.0 for x in xa)
    return diff, diff / scale if scale else diff


def kernels(n):
    """(name, work units, callable) of each parallel kernel on the mesh n x n."""
    import fastmem as fm
    from fastmem.estimators.flux import reconstruct
    from fastmem.fem.assembly import assemble_stiffness
    from fastmem.solver.nested import interpolation_matrix

    mesh = fm.Mesh.square(n)
    scene = fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    r = fm.solve(scene, method="exact-amg", estimate=False)
    u1, u2, lam = r.u1, r.u2, r.lam
    coarse = mesh.coarser()
    out = [
        ("assembly", mesh.n_triangles, "triangles", lambda: assemble_stiffness(mesh)),
        ("flux", mesh.n_vertices, "patches", lambda: reconstruct(scene, u1, u2, lam)),
        ("estimate", mesh.n_vertices, "patches", lambda: fm.estimate(scene, u1, u2, lam)),
    ]
    if coarse is not None:
        out.append(
            ("locate", mesh.n_vertices, "points", lambda: interpolation_matrix(coarse, mesh))
        )
    return mesh, out


def run(sizes, threads, repeat):
    import fastmem as fm
    from fastmem.config import blas_limits

    old = fm.get_threads()["numba"]
    try:
        with blas_limits():
            return _run(sizes, threads, repeat)
    finally:
        fm.set_threads(numba=old)


def _run(sizes, threads, repeat):
    import fastmem as fm

    rows = []
    for n in sizes:
        fm.set_threads(numba=max(threads))
        mesh, ks = kernels(n)
        for name, work, unit, fn in ks:
            row = {"n": n, "vertices": mesh.n_vertices, "triangles": mesh.n_triangles}
            row.update(measure(name, work, unit, fn, threads, repeat))
            rows.append(row)
            lo, hi = str(min(threads)), str(max(threads))
            progress(
                f"threads: n = {n:5d} {name:9s} {lo} thread {row['seconds'][lo]['median']:.4f}s "
                f"{hi} threads {row['seconds'][hi]['median']:.4f}s speed-up "
                f"{row['speedup']:.2f} (cpu/wall at {hi}: {row['cpu_over_wall'][hi]:.2f})"
                f"  max diff {row['max_abs_diff']:.1e}"
            )
    return rows


def measure(name, work, unit, fn, threads, repeat):
    """Time ``fn`` at each thread count, alternating; compare the outputs."""
    import fastmem as fm

    outputs = {}
    times = {k: [] for k in threads}
    cpu = {k: [] for k in threads}
    for k in threads:  # warm-up (JIT caches, per-mesh caches) per thread count
        fm.set_threads(numba=k)
        outputs[k] = fn()
    for _ in range(repeat):
        for k in threads:
            fm.set_threads(numba=k)
            c0, t0 = time.process_time(), time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t0)
            cpu[k].append(time.process_time() - c0)
    lo, hi = min(threads), max(threads)
    diff, rel = _difference(outputs[lo], outputs[hi])
    stats = {str(k): summary(v) for k, v in times.items()}
    return {
        "kernel": name,
        "work": work,
        "work_unit": unit,
        "seconds": stats,
        "speedup": stats[str(lo)]["median"] / stats[str(hi)]["median"],
        # CPU seconds (all threads) per wall second: about k when k threads really ran
        "cpu_over_wall": {
            str(k): sum(cpu[k]) / sum(times[k]) if sum(times[k]) else None for k in threads
        },
        f"{unit}_per_s": {k: work / s["median"] for k, s in stats.items()},
        "max_abs_diff": diff,
        "max_rel_diff": rel,
        "identical": diff == 0.0,
        "peak_rss_mb": peak_rss_mb(),
    }


def main(argv=None):
    import numba

    p = parser(__doc__)
    p.add_argument("--threads", type=int, nargs="*", default=None, help="default: 1 and all")
    args = parse(p, argv)
    sizes = args.sizes or (QUICK_SIZES if args.quick else FULL_SIZES)
    threads = sorted(set(args.threads or [1, numba.config.NUMBA_NUM_THREADS]))
    if args.quick and args.repeat == p.get_default("repeat"):
        args.repeat = 1
    if len(threads) < 2:
        progress("threads: only one Numba thread available; the speed-up is 1 by construction")
    payload = {
        "parameters": {
            "sizes": sizes,
            "threads": threads,
            "repeat": args.repeat,
            "quick": args.quick,
            "numba_num_threads": numba.config.NUMBA_NUM_THREADS,
            "schedule": "warm-up per thread count, then repetitions alternating the counts",
        },
        "rows": run(sizes, threads, args.repeat),
    }
    finish("threads", payload, args.quick)


if __name__ == "__main__":
    main()
