"""Sweep engine: the dask.distributed cluster of a sweep and the threads of its tasks.

Part of :mod:`fastmem.sweeps.study`: :func:`_connect` yields a Client on a new
LocalCluster, an address or a given Client, with the Numba threads each task
sets (:func:`_threads_by_host`).  dask is imported only when a cluster is used.
"""

from __future__ import annotations

import contextlib
import os

from ..errors import InputTypeError
from .grid import _require_dask


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


@contextlib.contextmanager
def _connect(client, workers, numba_threads, max_retries):
    """Yield ``(distributed.Client, threads)``: a new LocalCluster, an address or a Client."""
    distributed = _require_dask()
    import dask

    # A ``with dask.config.set(...)`` block around the first import of distributed
    # removes distributed's whole config section when the block ends (set() puts the
    # key back to "absent"), and the next cluster fails with KeyError: 'nanny'.  Fill
    # in the defaults of every missing key (existing values are kept).
    if "distributed" not in dask.config.config:
        for defaults in dask.config.defaults:
            dask.config.update(dask.config.config, defaults, priority="old")

    if client is None:
        cores = os.cpu_count() or 1
        n = cores if workers is None else workers
        per = max(1, cores // n) if numba_threads is None else numba_threads
        # Numba threads: numba.set_num_threads(per) in each task (_set_task_threads), not
        # NUMBA_NUM_THREADS: a worker whose main module imports fastmem may start Numba's
        # pool before a post-spawn variable is set, and a pre-spawn one leaks into this
        # process, whose next compilation would then refuse the changed value.
        pre_spawn = dict(dask.config.get("distributed.nanny.pre-spawn-environ"))
        config = {
            "distributed.scheduler.allowed-failures": max_retries,
            "distributed.scheduler.worker-saturation": 1.0,
            # see _tune_malloc: not set at all in our workers (the whole dict is
            # replaced: a dotted key set to None would delete the nanny section
            # from dask's config when the block ends)
            "distributed.nanny.pre-spawn-environ": {
                k: v for k, v in pre_spawn.items() if k != "MALLOC_TRIM_THRESHOLD_"
            },
            # no dashboard: nobody reads the workers' statistical profile (a thread
            # sampling the task's stack every 10 ms) or the 0.5 s system monitors, and the
            # 20 ms event-loop watchdog only warns.  Idle, they cost the client process
            # 48 ms/s and each worker 38 ms/s of CPU; with these 11-19 and 6-8 ms/s
            # (docs/sweeps.md, Threads and memory), CPU the solves get back.
            "distributed.worker.profile.enabled": False,
            "distributed.admin.system-monitor.interval": "2s",
            "distributed.admin.tick.interval": "200ms",
        }
        touched = [*pre_spawn, "PYTHONHASHSEED"]
        with _restored_environ(touched), dask.config.set(config):
            with (
                distributed.LocalCluster(
                    n_workers=n,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                ) as cluster,
                distributed.Client(cluster) as c,
            ):
                yield c, {"*": per}
        return
    if isinstance(client, str):
        with distributed.Client(client) as c:
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
