"""Sweep tasks: what a worker does for one run, and the table row of a run.

Part of :mod:`fastmem.sweeps.study`: :func:`_run_job` (the task) makes the scene,
solves it, writes its archive and the write log, and returns its row;
:func:`_valid_archive` decides whether a run is done.
"""

from __future__ import annotations

import json
import logging
import math
import os
import socket
import time
import traceback
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numba
import numpy as np

from ..errors import ArchiveError, InputTypeError
from ..fem.obstacle import Obstacle
from ..fem.scene import Scene
from ..io.archive import load
from ..memory import fix_mmap_threshold, keep_freed_memory, release_memory
from ..pipeline import solve
from .claims import CLAIMS_DIR, LEASE, acquire
from .engine import _host
from .grid import _FLOATS, _INTS, RUNS_DIR, _key

logger = logging.getLogger("fastmem.sweeps.study")


@dataclass(frozen=True)
class _Job:
    """Everything a worker needs for one run (pickled to the worker)."""

    factory: object
    params: dict
    name: str
    archive: str
    solve_options: dict
    log: str
    threads: dict  # host -> Numba threads; "*" -> fixed count for every host
    lease: float = LEASE  # seconds after which an untouched claim of another machine is stale


def _summary(result, name: str, params: dict, archive: str) -> dict:
    """Return the table row of a finished run, from its Result (in memory or loaded)."""
    totals = {} if result.estimate is None else result.estimate.totals
    levels = result.parameters.get("solver", {}).get("levels")
    if result.adaptivity is not None:
        cg = int(np.sum(result.adaptivity["inner"]))
    elif levels is not None:
        cg = int(sum(lv.get("inner", 0) for lv in levels))
    else:  # an obstacle result: one history row per Newton step
        cg = int(np.sum(result.history.get("inner", 0)))
    return {
        "run": name,
        "key": _key(params),
        "params": params,
        "status": "done",
        "converged": bool(result.converged),
        **{k: float(totals.get(k, math.nan)) for k in _FLOATS[:4]},
        "contact_fraction": result.contact_fraction,
        "newton_steps": int(result.n_newton),
        "cg_iterations": cg,
        "vertices": int(result.mesh.n_vertices),
        "triangles": int(result.mesh.n_triangles),
        "seconds": float(result.timings.get("total", 0.0) + result.timings.get("scene", 0.0)),
        "archive": archive,
        "error": "",
        "traceback": "",
    }


def _failed_row(name, params, error, trace="") -> dict:
    return {
        "run": name,
        "key": _key(params),
        "params": params,
        "status": "failed",
        "converged": None,
        **dict.fromkeys(_FLOATS, math.nan),
        **dict.fromkeys(_INTS, -1),
        "archive": "",
        "error": error,
        "traceback": trace,
    }


def _pending_row(name, params) -> dict:
    row = _failed_row(name, params, "")
    row["status"] = "pending"
    return row


def _valid_archive(path: Path, params: dict):
    """Return the Result of ``path`` if it exists, validates, records ``params``; else None."""
    if not path.is_file():
        return None
    try:
        result = load(path)
    except ArchiveError as exc:
        logger.warning("sweep: %s is not a valid archive, solving the run again: %s", path, exc)
        return None
    recorded = result.parameters.get("sweep", {}).get("params")
    if recorded != params:
        logger.warning("sweep: %s records other parameters (%s), solving again", path, recorded)
        return None
    return result


_MMAP_THRESHOLD = 32 << 20  # bytes: heap (not mmap) for arrays below 32 MiB
_malloc_tuned = []


def _tune_malloc() -> None:
    """Undo the cost of dask's ``MALLOC_TRIM_THRESHOLD_`` in this worker process (glibc).

    dask's Nanny sets ``MALLOC_TRIM_THRESHOLD_=65536`` in its workers.  Any
    such setting switches off glibc's dynamic mmap threshold, so that every
    array above 128 KiB is a fresh mmap whose pages fault in again: a solve at
    n = 256 took 1.5x as long (1.21 s instead of 0.80 s, one thread).  A fixed
    mmap threshold of 32 MiB gives the time back (0.83 s) and keeps the trimming.
    Once per process, and only when the variable is set and fastmem's own
    setting (:func:`fastmem.memory.keep_freed_memory`: no mmapped arrays at all,
    made at import) is switched off.
    """
    if _malloc_tuned or "MALLOC_TRIM_THRESHOLD_" not in os.environ or keep_freed_memory():
        return
    _malloc_tuned.append(True)
    fix_mmap_threshold(_MMAP_THRESHOLD)  # (a no-op where the C library is not glibc)


