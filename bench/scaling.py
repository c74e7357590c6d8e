"""Scaling of the whole pipeline mesh -> solve -> estimate -> archive.

The default scene (docs/method.md §8) on the structured n x n square mesh,
one subprocess per size so that the peak resident memory is that of one
size alone.  Phases, each timed on its own:

* ``mesh``: ``fm.Mesh.square(n)`` and its derived topology (edges,
  triangle-edge map, vertex patches, boundary);
* ``solve``: ``fm.solve(scene, method=...)`` on a fresh scene (assembly
  included; ``inexact`` evaluates the estimators inside its stopping test);
* ``estimate``: ``fm.estimate`` of the returned triple (the stand-alone
  guaranteed bound: flux reconstruction and all estimators; the bound the
  solve attached is dropped first, as a user replacing it would);
* ``archive``: ``result.save`` to an HDF5 file in a temporary folder
  (atomic write, compressed chunks).

Each phase is repeated (fresh objects every time) up to ``--repeat`` times,
fewer when one pipeline takes longer than ``--budget`` seconds; the JIT caches
are loaded by a pipeline on a tiny mesh first.  The growth exponent p of
each phase, time ~ N^p in the number of vertices N, is fitted by least
squares on log-log over the sizes with N >= 1e4 (all sizes with --quick), and
so is the peak resident memory (``VmHWM`` of the size's worker, read before the
Poisson unit).  After the pipeline the worker also measures the Poisson unit on
the same mesh (:func:`bench._common.poisson_unit`, one repetition from n = 2048):
each row has ``poisson_s`` and ``solve_poisson_units``, and the figure draws the
unit beside the phases.

``--merge`` keeps the rows of the other sizes already in the result file (same
method) and fits the exponents over all of them: a size too big to share an
exclusive run with the others (n = 4096: about 5 minutes and 20 GB) is
measured on its own.

    python -m bench.scaling [--quick] [--sizes 64 128 256 512 1024 2048] [--method inexact]
    python -m bench.scaling --sizes 4096 --repeat 1 --merge
"""

import argparse
import gc
import tempfile
import time
from pathlib import Path

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
    summary,
)

FULL_SIZES = [64, 128, 256, 512, 1024, 2048]
QUICK_SIZES = [16, 32]
PHASES = ("mesh", "solve", "estimate", "archive")


