"""Solve and estimate on many cores: one process, the Numba threads lowered step by step.

Issue 33's many-core check.  The default scene (docs/method.md §8; with
``--scenes`` also the manufactured one, :class:`fastmem.problems.Manufactured`)
on the structured n x n square, in one process:

1. ``fm.warm_up(large=True)`` (the kernels compiled or loaded), the mesh built, on
   the first size one solve of the first scene at the most threads (the solve a
   user meets: ``user_first_s``, before anything else has touched the memory it
   needs), then the Poisson unit measured (:func:`bench._common.poisson_unit`, all
   threads);
2. for each thread count, from the most to the fewest (``fm.set_threads``),
   and each multigrid (``multigrid="geometric"``, the nested-hierarchy
   multigrid, which the default ``"auto"`` takes on these levels, and
   ``"algebraic"``, pyamg as before issue 33):
   ``fm.solve(scene, method="inexact")`` on a fresh scene (nested iteration,
   the bound included), then ``fm.estimate`` of its triple (the stand-alone
   bound: flux reconstruction and every estimator);
3. with ``--repeat R``, R - 1 more rounds of the same solves, the order of the
   thread counts alternating, and the medians (``solve_median_s``, and
   ``solve_speedup_median``): the first pass's first solve pays the process's
   first touch of its memory, which the later ones do not;
4. the speed-ups T(1)/T(k) of each column, from the same process, beside the
   speed-up of one threaded CSR product with the interior Laplacian (the
   smoothers' and the CG's kernel; ``product_ms``, ``product_speedup``): the
   memory bandwidth of the machine bounds what a memory-bound solve gains.

The row with ``user_first_s`` is the solve a user meets after the warm-up
(``user_first_pu`` against the unit measured right after it), with its CPU
seconds and minor page faults (``user_first_system_s``, ``user_first_minor_faults``;
every solve row has ``solve_system_s`` and ``solve_minor_faults``): on the 2-core VM
the first solve's extra time over a later one is system time, the first touch of
its new memory (:func:`bench._common.process_times`); the rows'
``first_solve_in_process`` marks the first timed solve after the unit, which
runs on memory the unit has already faulted in.  A per-thread count row
has the seconds of every level, its Newton steps, CG iterations, multigrid
setups and flux seconds, so that what does not scale can be named.  With
``--profile`` the solve at the most threads is profiled once more
(cProfile, the 25 largest self times go into the JSON).

``--deadline`` (seconds from the start) skips what would not finish: a row
is started only while its predicted time, scaled from the rows already
done, fits.  ``--adaptive N`` adds the adaptive loop on the L-shape
(f = (-1, -1), g = 0.1, from ``Mesh.lshape(8)``) to the bound uniform
refinement reaches at n = N (one uniform solve at the most threads sets the
tolerance), timed at every thread count, ``--repeat`` rounds alternating the
order, with its T(1)/T(k) and the final mesh (rows with ``adaptive_s``; the
same final mesh and η at every thread count, or ``eta_mismatch``).
``--intermediate cg bound`` runs the loop both ways, alternating within each
round: the intermediate meshes' CGs stopped by their own error estimate (the
default) and by the guaranteed η_alg (rows' ``intermediate``).
``--large N`` then solves one larger mesh once at the most threads, with
peak memory per vertex.

    python -m bench.manycore [--quick] [--sizes 2048] [--threads 16 8 4 2 1]
                             [--scenes default manufactured]
    python -m bench.manycore --sizes 2048 --threads 16 8 4 2 1 --deadline 420 --profile
    python -m bench.manycore --sizes 1024 --threads 2 1 --repeat 3 --adaptive 2048
    python -m bench.manycore --sizes 64 --threads 2 --repeat 4 --adaptive 2048 \
        --intermediate cg bound
"""

import cProfile
import io
import pstats
import time

from bench._common import (
    current_rss_mb,
    finish,
    first_touch_ms_per_mb,
    parse,
    parser,
    peak_rss_mb,
    poisson_unit,
    process_times,
    progress,
    times_since,
)

QUICK_SIZES = [64]
FULL_SIZES = [2048]
MULTIGRIDS = ("geometric", "algebraic")


SCENES = ("default", "manufactured")


def _scene(mesh, which="default"):
    import fastmem as fm

    if which == "manufactured":
        from fastmem.problems import Manufactured

        return Manufactured().scene(mesh)
    return fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)