def _set_task_threads(threads: dict) -> None:
    """Numba threads of this task thread (``set_num_threads`` is per thread)."""
    _tune_malloc()

    count = threads.get("*")
    if count is None:
        try:
            from distributed import get_worker

            host = _host(get_worker().address)
        except (ImportError, ValueError):  # called outside a dask worker
            return
        count = threads.get(host, min(threads.values(), default=None))
    if count:
        numba.set_num_threads(max(1, min(int(count), numba.config.NUMBA_NUM_THREADS)))


def _log_write(log: str, job: _Job, seconds: float) -> None:
    """Append one JSON line to the write log (one ``write`` with O_APPEND: atomic)."""
    line = json.dumps(
        {
            "run": job.name,
            "time": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "seconds": round(seconds, 6),
        }
    )
    fd = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, (line + "\n").encode("utf-8"))
    finally:
        os.close(fd)


def _run_job(job: _Job) -> dict:
    """Solve one run and write its archive (the task a worker executes); return its row.

    A run whose archive is already valid is not solved again (a retry after a
    worker died once the archive was written), and a run claimed by a live task
    (fastmem.sweep_claims: an orphan of a dead client, still executing) is
    waited for instead of solved a second time.  Exceptions of the factory, the
    solve or the write are returned as a failed row with their text.
    """
    archive = Path(job.archive)
    rel = f"{RUNS_DIR}/{archive.name}"
    claims = archive.parent.parent / CLAIMS_DIR
    state, held = acquire(claims, job.name, lambda: _valid_archive(archive, job.params), job.lease)
    if state == "done":
        return _summary(held, job.name, job.params, rel) | {"solved": False}
    holder = [held]  # the claim released at the end (replaced if this one is superseded)
    try:
        return _solve_claimed(job, archive, rel, claims, holder)
    finally:
        holder[0].release()
        # the run's arrays are freed: give their memory back, so that the worker's
        # memory monitor (dask pauses a worker above 80 % of its limit) sees it go
        release_memory()


def _solve_claimed(job: _Job, archive: Path, rel: str, claims: Path, holder: list) -> dict:
    """Make, solve and save a run whose claim (``holder[0]``) this task holds; return its row."""
    _set_task_threads(job.threads)
    t0 = time.perf_counter()
    stage = getattr(job.factory, "__qualname__", "the scene factory")  # its own name
    try:
        scene = job.factory(**job.params)
        if not isinstance(scene, (Scene, Obstacle)):
            raise InputTypeError(
                f"{job.factory.__qualname__}() returned {type(scene).__name__}, not a "
                "fastmem.Scene or fastmem.Obstacle"
            )
        t_scene = time.perf_counter() - t0
        stage = "solve"
        result = solve(scene, **job.solve_options)
        result.timings["scene"] = t_scene
        result.parameters["sweep"] = {"params": job.params, "run": job.name}
        stage = "save"
        if holder[0].superseded():  # our heartbeat stalled beyond the lease: wait for the owner
            holder[0].release()
            state, held = acquire(
                claims, job.name, lambda: _valid_archive(archive, job.params), job.lease
            )
            if state == "done":
                return _summary(held, job.name, job.params, rel) | {"solved": False}
            holder[0] = held
        done = _valid_archive(archive, job.params)  # written meanwhile by an orphaned task?
        if done is not None:
            return _summary(done, job.name, job.params, rel) | {"solved": False}
        result.save(archive)
    except Exception as exc:
        text = f"{type(exc).__name__} in {stage}: {exc}"
        return _failed_row(job.name, job.params, text, traceback.format_exc())
    _log_write(job.log, job, time.perf_counter() - t0)
    return _summary(result, job.name, job.params, rel) | {"solved": True}
