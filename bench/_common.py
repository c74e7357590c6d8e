"""Shared helpers: machine info, repeated timing, JSON output."""

import json
import os
import platform
import resource
import statistics
import sys
import time
from datetime import datetime, timezone
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def machine_info():
    import numba

    from fastmem.config import get_threads

    versions = {}
    for pkg in ("fastmem", "numpy", "scipy", "numba", "pyamg", "scikit-fem", "h5py", "meshio"):
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
        "versions": versions,
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }


def _threading_layer():
    import numba

    try:
        return numba.threading_layer()
    except ValueError:  # no parallel region run yet
        return None


def timed(fn, repeat=3, warmup=1):
    """Run fn warmup + repeat times; return (last result, dict of min/median/max/all)."""
    out = None
    for _ in range(warmup):
        out = fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, {
        "min": min(times),
        "median": statistics.median(times),
        "max": max(times),
        "all": times,
    }


def peak_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def write_json(name, payload):
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / f"{name}.json"
    tmp = path.with_suffix(".json.tmp")
    payload = {"benchmark": name, "machine": machine_info(), **payload}
    tmp.write_text(json.dumps(payload, indent=2, default=float))
    os.replace(tmp, path)
    return path


def progress(msg):
    sys.stderr.write(msg + "\n")
    sys.stderr.flush()
