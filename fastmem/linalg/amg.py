"""Algebraic multigrid (pyamg) and a resumable preconditioned conjugate gradient.

The adaptive solver needs to look at the iterate between CG iterations (to
evaluate the estimators) and to stop CG at any point; scipy's and pyamg's
Krylov drivers only offer a callback.  :class:`PCG` is the textbook
preconditioned conjugate gradient as an object with a :meth:`PCG.step`
method, so that the caller decides when to stop.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import threading
import time

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..errors import ParameterError

try:  # scipy's BSR base class, patched while a hierarchy is set up (_fast_bsr_dedup)
    from scipy.sparse._bsr import _bsr_base
except ImportError:  # pragma: no cover - another scipy layout: keep its own method
    _bsr_base = None
from ..kernels import pool as _par
from ..kernels.smooth import (
    active_diagonal_range,
    cg_direction_range,
    cg_update_range,
    copy_range,
    copy_vector,
    cross_block_dominant,
    csr_diagonal_range,
    csr_matvec_range,
    gs_hybrid_range,
    masked_rhs_range,
)
from .sparse import (
    THREADED_ROWS,
    ThreadedCSR,
    _kernel_arrays,
    as_unsigned,
    plain_float64,
    read_only,
    threaded,
)

__all__ = [
    "AMG_DEFAULTS",
    "PCG",
    "CoarseCholesky",
    "CoarseDirect",
    "LazyAMG",
    "TwoGridLaplacian",
    "amg_preconditioner",
    "check_amg_options",
    "coarse_factor",
    "dense_coarse_factor",
]

#: Default pyamg options: smoothed aggregation, symmetric strength, V(1,1) cycles
#: with symmetric Gauss-Seidel (an SPD preconditioner, as CG requires).  The
#: prolongation smoother uses pyamg's row-wise Gershgorin ("local") weighting
#: instead of a spectral-radius estimate: at n = 512 (default scene, nested
#: inexact solve) the setups took 0.83 s instead of 1.15 s with the same 75 CG
#: iterations, the whole solve 6.3 s instead of 6.8 s (medians of 3, same run).
#: The coarsest level (at most ``max_coarse`` unknowns) is solved by a sparse LU
#: factorisation (:class:`CoarseDirect`, ``"direct"``), with pyamg's pseudo-inverse
#: (its default, an SVD) as the fallback where the matrix is singular.  The SVD of a
#: 500 x 500 matrix took about 6 ms, at every setup and update of a hierarchy: 0.11 s
#: of an adaptive L-shape loop of 0.87 s.  Adaptive L-shape (f = (-1, -1), tol 9e-3,
#: 23 meshes), medians of 5 alternating in one process: 0.793 s with the SVD, 0.676 s
#: with a dense Cholesky factorisation (:class:`CoarseCholesky`, ``"cholesky"``, the
#: default until 2026-12-04), whose factor of 385 unknowns took 2.9 ms and each solve
#: 0.2 ms, against 0.6 ms and 0.02 ms for the sparse LU.
AMG_DEFAULTS = {
    "strength": "symmetric",
    "smooth": ("jacobi", {"weighting": "local"}),
    "max_coarse": 500,
    "presmoother": ("gauss_seidel", {"sweep": "symmetric"}),
    "postsmoother": ("gauss_seidel", {"sweep": "symmetric"}),
    "coarse_solver": "direct",
    "cycle": "V",
}


#: Keys accepted in ``amg_options``: the cycle type and the keyword arguments of
#: ``pyamg.smoothed_aggregation_solver`` that configure the hierarchy.
_AMG_KEYS = frozenset(
    {
        "cycle",
        "B",
        "BH",
        "symmetry",
        "strength",
        "aggregate",
        "smooth",
        "presmoother",
        "postsmoother",
        "improve_candidates",
        "max_levels",
        "max_coarse",
        "diagonal_dominance",
        "keep",
        "coarse_solver",
    }
)


def check_amg_options(options) -> dict:
    """Merge user AMG options with :data:`AMG_DEFAULTS`; refuse non-dict input."""
    if options is None:
        return dict(AMG_DEFAULTS)
    if not isinstance(options, dict):
        raise ParameterError(f"amg_options must be a dict of pyamg options, got {options!r}")
    unknown = sorted(str(k) for k in options if k not in _AMG_KEYS)
    if unknown:
        raise ParameterError(f"amg_options has unknown keys {unknown}; known: {sorted(_AMG_KEYS)}")
    out = dict(AMG_DEFAULTS)
    out.update(options)
    if out["cycle"] not in ("V", "W", "F"):
        raise ParameterError(f"amg_options['cycle'] must be 'V', 'W' or 'F', got {out['cycle']!r}")
    return out


#: A coarsest operator whose LU pivots span more than this ratio (smallest to largest
#: magnitude) is treated as singular: for a symmetric positive definite matrix the
#: ratio is at least 1 / cond(A), so only operators beyond double precision go.
SINGULAR_PIVOTS = 1e-13


def coarse_factor(a):
    """Factor a coarsest operator ``a`` (square, sparse or dense); return an object with ``solve``.

    SuperLU with the minimum-degree ordering of ``A + A^T`` and diagonal pivots
    (``SymmetricMode``).  On the coarsest levels of the multigrids (pyamg's of at most
    ``max_coarse`` = 500 unknowns, the nested chains' of at most
    :data:`fastmem.linalg.gmg.COARSE_DIRECT`) it took 0.6-4.5 ms whatever the
    numbering (a random permutation included), where a dense Cholesky factorisation
    took 3-440 ms; the ordering's cost on large badly numbered meshes
    (:mod:`fastmem.linalg.direct`) does not arise at these sizes.  An exactly singular
    operator, or one whose pivots span more than :data:`SINGULAR_PIVOTS`, is solved
    with its pseudo-inverse (minimum-norm solutions, pyamg's default).
    """
    n = a.shape[0]
    if n == 0:
        return _PseudoInverse(np.zeros((0, 0)))
    csc = sp.csc_matrix(a, dtype=np.float64)
    try:
        lu = spla.splu(
            csc, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
    except RuntimeError:  # exactly singular
        lu = None
    if lu is not None:
        pivots = np.abs(lu.U.diagonal())
        if pivots.min() > SINGULAR_PIVOTS * pivots.max():
            return lu
    return _PseudoInverse(scipy.linalg.pinv(csc.toarray()))


class _PseudoInverse:
    """``solve(b) = pinv @ b``: the solver of a singular coarsest operator."""

    def __init__(self, pinv):
        self.pinv = pinv

    def solve(self, b):
        return self.pinv @ b


class _DenseCholesky:
    """``solve(b)`` by the dense Cholesky factors of ``a`` (``scipy.linalg.cho_factor``)."""

    def __init__(self, a):
        self.factor = scipy.linalg.cho_factor(a, check_finite=False)

    def solve(self, b):
        return scipy.linalg.cho_solve(self.factor, b, check_finite=False)


def dense_coarse_factor(a):
    """Dense Cholesky factors of ``a`` (an object with ``solve``).

    The pseudo-inverse when ``a`` is not positive definite (a singular coarse
    operator), pyamg's default.
    """
    dense = a.toarray() if sp.issparse(a) else np.asarray(a, dtype=np.float64)
    try:
        return _DenseCholesky(dense)
    except np.linalg.LinAlgError:
        return _PseudoInverse(scipy.linalg.pinv(dense))


class CoarseDirect:
    """Solve on the coarsest level by sparse LU (:func:`coarse_factor`).

    A callable ``(A, b) -> x`` for pyamg's ``coarse_solver``: the matrix is
    factored at the first call and the factors are kept while ``A`` is the same
    object; a singular matrix is solved with its pseudo-inverse.  The value
    ``"direct"`` of ``amg_options["coarse_solver"]`` (the default) selects it (a
    fresh instance per hierarchy and update).
    """

    #: the factorisation: ``a -> object with solve(b)``
    factorize = staticmethod(coarse_factor)

    def __init__(self):
        self._matrix = None
        self._factor = None

    def __call__(self, a, b):
        """Return the solution of ``a x = b`` (``a`` factored on its first call)."""
        if a is not self._matrix:
            self._matrix, self._factor = a, self.factorize(a)
        return self._factor.solve(np.asarray(b, dtype=np.float64))


class CoarseCholesky(CoarseDirect):
    """:class:`CoarseDirect` with dense Cholesky factors (:func:`dense_coarse_factor`).

    The value ``"cholesky"`` of ``amg_options["coarse_solver"]``; fastmem's default
    until 2026-12-04.
    """

    factorize = staticmethod(dense_coarse_factor)


def _coarse_solver(name):
    """Return pyamg's ``coarse_solver`` for the option ``name`` ("direct", "cholesky": ours)."""
    if name == "direct":
        return CoarseDirect()
    return CoarseCholesky() if name == "cholesky" else name


def _trim(ml):
    """Drop what the cycles of a finished hierarchy never read.

    - ``B``/``BH`` (the near-nullspace candidates) serve the setup only;
    - with symmetric smoothed aggregation pyamg keeps ``R`` as a copy of
      ``P.T``.  With scalar (1 x 1) blocks, ``P`` becomes the CSR matrix on the
      same arrays (scipy multiplies 1 x 1 BSR matrices with the CSR kernel)
      and ``R`` its transpose view (CSC on P's arrays): the CSC product sums
      each entry of ``R r`` over increasing rows of ``P``, the order in which
      the CSR product of the copy (sorted columns) sums it, so restriction and
      interpolation are computed bit for bit as before (checked on every level:
      the copy must equal the view entry for entry, else it is kept).  About
      a third of a hierarchy.
    - the coarse-level operators ``A`` (Galerkin products, scalar BSR) become CSR
      matrices on the same arrays: pyamg's Gauss-Seidel takes its CSR kernel
      instead of the block kernel, whose per-block overhead made the coarse levels'
      smoothing cost more than the finest level's (V-cycle at n = 1024: 0.128 s ->
      0.085 s).  The sweep is the same; only the diagonal division is rounded
      differently (the block kernel multiplies by the inverted 1 x 1 block), so
      cycles agree to round-off (5e-16 relative), not bit for bit.
    """
    for lv in ml.levels:
        for name in ("B", "BH"):
            lv.__dict__.pop(name, None)
        a = getattr(lv, "A", None)
        if a is not None and a.format == "bsr" and a.blocksize == (1, 1):
            lv.A = sp.csr_matrix((a.data.reshape(-1), a.indices, a.indptr), shape=a.shape)
        r, p = getattr(lv, "R", None), getattr(lv, "P", None)
        if r is None or p is None or r.format != "bsr" or p.format != "bsr":
            continue
        if r.blocksize != (1, 1) or p.blocksize != (1, 1) or r.dtype != p.dtype:
            continue
        pc = sp.csr_matrix((p.data.reshape(-1), p.indices, p.indptr), shape=p.shape)
        rc = sp.csr_matrix((r.data.reshape(-1), r.indices, r.indptr), shape=r.shape)
        view = pc.T.tocsr()  # transient: the copy R would be, to check it entry for entry
        same = rc.has_sorted_indices and all(
            np.array_equal(getattr(rc, k), getattr(view, k)) for k in ("data", "indices", "indptr")
        )
        del view
        if same:
            lv.P = pc
            lv.R = pc.T


def _bsr_is_canonical(m) -> bool:
    """Whether a BSR matrix has sorted block columns without duplicates in every row.

    O(nnz) vector work: within each block row the column indices must increase
    strictly; the first entry of a row is compared with nothing.
    """
    idx, ptr = m.indices, m.indptr
    nnz = int(ptr[-1])
    if idx.size != nnz or m.data.shape[0] != nnz:
        return False  # arrays longer than the matrix: let scipy prune them
    if nnz < 2:
        return True
    step = np.diff(idx) > 0
    starts = ptr[1:-1]
    starts = starts[(starts > 0) & (starts < nnz)]
    step[starts - 1] = True
    return bool(step.all())


_BSR_LOCK = threading.Lock()
_BSR_DEPTH = 0
_BSR_ORIGINAL = None


def _checked_sum_duplicates(self):
    # scipy's BSR ``sum_duplicates`` sorts the indices (compiled) and then sums
    # duplicates in a Python loop over the block rows whenever the matrix is not
    # *flagged* canonical.  The Galerkin products ``R A P`` of pyamg's setup have
    # unsorted indices but no duplicates: pyamg's "local" Jacobi weighting (``abs(A)``)
    # spent 0.5-0.7 s in that loop on the coarse levels of an n = 1024 hierarchy (half
    # of the setup).  Sorted here the same way, a matrix found canonical by an O(nnz)
    # vector test is flagged and left as it is, which is all the loop would have done.
    if not self.has_canonical_format:
        self.sort_indices()
        if _bsr_is_canonical(self):
            self.has_canonical_format = True
    return _BSR_ORIGINAL(self)


def _reset_after_fork():
    # a fork during another thread's setup: the child has no setup running, and the lock
    # may have been held at the fork
    global _BSR_LOCK, _BSR_DEPTH, _BSR_ORIGINAL
    _BSR_LOCK = threading.Lock()
    if _BSR_DEPTH:
        _bsr_base.sum_duplicates = _BSR_ORIGINAL
    _BSR_DEPTH = 0


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_reset_after_fork)


