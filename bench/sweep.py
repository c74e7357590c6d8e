"""Parameter sweeps on Dask: a LocalCluster of 2 workers against a serial loop, same run.

The study: ``fastmem.sweeps.study.standard_scene`` (the default data of ``fastmem
run``, docs/method.md §8) at n = 256 over 8 stiffness ratios mu2 x 4 gaps g =
32 scenes, each solved with ``fm.solve`` defaults (inexact Newton-min, nested
iteration, guaranteed bound) and written as an archive.  ``--quick``: 8 scenes
at n = 32.

* **Serial loop**: ``for params in runs: fm.solve(standard_scene(**params)
  ).save(...)`` in a fresh process per repetition (after a warm-up solve on a
  tiny mesh), with fastmem's default threads (all cores for Numba, one for
  BLAS): what a user writes without Dask.  Not in this process: the
  cluster's scheduler and nannies live here, and their event loop took 10-15%
  of a loop run beside them.
* **Sweep**: ``fm.sweep(standard_scene, grid, out, client=c)`` on a
  LocalCluster configured as ``fm.sweep(client=None, workers=2)`` configures
  it (2 processes, 1 task thread each, Numba threads = cores // 2), into a
  fresh study folder each time.  The cluster is started once
  (``cluster_start_s``); its first sweep runs on cold workers (``first``:
  imports and JIT cache loading in each worker), the later ones are warm.

The repetitions alternate serial loop and warm sweep (both see the same
machine state).  Headline: ``throughput_ratio`` = median serial time / median
warm sweep time (target >= 1.7 on 2 cores); also the ratio of the first sweep
(with and without the cluster start).

Scheduler overhead per task, three ways: ``idle_per_task_ms`` = (sweep wall
time x workers - the seconds the tasks spent making, solving and saving their
scene, from the write log) / tasks: every cost of the sweep that is not a
solve (scheduling, the client's index writes, the tail where one worker
waits; target <= 50 ms); ``noop_latency_ms``: median round trip of one no-op
task (submit -> result, nothing queued); ``noop_throughput_ms``: wall time of
many no-op tasks at once / their number.

Ceiling without Dask: a **pool** of 2 plain processes (``multiprocessing``,
spawned, 1 Numba thread and BLAS 1 each, as dask's workers; runs handed out one
at a time), solving and saving the same 32 runs, in the same repetitions
(fresh pool each, started outside the timing).  ``ceiling_ratio`` = serial /
pool is what two single-threaded processes give on this machine with no
scheduler at all; ``sweep_vs_pool`` = pool / sweep is Dask's efficiency against
it.  Per-task split of the sweeps (from the archives' timings and the write
log): scene factory, assembly, coarsening, solve (Newton + estimate), and the
rest of the task (claim, archive checks, write + fsync, log); CPU seconds of
the client process (client, scheduler and nannies of the LocalCluster) and of
the workers during each sweep; and the client's index rewrite (32 rows), timed
alone.

Memory: ``VmHWM`` (peak resident set) of each worker process after all
sweeps, and of the serial loop's process.  Correctness: every sweep table
is compared with the serial results (eta, contact fraction, Newton steps,
CG iterations, max |u1 - u1| of the archives) and recorded; the workers
run one Numba thread, the serial loop two, so round-off may differ.

    python -m bench.sweep [--quick] [--repeat 3] [--n 256]
"""

import argparse
import json
import multiprocessing
import os
import statistics
import tempfile
import time
from pathlib import Path

from bench._common import (
    emit_worker_result,
    finish,
    parse,
    parser,
    peak_rss_mb,
    poisson_unit,
    progress,
    run_worker,
    summary,
)

FULL = {"n": 256, "mu2": [0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 8.0], "g": [0.0, 0.05, 0.1, 0.2]}
QUICK = {"n": 32, "mu2": [0.5, 1.0, 2.0, 4.0], "g": [0.0, 0.1]}
WORKERS = 2
NOOPS = 400


def _noop(i):
    return i


