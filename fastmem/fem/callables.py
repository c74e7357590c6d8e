"""User callables ``f(x, y)``: checked evaluation and the blocked quadrature pass.

The lowest layer of the load data: :func:`fastmem.fem.assembly.assemble_load`
(callable loads), :func:`fastmem.fem.loaddata.integrals` (load vector, flux
moments and oscillation from one evaluation) and the scene (boundary values
``g``) all evaluate user callables here.  It imports neither of them (the
dependency goes one way: loaddata -> assembly -> callables).
"""

from __future__ import annotations

import concurrent.futures
import logging
import threading

import numpy as np

from ..errors import DataError
from ..kernels import assembly as _k
from ..kernels import pool as _par
from .quadrature import quadrature_points, triangle_rule

__all__ = ["BLOCK", "HINT_TRIANGLES", "callable_integrals", "evaluate_callable", "run_blocks"]

logger = logging.getLogger(__name__)

#: Triangles per block when a callable is evaluated: the (block, n_points) temporaries
#: (coordinates, values, the callable's own intermediates) stay in the cores' caches,
#: 0.5 MB each at the 7 points of degree 5.  Blocks of 2^17 triangles (7 MB each) made
#: every NumPy operation stream through memory: the manufactured load at n = 1024 took
#: 0.51 s (load vector) and 1.23 s (with moments and oscillation) against 0.20 s and
#: 0.32 s with 2^13 (2 threads, medians of 5, same bits).
BLOCK = 1 << 13


def evaluate_callable(f, x, y, name="f"):
    """Evaluate a user callable ``f(x, y)`` on arrays, checking shape and finiteness."""
    try:
        val = f(x, y)
    except Exception as exc:
        raise DataError(f"{name}(x, y) raised {type(exc).__name__}: {exc}") from exc
    try:
        raw = np.asarray(val)
    except Exception as exc:
        raise DataError(f"{name}(x, y) returned a value that is not an array: {exc}") from exc
    if raw.dtype.kind not in "iufb":
        raise DataError(
            f"{name}(x, y) must return real numbers, got {type(val).__name__} "
            f"with dtype {raw.dtype}"
        )
    val = raw.astype(np.float64) if raw.ndim else np.full(x.shape, float(raw))
    if val.shape != x.shape:
        try:
            val = np.broadcast_to(val, x.shape)
        except ValueError as exc:
            raise DataError(
                f"{name}(x, y) returned shape {val.shape}, expected {x.shape} "
                "(evaluate elementwise on the arrays x and y)"
            ) from exc
    if not np.isfinite(val).all():
        raise DataError(
            f"{name}(x, y) returned NaN or inf at {int((~np.isfinite(val)).sum())} points"
        )
    return val


#: From this many triangles a serial callable pass logs (once per process, INFO) that
#: ``parallel_callables=True`` would evaluate the callable in all threads.
HINT_TRIANGLES = 1 << 18

_hinted = False


def _hint_parallel(name: str) -> None:
    global _hinted
    if not _hinted:
        _hinted = True
        logger.info(
            "%s(x, y) is evaluated in the calling thread only; if the loads are thread-safe "
            "(vectorised NumPy without shared mutable state), Scene(..., parallel_callables=True) "
            "evaluates them in all %d threads",
            name,
            _par.n_threads(),
        )


