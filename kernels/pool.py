"""Parallel loops over index ranges: serial Numba kernels run by a pool of Python threads.

Why not ``parallel=True``: Numba's parallel compiler (parfors) is the largest
part of fastmem's first-run compile time.  The flux reconstruction kernel took
21 s to compile with ``prange`` against 9 s as a serial kernel over an index
range (``bench/coldstart.py``), at the same run-time speed; the mesh
refinement's three ``prange`` kernels (longest edges, newest-vertex bisection,
the derived edge topology), the last ones, took 9.6–11.6 s against 4.6 s for their
serial range kernels (2026-12-02, 2 cores).  A kernel written
as ``kernel(lo, hi, ...)`` over ``range(lo, hi)`` with ``nogil=True`` (every
fastmem kernel, :mod:`._jit`) releases the GIL, so Python threads run its
chunks truly in parallel.

Determinism: the ranges are fixed by the length and the thread count; each
chunk writes only its own rows, so the result does not depend on the number
of threads or on the scheduling.

The pool is created on first use and sized by :func:`numba.get_num_threads`
(which :func:`fastmem.set_threads` and ``NUMBA_NUM_THREADS`` control); a
forked child process starts without it (a thread pool does not survive
``fork``).
"""

import concurrent.futures
import itertools
import os
import threading

import numba
import numpy as np

__all__ = [
    "GRAIN",
    "n_threads",
    "parallel_for",
    "ranges",
    "run_pieces",
    "run_ranges",
    "worker_pool",
    "zeros",
]

#: fewest loop iterations per thread: shorter loops run in the calling thread
#: (handing a chunk to a pool thread costs tens of microseconds)
GRAIN = 4096

_LOCK = threading.Lock()
_POOL = None
_POOL_SIZE = 0


def _forget_pool():
    global _LOCK, _POOL, _POOL_SIZE
    _LOCK = threading.Lock()  # a fork while another thread held it would leave it held
    _POOL = None
    _POOL_SIZE = 0


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def n_threads() -> int:
    """Threads a parallel loop of the calling thread may use (``numba.get_num_threads``)."""
    return max(1, int(numba.get_num_threads()))


def ranges(n: int, threads: int, grain: int) -> list:
    """Split ``range(n)`` into at most ``threads`` contiguous chunks of at least ``grain``.

    Returns a list of ``(lo, hi)`` pairs covering ``range(n)`` in order (one
    pair ``(0, n)`` when ``n`` is small).
    """
    k = max(1, min(int(threads), int(n) // max(1, int(grain))))
    return [(n * j // k, n * (j + 1) // k) for j in range(k)]


def worker_pool():
    """Return the shared pool (at least :func:`n_threads` threads), for work beside the caller's.

    For NumPy work that releases the GIL (:func:`fastmem.fem.callables.callable_integrals`
    forms a block's integrals there while the caller evaluates the next block).
    """
    return _pool(n_threads())


def _pool(size: int):
    # Sized once for the most threads Numba allows (``set_threads`` cannot go beyond
    # NUMBA_NUM_THREADS; the executor starts its threads only when work needs them), so
    # the pool never grows: replacing it would shut down a pool that another thread (a
    # pipelined callable pass, a run_ranges in another thread) is about to submit to.
    global _POOL, _POOL_SIZE
    with _LOCK:
        if _POOL is None or _POOL_SIZE < size:
            if _POOL is not None:  # only when asked beyond NUMBA_NUM_THREADS
                _POOL.shutdown(wait=False)
            size = max(int(size), int(numba.config.NUMBA_NUM_THREADS))
            _POOL = concurrent.futures.ThreadPoolExecutor(
                max_workers=size, thread_name_prefix="fastmem-kernel"
            )
            _POOL_SIZE = size
        return _POOL


def run_ranges(fn, chunks) -> None:
    """Call ``fn(lo, hi)`` for every pair of ``chunks``, in parallel threads.

    The calling thread runs the first chunk itself; the others go to the pool.
    Exceptions of any chunk are raised here, after every chunk has finished.
    """
    if len(chunks) <= 1:
        for lo, hi in chunks:
            fn(lo, hi)
        return
    pool = _pool(len(chunks) - 1)
    futures = [pool.submit(fn, lo, hi) for lo, hi in chunks[1:]]
    try:
        fn(*chunks[0])
    finally:
        errors = [f.exception() for f in futures]
    for err in errors:
        if err is not None:
            raise err


def run_pieces(fn, pieces, threads: int) -> None:
    """Call ``fn(lo, hi)`` for every pair of ``pieces``, handed out one at a time to ``threads``.

    Dynamic scheduling for loops whose chunks cost unequal time (or run on a core
    the machine has slowed down): each thread takes the next piece from a shared
    counter until none is left.  Each piece is computed by the same operations
    whichever thread takes it, so results do not depend on the scheduling as long
    as ``fn`` writes only what no other piece writes.
    """
    pieces = list(pieces)
    threads = max(1, min(int(threads), len(pieces)))
    if threads == 1:
        for lo, hi in pieces:
            fn(lo, hi)
        return
    counter = itertools.count()  # next() of a count is atomic under the GIL

    def worker(_lo, _hi):
        k = next(counter)
        while k < len(pieces):
            fn(*pieces[k])
            k = next(counter)

    run_ranges(worker, [(0, 0)] * threads)


def parallel_for(kernel, n: int, *args, grain: int | None = None, pieces: int = 1) -> None:
    """Run the serial kernel ``kernel(lo, hi, *args)`` over ``range(n)`` in chunks.

    ``kernel`` must release the GIL (``nogil=True``) and write, for index k,
    only what no other index writes (the contract of a ``prange`` loop).
    ``grain``: fewest indices per chunk (default :data:`GRAIN`).  ``pieces``:
    chunks per thread; above 1 they are handed out one at a time
    (:func:`run_pieces`), for loops whose indices cost unequal time.
    """
    grain = GRAIN if grain is None else grain
    threads = n_threads()
    if pieces > 1 and threads > 1:
        run_pieces(
            lambda lo, hi: kernel(lo, hi, *args), ranges(n, pieces * threads, grain), threads
        )
        return
    run_ranges(lambda lo, hi: kernel(lo, hi, *args), ranges(n, threads, grain))


#: fewest elements per thread of :func:`zeros` (smaller arrays: the calling thread alone)
TOUCH_GRAIN = 1 << 20


def zeros(shape, dtype) -> np.ndarray:
    """Return a new zero-filled array whose pages are first touched by the pool's threads.

    For the large arrays that a serial kernel then fills in a scattered order.  The
    first touch of new memory is what costs: on the 2-vCPU VM of the benchmarks,
    guest memory that was freed for a few seconds is handed back to the host (free
    page reporting) and faulting it in again costs about 2.3 s per GB of system time
    in one thread, 1.2 s per GB in two (the faults of two vCPUs run concurrently);
    memory faulted recently costs about 0.07 s per GB.  ``np.zeros`` (calloc) would
    defer every fault to the single thread of the kernel.  NumPy's assignment
    releases the GIL, so the chunks are written in parallel.
    """
    a = np.empty(shape, dtype)
    flat = a.reshape(-1)

    def zero(lo, hi):
        flat[lo:hi] = 0

    run_ranges(zero, ranges(flat.size, n_threads(), TOUCH_GRAIN))
    return a
