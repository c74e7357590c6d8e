"""Shared helpers: command line, machine info, repeated timing, JSON output, the Poisson unit.

Every benchmark script takes ``--quick`` (tiny sizes, seconds) and
``--results DIR`` (where JSON and PNG files go; default ``bench/results``, or
the environment variable ``FASTMEM_BENCH_RESULTS``).  Quick runs write
``<name>_quick.json`` so they never overwrite the full results ``<name>.json``.
"""

import argparse
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from datetime import datetime, timezone
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

#: Default folder of the result files.
RESULTS = Path(__file__).resolve().parent / "results"

#: Environment variable that redirects the result files (tests use a temporary folder).
RESULTS_ENV = "FASTMEM_BENCH_RESULTS"

#: Relative residual of the CG solve that defines the Poisson unit.
POISSON_TOL = 1e-8


# ------------------------------------------------------------------ command line


def parser(doc, repeat=3):
    """Argument parser with the options every benchmark shares."""
    p = argparse.ArgumentParser(
        description=doc.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--quick", action="store_true", help="tiny sizes, seconds")
    p.add_argument("--sizes", type=int, nargs="*", default=None, help="cells per side n")
    p.add_argument("--repeat", type=int, default=repeat, help="timed repetitions (after warm-up)")
    p.add_argument(
        "--results",
        type=Path,
        default=None,
        help=f"folder for JSON/PNG output (default bench/results or ${RESULTS_ENV})",
    )
    return p


def parse(p, argv=None):
    """Parse ``argv``; ``--results`` is exported so that worker subprocesses inherit it."""
    args = p.parse_args(argv)
    if args.results is not None:
        os.environ[RESULTS_ENV] = str(Path(args.results).resolve())
    return args


def results_dir():
    """Folder of the result files (``$FASTMEM_BENCH_RESULTS`` or ``bench/results``)."""
    env = os.environ.get(RESULTS_ENV)
    return Path(env) if env else RESULTS


def result_name(name, quick):
    """``<name>_quick`` for quick runs, ``<name>`` otherwise (quick never overwrites full)."""
    return f"{name}_quick" if quick else name


# ------------------------------------------------------------------ machine and threads


def blas_info():
    """BLAS libraries seen by threadpoolctl with their current thread counts."""
    import numpy  # noqa: F401  (load the BLAS libraries before asking)
    import scipy.sparse.linalg  # noqa: F401
    from threadpoolctl import threadpool_info

    keys = ("user_api", "internal_api", "num_threads", "version")
    return [{k: d.get(k) for k in keys} for d in threadpool_info()]


def machine_info():
    import numba

    from fastmem.config import get_threads

    versions = {}
    for pkg in (
        "fastmem",
        "numpy",
        "scipy",
        "numba",
        "pyamg",
        "scikit-fem",
        "h5py",
        "meshio",
        "threadpoolctl",
        "matplotlib",
    ):
        try:
            versions[pkg] = version(pkg)
        except PackageNotFoundError:
            versions[pkg] = None
    return {
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "cores": os.cpu_count(),
        "numba_threads": numba.get_num_threads(),
        "numba_threading_layer": _threading_layer(),
        "fastmem_threads": get_threads(),
        "blas_libraries": blas_info(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "versions": versions,
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }


def _threading_layer():
    import numba

    try:
        return numba.threading_layer()
    except ValueError:  # no parallel region run yet
        return None


# ------------------------------------------------------------------ timing and memory


def summary(times):
    """min/median/max/all of a list of seconds."""
    return {
        "min": min(times),
        "median": statistics.median(times),
        "max": max(times),
        "all": list(times),
    }


def timed(fn, repeat=3, warmup=1, min_seconds=0.0, max_repeat=50):
    """Run fn warmup + repeat times; return (last result, dict of min/median/max/all).

    ``min_seconds``: go on repeating (up to ``max_repeat`` runs) until the timed runs
    add up to this much, as ``timeit``'s autorange does: a run of a few tens of
    milliseconds is at the mercy of one hiccup of the machine in a median of three.
    """
    out = None
    for _ in range(warmup):
        out = fn()
    times = []
    while len(times) < repeat or (sum(times) < min_seconds and len(times) < max_repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, summary(times)


def timed_budget(fn, repeat=3, budget=60.0):
    """Like :func:`timed` without warm-up, but stop repeating once ``budget`` seconds are spent.

    For expensive runs whose JIT is already warm (a run on a tiny mesh first):
    at least one repetition, at most ``repeat``; the count is in ``len(all)``.
    """
    times = []
    out = None
    while len(times) < max(1, repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
        if sum(times) > budget:
            break
    return out, summary(times)


def peak_rss_mb():
    """Peak resident memory of this process so far, in MiB.

    Linux: ``VmHWM`` of /proc/self/status, the high-water mark of this
    process's own memory.  Not ``ru_maxrss``: Linux carries it over fork and
    exec, so a worker started by a process of 17 GB reported 17 GB from its
    first line (bench.adaptivity, 2026-11-23).  Elsewhere ``ru_maxrss``.
    """
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def first_touch_ms_per_mb(megabytes=256):
    """Milliseconds per MiB to allocate and first write fresh memory (``np.ones``).

    The cost of memory a process has not touched yet.  On an ordinary machine it is
    ~0.1-0.3 ms/MiB (the kernel zeroes the pages).  On the 2-core machine of
    2026-12-02 (a virtual machine) it measured 3-16 ms/MiB, varying from run to run:
    there every solve that grows the process's memory pays this rate, which weighs on a
    first solve more than on a second one and more than on the Poisson unit.  Call it
    at the start of a benchmark process, before other work has grown its memory.
    """
    import numpy as np

    t = time.perf_counter()
    block = np.ones(int(megabytes) * (1 << 20) // 8)
    seconds = time.perf_counter() - t
    del block
    return 1000.0 * seconds / megabytes


def process_times():
    """CPU seconds and minor page faults of this process so far (``getrusage``).

    Returns ``{"user_s", "system_s", "minor_faults"}``; subtract two readings to get
    a phase's share.  The system seconds of a solve are, on the benchmark VM, almost
    all first touches of new memory (:func:`first_touch_ms_per_mb`): the difference
    between a process's first solve and its second is there, not in fastmem's code.
    """
    r = resource.getrusage(resource.RUSAGE_SELF)
    return {"user_s": r.ru_utime, "system_s": r.ru_stime, "minor_faults": r.ru_minflt}


def times_since(before):
    """The change of :func:`process_times` since ``before`` (same keys)."""
    now = process_times()
    return {k: now[k] - before[k] for k in now}


def current_rss_mb():
    """Current resident memory of this process (Linux /proc; None elsewhere)."""
    try:
        with open("/proc/self/statm") as fh:
            pages = int(fh.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return None


def run_worker(module, args, timeout=None):
    """Run ``python -m <module> <args>`` and return the JSON object on its last stdout line.

    One process per mesh size, so that ``peak_rss_mb`` reported by the worker
    is the peak of that size alone.  The worker's stderr (progress) passes through.
    """
    cmd = [sys.executable, "-m", module, *map(str, args)]
    res = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, timeout=timeout, check=False)
    if res.returncode != 0:
        raise RuntimeError(f"worker {' '.join(cmd)} failed with exit code {res.returncode}")
    lines = [ln for ln in res.stdout.splitlines() if ln.strip()]
    return json.loads(lines[-1])


def emit_worker_result(row):
    """Print a worker's result as one JSON line on stdout (read by :func:`run_worker`)."""
    sys.stdout.write(json.dumps(row, default=_json_default) + "\n")
    sys.stdout.flush()


def fit_exponent(sizes, seconds):
    """Least-squares slope p of log(seconds) = p log(size) + c; None with < 2 points."""
    pts = [(math.log(s), math.log(t)) for s, t in zip(sizes, seconds, strict=True) if t > 0]
    if len(pts) < 2:
        return None
    mx = sum(x for x, _ in pts) / len(pts)
    my = sum(y for _, y in pts) / len(pts)
    sxx = sum((x - mx) ** 2 for x, _ in pts)
    if sxx == 0:
        return None
    return sum((x - mx) * (y - my) for x, y in pts) / sxx


# ------------------------------------------------------------------ the Poisson unit


def poisson_unit(mesh, repeat=3, warmup=1, blas_threads=None):
    """One pyamg smoothed-aggregation Poisson solve: the unit of solver cost.

    The P1 Laplacian of ``mesh`` restricted to the interior vertices
    (homogeneous Dirichlet conditions), without stored zeros, right-hand side
    ``f = 1`` (the lumped mass ``B``, exact for constant f), pyamg's default
    smoothed-aggregation
    hierarchy as preconditioner of CG, stopped at relative residual
    :data:`POISSON_TOL`.  BLAS threads are limited as in fastmem's solver
    phases (:func:`fastmem.config.blas_limits`, default 1).

    Returns a dict with ``setup_s``, ``solve_s`` and ``total_s`` (each
    min/median/max/all over ``repeat`` repetitions after ``warmup``), CG
    ``iterations``, the checked ``relative_residual`` of the returned
    solution, the hierarchy's ``levels`` and ``operator_complexity``, and
    ``seconds`` (the median of ``total_s``, the unit itself).
    """
    import numpy as np
    import pyamg

    from fastmem.config import blas_limits, get_threads
    from fastmem.fem.assembly import assemble_stiffness

    ii = mesh.interior_vertices
    a_ii = assemble_stiffness(mesh)[ii][:, ii].tocsr()
    # fastmem's matrices store the full vertex graph, also the couplings that vanish
    # across the hypotenuse of a right-triangle pair: 7 entries per row instead of 5
    # on a structured mesh.  pyamg's aggregation counts stored zeros as connections:
    # 25 CG iterations instead of 16 at n = 1024, a unit 15-20 % slower, and every
    # ratio to it flattered by as much (issue 33).  The unit is the zero-free matrix,
    # as a user would hand it to pyamg (the same iterations as pyamg.gallery.poisson).
    stored_zeros = int(a_ii.nnz)
    a_ii.eliminate_zeros()
    stored_zeros -= int(a_ii.nnz)
    b = np.ascontiguousarray(mesh.lumped_mass[ii])
    setup, solve, total = [], [], []
    with blas_limits(blas_threads):
        for rep in range(warmup + repeat):
            t0 = time.perf_counter()
            ml = pyamg.smoothed_aggregation_solver(a_ii)
            t1 = time.perf_counter()
            res = []
            x = ml.solve(b, tol=POISSON_TOL, accel="cg", residuals=res)
            t2 = time.perf_counter()
            if rep >= warmup:
                setup.append(t1 - t0)
                solve.append(t2 - t1)
                total.append(t2 - t0)
    rel = float(np.linalg.norm(b - a_ii @ x) / np.linalg.norm(b))
    out = {
        "unknowns": int(ii.size),
        "nnz": int(a_ii.nnz),
        "stored_zeros_dropped": stored_zeros,
        "tol": POISSON_TOL,
        "blas_threads": blas_threads if blas_threads is not None else get_threads()["blas"],
        "setup_s": summary(setup),
        "solve_s": summary(solve),
        "total_s": summary(total),
        "iterations": len(res) - 1,
        "relative_residual": rel,
        "levels": len(ml.levels),
        "operator_complexity": float(ml.operator_complexity()),
    }
    out["seconds"] = out["total_s"]["median"]
    return out


# ------------------------------------------------------------------ output


def _json_default(obj):
    import numpy as np

    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return float(obj)


def write_json(name, payload, quick=False):
    """Write ``<results>/<name>[_quick].json`` atomically with machine info; return its path."""
    out_dir = results_dir()
    out_dir.mkdir(parents=True, exist_ok=True)
    full = result_name(name, quick)
    path = out_dir / f"{full}.json"
    tmp = path.with_suffix(".json.tmp")
    payload = {"benchmark": name, "quick": bool(quick), "machine": machine_info(), **payload}
    tmp.write_text(json.dumps(payload, indent=2, default=_json_default))
    os.replace(tmp, path)
    return path


def finish(name, payload, quick):
    """Write the JSON and the figure of a benchmark; report both on stderr."""
    path = write_json(name, payload, quick)
    progress(f"wrote {path}")
    from bench import _plots

    png = _plots.figure(name, json.loads(path.read_text()), path.with_suffix(".png"))
    if png is not None:
        progress(f"wrote {png}")
    return path


def progress(msg):
    sys.stderr.write(msg + "\n")
    sys.stderr.flush()


def keep_sections(name, only, quick, payload):
    """With ``--only SECTION``: the earlier run's payload of ``name`` updated with ``payload``."""
    if only is None:
        return payload
    path = Path(results_dir()) / f"{result_name(name, quick)}.json"
    earlier = json.loads(path.read_text()) if path.exists() else {}
    return {**earlier, **payload}


def section_rows(payload, keys):
    """The rows of the sections ``keys`` of a payload, each tagged with its section."""
    return [{"section": key, **row} for key in keys for row in payload.get(key, [])]


def sectioned_parser(doc, sections, repeat=5):
    """:func:`parser` with ``--ref-levels`` and ``--only SECTION`` (benchmarks in sections)."""
    p = parser(doc, repeat=repeat)
    p.add_argument("--ref-levels", type=int, default=3)
    p.add_argument("--only", choices=sections, default=None)
    return p