def pipeline(n, method, folder):
    """One pass of the pipeline; returns (seconds per phase, info)."""
    import fastmem as fm

    t = {}
    t0 = time.perf_counter()
    mesh = fm.Mesh.square(n)
    _ = mesh.edges, mesh.triangle_edges, mesh.patch_ptr, mesh.interior_vertices
    t["mesh"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    scene = fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    result = fm.solve(scene, method=method)
    t["solve"] = time.perf_counter() - t0

    eta_solve = None if result.estimate is None else result.eta
    result.estimate = None  # its maps (about 100 bytes per vertex) are replaced below
    t0 = time.perf_counter()
    est = fm.estimate(scene, result.u1, result.u2, result.lam)
    t["estimate"] = time.perf_counter() - t0

    path = Path(folder) / f"run_{n}.h5"
    result.estimate = est
    t0 = time.perf_counter()
    result.save(path)
    t["archive"] = time.perf_counter() - t0

    info = {
        "newton_finest": result.n_newton,
        "converged": bool(result.converged),
        "eta": est.eta,
        "contact_fraction": result.contact_fraction,
        "solve_timings": result.timings,
        "archive_mb": path.stat().st_size / 2**20,
    }
    if eta_solve is not None and method == "inexact":
        info["eta_inside_solve"] = eta_solve
    # round trip, not timed: the loaded copy alone (with the solve's objects still alive it
    # was the peak of the whole pipeline, about 1.3 kB per vertex at n = 4096)
    u1, lam = result.u1, result.lam
    del result, est, scene, mesh
    back = fm.load(path)
    info["archive_roundtrip_max_diff"] = float(
        max(abs(back.u1 - u1).max(), abs(back.lam - lam).max())
    )
    path.unlink()
    return t, info


def measure(n, method, repeat, budget):
    """One size in this process (a worker): the row of the JSON."""
    with tempfile.TemporaryDirectory(prefix="fastmem-bench-") as folder:
        pipeline(8, method, folder)  # JIT caches, h5py
        rss0 = current_rss_mb()
        per_phase = {ph: [] for ph in PHASES}
        spent = 0.0
        info = None
        while len(per_phase["mesh"]) < max(1, repeat):
            t, info = pipeline(n, method, folder)
            # free the repetition's reference cycles now: the peak is per repetition
            # (without it, 2 repetitions at n = 2048 peaked at 16.0 GB, one alone at 10.3 GB)
            gc.collect()
            for ph in PHASES:
                per_phase[ph].append(t[ph])
            spent += sum(t.values())
            if spent > budget:
                break
    import fastmem as fm

    peak = peak_rss_mb()  # the pipeline's peak, before the Poisson unit's matrices
    mesh = fm.Mesh.square(n)
    phases = {ph: summary(v) for ph, v in per_phase.items()}
    # the unit of solver cost on the same mesh, after the pipeline (not in its peak); one
    # repetition where one takes long
    unit = poisson_unit(mesh, repeat=1 if n >= 2048 else repeat)
    total = [sum(per_phase[ph][i] for ph in PHASES) for i in range(len(per_phase["mesh"]))]
    return {
        "n": n,
        "vertices": mesh.n_vertices,
        "triangles": mesh.n_triangles,
        "method": method,
        "phases": phases,
        "total_s": summary(total),
        "repetitions": len(total),
        **info,
        "poisson_s": unit["seconds"],
        "poisson": unit,
        "solve_poisson_units": phases["solve"]["median"] / unit["seconds"],
        "rss_before_mb": rss0,
        "peak_rss_mb": peak,
    }


def exponents(rows, min_vertices):
    use = [r for r in rows if r["vertices"] >= min_vertices]
    if len(use) < 2:
        use = rows
    nv = [r["vertices"] for r in use]
    out = {ph: fit_exponent(nv, [r["phases"][ph]["median"] for r in use]) for ph in PHASES}
    out["total"] = fit_exponent(nv, [r["total_s"]["median"] for r in use])
    out["peak_rss_mb"] = fit_exponent(nv, [r["peak_rss_mb"] for r in use])
    if all("poisson_s" in r for r in use):  # rows kept by --merge from before may lack it
        out["poisson_unit"] = fit_exponent(nv, [r["poisson_s"] for r in use])
    out["sizes_used"] = [r["n"] for r in use]
    out["min_vertices"] = min_vertices
    return out


def _kept_rows(args, sizes):
    """Rows of the other sizes in the existing result file (``--merge``), same method."""
    import json

    from bench._common import result_name, results_dir

    path = results_dir() / f"{result_name('scaling', args.quick)}.json"
    if not path.exists():
        return []
    old = json.loads(path.read_text())
    if old.get("parameters", {}).get("method") != args.method:
        raise SystemExit(f"--merge: {path} holds method {old['parameters'].get('method')!r}")
    return [r for r in old.get("rows", []) if r["n"] not in sizes]


def main(argv=None):
    p = parser(__doc__)
    p.add_argument("--method", default="inexact", choices=("inexact", "exact-amg", "exact"))
    p.add_argument("--budget", type=float, default=60.0, help="stop repeating after this")
    p.add_argument("--in-process", action="store_true", help="no subprocess per size")
    p.add_argument(
        "--merge",
        action="store_true",
        help="keep the other sizes' rows of the existing result file (same method)",
    )
    p.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    args = parse(p, argv)
    if args.worker is not None:
        emit_worker_result(measure(args.worker, args.method, args.repeat, args.budget))
        return
    sizes = args.sizes or (QUICK_SIZES if args.quick else FULL_SIZES)
    if args.quick and args.repeat == p.get_default("repeat"):
        args.repeat = 1
    rows = []
    for n in sizes:
        if args.in_process:
            row = measure(n, args.method, args.repeat, args.budget)
        else:
            row = run_worker(
                "bench.scaling",
                ["--worker", n, "--method", args.method, "--repeat", args.repeat]
                + ["--budget", args.budget],
            )
        rows.append(row)
        ph = row["phases"]
        progress(
            f"scaling: n = {n:5d} ({row['vertices']} vertices) "
            + " ".join(f"{k} {ph[k]['median']:.3f}s" for k in PHASES)
            + f" peak {row['peak_rss_mb']:.0f} MB ({row['repetitions']} reps)"
            + f" Poisson unit {row['poisson_s']:.3f}s (solve {row['solve_poisson_units']:.2f} PU)"
        )
    kept = _kept_rows(args, sizes) if args.merge else []
    rows = sorted(kept + rows, key=lambda r: r["n"])
    payload = {
        "parameters": {
            "sizes": [r["n"] for r in rows],
            "merged": (
                {"kept": [r["n"] for r in kept], "measured_now": sizes} if args.merge else None
            ),
            "method": args.method,
            "repeat": args.repeat,
            "budget_s": args.budget,
            "quick": args.quick,
            "scene": "default (docs/method.md §8): mu=(1, 1), f=(-1, 1), g=0.1",
            "memory": "subprocess per size" if not args.in_process else "one process",
        },
        "phases": list(PHASES),
        "rows": rows,
        "exponents": exponents(rows, 1 if args.quick else 10_000),
    }
    finish("scaling", payload, args.quick)
    ex = payload["exponents"]
    progress(
        "scaling: fitted exponents "
        + " ".join(f"{k} {ex[k]:.2f}" for k in (*PHASES, "total") if ex[k] is not None)
    )


if __name__ == "__main__":
    main()
