"""Geometric multigrid on nested hierarchies, in the kernel threads (issue 33).

Nested iteration solves a problem on a chain of meshes, each the refinement
of the one before (or, for meshes that came from elsewhere, an auxiliary
coarse mesh).  The P1 interpolation between consecutive meshes is known from
the chain (:func:`fastmem.solver.nested.interpolation_matrix`); a multigrid
hierarchy built on it needs no aggregation, no strength graph and no
smoothed prolongators, so its setup is only the coarse operators:

- the Galerkin products ``A_(l+1) = P_l^T A_l P_l``, computed coarse row by
  coarse row in parallel row chunks (:func:`galerkin`,
  :func:`fastmem.kernels.mg.galerkin_rows`); for the Laplacian of nested P1
  meshes they are the coarser meshes' own Laplacians, so where the caller
  knows those (nested iteration and the adaptive loop assemble them anyway)
  it attaches them to the interpolations (:func:`attach_coarse_operator`) and
  no product is formed: each is checked against the finer operator by one
  probe vector and used only where it is that level's Galerkin product to
  round-off (on the structured meshes it is, bit for bit);
- for the gap system of a Newton-min step (the Laplacian with the active
  rows and columns replaced by the diagonal), the *truncated* first
  interpolation ``K P`` (``K`` keeps the inactive vertices): the coarse
  spaces vanish on the active set, as the gap does, and a coarse unknown
  that the mask cuts off entirely gets a unit diagonal;
- the coarsest level (at most :data:`COARSE_DIRECT` unknowns) is factored
  by sparse LU (SuperLU, minimum degree on A + A^T, diagonal pivots); a
  larger one (a chain that stopped early) gets one smoothed-aggregation
  V-cycle of pyamg.

The cycle is a V(1,1): a forward hybrid Gauss-Seidel sweep, the coarse
correction, a backward sweep.  The sweeps are those of
:class:`fastmem.linalg.amg.HybridGaussSeidel` (Gauss-Seidel in fixed row
blocks, Jacobi across them, blocks independent of the thread count), so the
cycle is a symmetric positive definite preconditioner and gives the same
numbers with any number of threads.  Residuals, restrictions and
prolongations are row-chunk kernels (:mod:`fastmem.kernels.mg`).
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from ..kernels import pool as _par
from ..kernels import sparsity as _sparsity
from ..kernels.mg import MAX_ROW, galerkin_rows, galerkin_values, prolong_add_range, residual_range
from ..kernels.smooth import (
    copy_vector,
    cross_block_dominant,
    csr_matvec_range,
    gs_hybrid_range,
)
from .amg import amg_preconditioner, coarse_factor, hybrid_blocks
from .sparse import THREADED_ROWS, as_unsigned, read_only, threaded

__all__ = [
    "COARSE_DIRECT",
    "NestedChain",
    "NestedMG",
    "attach_coarse_operator",
    "galerkin",
    "precompile",
]

#: The coarsest level is factored by sparse LU (:func:`fastmem.linalg.amg.coarse_factor`)
#: up to this many unknowns.  Until 2026-12-04 it was factored densely (Cholesky): 15-90 ms for the
#: 1,000-1,400 interior vertices of an adaptive chain's coarsest mesh and 1.1 ms per
#: solve, against 1.5-2.1 ms and 0.06-0.07 ms for SuperLU (2,581 unknowns: 290-440 ms
#: against 4.5 ms), once per multigrid setup and per active-set update.
COARSE_DIRECT = 2000


def _canonical(a) -> sp.csr_matrix:
    """Return ``a`` as a sorted float64 CSR matrix with int32 indices (int64 when it must)."""
    a = a if sp.isspmatrix_csr(a) else sp.csr_matrix(a)
    if not a.has_sorted_indices:
        a = a.copy()
        a.sort_indices()
    if a.dtype != np.float64:
        a = a.astype(np.float64)
    small = a.nnz < 2**31 - 1 and max(a.shape) < 2**31 - 1
    dt = np.int32 if small else np.int64
    if a.indptr.dtype != dt or a.indices.dtype != dt:
        a = sp.csr_matrix(
            (a.data, a.indices.astype(dt), a.indptr.astype(dt)), shape=a.shape, copy=False
        )
        a.has_sorted_indices = True
    return a


def galerkin(a, p, r=None, keep=None, drop=True) -> sp.csr_matrix:
    """Return ``P^T K A K P`` (CSR, sorted), computed in parallel row chunks.

    ``a``: n x n CSR; ``p``: n x m CSR; ``r``: ``p.T`` as CSR (computed when not
    given); ``keep``: bool (n,), the diagonal of ``K`` (all True when None).  A
    coarse row that ``K`` cuts off entirely gets a unit diagonal.  ``drop``:
    entries that cancel exactly are not stored (with ``drop=False`` the result
    holds the whole pattern of the product, a pattern every masked product
    fits in).  Falls back to scipy's products (serial) when a row would exceed
    :data:`fastmem.kernels.mg.MAX_ROW` entries.
    """
    a, p = _canonical(a), _canonical(p)
    r = _canonical(p.T.tocsr() if r is None else r)
    n, m = p.shape
    if a.shape != (n, n) or r.shape != (m, n):
        raise ValueError(f"galerkin: shapes {a.shape}, {p.shape}, {r.shape} do not match")
    keep_arr = np.ones(n, dtype=np.bool_) if keep is None else np.ascontiguousarray(keep, np.bool_)
    arrays = []
    for mat in (r, a, p):
        arrays += [as_unsigned(mat.indptr), as_unsigned(mat.indices), mat.data]
    counts = np.empty(m, dtype=np.int64)
    # the column indices in the result's index type from the start (no serial astype
    # of the product's nnz afterwards: 66 ms of the default solve at n = 2048); the
    # count pass passes the same type, so that both passes share one compiled kernel
    dt = np.int32 if m < 2**31 - 1 else np.int64
    dummy_i = np.empty(0, dtype=dt)
    dummy_d = np.empty(0, dtype=np.float64)
    _par.parallel_for(galerkin_rows, m, *arrays, keep_arr, False, drop, counts, dummy_i, dummy_d)
    if m and counts.min() < 0:  # a row too long for the kernel's buffer: scipy's products
        k = sp.diags(keep_arr.astype(np.float64))
        out = (r @ (k @ a @ k) @ p).tocsr()
        out.sort_indices()
        if drop:
            out.eliminate_zeros()
        diag = out.diagonal()
        empty = np.diff(out.indptr) == 0
        if empty.any():
            out = (out + sp.diags(np.where(empty & (diag == 0.0), 1.0, 0.0))).tocsr()
        return _canonical(out)
    starts = np.zeros(m, dtype=np.int64)  # each row's first slot (the kernel's cursors)
    np.cumsum(counts[:-1], out=starts[1:])
    nnz = int(starts[-1] + counts[-1]) if m else 0
    if nnz >= 2**31 - 1:
        dt = np.int64
    indptr = np.empty(m + 1, dtype=dt)
    indptr[:-1] = starts
    indptr[-1] = nnz
    idx = np.empty(nnz, dtype=dt)
    data = np.empty(nnz, dtype=np.float64)
    _par.parallel_for(galerkin_rows, m, *arrays, keep_arr, True, drop, starts, idx, data)
    out = sp.csr_matrix((data, idx, indptr), shape=(m, m), copy=False)
    out.has_sorted_indices = True
    return out


def galerkin_into(c, a, p, r, keep, rows=None) -> None:
    """Recompute rows of ``c = P^T K A K P`` in place, on ``c``'s pattern.

    ``c``'s pattern must hold every entry of the product (the unmasked
    product's, cancellations kept: :func:`galerkin` with ``drop=False``).
    ``rows``: the coarse rows to recompute (all when None); the others keep
    their values.  Each row is summed as :func:`galerkin` sums it, so
    recomputing the rows that changed gives the matrix a full recomputation
    gives, bit for bit.
    """
    m = c.shape[0]
    if m and int(np.diff(c.indptr).max()) > MAX_ROW:
        raise ValueError(f"galerkin_into: a coarse row has more than {MAX_ROW} entries")
    rows = np.arange(m, dtype=np.int64) if rows is None else np.asarray(rows, dtype=np.int64)
    arrays = []
    for mat in (r, a, p):
        arrays += [as_unsigned(mat.indptr), as_unsigned(mat.indices), mat.data]
    keep_arr = np.ascontiguousarray(keep, np.bool_)
    _par.parallel_for(
        galerkin_values,
        rows.size,
        rows,
        *arrays,
        keep_arr,
        as_unsigned(c.indptr),
        as_unsigned(c.indices),
        c.data,
    )


def _transpose(p) -> sp.csr_matrix:
    """``P^T``, canonical (:func:`restriction`)."""
    if p.shape[0] < THREADED_ROWS or _par.n_threads() < _sparsity.BLOCK_THREADS:
        return _canonical(p.T.tocsr())
    p = _canonical(p)
    m, n = p.shape
    dt = p.indices.dtype  # canonical: int32 when the entries and both sizes allow
    indptr, indices, data = _sparsity.csr_transpose(p.indptr, p.indices, p.data, n, dt)
    out = sp.csr_matrix((data, indices, indptr), shape=(n, m), copy=False)
    out.has_sorted_indices = True
    return out


def restriction(p) -> sp.csr_matrix:
    """Return ``P^T`` as a canonical CSR matrix, formed once per interpolation ``p``.

    Kept on ``p`` itself: nested iteration builds a chain on every level from the
    links of the level below and one more, so without it a solve of L levels
    formed L (L - 1) / 2 transposes instead of L - 1 (scipy's serial
    ``csr_tocsc``: 0.25 s of the default solve at n = 2048).  ``p`` must not be
    changed in place afterwards (no fastmem code changes an interpolation).

    With :data:`~fastmem.kernels.sparsity.BLOCK_THREADS` kernel threads or more,
    from :data:`~fastmem.linalg.sparse.THREADED_ROWS` rows on, the transpose is
    formed in the kernel threads (:func:`fastmem.kernels.sparsity.csr_transpose`:
    the same matrix, entry for entry); below, by scipy.
    """
    r = getattr(p, "_fastmem_restriction", None)
    if r is None or r.shape != (p.shape[1], p.shape[0]):
        r = _transpose(p)
        try:
            p._fastmem_restriction = r
        except AttributeError:  # pragma: no cover - a matrix type without attributes
            pass
    return r


#: Use the coarse operators attached to the interpolations (:func:`attach_coarse_operator`)
#: instead of forming the Galerkin products; False: always form them (the reference).
ATTACHED_COARSE = True
#: An attached operator ``C`` is used for ``P^T A P`` when, for one probe vector ``x``,
#: ``|P^T A P x - C x|_max <= ATTACHED_RTOL |C|_inf |x|_max`` (round-off passes, a coarse
#: mesh that is not nested in the fine one does not).
ATTACHED_RTOL = 1e-10
_ATTR = "_fastmem_coarse_operator"


def attach_coarse_operator(p, a_coarse) -> None:
    """Record ``a_coarse`` as the operator on the coarse side of the interpolation ``p``.

    ``a_coarse`` (m x m for an n x m ``p``) is the coarse mesh's own matrix of the
    operator whose fine matrix the chain will be given, e.g. the interior Laplacian
    of the coarser mesh of a nested pair: for nested P1 spaces it is the Galerkin
    product ``P^T A P`` in exact arithmetic, and its pattern (every pair of vertices
    of a coarse triangle, stored zeros included) holds that of the product and of
    every masked product, as :meth:`NestedChain.full_operators` needs.  The chain
    checks it before use (:data:`ATTACHED_RTOL`); ``p`` keeps the reference, so
    attach only to an interpolation that lives as long as the operator is useful.
    """
    m = p.shape[1]
    if a_coarse.shape != (m, m):
        raise ValueError(f"attach_coarse_operator: a {a_coarse.shape} operator for a {p.shape} P")
    setattr(p, _ATTR, _canonical(a_coarse))


def _probe_matches(c, a, p, r) -> bool:
    """Tell whether ``c`` is ``r a p`` (``r = p^T``) to round-off, by one probe vector.

    The scale is ``max |c_ij|`` times the longest row of ``c`` (at least its
    largest absolute row sum), so the test costs four products and no copy of ``c``.
    """
    if not c.nnz:
        return False
    x = np.random.default_rng(20261203).random(p.shape[1])
    diff = threaded(r) @ (threaded(a) @ (threaded(p) @ x))
    diff -= threaded(c) @ x
    scale = max(float(c.data.max()), -float(c.data.min())) * int(np.diff(c.indptr).max())
    err = max(float(diff.max()), -float(diff.min()))
    return bool(np.isfinite(err)) and err <= ATTACHED_RTOL * scale


class NestedChain:
    """The interior-to-interior interpolations of a nested chain, finest first.

    ``prolongations[0]`` maps the second finest level to the finest, and so on
    down.  Their transposes (the restrictions) are formed once, on first use,
    and shared by every hierarchy built on the chain.
    """

    def __init__(self, prolongations):
        self.p = [_canonical(q) for q in prolongations]
        #: the coarse operators attached to the interpolations (None where none is)
        self.attached = [getattr(q, _ATTR, None) for q in prolongations]
        #: levels of the last :meth:`full_operators` that used the attached operator
        self.attached_used = 0
        for fine, coarse in zip(self.p, self.p[1:], strict=False):
            if fine.shape[1] != coarse.shape[0]:
                raise ValueError(
                    f"nested chain: a {fine.shape} interpolation follows a {coarse.shape} one"
                )
        self._r = [None] * len(self.p)
        self._full = None  # (base, the unmasked coarse operators, cancellations kept)
        self._blocks = None  # the chain of two unknowns per vertex (blocks())

    def full_operators(self, base) -> list:
        """Return the coarse operators of ``base`` with every entry of their pattern stored.

        ``P_0^T base P_0``, then each next one from the one before; cached for
        ``base`` (the same object) until :meth:`drop_cache`.  Their patterns
        hold every masked product (:meth:`NestedMG.build` for a gap system).
        Where an operator is attached to the level's interpolation
        (:func:`attach_coarse_operator`) and passes the probe against the operator
        above it, it is used instead of the product (:attr:`attached_used` counts
        them); a level below one that was formed is checked the same way.
        """
        if self._full is None or self._full[0] is not base:
            ops, cur = [], _canonical(base)
            used = 0
            for lev in range(len(self.p)):
                c = self.attached[lev] if ATTACHED_COARSE else None
                if c is not None and _probe_matches(c, cur, self.p[lev], self.r(lev)):
                    cur = c
                    used += 1
                else:
                    cur = galerkin(cur, self.p[lev], self.r(lev), drop=False)
                ops.append(cur)
            self._full = (base, ops)
            self.attached_used = used
        return self._full[1]

    def drop_cache(self) -> None:
        """Free the cached coarse operators (:meth:`full_operators` forms them again)."""
        self._full = None

    def __len__(self):
        return len(self.p)

    def blocks(self) -> NestedChain:
        """Return the chain of two unknowns per vertex: ``blockdiag(P_l, P_l)`` per link.

        Cached: the general path's hierarchies (:meth:`with_first`) share it.
        """
        if self._blocks is None:
            self._blocks = NestedChain([sp.block_diag((q, q), format="csr") for q in self.p])
        return self._blocks

    def with_first(self, first) -> NestedChain:
        """Return this chain with its finest link replaced by ``first`` (the rest shared).

        The transposes of the shared links are not formed again.
        """
        out = NestedChain([first] + self.p[1:])
        out._r[1:] = [self.r(k) for k in range(1, len(self.p))]
        return out

    def r(self, level: int) -> sp.csr_matrix:
        """Return the restriction ``P_level^T`` (CSR)."""
        if self._r[level] is None:
            self._r[level] = restriction(self.p[level])
        return self._r[level]

    @property
    def n_fine(self) -> int:
        """Unknowns of the finest level."""
        return self.p[0].shape[0] if self.p else 0


class _Level:
    """One level of a cycle: its operator (kernel arrays) and its sweep's blocks."""

    def __init__(self, a):
        self.a = a
        self.n = a.shape[0]
        self.arrays = (as_unsigned(a.indptr), as_unsigned(a.indices), a.data)
        nb = hybrid_blocks(self.n)
        if nb and not cross_block_dominant(*self.arrays, nb):
            nb = 0  # the hybrid sweep may not converge on this operator: plain Gauss-Seidel
        self.blocks = [(self.n * k // nb, self.n * (k + 1) // nb) for k in range(nb)] or [
            (0, self.n)
        ]
        self.old = None

    def sweep(self, x, b, forward):
        """One hybrid Gauss-Seidel sweep in place (plain Gauss-Seidel with one block)."""
        indptr, indices, data = self.arrays
        if len(self.blocks) == 1:
            gs_hybrid_range(0, self.n, forward, indptr, indices, data, x, x, b)
            return
        if self.old is None:
            self.old = np.empty(self.n)
        old = self.old
        copy_vector(x, old, THREADED_ROWS)

        def one(lo, hi):
            gs_hybrid_range(lo, hi, forward, indptr, indices, data, x, old, b)

        _par.run_pieces(one, self.blocks, _par.n_threads())

    def residual(self, x, b):
        r = np.empty(self.n)
        _par.parallel_for(residual_range, self.n, *self.arrays, x, b, r)
        return r


class NestedMG:
    """V(1,1) geometric multigrid over a :class:`NestedChain`, an SPD preconditioner.

    Parameters
    ----------
    matrix : sparse matrix
        The finest operator (the CG's matrix).
    chain : NestedChain or list of sparse matrices
        Interpolations onto the finest level and below it, finest first.
    stats : dict, optional
        Per-level counters; a build adds to ``{key}_setups`` and
        ``{key}_setup_seconds`` (``key`` "amg" by default, as the AMG setups).
    base, active : optional
        For a gap system: ``base`` is the unmasked operator (the interior
        Laplacian) and ``active`` the active set; the first coarse operator is
        then ``P^T K base K P`` with ``K = diag(~active)``.
    options : dict, optional
        AMG options, for the coarsest level when it is too large to factor.

    The same interface as :class:`fastmem.linalg.amg.LazyAMG`: built on first
    use, :meth:`release` frees the coarse levels (and with ``final`` the chain).
    """

    #: a gap system's hierarchy moves to a new active set by :meth:`update`
    can_update = True

    def __init__(self, matrix, chain, stats=None, base=None, active=None, options=None):
        self.matrix = matrix
        self.chain = chain if isinstance(chain, NestedChain) else NestedChain(chain)
        if self.chain.n_fine != matrix.shape[0]:
            raise ValueError(
                f"nested multigrid: matrix of size {matrix.shape[0]}, chain for {self.chain.n_fine}"
            )
        self.stats = {} if stats is None else stats
        self.base = base
        self.active = None if active is None else np.asarray(active, dtype=bool)
        self.options = options
        self.levels = None
        self._ops = self._base = None
        self.setup_seconds = 0.0
        self.n = matrix.shape[0]

    @property
    def built(self) -> bool:
        """True while a hierarchy exists."""
        return self.levels is not None

    def build(self, key: str = "amg") -> None:
        """Form the coarse operators and factor the coarsest one."""
        t0 = time.perf_counter()
        chain = self.chain
        fine = _canonical(self.matrix)
        ops = [fine]
        self._keep = np.ones(self.n, dtype=np.bool_)
        if len(chain):
            base = _canonical(self.matrix if self.base is None else self.base)
            full = chain.full_operators(self.matrix if self.base is None else self.base)
            if self.active is None:  # the unmasked hierarchy: cancellations dropped
                for op in full:
                    c = op.copy()
                    c.eliminate_zeros()
                    ops.append(c)
            else:  # the gap system's: values of the truncated products on the full patterns
                self._keep = ~self.active
                self._base = base
                for lev, op in enumerate(full):
                    c = sp.csr_matrix(
                        (np.empty_like(op.data), op.indices, op.indptr), shape=op.shape, copy=False
                    )
                    c.has_sorted_indices = True
                    keep = self._keep if lev == 0 else self._ones_of(lev)
                    galerkin_into(c, ops[-1] if lev else base, chain.p[lev], chain.r(lev), keep)
                    ops.append(c)
        self._ops = ops
        self.levels = [_Level(a) for a in ops[:-1]]
        self._transfer = [
            (
                as_unsigned(chain.p[k].indptr),
                as_unsigned(chain.p[k].indices),
                chain.p[k].data,
                as_unsigned(chain.r(k).indptr),
                as_unsigned(chain.r(k).indices),
                chain.r(k).data,
            )
            for k in range(len(chain))
        ]
        self._ones = [self._ones_of(k) for k in range(1, len(chain))]
        self._factor_coarsest()
        self._book(key, time.perf_counter() - t0)

    def _ones_of(self, lev):
        return np.ones(self.chain.p[lev].shape[0], dtype=np.bool_)

    def _book(self, key, seconds):
        self.setup_seconds = seconds
        self.stats[f"{key}_setups"] = self.stats.get(f"{key}_setups", 0) + 1
        self.stats[f"{key}_setup_seconds"] = self.stats.get(f"{key}_setup_seconds", 0.0) + seconds

    def _factor_coarsest(self):
        coarse = self._ops[-1]
        self._factor = self._amg = None
        if coarse.shape[0] <= COARSE_DIRECT:
            self._factor = coarse_factor(coarse)
        else:
            self._amg = amg_preconditioner(threaded(coarse), dict(self.options or {}))

    def update(self, matrix, active) -> float:
        """Move a gap system's hierarchy to a new active set; returns the seconds taken.

        Only the coarse rows near the vertices whose activity changed are
        recomputed, level by level (a row of ``P^T K A K P`` changes only if a
        fine vertex of its support or a neighbour of one changed); the others
        are those a full build gives, so the result is the hierarchy
        :meth:`build` makes for ``active``, bit for bit.  O(size of the change)
        per level, plus the coarsest factorisation.
        """
        if self.active is None:
            raise ValueError("update applies to a gap system's hierarchy (built with active)")
        t0 = time.perf_counter()
        active = np.asarray(active, dtype=bool)
        self.matrix = matrix
        if self.levels is None or not len(self.chain):
            self.active = active
            return time.perf_counter() - t0
        keep = ~active
        flipped = np.flatnonzero(keep != self._keep)
        self.active = active
        self._keep = keep
        self._ops[0] = fine = _canonical(matrix)
        self.levels[0] = _Level(fine)
        if flipped.size:
            chain, ops = self.chain, self._ops
            near = np.union1d(flipped, self._base[flipped].indices)
            rows = np.unique(chain.p[0][near].indices)
            galerkin_into(ops[1], self._base, chain.p[0], chain.r(0), keep, rows)
            for lev in range(1, len(chain)):
                near = np.union1d(rows, ops[lev][rows].indices)
                rows = np.unique(chain.p[lev][near].indices)
                galerkin_into(
                    ops[lev + 1], ops[lev], chain.p[lev], chain.r(lev), self._ones_of(lev), rows
                )
            for lev in range(1, len(self.levels)):  # the sweeps' convergence test, again
                self.levels[lev] = _Level(ops[lev])
            self._factor_coarsest()
        seconds = time.perf_counter() - t0
        self.stats["amg_updates"] = self.stats.get("amg_updates", 0) + 1
        self.stats["amg_update_seconds"] = self.stats.get("amg_update_seconds", 0.0) + seconds
        return seconds

    @property
    def n_levels(self) -> int:
        """Levels of the hierarchy (the finest and the coarsest included)."""
        return len(self.chain) + 1

    def operators(self) -> list:
        """Return the hierarchy's operators, finest first, coarsest included (built if needed)."""
        if self.levels is None:
            self.build()
        return list(self._ops)

    def _coarse_solve(self, b):
        if self._amg is not None:
            return self._amg(b)
        return self._factor.solve(b)

    def _cycle(self, lev, b):
        if lev == len(self.levels):
            return self._coarse_solve(b)
        level = self.levels[lev]
        x = np.zeros(level.n)
        level.sweep(x, b, True)
        r = level.residual(x, b)
        pp, pi, pd, rp, ri, rd = self._transfer[lev]
        m = self.chain.p[lev].shape[1]
        bc = np.empty(m)
        _par.parallel_for(csr_matvec_range, m, rp, ri, rd, read_only(r), bc)
        del r
        xc = self._cycle(lev + 1, bc)
        keep = self._keep if lev == 0 else self._ones[lev - 1]
        _par.parallel_for(prolong_add_range, level.n, pp, pi, pd, keep, xc, x)
        level.sweep(x, b, False)
        return x

    def __call__(self, r: np.ndarray) -> np.ndarray:
        """One V(1,1) cycle from a zero initial guess: ``z ~ A^-1 r``."""
        if self.levels is None:
            self.build()
        b = np.ascontiguousarray(r, dtype=np.float64)
        if not len(self.chain):
            return self._coarse_solve(b)
        return self._cycle(0, b)

    def release(self, final: bool = False):
        """Free the hierarchy (a later call builds it again); ``final``: the chain too."""
        self.levels = self._transfer = self._factor = self._amg = None
        self._ops = self._base = None
        if final:
            self.chain = NestedChain([])


def precompile() -> None:
    """Compile (or load) the kernels of :class:`NestedMG`, with the argument types of a solve.

    On a 1D chain of three levels (7, 3 and 1 interior unknowns): the unmasked
    and the masked hierarchy, an update, one cycle; :func:`fastmem.warm_up`'s
    tiny problem is too small for nested iteration.  With
    :data:`~fastmem.kernels.sparsity.BLOCK_THREADS` threads or more, the
    transpose of the restrictions too.
    """

    def laplacian(n):
        return sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tocsr()

    def interpolation(m):  # m coarse interior unknowns -> 2m+1 fine ones
        rows, cols, vals = [], [], []
        for c in range(m):
            rows += [2 * c, 2 * c + 1, 2 * c + 2]
            cols += [c, c, c]
            vals += [0.5, 1.0, 0.5]
        return sp.csr_matrix((vals, (rows, cols)), shape=(2 * m + 1, m))

    a = laplacian(7)
    chain = NestedChain([interpolation(3), interpolation(1)])
    NestedMG(a, chain)(np.ones(7))
    active = np.zeros(7, dtype=bool)
    active[0] = True
    mg = NestedMG(a, chain, base=a, active=active)
    mg.build()
    active[6] = True
    mg.update(a, active)
    mg(np.ones(7))
    if _par.n_threads() >= _sparsity.BLOCK_THREADS:  # the restrictions of large levels
        p = _canonical(interpolation(3))
        for threads in (1, 2):  # one column block, and several (the column spans)
            _sparsity.csr_transpose(p.indptr, p.indices, p.data, 3, p.indices.dtype, threads, 1)