@contextlib.contextmanager
def _fast_bsr_dedup():
    """Within the block, BSR ``sum_duplicates`` skips canonical matrices without a loop.

    Same result as scipy's method (which changes nothing on a canonical matrix);
    installed on scipy's BSR base class only while a hierarchy is set up (nested and
    concurrent setups share one installation, which every thread of the process sees
    meanwhile: harmless, it is equivalent), and only where scipy has that class.
    """
    global _BSR_DEPTH, _BSR_ORIGINAL
    cls = _bsr_base
    if cls is None:  # another scipy layout: keep its own method
        yield
        return
    with _BSR_LOCK:
        if _BSR_DEPTH == 0:
            _BSR_ORIGINAL = cls.sum_duplicates
            cls.sum_duplicates = _checked_sum_duplicates
        _BSR_DEPTH += 1
    try:
        yield
    finally:
        with _BSR_LOCK:
            _BSR_DEPTH -= 1
            if _BSR_DEPTH == 0:
                cls.sum_duplicates = _BSR_ORIGINAL


#: Hybrid Gauss-Seidel (:mod:`fastmem.kernels.smooth`) on the levels with at least
#: ``2 * HYBRID_BLOCK_ROWS`` rows: blocks of at least this many rows, at most
#: ``HYBRID_MAX_BLOCKS`` of them; the blocks depend on the level's size only (never
#: on the thread count), so results are the same with any number of threads.
HYBRID_BLOCK_ROWS = 16384
HYBRID_MAX_BLOCKS = 16