def callable_integrals(mesh, f, degree, name="f", want_all=False, parallel=False) -> dict:
    """One blocked pass of the callable ``f(x, y)`` over the points of the rule of ``degree``.

    Returns ``{"F": load vector}``, with ``want_all`` also ``"moments"`` (M, 3, 3)
    and ``"osc_norm"`` (M,), the norms ``||f - Pi_K f||_K`` of the oscillation.
    The single implementation behind :func:`fastmem.fem.assembly.assemble_load`
    (callables) and :func:`fastmem.fem.loaddata.integrals`.

    With more than one thread (:func:`fastmem.set_threads`) the integrals of a
    block are formed in a pool thread while the calling thread maps the next
    block's points and evaluates ``f`` there (``f`` itself is only ever called
    from the calling thread, so it need not be thread-safe).  At most one block
    waits: the temporaries stay bounded by two blocks, and every number is
    computed by the same operations as in one thread (bit-identical results).

    ``parallel``: ``f`` may be called from several threads at once (the scene's
    ``parallel_callables``).  Then every thread takes whole blocks in turn (points,
    ``f``, integrals): NumPy releases the GIL inside its array operations, so a
    vectorised ``f`` runs on all cores.  Still one block per thread in flight,
    and bit-identical results; if ``f`` fails, the error raised is that of the
    first failing block, as in one thread.
    """
    m = mesh.n_triangles
    bary, w = triangle_rule(degree)
    local = np.empty((m, 3))
    if want_all:
        mom = np.empty((m, 3, 3))
        norm = np.empty(m)  # ||f - Pi_K f||_K

    # one signature of the kernel: writable C arrays, empty moments when not wanted
    bary_c, w_c = np.array(bary, dtype=np.float64), np.array(w, dtype=np.float64)
    outer = (bary_c[:, :, None] * bary_c[:, None, :]).reshape(-1, 9)
    areas = np.ascontiguousarray(mesh.areas, dtype=np.float64)
    if not want_all:
        mom, norm = np.empty((0, 3, 3)), np.empty(0)

    def integrate(fv, start, stop):
        fv = np.ascontiguousarray(fv, dtype=np.float64)  # (a broadcast value: a C copy)
        _k.load_block(fv, w_c, bary_c, outer, areas, start, local, mom, norm)

    threads = _par.n_threads()
    if parallel and m > BLOCK and threads > 1:
        _blocks_in_threads(mesh, f, name, bary, integrate, threads)
        return _finish(mesh, local, mom if want_all else None, norm if want_all else None)
    if not parallel and m >= HINT_TRIANGLES and threads > 1:
        _hint_parallel(name)
    pool = _par.worker_pool() if m > BLOCK and threads > 1 else None
    if pool is not None:  # NumPy's error settings are per thread: the caller's apply there too
        errors, plain = np.geterr(), integrate

        def integrate(fv, start, stop):
            with np.errstate(**errors):
                plain(fv, start, stop)

    pending = None
    try:
        for start in range(0, m, BLOCK):
            stop = min(start + BLOCK, m)
            # with the pool integrating the previous block, the points in this thread alone
            x, y = quadrature_points(
                mesh.vertices, mesh.triangles[start:stop], bary, parallel=pool is None
            )
            fv = evaluate_callable(f, x, y, name)  # (m_b, nq)
            del x, y
            if pool is None:
                integrate(fv, start, stop)
                continue
            if pending is not None:
                pending.result()  # the previous block first: at most one block in flight
            pending = pool.submit(integrate, fv, start, stop)
        if pending is not None:
            pending.result()
    finally:  # an error in the calling thread: let the pool thread finish its block first
        if pending is not None:
            concurrent.futures.wait([pending])
    return _finish(mesh, local, mom if want_all else None, norm if want_all else None)


def _finish(mesh, local, mom, norm) -> dict:
    vec = _k.gather_vector(local, mesh.patch_ptr, mesh.patch_triangles, mesh.patch_local)
    out = {"F": vec}
    if mom is not None:
        out["moments"] = mom
        out["osc_norm"] = norm
    return out


def _blocks_in_threads(mesh, f, name, bary, integrate, threads) -> None:
    """Run the blocks of :func:`callable_integrals` in ``threads`` threads (:func:`run_blocks`)."""

    def block(start, stop):
        x, y = quadrature_points(mesh.vertices, mesh.triangles[start:stop], bary, parallel=False)
        fv = evaluate_callable(f, x, y, name)
        del x, y
        integrate(fv, start, stop)

    run_blocks(block, mesh.n_triangles, BLOCK, threads)


def run_blocks(fn, n: int, block: int, threads: int) -> None:
    """Call ``fn(start, stop)`` on the blocks of ``range(n)``, taken in turn by ``threads`` threads.

    For user callables on blocks of rows (``parallel_callables``): ``fn`` writes only
    its own rows, so the result does not depend on the scheduling.  Blocks are
    handed out in order from a shared counter; after a block fails, only the
    blocks before it still run, and the error of the first failing block is
    raised, as in one thread.  NumPy's error settings of the calling thread apply
    in every thread.
    """
    errors = np.geterr()  # NumPy's error settings are per thread: the caller's apply
    failed = {}  # block start -> exception
    lock = threading.Lock()
    pieces = [(start, min(start + block, n)) for start in range(0, n, block)]

    def one(start, stop):
        with lock:
            if failed and start > min(failed):
                return
        try:
            with np.errstate(**errors):
                fn(start, stop)
        except Exception as exc:  # noqa: BLE001 - re-raised below, after the other blocks
            with lock:
                failed[start] = exc

    _par.run_pieces(one, pieces, max(1, int(threads)))
    if failed:
        raise failed[min(failed)]
