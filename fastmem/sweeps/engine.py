"""Sweep engine: the dask.distributed cluster of a sweep and the threads of its tasks.

Part of :mod:`fastmem.sweeps.study`: :func:`_connect` yields a Client on a new
LocalCluster, an address or a given Client, with the Numba threads each task
sets (:func:`_threads_by_host`).  dask is imported only when a cluster is used.

The LocalCluster is quiet: distributed logs 30-odd INFO lines while a cluster
starts and stops (scheduler and nanny addresses, worker registrations, a
dashboard link), which say nothing about the runs.  While a sweep's own cluster
or client is open the ``distributed`` logger passes WARNING and above only
(:func:`_quiet_logs`), also in the worker processes
(:data:`WORKER_LOG_LEVEL`), unless the user configured distributed's logging
in dask's config (e.g. ``DASK_LOGGING__DISTRIBUTED=info``).  The scheduler
serves no dashboard, and its small HTTP server (health checks) listens on a
free port of the loopback interface instead of 8787.
"""

from __future__ import annotations

import contextlib
import logging
import os

from ..errors import InputTypeError
from .grid import _require_dask

#: Level of distributed's loggers while a sweep's cluster or client is open.
QUIET_LEVEL = logging.WARNING

#: The environment variable (and value) that sets the level of the ``distributed``
#: logger in the worker processes of a sweep's LocalCluster, when distributed is
#: imported there (dask's config from the environment; a value the user set wins).
WORKER_LOG_LEVEL = ("DASK_DISTRIBUTED__LOGGING__DISTRIBUTED", "warning")

#: The scheduler's HTTP server: no dashboard, a free port on the loopback interface.
_SCHEDULER_HTTP = {"dashboard": False, "dashboard_address": "127.0.0.1:0"}


def _host(address: str) -> str:
    return address.split("://")[-1].rsplit(":", 1)[0]


@contextlib.contextmanager
def _restored_environ(keys):
    """Undo the environment variables a dask Nanny sets in this process (pre-spawn-environ)."""
    saved = {k: os.environ.get(k) for k in keys}
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


#: dask config keys through which a user chooses distributed's logging (docs/sweeps.md).
_LOGGING_KEYS = (
    "logging",
    "logging-file-config",
    "distributed.logging",
    "distributed.logging-file-config",
)


def _logging_configured(dask) -> bool:
    """Return whether the user configured distributed's logging (dask config or environment)."""
    return any(dask.config.get(key, None) is not None for key in _LOGGING_KEYS)


@contextlib.contextmanager
def _quiet_logs(enabled: bool = True, level: int = QUIET_LEVEL):
    """Raise the ``distributed`` logger to ``level`` (if it is below) for the block.

    Its child loggers without a level of their own follow it; records below
    ``level`` are dropped before any handler sees them, the root logger's
    included (so the ``fastmem`` command line does not print them as its own).
    Nothing changes when ``enabled`` is false.
    """
    log = logging.getLogger("distributed")
    old = log.level
    if enabled and (old == logging.NOTSET or old < level):
        log.setLevel(level)
    try:
        yield
    finally:
        log.setLevel(old)


@contextlib.contextmanager
def _connect(client, workers, numba_threads, max_retries):
    """Yield ``(distributed.Client, threads)``: a new LocalCluster, an address or a Client.

    The LocalCluster and the Client of an address are quiet (:func:`_quiet_logs`);
    a Client passed in is used as it is, logging included.
    """
    distributed = _require_dask()
    import dask

    # A ``with dask.config.set(...)`` block around the first import of distributed
    # removes distributed's whole config section when the block ends (set() puts the
    # key back to "absent"), and the next cluster fails with KeyError: 'nanny'.  Fill
    # in the defaults of every missing key (existing values are kept).
    if "distributed" not in dask.config.config:
        for defaults in dask.config.defaults:
            dask.config.update(dask.config.config, defaults, priority="old")
    quiet = not _logging_configured(dask)  # a user's logging config is kept as it is

    if client is None:
        cores = os.cpu_count() or 1
        n = cores if workers is None else workers
        per = max(1, cores // n) if numba_threads is None else numba_threads
        # Numba threads: numba.set_num_threads(per) in each task (_set_task_threads), not
        # NUMBA_NUM_THREADS: a worker whose main module imports fastmem may start Numba's
        # pool before a post-spawn variable is set, and a pre-spawn one leaks into this
        # process, whose next compilation would then refuse the changed value.
        pre_spawn = dict(dask.config.get("distributed.nanny.pre-spawn-environ"))
        environ = {k: v for k, v in pre_spawn.items() if k != "MALLOC_TRIM_THRESHOLD_"}
        if quiet:
            environ.setdefault(*WORKER_LOG_LEVEL)
        config = {
            "distributed.scheduler.allowed-failures": max_retries,
            "distributed.scheduler.worker-saturation": 1.0,
            # see _tune_malloc: not set at all in our workers (the whole dict is
            # replaced: a dotted key set to None would delete the nanny section
            # from dask's config when the block ends); quiet workers (WORKER_LOG_LEVEL)
            "distributed.nanny.pre-spawn-environ": environ,
            # no dashboard: nobody reads the workers' statistical profile (a thread
            # sampling the task's stack every 10 ms) or the 0.5 s system monitors, and the
            # 20 ms event-loop watchdog only warns.  Idle, they cost the client process
            # 48 ms/s and each worker 38 ms/s of CPU; with these 11-19 and 6-8 ms/s
            # (docs/sweeps.md, Threads and memory), CPU the solves get back.
            "distributed.worker.profile.enabled": False,
            "distributed.admin.system-monitor.interval": "2s",
            "distributed.admin.tick.interval": "200ms",
        }
        touched = [*environ, "PYTHONHASHSEED"]
        with _quiet_logs(quiet), _restored_environ(touched), dask.config.set(config):
            with (
                distributed.LocalCluster(
                    n_workers=n,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                    scheduler_kwargs=_SCHEDULER_HTTP,
                    # dask's default; False keeps a user's logging config in force
                    silence_logs=QUIET_LEVEL if quiet else False,
                ) as cluster,
                distributed.Client(cluster) as c,
            ):
                yield c, {"*": per}
        return
    if isinstance(client, str):
        with _quiet_logs(quiet), distributed.Client(client) as c:
            yield c, _threads_by_host(c, numba_threads)
        return
    if isinstance(client, distributed.Client):
        yield client, _threads_by_host(client, numba_threads)
        return
    raise InputTypeError(
        f"client must be None, a scheduler address or a distributed.Client, "
        f"got {type(client).__name__}"
    )


def _threads_by_host(client, numba_threads) -> dict:
    """Numba threads per task on each host: cores // task threads of its workers."""
    if numba_threads is not None:
        return {"*": numba_threads}
    cores = client.run(os.cpu_count)
    slots, host_cores = {}, {}
    for address, nthreads in client.nthreads().items():
        host = _host(address)
        slots[host] = slots.get(host, 0) + nthreads
        host_cores[host] = cores.get(address) or 1
    return {h: max(1, host_cores[h] // slots[h]) for h in slots}