def _levels(result):
    keys = ("n_vertices", "newton", "inner", "seconds", "amg_setups", "amg_setup_seconds")
    keys += ("flux_evaluations", "flux_seconds")
    return [{k: lv.get(k) for k in keys} for lv in result.parameters["solver"]["levels"]]


def _one(mesh, multigrid, which):
    import fastmem as fm

    cpu = process_times()
    t0 = time.perf_counter()
    r = fm.solve(_scene(mesh, which), method="inexact", multigrid=multigrid)
    solve_s = time.perf_counter() - t0
    cpu = times_since(cpu)
    t0 = time.perf_counter()
    est = fm.estimate(_scene(mesh, which), r.u1, r.u2, r.lam)
    estimate_s = time.perf_counter() - t0
    return {
        "solve_s": solve_s,
        "solve_user_s": cpu["user_s"],
        "solve_system_s": cpu["system_s"],
        "solve_minor_faults": cpu["minor_faults"],
        "estimate_s": estimate_s,
        "eta": float(r.eta),
        "eta_estimate": float(est.eta),
        "n_newton": int(r.n_newton),
        "timings": dict(r.timings),
        "levels": _levels(r),
    }


def _repeat_rows(rows, mesh, repeat, deadline, t_start):
    """Solve each row's case ``repeat - 1`` more times, in rounds that alternate the order
    of the thread counts (fewest first, then most first, ...), and add the medians.

    The first pass goes from the most threads to the fewest, so its first solve pays
    the process's first touch of the memory a solve needs (on the benchmark VM about
    1-2 s at n = 1024) and the others do not: its T(1)/T(k) understates the scaling.
    The medians over all rounds compare like with like.
    """
    import statistics

    import fastmem as fm

    if repeat <= 1 or not rows:
        return
    for r in rows:
        r["solve_all_s"] = [r["solve_s"]]
        r["estimate_all_s"] = [r["estimate_s"]]
        r["solve_system_all_s"] = [r["solve_system_s"]]
    counts = sorted({r["threads"] for r in rows})
    for k in range(1, repeat):
        for t in counts if k % 2 else counts[::-1]:
            fm.set_threads(numba=t)
            for r in [r for r in rows if r["threads"] == t]:
                if deadline and time.perf_counter() - t_start + 1.5 * r["solve_s"] > deadline:
                    continue
                again = _one(mesh, r["multigrid"], r["scene"])
                if again["eta"] != r["eta"]:  # the same bits for any thread count and run
                    r["eta_mismatch"] = again["eta"]
                r["solve_all_s"].append(again["solve_s"])
                r["estimate_all_s"].append(again["estimate_s"])
                r["solve_system_all_s"].append(again["solve_system_s"])
    for r in rows:
        r["solve_median_s"] = statistics.median(r["solve_all_s"])
        r["estimate_median_s"] = statistics.median(r["estimate_all_s"])
        r["solve_median_pu"] = r["solve_median_s"] / r["poisson_s"]
        progress(
            f"n={r['n']} threads={r['threads']:2d} {r['scene']:12s} {r['multigrid']:9s}: median "
            f"of {len(r['solve_all_s'])} solves {r['solve_median_s']:.2f} s "
            f"({r['solve_median_pu']:.2f} PU), estimate {r['estimate_median_s']:.2f} s"
        )


def _profile(mesh, multigrid, which, top=25):
    import fastmem as fm

    pr = cProfile.Profile()
    pr.enable()
    fm.solve(_scene(mesh, which), method="inexact", multigrid=multigrid)
    pr.disable()
    out = io.StringIO()
    pstats.Stats(pr, stream=out).sort_stats("tottime").print_stats(top)
    text = out.getvalue()
    return text[text.find("ncalls") :]


def _product_ceiling(mesh, threads, products=40):
    """Milliseconds of one threaded CSR product with the interior Laplacian, per thread count.

    The solve's largest kernels stream matrices and vectors through memory, so the
    speed-up of this product (:class:`fastmem.linalg.sparse.ThreadedCSR`, the one the
    smoothers and the CG use) is about the most a memory-bound solve can get from more
    threads on this machine: on the 2-core benchmark VM it was 1.6x for 2 threads while a
    compute-bound loop scaled 1.9x.  The best of three rounds of ``products`` products.
    """
    import numpy as np

    import fastmem as fm
    from fastmem.fem.assembly import assemble_stiffness
    from fastmem.linalg.sparse import ThreadedCSR

    ii = mesh.interior_vertices
    a = assemble_stiffness(mesh)[ii][:, ii].tocsr()
    a.eliminate_zeros()
    op = ThreadedCSR((a.data, a.indices, a.indptr), shape=a.shape)
    x = np.random.default_rng(0).random(a.shape[0])
    out = {}
    for t in sorted(threads, reverse=True):
        fm.set_threads(numba=t)
        op @ x
        best = float("inf")
        for _ in range(3):
            t0 = time.perf_counter()
            for _ in range(products):
                op @ x
            best = min(best, (time.perf_counter() - t0) / products)
        out[t] = 1e3 * best
    return out