def hybrid_blocks(n: int) -> int:
    """Return the number of row blocks of the hybrid sweep on ``n`` rows (0: plain GS)."""
    nb = min(HYBRID_MAX_BLOCKS, n // HYBRID_BLOCK_ROWS)
    return nb if nb >= 2 else 0


class HybridGaussSeidel:
    """Symmetric hybrid Gauss-Seidel sweep, a pyamg smoother ``(A, x, b)``.

    Forward sweep, then backward sweep (pyamg's ``sweep="symmetric"``), each
    Gauss-Seidel inside ``n_blocks`` contiguous row blocks and Jacobi across
    them (:func:`fastmem.kernels.smooth.gs_hybrid_range`); the blocks are swept
    in parallel by the kernel threads.  Symmetric, so the V-cycle stays an SPD
    preconditioner.  On the finest level of an n = 1024 square a symmetric
    sweep took 18.5 ms with pyamg's serial kernel.
    """

    def __init__(self, n_blocks: int, directions=(True, False)):
        self.n_blocks = n_blocks
        #: the sweeps of one call: forward (True) and/or backward (False), in this order
        self.directions = tuple(directions)
        self._old = None  # x before the sweep: one buffer per level, reused
        self._busy = threading.Lock()  # a concurrent call (another thread) gets its own

    def __call__(self, a, x, b):
        n = a.shape[0]
        nb = self.n_blocks
        edges = [n * k // nb for k in range(nb + 1)]
        indptr, indices, data = as_unsigned(a.indptr), as_unsigned(a.indices), a.data
        own = self._busy.acquire(blocking=False)
        try:
            if not own:  # the buffer is in use by a cycle in another thread
                self._sweeps(
                    nb, edges, indptr, indices, data, x, np.empty_like(x), b, self.directions
                )
                return
            if self._old is None or self._old.shape != x.shape:
                # kept: a fresh copy per sweep cost more in page faults than the sweep gained
                self._old = np.empty_like(x)
            self._sweeps(nb, edges, indptr, indices, data, x, self._old, b, self.directions)
        finally:
            if own:
                self._busy.release()

    @staticmethod
    def _sweeps(nb, edges, indptr, indices, data, x, x_old, b, directions=(True, False)):

        threads = min(_par.n_threads(), nb)
        for forward in directions:
            copy_vector(x, x_old, THREADED_ROWS)
            # blocks handed out one at a time (a shared counter): a thread that runs
            # slower (a core the machine has just woken up) takes fewer of them; each
            # block's arithmetic is the same whichever thread sweeps it
            counter = itertools.count()

            def sweep(lo, hi, forward=forward, counter=counter):
                k = next(counter)
                while k < nb:
                    gs_hybrid_range(
                        edges[k], edges[k + 1], forward, indptr, indices, data, x, x_old, b
                    )
                    k = next(counter)

            _par.run_ranges(sweep, [(0, 0)] * threads)


def precompile() -> None:
    """Compile (or load) the kernels of the hybrid sweep, the threaded products and the CG.

    With the argument types of a solve (uint32 index views; the vector of a
    product read-only, :func:`fastmem.linalg.sparse.read_only`), on a 2 x 2 matrix:
    the tiny problem of :func:`fastmem.warm_up` is below the sizes that use them.
    """
    a = sp.csr_matrix(np.array([[2.0, -1.0], [-1.0, 2.0]]))
    indptr, indices = (
        as_unsigned(a.indptr.astype(np.int32)),
        as_unsigned(a.indices.astype(np.int32)),
    )
    x, b, old = np.zeros(2), np.ones(2), np.zeros(2)
    gs_hybrid_range(0, 2, True, indptr, indices, a.data, x, old, b)
    cross_block_dominant(indptr, indices, a.data, 2)  # (its range kernel)
    frozen = np.ones(2)
    frozen.setflags(write=False)
    csr_matvec_range(0, 2, indptr, indices, a.data, frozen, x)
    # the CG's vector updates and the gap system's masking (fastmem.solver.steps)
    cg_update_range(0, 2, 0.5, frozen, frozen, x, old)
    cg_direction_range(0, 2, 0.5, frozen, x)
    active = np.zeros(2, dtype=np.bool_)
    masked_rhs_range(0, 2, active, frozen, x)
    active_diagonal_range(0, 2, active, frozen, frozen, x)
    csr_diagonal_range(0, 2, indptr, indices, a.data, x)  # ThreadedCSR.diagonal
    copy_range(0, 2, x, old)  # the hybrid sweeps' copy of x


def _sweeps_read_matrix_at_call(options: dict) -> bool:
    """Whether both smoothers read the level's matrix when called (nothing from the setup).

    pyamg's Gauss-Seidel and SOR do; Jacobi, Richardson and Chebyshev keep a step size,
    Schwarz, block Jacobi and the normal-equation sweeps a copy or a factor of the setup's
    matrix, so a hierarchy with those cannot take :meth:`AMGPreconditioner.update`.
    """

    def name(opt):
        return opt if isinstance(opt, str) else opt[0] if isinstance(opt, tuple | list) else None

    ok = {"gauss_seidel", "sor"}
    return name(options.get("presmoother")) in ok and name(options.get("postsmoother")) in ok


def _hybrid_candidates(ml, options: dict) -> list:
    """Per level: the hybrid sweep's block count where it may replace pyamg's, else 0."""
    gs = ("gauss_seidel", {"sweep": "symmetric"})
    if options.get("presmoother") != gs or options.get("postsmoother") != gs:
        return [0] * len(ml.levels)
    out = []
    for lv in ml.levels[:-1]:
        a = lv.A
        nb = hybrid_blocks(a.shape[0])
        usable = a.format == "csr" and a.dtype == np.float64 and _kernel_arrays(a)
        out.append(nb if usable else 0)
    return out + [0]


def _select_smoothers(ml, plain, hybrid) -> None:
    """Each candidate level gets the hybrid sweep where it converges on the level's matrix.

    Decided from the current matrix alone (not from earlier updates), so a hierarchy
    rebuilt and updated to the same matrix gets the same smoothers.
    """
    for lv, (pre, post), sweep in zip(ml.levels, plain, hybrid, strict=True):
        if sweep is None:
            continue
        if _hybrid_converges(lv.A, sweep.n_blocks):
            lv.presmoother = lv.postsmoother = sweep
        else:
            lv.presmoother, lv.postsmoother = pre, post


def _hybrid_converges(a, n_blocks: int) -> bool:
    """Whether the hybrid sweep is a convergent smoother of ``a`` (a sufficient test).

    :func:`fastmem.kernels.smooth.cross_block_dominant`: each row's diagonal
    exceeds its entries coupling other blocks (a few rows per block boundary;
    true for every M-matrix).  Otherwise the level keeps pyamg's sweep.
    """
    return bool(
        cross_block_dominant(as_unsigned(a.indptr), as_unsigned(a.indices), a.data, n_blocks)
    )


class AMGPreconditioner:
    """A smoothed-aggregation hierarchy used as a fixed SPD preconditioner.

    Attributes
    ----------
    setup_seconds : float
        Wall time of the hierarchy setup.
    n : int
        Size of the matrix the hierarchy was built for.
    """

    def __init__(self, matrix, options: dict):
        import pyamg  # lazy: pyamg adds 0.18 s to import fastmem

        opts = dict(options)
        cycle = opts.pop("cycle")
        self._coarse = opts.pop("coarse_solver", "pinv")  # pyamg's default for SA
        opts["coarse_solver"] = _coarse_solver(self._coarse)
        t0 = time.perf_counter()
        with _fast_bsr_dedup():
            self.ml = pyamg.smoothed_aggregation_solver(sp.csr_matrix(matrix), **opts)
        _trim(self.ml)
        levels = self.ml.levels
        for lv in levels[:-1]:  # products in the kernel threads (the same numbers)
            lv.A = threaded(lv.A)
            if getattr(lv, "P", None) is not None:
                lv.P = threaded(lv.P)  # interpolation P x (rows: this level's unknowns)
        # pyamg's sweeps, and the hybrid sweep of each level large enough for it
        self._plain = [
            (getattr(lv, "presmoother", None), getattr(lv, "postsmoother", None)) for lv in levels
        ]
        blocks = _hybrid_candidates(self.ml, opts)
        self._hybrid = [HybridGaussSeidel(nb) if nb else None for nb in blocks]
        _select_smoothers(self.ml, self._plain, self._hybrid)
        #: whether :meth:`update` applies (the smoothers read the matrix at call time)
        self.can_update = _sweeps_read_matrix_at_call(opts)
        self.setup_seconds = time.perf_counter() - t0
        self.cycle = cycle
        self.n = matrix.shape[0]
        self._op = self.ml.aspreconditioner(cycle=cycle)
        # pyamg's recursive cycle (private; the solve loop is the fallback)
        self._cycle = getattr(self.ml, "_MultilevelSolver__solve", None)
        if len(self.ml.levels) < 2:
            self._cycle = None
        self._setup_ops = None  # the setup's coarse operators, once :meth:`update` runs
        self.updates = 0

    def __call__(self, r: np.ndarray) -> np.ndarray:
        """One multigrid cycle from a zero initial guess: ``z ~ A^-1 r``.

        The cycle itself, without pyamg's ``solve`` loop around it: as a
        preconditioner (``aspreconditioner``, one iteration) that loop forms
        ``b - A x`` and its norm before the cycle (with ``x = 0``) and again
        after it, two finest-level products and norms that nothing reads.
        Same operations otherwise, so the same result bit for bit.
        """
        cycle = self._cycle
        if cycle is None:
            return self._op.matvec(r)
        b = np.ravel(np.asarray(r, dtype=np.float64))
        x = np.zeros_like(b)
        try:
            cycle(0, x, b, str(self.cycle).upper(), 1)
        except TypeError:  # another pyamg: its public loop from now on
            self._cycle = None
            return self._op.matvec(r)
        return x

    def update(self, matrix, index: np.ndarray, delta) -> float:
        """Galerkin update: the hierarchy of the setup's prolongators for a changed matrix.

        ``matrix`` is the new finest operator ``A = A_0 + D``, where ``A_0`` is the
        matrix the hierarchy was *set up* for and ``D`` (symmetric) is zero outside
        the rows and columns ``index``; ``delta`` is ``D[index][:, index]``.  The
        prolongators ``P_l`` (and the aggregation, strength and smoothing behind
        them) are kept; every coarse operator becomes the exact Galerkin product
        of the new matrix, ``A_(l+1) = P_l^T A_l P_l``, computed as the setup's
        operator plus ``P_l^T D_l P_l`` restricted to the rows of ``P_l`` that
        ``D_l`` touches: O(size of the change) sparse work per level instead of a
        new setup.  The coarsest level's solver is refactored (at most
        ``max_coarse`` unknowns).

        Always relative to the setup's operators (kept, not modified), so the
        result does not depend on the updates made before: an update to the same
        matrix after a rebuild of the hierarchy is bit for bit the same
        hierarchy.  Returns the seconds taken.

        Why: the inexact Newton-min step's gap system changes in a band of a
        few thousand vertices along the free boundary from one Newton step to
        the next.  Reused unchanged (the preconditioner of an older active set),
        its CG converged at 0.7-0.87 per iteration instead of about 0.15; a new
        setup per step cost about as much as the iterations it saved.
        """
        from pyamg.multilevel import coarse_grid_solver  # lazy: pyamg adds 0.18 s to import fastmem

        if not self.can_update:
            raise ValueError("this hierarchy's smoothers keep data of the setup's matrix")
        t0 = time.perf_counter()
        levels = self.ml.levels
        if self._setup_ops is None:  # the setup's coarse operators (references, not copies)
            self._setup_ops = [lv.A for lv in levels[1:]]
        levels[0].A = threaded(matrix.tocsr())
        rows = np.asarray(index)
        d = sp.csr_matrix(delta)
        for lev in range(len(levels) - 1):
            p = levels[lev].P
            p_rows = (p if p.format == "csr" else p.tocsr())[rows]
            dc = (p_rows.T @ (d @ p_rows)).tocsr()
            dc.eliminate_zeros()
            base = self._setup_ops[lev]
            new = base + dc.astype(base.dtype, copy=False)
            new = new.tocsr() if new.format != "csr" else new
            levels[lev + 1].A = threaded(new) if lev + 1 < len(levels) - 1 else new
            rows = np.flatnonzero(np.diff(dc.indptr))
            d = dc[rows][:, rows]
        _select_smoothers(self.ml, self._plain, self._hybrid)  # convergent on the new operators
        self.ml.coarse_solver = coarse_grid_solver(_coarse_solver(self._coarse))
        self.updates += 1
        return time.perf_counter() - t0


def amg_preconditioner(matrix, options: dict | None = None) -> AMGPreconditioner:
    """Build an :class:`AMGPreconditioner` for an SPD sparse matrix."""
    return AMGPreconditioner(matrix, check_amg_options(options))


class LazyAMG:
    """An :class:`AMGPreconditioner` built on its first use (and again after :meth:`release`).

    The Laplacian's hierarchy of the decoupled path serves the CG of the sum
    ``s``, which on the finest level of nested iteration usually does no
    iteration at all (its prolonged start is accurate enough): built eagerly
    it cost a setup and, at the final flux reconstruction, about 120 bytes
    per vertex that nothing used.  The hierarchy is deterministic, so one
    built late is the one that would have been built early.

    ``stats``: the per-level counters (``amg_setups``, ``amg_setup_seconds``),
    updated when the hierarchy is actually built.
    """

    def __init__(self, matrix, options: dict, stats: dict):
        self.matrix = matrix
        self.options = options
        self.stats = stats
        self.pre = None

    @property
    def built(self) -> bool:
        """True while a hierarchy exists."""
        return self.pre is not None

    def build(self, key: str = "amg") -> None:
        """Set up the hierarchy (booked as ``{key}_setups``, ``{key}_setup_seconds``).

        ``key="spill"``: a rebuild after :meth:`fastmem.solver.steps.DecoupledCG.spill`.
        """
        self.pre = amg_preconditioner(self.matrix, dict(self.options))
        self._book(key, self.pre.setup_seconds)

    def _book(self, key, seconds):
        self.stats[f"{key}_setups"] = self.stats.get(f"{key}_setups", 0) + 1
        self.stats[f"{key}_setup_seconds"] = self.stats.get(f"{key}_setup_seconds", 0.0) + seconds

    def __call__(self, r: np.ndarray) -> np.ndarray:
        """One multigrid cycle (the hierarchy built first if there is none)."""
        if self.pre is None:
            self.build()
        return self.pre(r)

    def release(self, final: bool = False):
        """Free the hierarchy (a later call builds it again); ``final``: nothing more to free."""
        self.pre = None


class TwoGridLaplacian(LazyAMG):
    """Preconditioner of a nested level's interior Laplacian: smoother + the coarser level's AMG.

    For the CG of the sum ``s`` on a level of nested iteration (the interior
    Laplacian ``A``), in place of a smoothed-aggregation setup on ``A``: one
    Gauss-Seidel sweep forward, the coarse correction ``P M_c^-1 P^T r`` with
    ``P`` the P1 interpolation from the coarser level (interior to interior)
    and ``M_c`` one V-cycle of an AMG hierarchy of the Galerkin operator
    ``A_c = P^T A P`` (for nested P1 meshes the coarser level's own Laplacian,
    exactly), then one sweep backward: a symmetric V(1,1) cycle, so an SPD
    preconditioner.  Sweeps as in :class:`AMGPreconditioner` (the hybrid
    sweep where :func:`_hybrid_converges`, else pyamg's Gauss-Seidel), whatever
    smoothers ``options`` name: they apply to the coarse hierarchy only.

    Why: on the finest level of an n = 1024 square the AMG setup of ``A``
    took 0.3-0.85 s (about 120 bytes per vertex) for the 5 CG iterations of
    ``s`` on the manufactured scene; ``P^T A P`` and the coarse setup take
    0.13 s and a quarter of the memory, and the two-grid cycle reduces the
    residual faster per iteration (0.3 against 0.4 per iteration on a random
    right-hand side, 70 -> 62 ms per iteration with the split sweeps).

    The same interface as :class:`LazyAMG`: built on first use, :meth:`release`
    frees the coarse hierarchy, ``matrix`` may be replaced (spill / restore).
    """

    def __init__(self, matrix, prolongation, options: dict, stats: dict):
        super().__init__(matrix, options, stats)
        self.p = threaded(sp.csr_matrix(prolongation))
        self._r = None
        self._sweeps = None

    def build(self, key: str = "amg") -> None:
        """Set up the coarse hierarchy (booked as ``{key}_setups``, ``{key}_setup_seconds``)."""
        t0 = time.perf_counter()
        a = self.matrix
        if self.p is None:  # released for good (:meth:`release`): AMG on the matrix itself
            super().build(key)
            return
        r = self.p.T.tocsr()
        coarse = (r @ (a @ self.p)).tocsr()
        coarse.sort_indices()
        self.pre = amg_preconditioner(coarse, dict(self.options))
        self._r = threaded(r)
        nb = hybrid_blocks(a.shape[0])
        if nb and _kernel_arrays(a) and a.dtype == np.float64 and _hybrid_converges(a, nb):
            self._sweeps = (HybridGaussSeidel(nb, (True,)), HybridGaussSeidel(nb, (False,)))
        else:
            self._sweeps = (_PlainSweep("forward"), _PlainSweep("backward"))
        self._book(key, time.perf_counter() - t0)

    def __call__(self, r: np.ndarray) -> np.ndarray:
        """One V(1,1) two-grid cycle from a zero initial guess: ``z ~ A^-1 r``."""
        if self.pre is None:
            self.build()
        if self._sweeps is None:  # no interpolation any more: the fine hierarchy's cycle
            return self.pre(r)
        a = self.matrix
        b = np.ravel(np.asarray(r, dtype=np.float64))
        x = np.zeros_like(b)
        pre, post = self._sweeps
        pre(a, x, b)
        x += self.p @ self.pre(self._r @ (b - a @ x))
        post(a, x, b)
        return x

    def release(self, final: bool = False):
        """Free the coarse hierarchy (a later call builds it again).

        ``final``: the interpolation goes too (about 30 bytes per fine vertex); a
        later call then sets up AMG on the matrix itself, as :class:`LazyAMG` would.
        """
        self.pre = self._r = self._sweeps = None
        if final:
            self.p = None


class _PlainSweep:
    """pyamg's serial Gauss-Seidel, one sweep in one direction, as a smoother ``(A, x, b)``."""

    def __init__(self, sweep: str):
        self.sweep = sweep

    def __call__(self, a, x, b):
        from pyamg.relaxation.relaxation import (
            gauss_seidel,  # lazy: pyamg adds 0.18 s to import fastmem
        )

        gauss_seidel(a, x, b, iterations=1, sweep=self.sweep)


class PCG:
    """Preconditioned conjugate gradient for ``A x = b``, advanced one iteration at a time.

    Robustness (the stress suite, issue 6): the recursively updated residual
    of CG drifts away from the true one ``b - A x`` on ill-conditioned systems
    (contrast 1e12 in the coefficients), and it can reach exactly zero (or
    underflow) while the true residual cannot; both used to freeze the
    iteration.  Hence:

    - a start ``x0`` whose residual exceeds ``||b||`` is replaced by zero (a
      wild initial guess, e.g. ``1e80``, would otherwise need a reduction far
      beyond what the iteration budget allows);
    - on breakdown (``r.z <= 0`` or ``p.Ap <= 0``) the iteration is restarted
      once from the true residual; a second breakdown without progress sets
      :attr:`stuck`, and :meth:`step` returns False from then on;
    - :meth:`solve` stops on the recursive residual, then verifies the true
      one and restarts from it (residual replacement) while that still
      helps;
    - :meth:`at_roundoff` compares the true residual with what float64 can
      attain, ``||b - A x|| <~ eps (||A|| |x| + |b|)``.

    Memory: the preconditioned residual ``z``, the direction ``p`` and
    ``r.z`` of a (re)start are computed by the first :meth:`step` after it,
    from the same ``r`` (so bit for bit as if computed at once): a CG that is
    set up but never advanced applies no preconditioner and holds two
    vectors fewer.  ``z`` lives only inside :meth:`step` (between iterations
    the CG holds ``x``, ``r``, ``p`` and ``b``: one vector less under the
    estimators of a check).  Likewise the preconditioned residual of an
    iteration, and the direction update it feeds, are computed by the *next*
    :meth:`step`: the same operations on the same ``r`` and ``p``, so the
    same bits, but a CG that stops after an iteration (every inexact Newton
    step does) has applied the preconditioner once per iteration, not once
    more for a direction it never uses.  :meth:`release` drops them (and the
    preconditioner) for good once the caller is done iterating.

    Parameters
    ----------
    matrix : sparse matrix
        SPD system matrix.
    rhs : ndarray
    x0 : ndarray
        Initial guess (copied, unless ``copy=False``).
    precond : callable
        SPD preconditioner ``z = M(r)``.
    copy : bool
        False: iterate in ``x0`` itself when it is a float64 array (a start the
        caller made for this CG and does not use again: no copy of N values).

    Attributes
    ----------
    x : ndarray
        Current iterate.
    iterations : int
        Iterations done so far.
    stuck : bool
        True when the iteration broke down from a freshly computed true residual
        (nothing more can be gained by iterating).
    restarts : int
        Restarts from the true residual so far.
    """

    #: Residual replacements :meth:`solve` tries before it accepts the true residual.
    MAX_REPLACEMENTS = 8

    def __init__(self, matrix, rhs, x0, precond, copy=True):
        self.a = matrix
        self.b = rhs
        self.m = precond
        self.b_norm = float(np.linalg.norm(rhs)) or 1.0
        writable = isinstance(x0, np.ndarray) and x0.flags.writeable
        if copy or not writable:
            self.x = np.array(x0, dtype=np.float64, copy=True)
        else:
            self.x = np.asarray(x0, dtype=np.float64)
        self.iterations = 0
        self.restarts = 0
        self.stuck = False
        # the last two Hestenes-Stiefel terms alpha_k (r_k, z_k) = ||x_(k+1) - x_k||_A^2
        self._tau = (None, None)
        self._true = None  # (iterations, true residual norm) cache
        self._floor = None  # last attainable() value
        self.restart()
        if self.residual_norm > 1e3 * self.b_norm and np.any(self.x):
            self.x[:] = 0.0
            self.restart()
        self.restarts = 0

    def restart(self):
        """Recompute the residual from ``x`` and restart the search direction."""
        self.r = self._residual()
        self.p = self.rz = None  # computed by the next step (see the class notes)
        self._pending = False  # no direction update owed (p is formed afresh from r)
        self.restarts += 1
        self._fresh = True
        self._true = (self.iterations, float(np.linalg.norm(self.r)))

    @property
    def residual_norm(self) -> float:
        """Euclidean norm of the (recursively updated) residual ``b - A x``."""
        return float(np.linalg.norm(self.r))

    @property
    def relative_residual(self) -> float:
        """``||r|| / ||b||`` with the recursively updated residual."""
        return self.residual_norm / self.b_norm

    def true_residual_norm(self) -> float:
        """``||b - A x||`` recomputed (one product with A, cached per iteration)."""
        if self._true is None or self._true[0] != self.iterations:
            self._true = (self.iterations, float(np.linalg.norm(self._residual())))
        return self._true[1]

    def _residual(self) -> np.ndarray:
        """``b - A x``: in one pass of the kernel threads for a threaded matrix (same bits)."""
        if isinstance(self.a, ThreadedCSR):
            return self.a.residual(self.x, self.b)
        return self.b - self.a @ self.x

    def attainable(self) -> float:
        """Smallest residual norm float64 can resolve here: ``64 eps ||(|A| |x| + |b|)||``."""
        a = self.a
        if isinstance(a, ThreadedCSR):  # large: fused, in the kernel threads, same bits
            scale = a.abs_product_plus(self.x, self.b)
            return 64.0 * np.finfo(np.float64).eps * float(np.linalg.norm(scale))
        if getattr(a, "format", None) == "csr":  # |A| on A's pattern, not kept: no index copy
            abs_a = sp.csr_matrix((np.abs(a.data), a.indices, a.indptr), shape=a.shape)
        else:
            abs_a = abs(a)
        scale = abs_a @ np.abs(self.x) + np.abs(self.b)
        return 64.0 * np.finfo(np.float64).eps * float(np.linalg.norm(scale))

    def at_roundoff(self, rtol: float) -> bool:
        """Return True at the true residual ``rtol ||b||`` or the attainable level, or if stuck."""
        if self.stuck:
            return True
        target = rtol * self.b_norm
        # far above both levels: the true residual is too (drift makes the recursive
        # residual smaller than the true one, not larger); no products with A needed
        if self._floor is not None and self.residual_norm > 100.0 * max(target, self._floor):
            return False
        res = self.true_residual_norm()
        if res <= target:
            return True
        self._floor = self.attainable()
        return res <= self._floor

    def _breakdown(self) -> bool:
        if self._fresh:  # already restarted from the true residual: nothing to gain
            self.stuck = True
            return False
        self.restart()
        return self.step()

    def release(self):
        """Drop the preconditioner and the search state: :meth:`step` cannot be called again.

        ``x``, ``r`` and the residual checks stay usable.
        """
        self.m = self.p = self.rz = None
        self.stuck = True

    def step(self) -> bool:
        """One CG iteration.  Returns False when the iteration cannot proceed (:attr:`stuck`)."""
        if self.stuck:
            return False
        n = self.x.shape[0]
        if self.rz is None:  # first step after a (re)start
            self.p = self.m(self.r)  # z of the restart: only p keeps it (updated in place)
            self.rz = float(self.r @ self.p)
        elif self._pending:  # the previous iteration's z and direction (see the class notes)
            self._direction(n)
        if self.rz <= 0.0 or not np.isfinite(self.rz):
            return self._breakdown()
        ap = self.a @ self.p
        pap = float(self.p @ ap)
        if pap <= 0.0 or not np.isfinite(pap):
            return self._breakdown()
        alpha = self.rz / pap
        self._tau = (self._tau[1], alpha * self.rz)
        fused = n >= THREADED_ROWS and plain_float64((self.x, self.r, self.p, ap), n)
        if fused:  # NumPy's operations in the kernel threads, no temporaries
            _par.parallel_for(
                cg_update_range, n, alpha, read_only(self.p), read_only(ap), self.x, self.r
            )
        else:
            self.x += alpha * self.p
            self.r -= alpha * ap
        del ap
        self._pending = True  # z = M r and the new direction: the next step forms them
        self.iterations += 1
        self._fresh = False
        return True

    def _direction(self, n):
        """``z = M r``, ``beta = r.z / r.z_old`` and ``p = z + beta p`` of the last iteration."""
        self._pending = False
        z = self.m(self.r)
        rz_new = float(self.r @ z)
        beta = rz_new / self.rz
        self.rz = rz_new
        fused = n >= THREADED_ROWS and plain_float64((self.x, self.r, self.p, z), n)
        if fused:
            _par.parallel_for(cg_direction_range, n, beta, read_only(z), self.p)
        else:
            self.p *= beta
            self.p += z

    #: the largest contraction per iteration :meth:`error_estimate` assumes
    MAX_RATIO = 0.5

    def error_estimate(self) -> float | None:
        """Estimate the squared A-norm error ``||x* - x||_A^2`` of the iterate (None: no step yet).

        In exact arithmetic the Hestenes-Stiefel terms ``tau_k = alpha_k (r_k, z_k)
        = ||x_(k+1) - x_k||_A^2`` of the iterations from ``x_k`` on sum to
        ``||x* - x_k||_A^2`` (Strakos and Tichy, 2002).  With the last two terms and
        ``q = tau_k / tau_(k-1)`` (at most :data:`MAX_RATIO`), ``tau_k / (1 - q)``
        estimates the error of the previous iterate, which is at least that of the
        current one.  An estimate, not a bound: it relies on the contraction holding
        on; it is sharp for the fast, steady convergence of a multigrid-preconditioned
        CG and costs nothing (``r.z`` and ``alpha`` are formed anyway).
        """
        prev, last = self._tau
        if last is None:
            return None
        q = self.MAX_RATIO if prev is None or prev <= 0.0 else min(last / prev, self.MAX_RATIO)
        return max(last, 0.0) / (1.0 - q)

    def solve(self, rtol: float, maxiter: int) -> int:
        """Iterate until ``||b - A x|| <= rtol ||b||`` (true residual) or round-off.

        Stops after ``maxiter`` iterations at most; returns the count.
        """
        start = self.iterations
        target = rtol * self.b_norm
        replaced = 0
        while self.iterations - start < maxiter and not self.stuck:
            if self.residual_norm > target:
                if not self.step():
                    break
                continue
            true = self.true_residual_norm()
            if true <= target or true <= self.attainable() or replaced >= self.MAX_REPLACEMENTS:
                break
            replaced += 1
            self.restart()
        return self.iterations - start