def _vmhwm_mb():
    """Peak resident memory of the calling process (run on each worker)."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return None


_ONE_THREAD_BLAS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _pool_init():
    """A pool process as dask gives its workers: 1 Numba thread; warm (JIT caches)."""
    import numba

    import fastmem as fm
    from fastmem.sweeps import study as sweeps

    numba.set_num_threads(1)
    fm.solve(sweeps.standard_scene(n=8))


def _pid(_):
    return os.getpid()


def _pool_run(job):
    """Solve and save one run in a pool process; return its seconds."""
    import fastmem as fm
    from fastmem.sweeps import study as sweeps

    folder, params = job
    t0 = time.perf_counter()
    fm.solve(sweeps.standard_scene(**params)).save(Path(folder) / f"{sweeps.run_name(params)}.h5")
    return time.perf_counter() - t0


def pool_loop(runs, folder, workers):
    """The runs on a fresh pool of plain processes (no Dask); return wall time and task times."""
    from fastmem.sweeps.study import _restored_environ

    with _restored_environ(_ONE_THREAD_BLAS):
        os.environ.update(dict.fromkeys(_ONE_THREAD_BLAS, "1"))  # inherited by the spawned pool
        pool = multiprocessing.get_context("spawn").Pool(workers, initializer=_pool_init)
    folder.mkdir()
    with pool:
        pids = set()
        while len(pids) < workers:  # every process has finished its initializer
            pids.update(pool.map(_pid, range(workers), chunksize=1))
        t0 = time.perf_counter()
        seconds = pool.map(_pool_run, [(str(folder), p) for p in runs], chunksize=1)
        wall = time.perf_counter() - t0
    return wall, seconds


def _cpu_seconds():
    """User + system CPU seconds of the calling process (run on each worker, and here)."""
    import psutil

    t = psutil.Process().cpu_times()
    return t.user + t.system


def task_split(table, log):
    """Median seconds per task: scene, assembly, coarsening, solve (+ estimate), rest of task."""
    import fastmem as fm

    task = {e["run"]: e["seconds"] for e in log}
    parts = {k: [] for k in ("scene", "assembly", "coarsening", "solve", "rest_of_task", "task")}
    for row in table.itertuples():
        t = fm.load(row.archive).timings
        parts["scene"].append(t["scene"])
        for k in ("assembly", "coarsening", "solve"):
            parts[k].append(t.get(k, 0.0))
        parts["rest_of_task"].append(task[row.run] - t["scene"] - t["total"])
        parts["task"].append(task[row.run])
    return {k: statistics.median(v) for k, v in parts.items()}


def index_write_ms(table, folder, repeat=20):
    """Milliseconds of one rewrite of the study's index (the client's work after each run)."""
    from fastmem.sweeps.index import _read_index, _write_index

    attrs, rows = _read_index(folder)
    t0 = time.perf_counter()
    for _ in range(repeat):
        _write_index(folder, attrs["spec"], rows, {"running": 0, "active": False})
    return 1000.0 * (time.perf_counter() - t0) / repeat


def serial_loop(runs, folder):
    """Solve and save every run in this process; return the seconds of the whole loop."""
    import fastmem as fm
    from fastmem.sweeps import study as sweeps

    t0 = time.perf_counter()
    for params in runs:
        result = fm.solve(sweeps.standard_scene(**params))
        result.save(folder / f"{sweeps.run_name(params)}.h5")
    return time.perf_counter() - t0


def serial_worker(grid, folder):
    """``--serial-worker``: warm up, then time the serial loop in this fresh process."""
    import fastmem as fm
    from fastmem.sweeps import study as sweeps

    t0 = time.perf_counter()
    fm.solve(sweeps.standard_scene(n=8))  # JIT caches (excluded from the loop)
    warmup = time.perf_counter() - t0
    seconds = serial_loop(sweeps.expand_grid(grid), Path(folder))
    emit_worker_result({"seconds": seconds, "warmup_s": warmup, "peak_rss_mb": peak_rss_mb()})


def serial(grid, folder):
    """The serial loop in its own process (not beside the cluster's scheduler and nannies)."""
    folder.mkdir()
    return run_worker("bench.sweep", ["--serial-worker", str(folder), json.dumps(grid)])


def reference(runs, folder):
    """The serial results, read from the archives of a serial loop."""
    import fastmem as fm
    from fastmem.sweeps import study as sweeps

    out = {}
    for params in runs:
        name = sweeps.run_name(params)
        result = fm.load(folder / f"{name}.h5")
        out[name] = {
            "eta": result.eta,
            "contact_fraction": result.contact_fraction,
            "newton_steps": result.n_newton,
            "cg_iterations": sum(lv["inner"] for lv in result.parameters["solver"]["levels"]),
            "u1": result.u1,
        }
    return out


def run_sweep(client, grid, folder):
    """One sweep into a fresh folder; return its wall time, table, write log and CPU seconds."""
    import fastmem as fm
    from fastmem.sweeps import study as sweeps

    workers0, client0 = client.run(_cpu_seconds), _cpu_seconds()
    t0 = time.perf_counter()
    table = fm.sweep(sweeps.standard_scene, grid, folder, client=client)
    wall = time.perf_counter() - t0
    cpu = {
        "client_process": _cpu_seconds() - client0,
        "workers": sum(client.run(_cpu_seconds).values()) - sum(workers0.values()),
    }
    log = [json.loads(ln) for ln in (folder / sweeps.WRITE_LOG).read_text().splitlines()]
    return wall, table, log, cpu


def compare(table, expected):
    """Largest differences between a sweep table and the serial results."""
    import numpy as np

    import fastmem as fm

    worst = {"eta_rel": 0.0, "contact_fraction": 0.0, "u1_abs": 0.0, "steps_differ": 0}
    for row in table.itertuples():
        ref = expected[row.run]
        worst["eta_rel"] = max(worst["eta_rel"], abs(row.eta - ref["eta"]) / ref["eta"])
        worst["contact_fraction"] = max(
            worst["contact_fraction"], abs(row.contact_fraction - ref["contact_fraction"])
        )
        same = (row.newton_steps, row.cg_iterations) == (ref["newton_steps"], ref["cg_iterations"])
        worst["steps_differ"] += int(not same)
        u1 = fm.load(row.archive).u1
        worst["u1_abs"] = max(worst["u1_abs"], float(np.abs(u1 - ref["u1"]).max()))
    worst["all_done"] = bool((table.status == "done").all())
    return worst


def sweep_row(kind, wall, table, log, workers, cpu):
    busy = sum(entry["seconds"] for entry in log)
    tasks = len(table)
    by_pid = {}
    for entry in log:
        by_pid.setdefault(entry["pid"], []).append(entry["seconds"])
    later = [s for v in by_pid.values() for s in v[1:]]
    return {
        "kind": kind,
        "seconds": wall,
        "tasks": tasks,
        "solved": len(log),
        "task_seconds": summary([e["seconds"] for e in log]),
        "busy_fraction": busy / (wall * workers),
        "idle_per_task_ms": 1000.0 * (wall * workers - busy) / tasks,
        "first_task_per_worker_s": [v[0] for v in by_pid.values()],
        "later_tasks_median_s": statistics.median(later) if later else None,
        "cpu_s": cpu,
        "task_split_median_s": task_split(table, log),
    }


def noop_overhead(client):
    """Round trip of one no-op task, and cost per task of many at once."""
    latency = []
    for i in range(50):
        t0 = time.perf_counter()
        client.submit(_noop, i, pure=False).result()
        latency.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    client.gather(client.map(_noop, range(NOOPS), pure=False))
    many = time.perf_counter() - t0
    return {
        "noop_latency_ms": 1000.0 * statistics.median(latency),
        "noop_throughput_ms": 1000.0 * many / NOOPS,
        "noops": NOOPS,
    }


def main(argv=None):
    import numba

    import fastmem as fm
    from fastmem.sweeps import study as sweeps

    p = parser(__doc__)
    p.add_argument("--n", type=int, default=None, help="cells per side (default 256, quick 32)")
    p.add_argument("--serial-worker", nargs=2, default=None, help=argparse.SUPPRESS)
    args = parse(p, argv)
    if args.serial_worker:
        serial_worker(json.loads(args.serial_worker[1]), args.serial_worker[0])
        return
    spec = dict(QUICK if args.quick else FULL)
    if args.n:
        spec["n"] = args.n
    repeat = 1 if args.quick and args.repeat == p.get_default("repeat") else args.repeat
    grid = {"n": spec["n"], "mu2": spec["mu2"], "g": spec["g"]}
    runs = sweeps.expand_grid(grid)
    progress(f"sweep: {len(runs)} scenes at n = {spec['n']}, {WORKERS} workers, {repeat} reps")

    t0 = time.perf_counter()
    fm.solve(sweeps.standard_scene(n=8))  # JIT caches of this process (excluded)
    warmup_s = time.perf_counter() - t0
    unit = poisson_unit(fm.Mesh.square(spec["n"]))

    rows, serial_times, warm_times, pool_times = [], [], [], []
    with tempfile.TemporaryDirectory(prefix="fastmem-bench-sweep-") as tmp:
        tmp = Path(tmp)
        first_serial = serial(grid, tmp / "serial-0")
        seconds = first_serial["seconds"]
        serial_peak = first_serial["peak_rss_mb"]
        reference_runs = reference(runs, tmp / "serial-0")
        serial_times.append(seconds)
        rows.append({"kind": "serial", "rep": 0, "tasks": len(runs), **first_serial})
        progress(f"sweep: serial loop {seconds:.2f} s ({seconds / len(runs):.3f} s per scene)")

        t0 = time.perf_counter()
        with sweeps._connect(None, WORKERS, None, 3) as (client, threads):
            start = time.perf_counter() - t0
            progress(f"sweep: LocalCluster of {WORKERS} workers started in {start:.2f} s")
            wall, table, log, cpu = run_sweep(client, grid, tmp / "sweep-first")
            first = sweep_row("sweep-first", wall, table, log, WORKERS, cpu)
            first["check"] = compare(table, reference_runs)
            rows.append(first)
            progress(f"sweep: first sweep (cold workers) {wall:.2f} s")
            for rep in range(repeat):
                if rep:  # rep 0's serial loop ran before the cluster started
                    out = serial(grid, tmp / f"serial-{rep}")
                    serial_times.append(out["seconds"])
                    rows.append({"kind": "serial", "rep": rep, "tasks": len(runs), **out})
                pool_wall, pool_seconds = pool_loop(runs, tmp / f"pool-{rep}", WORKERS)
                pool_times.append(pool_wall)
                rows.append(
                    {
                        "kind": "pool",
                        "rep": rep,
                        "tasks": len(runs),
                        "seconds": pool_wall,
                        "task_seconds": summary(pool_seconds),
                    }
                )
                wall, table, log, cpu = run_sweep(client, grid, tmp / f"sweep-{rep}")
                row = sweep_row("sweep-warm", wall, table, log, WORKERS, cpu)
                row["rep"] = rep
                row["check"] = compare(table, reference_runs)
                rows.append(row)
                warm_times.append(wall)
                progress(
                    f"sweep: rep {rep}: serial {serial_times[-1]:.2f} s, pool {pool_wall:.2f} s, "
                    f"sweep {wall:.2f} s, "
                    f"ratio {serial_times[-1] / wall:.2f}, idle/task {row['idle_per_task_ms']:.1f} "
                    f"ms, eta rel diff {row['check']['eta_rel']:.1e}"
                )
            index_ms = index_write_ms(table, tmp / f"sweep-{repeat - 1}")
            noop = noop_overhead(client)
            workers_mem = client.run(_vmhwm_mb)

    serial_med = statistics.median(serial_times)
    warm_med = statistics.median(warm_times)
    warm_rows = [r for r in rows if r["kind"] == "sweep-warm"]
    pool_med = statistics.median(pool_times)
    split = {
        k: statistics.median(r["task_split_median_s"][k] for r in warm_rows)
        for k in warm_rows[0]["task_split_median_s"]
    }
    result = {
        "throughput_ratio": serial_med / warm_med,
        "ceiling_ratio": serial_med / pool_med,
        "sweep_vs_pool": pool_med / warm_med,
        "pool_s": summary(pool_times),
        "pool_task_mean_s": statistics.median(
            r["task_seconds"]["median"] for r in rows if r["kind"] == "pool"
        ),
        "task_split_median_s": split,
        "client_process_cpu_s_per_sweep": statistics.median(
            r["cpu_s"]["client_process"] for r in warm_rows
        ),
        "worker_cpu_s_per_task": statistics.median(
            r["cpu_s"]["workers"] / r["tasks"] for r in warm_rows
        ),
        "index_write_ms": index_ms,
        "throughput_ratio_first_sweep": serial_med / first["seconds"],
        "throughput_ratio_first_with_cluster_start": serial_med / (first["seconds"] + start),
        "serial_s": summary(serial_times),
        "sweep_warm_s": summary(warm_times),
        "sweep_first_s": first["seconds"],
        "cluster_start_s": start,
        "idle_per_task_ms": summary([r["idle_per_task_ms"] for r in warm_rows]),
        "idle_per_task_ms_first": first["idle_per_task_ms"],
        **noop,
        "first_task_per_worker_s": first["first_task_per_worker_s"],
        "later_tasks_median_s": first["later_tasks_median_s"],
        "worker_peak_rss_mb": sorted(workers_mem.values()),
        "serial_process_peak_rss_mb": serial_peak,
        "scene_seconds_in_poisson_units": serial_med / len(runs) / unit["seconds"],
        "max_eta_rel_diff": max(r["check"]["eta_rel"] for r in rows if "check" in r),
        "max_u1_abs_diff": max(r["check"]["u1_abs"] for r in rows if "check" in r),
        "all_done": all(r["check"]["all_done"] for r in rows if "check" in r),
    }
    progress(
        f"sweep: ceiling (serial / pool of {WORKERS} plain processes) "
        f"{result['ceiling_ratio']:.2f}, sweep / pool {result['sweep_vs_pool']:.3f}; task split "
        + ", ".join(f"{k} {v:.3f}" for k, v in split.items())
        + f" s; client process CPU {result['client_process_cpu_s_per_sweep']:.2f} s per sweep"
    )
    progress(
        f"sweep: throughput ratio {result['throughput_ratio']:.2f} (first sweep "
        f"{result['throughput_ratio_first_sweep']:.2f}, with cluster start "
        f"{result['throughput_ratio_first_with_cluster_start']:.2f}); idle per task "
        f"{result['idle_per_task_ms']['median']:.1f} ms; no-op latency "
        f"{noop['noop_latency_ms']:.1f} ms, throughput {noop['noop_throughput_ms']:.2f} ms/task; "
        f"worker peak RSS {', '.join(f'{m:.0f}' for m in result['worker_peak_rss_mb'])} MB"
    )
    payload = {
        "parameters": {
            "grid": grid,
            "scenes": len(runs),
            "workers": WORKERS,
            "threads_per_worker": 1,
            # set by each task (numba.set_num_threads is per thread)
            "worker_numba_threads_per_task": threads,
            "serial_numba_threads": numba.get_num_threads(),
            "repeat": repeat,
            "quick": args.quick,
            "cores": os.cpu_count(),
            "solve_options": "fm.solve defaults (inexact, nested, bound)",
            "warmup_s": warmup_s,
        },
        "poisson_unit": unit,
        "result": result,
        "rows": rows,
    }
    finish("sweep", payload, args.quick)


if __name__ == "__main__":
    main()