def _adaptive_scene(fm, n):
    return fm.Scene(fm.Mesh.lshape(n), mu=(1.0, 1.0), f=(-1.0, -1.0), g=0.1)


def _adaptive_rows(n, threads, repeat, deadline, t_start, modes=("cg",)):
    """The adaptive L-shape loop to the bound of uniform n, at every thread count (docstring).

    ``modes``: the values of ``fastmem.adapt.loop.INTERMEDIATE_ALG`` to run, alternating
    within each round at each thread count (``--intermediate``; the rows' ``intermediate``).
    """
    import statistics

    import fastmem as fm
    from fastmem.adapt import loop

    default = loop.INTERMEDIATE_ALG
    fm.set_threads(numba=max(threads))
    t0 = time.perf_counter()
    uniform = fm.solve(_adaptive_scene(fm, n))
    uniform_s = time.perf_counter() - t0
    tol = float(uniform.eta) * (1.0 + 1e-6)
    del uniform
    progress(f"adaptive: tolerance {tol:.4e} (uniform n={n}: {uniform_s:.2f} s)")
    keys = [(t, m) for t in threads for m in modes]
    runs = {k: [] for k in keys}
    finals = {}
    order = sorted(threads, reverse=True)
    try:
        for rnd in range(max(1, repeat)):
            for t in order if rnd % 2 == 0 else order[::-1]:
                for m in modes if rnd % 2 == 0 else modes[::-1]:
                    done = [v for ts in runs.values() for v in ts]
                    guess = max(done) * max(threads) / t if done else uniform_s
                    if deadline and time.perf_counter() - t_start + guess > deadline:
                        progress(f"adaptive threads={t} {m}: skipped (deadline)")
                        continue
                    fm.set_threads(numba=t)
                    loop.INTERMEDIATE_ALG = m
                    t0 = time.perf_counter()
                    r = fm.solve(_adaptive_scene(fm, 8), tol=tol)
                    runs[(t, m)].append(time.perf_counter() - t0)
                    finals.setdefault((t, m), set()).add((r.mesh.n_vertices, float(r.eta)))
                    meshes = len(r.adaptivity["n_vertices"])
                    progress(
                        f"adaptive threads={t:2d} {m:>5}: {runs[(t, m)][-1]:.2f} s, "
                        f"{meshes} meshes, {r.mesh.n_vertices} vertices, eta {r.eta:.4e}, "
                        f"{int(sum(r.adaptivity['inner']))} CG iterations"
                    )
    finally:
        loop.INTERMEDIATE_ALG = default
    rows = []
    for t, m in keys:
        if not runs[(t, m)]:
            continue
        (vertices, eta), *more = sorted(finals[(t, m)])
        row = {
            "adaptive_n": n,
            "threads": t,
            "intermediate": m,
            "tol": tol,
            "uniform_s": uniform_s,
            "adaptive_s": runs[(t, m)][0],
            "adaptive_all_s": runs[(t, m)],
            "adaptive_median_s": statistics.median(runs[(t, m)]),
            "final_vertices": vertices,
            "eta": eta,
        }
        same_mode = [f for (_, mode), f in finals.items() if mode == m]
        if more or any(f != finals[(t, m)] for f in same_mode):
            row["eta_mismatch"] = sorted(set().union(*same_mode))
        rows.append(row)
    base = {(r["threads"], r["intermediate"]): r for r in rows}
    for r in rows:
        one = base.get((1, r["intermediate"]))
        if one is not None:
            r["adaptive_speedup_median"] = one["adaptive_median_s"] / r["adaptive_median_s"]
    return rows


def run(
    sizes,
    threads,
    multigrids,
    deadline,
    profile,
    large,
    t_start,
    scenes=("default",),
    repeat=1,
    adaptive=None,
    intermediate=("cg",),
):
    import numba

    import fastmem as fm

    rows = []
    fm.warm_up(large=True, adaptive=bool(adaptive))
    for n in sizes:
        mesh = fm.Mesh.square(n)
        fm.set_threads(numba=max(threads))
        user = None
        if n == sizes[0]:
            # the solve a user meets: before the unit, whose own solves would have
            # faulted in the memory this one touches first (3 s more at n = 2048)
            cpu = process_times()
            t0 = time.perf_counter()
            fm.solve(_scene(mesh, scenes[0]), method="inexact", multigrid=multigrids[0])
            first_s = time.perf_counter() - t0
            cpu = times_since(cpu)
            user = {
                "n": n,
                "vertices": mesh.n_vertices,
                "threads": max(threads),
                "multigrid": multigrids[0],
                "scene": scenes[0],
                "user_first_s": first_s,
                "user_first_user_s": cpu["user_s"],
                "user_first_system_s": cpu["system_s"],
                "user_first_minor_faults": cpu["minor_faults"],
                "peak_rss_mb": peak_rss_mb(),
            }
        # with --repeat, the unit is the median of three (it varied by 10 % between
        # processes on the 2-core VM; one timed run would carry that into every PU)
        pu = poisson_unit(mesh, repeat=3 if repeat > 1 else 1)
        if user is not None:
            user["poisson_s"] = pu["seconds"]
            user["user_first_pu"] = user["user_first_s"] / pu["seconds"]
            rows.append(user)
            progress(
                f"n={n}: the process's first solve ({scenes[0]}, before the unit) "
                f"{user['user_first_s']:.2f} s ({user['user_first_pu']:.2f} PU; "
                f"{user['user_first_system_s']:.2f} s system time, "
                f"{user['user_first_minor_faults']} minor page faults)"
            )
        progress(f"n={n}: {mesh.n_vertices} vertices, Poisson unit {pu['seconds']:.2f} s")
        product_ms = _product_ceiling(mesh, threads)
        progress(
            f"n={n}: threaded CSR product "
            + ", ".join(f"{t} threads {ms:.2f} ms" for t, ms in sorted(product_ms.items()))
        )
        first = True
        done = {}  # (threads, multigrid, scene) -> solve + estimate seconds
        for t in sorted(threads, reverse=True):
            fm.set_threads(numba=t)
            for which, mg in [(w, m) for w in scenes for m in multigrids]:
                # predicted from the same multigrid at more threads, as if nothing scaled
                known = [v for (k, m, w), v in done.items() if m == mg and w == which]
                guess = max(known) * max(threads) / t if known else 0.0
                guess = min(guess, 4.0 * max(known)) if known else 0.0
                if deadline and time.perf_counter() - t_start + guess > deadline:
                    progress(f"n={n} threads={t} {which} {mg}: skipped (deadline)")
                    continue
                row = {"n": n, "vertices": mesh.n_vertices, "threads": t, "multigrid": mg}
                row["scene"] = which
                row.update(_one(mesh, mg, which))
                row["first_solve_in_process"] = first
                row["poisson_s"] = pu["seconds"]
                row["poisson_all_s"] = list(pu["total_s"]["all"])
                row["product_ms"] = product_ms[t]  # the memory-bound ceiling (_product_ceiling)
                if 1 in product_ms:
                    row["product_speedup"] = product_ms[1] / product_ms[t]
                row["solve_pu"] = row["solve_s"] / pu["seconds"]
                row["peak_rss_mb"] = peak_rss_mb()
                row["rss_mb"] = current_rss_mb()
                row["numba_threads"] = numba.get_num_threads()
                first = False
                done[(t, mg, which)] = row["solve_s"] + row["estimate_s"]
                rows.append(row)
                progress(
                    f"n={n} threads={t:2d} {which:12s} {mg:9s}: solve {row['solve_s']:.2f} s "
                    f"({row['solve_pu']:.2f} PU; {row['solve_system_s']:.2f} s system), "
                    f"estimate {row['estimate_s']:.2f} s, "
                    f"eta {row['eta']:.4e}, Newton {row['n_newton']}"
                )
        timed = [r for r in rows if r["n"] == n and "solve_s" in r]
        _repeat_rows(timed, mesh, repeat, deadline, t_start)
        for which, mg in [(w, m) for w in scenes for m in multigrids]:
            base = {
                r["threads"]: r for r in timed if r["multigrid"] == mg and r.get("scene") == which
            }
            if 1 in base:
                for r in base.values():
                    r["solve_speedup"] = base[1]["solve_s"] / r["solve_s"]
                    r["estimate_speedup"] = base[1]["estimate_s"] / r["estimate_s"]
                    if "solve_median_s" in r and "solve_median_s" in base[1]:
                        r["solve_speedup_median"] = base[1]["solve_median_s"] / r["solve_median_s"]
                        r["estimate_speedup_median"] = (
                            base[1]["estimate_median_s"] / r["estimate_median_s"]
                        )
        if profile and not (deadline and time.perf_counter() - t_start > 0.8 * deadline):
            fm.set_threads(numba=max(threads))
            rows.append(
                {
                    "n": n,
                    "threads": max(threads),
                    "multigrid": multigrids[0],
                    "scene": scenes[0],
                    "profile": _profile(mesh, multigrids[0], scenes[0]),
                }
            )
        del mesh
    if adaptive:
        rows += _adaptive_rows(adaptive, threads, repeat, deadline, t_start, tuple(intermediate))
    if large:
        fm.set_threads(numba=max(threads))
        if deadline:
            left = deadline - (time.perf_counter() - t_start)
            progress(f"n={large}: {left:.0f} s left before the deadline")
        else:
            progress(f"n={large}: one solve at {max(threads)} threads")
        t0 = time.perf_counter()
        mesh = fm.Mesh.square(large)
        mesh_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        r = fm.solve(_scene(mesh), method="inexact", multigrid=multigrids[0])
        solve_s = time.perf_counter() - t0
        rows.append(
            {
                "n": large,
                "vertices": mesh.n_vertices,
                "threads": max(threads),
                "multigrid": multigrids[0],
                "large": True,
                "mesh_s": mesh_s,
                "solve_s": solve_s,
                "eta": float(r.eta),
                "levels": _levels(r),
                "peak_rss_mb": peak_rss_mb(),
                "bytes_per_vertex": peak_rss_mb() * 2**20 / mesh.n_vertices,
            }
        )
        progress(f"n={large}: mesh {mesh_s:.1f} s, solve {solve_s:.1f} s, eta {r.eta:.4e}")
    return rows


def main(argv=None):
    import numba

    t_start = time.perf_counter()
    p = parser(__doc__, repeat=1)
    p.add_argument("--threads", type=int, nargs="*", default=None, help="default: 1, 2 and all")
    p.add_argument("--multigrid", nargs="*", default=list(MULTIGRIDS), choices=MULTIGRIDS)
    p.add_argument("--scenes", nargs="*", default=["default"], choices=SCENES)
    p.add_argument("--deadline", type=float, default=None, help="seconds; later rows skipped")
    p.add_argument("--profile", action="store_true", help="cProfile one solve at the most threads")
    p.add_argument("--large", type=int, default=None, help="one larger n at the most threads")
    p.add_argument(
        "--adaptive", type=int, default=None, help="adaptive L-shape to the eta of uniform n"
    )
    p.add_argument(
        "--intermediate",
        nargs="+",
        default=["cg"],
        choices=["cg", "bound"],
        help="adaptive: what stops the intermediate meshes' CGs (fastmem.adapt.loop."
        "INTERMEDIATE_ALG); two values alternate in each round",
    )
    args = parse(p, argv)
    sizes = args.sizes or (QUICK_SIZES if args.quick else FULL_SIZES)
    most = numba.config.NUMBA_NUM_THREADS
    threads = sorted({t for t in (args.threads or [1, 2, most]) if 1 <= t <= most})
    touch = first_touch_ms_per_mb()  # before anything grows the process
    progress(f"fresh memory: {touch:.2f} ms per MiB to allocate and first write")
    payload = {
        "first_touch_ms_per_mib": touch,
        "parameters": {
            "sizes": sizes,
            "threads": threads,
            "multigrids": list(args.multigrid),
            "scenes": list(args.scenes),
            "deadline": args.deadline,
            "large": args.large,
            "adaptive": args.adaptive,
            "intermediate": list(args.intermediate),
            "quick": args.quick,
            "numba_num_threads": most,
            "schedule": "one process; thread counts from the most to the fewest; per count "
            "each multigrid: one solve (inexact, nested, the bound) and one fm.estimate; "
            "then repeat - 1 rounds alternating the order of the thread counts",
            "repeat": args.repeat,
        },
        "rows": run(
            sizes,
            threads,
            list(args.multigrid),
            args.deadline,
            args.profile,
            args.large,
            t_start,
            tuple(args.scenes),
            args.repeat,
            args.adaptive,
            args.intermediate,
        ),
    }
    finish("manycore", payload, args.quick)


if __name__ == "__main__":
    main()
