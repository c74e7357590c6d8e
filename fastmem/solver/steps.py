r"""Linear steps of Newton-min: one interface, three implementations.

Given the active set of a Newton-min step and the current triple (the warm
start), a linear step computes the next triple ``(u1, u2, lam)`` of docs/method.md
3.2 (general path) or 3.3 (decoupled path) and hands every iterate it wants
judged to the Newton layer's ``check`` (:class:`fastmem.solver.newton.Checks`),
which evaluates the estimators, records the history row and answers whether
the step may stop:

============================  =========================================  ======
class                         how the step is solved                     method
============================  =========================================  ======
:class:`DirectStep`           sparse direct factorisation                "exact"
:class:`AMGStep`              AMG-preconditioned CG to round-off         "exact-amg"
:class:`~fastmem.solver.inexact.    AMG-preconditioned CG stopped by the        "inexact"
AdaptiveStep`                 estimators (docs/method.md §6)
============================  =========================================  ======

Interface (duck-typed)::

    step.exact                        # True: every step is solved to round-off
    step.name                         # "general" or "decoupled" (the formulation)
    report = step.solve(active, [u1, u2, lam], check)   # -> StepReport
    triple = step.face_solve(active, (u1, u2))           # exact solve (safeguard)
    step.at_roundoff()                # the last solve reached round-off
    step.total_iterations             # CG iterations on this level so far (0: direct)
    step.stats                        # AMG setups, checks, ... of this level

A warm start handed over as a list is emptied by ``solve`` once the step
has started from it (:func:`release_warm`): the caller keeps no reference,
so the previous iterate (three vectors of length N) is freed before the
estimators of the new one run.

The formulations themselves (matrices, right-hand sides, the triple of a
solution) are :class:`fastmem.solver.linear.GeneralStep` and
:class:`fastmem.solver.linear.DecoupledStep`; the CG drivers over them are
:class:`GeneralCG` and :class:`DecoupledCG` here.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..estimators.terms import lumped_norm, mass_matrix
from ..kernels import pool as _par
from ..kernels.rows import gap_start_range
from ..kernels.smooth import active_diagonal_range, masked_rhs_range
from ..linalg.amg import PCG, LazyAMG, TwoGridLaplacian, amg_preconditioner
from ..linalg.gmg import NestedChain, NestedMG
from ..linalg.sparse import (
    THREADED_ROWS,
    masked_gap,
    plain_float64,
    read_only,
    submatrix,
    threaded,
)
from .linear import DecoupledStep

__all__ = [
    "EXACT_AMG_RTOL",
    "AMGStep",
    "DecoupledCG",
    "DirectStep",
    "GeneralCG",
    "StepReport",
]

#: Relative residual of the CG solves "to round-off" (``exact-amg`` and safeguard face solves).
EXACT_AMG_RTOL = 1e-12


@dataclass
class StepReport:
    """What a linear step tells the Newton loop: CG iterations of the step, iteration limit hit."""

    iterations: int = 0
    hit_max: bool = False


def release_warm(triple):
    """Empty a warm start handed over as a list: its arrays are freed once the step has started."""
    if isinstance(triple, list):
        triple.clear()


def new_stats() -> dict:
    """Per-level counters of the AMG steps (``parameters["solver"]["levels"]``)."""
    return {"amg_setups": 0, "amg_setup_seconds": 0.0, "checks": 0, "skipped_checks": 0}


def _resetup(matrix, options, stats):
    """Rebuild a hierarchy freed by a spill (booked apart: ``spill_setups``, not ``amg_setups``)."""
    pre = amg_preconditioner(matrix, dict(options.amg_options))
    stats["spill_setups"] = stats.get("spill_setups", 0) + 1
    stats["spill_setup_seconds"] = stats.get("spill_setup_seconds", 0.0) + pre.setup_seconds
    return pre


class GeneralCG:
    """CG on the reduced SPD system of one active set (general path, docs/method.md §3.2).

    Preconditioner: pyamg's smoothed aggregation, set up for every new active set; on
    a level of nested iteration with a :class:`fastmem.linalg.gmg.NestedChain`
    (``chain``), the geometric multigrid over the chain's block interpolations
    (:meth:`_geometric`).
    """

    def __init__(self, system, options, stats, chain=None):
        self.system = system
        self.options = options
        self.stats = stats
        self.active = None
        self.chain = chain if isinstance(chain, NestedChain) and len(chain) else None

    def _geometric(self, mat, active, key="amg"):
        """Build the geometric multigrid of the reduced matrix ``mat`` of ``active``.

        The reduced unknowns are u1 on the interior and u2 on its inactive vertices
        (u2 = u1 - g on the active ones); the coarse spaces hold both membranes on
        the coarser meshes, interpolated by ``P`` and restricted to the reduced
        unknowns: ``blockdiag(P_0, P_0[inactive])`` onto the finest level, then
        ``blockdiag(P_l, P_l)``.  The coarse operators are Galerkin products of the
        reduced matrix, so per-triangle tensions need no coarse tensions.
        """
        p0 = self.chain.p[0]
        first = sp.block_diag((p0, p0[~active]), format="csr")
        chain = self.chain.blocks().with_first(first)
        pre = NestedMG(mat, chain, self.stats, options=self.options.amg_options)
        pre.build(key)
        return pre

    def start(self, active, u1, u2):
        """Set up the CG of the step with active set ``active``, warm-started at ``(u1, u2)``."""
        st = self.system
        ii = st.interior
        p = st.prolongation(active)
        if self.active is None or not np.array_equal(active, self.active):
            self.mat = threaded((p.T @ st.k_ii @ p).tocsr())  # new size: new hierarchy
            if self.chain is not None:
                self.pre = self._geometric(self.mat, active)  # books its own setup
            else:
                self.pre = amg_preconditioner(self.mat, dict(self.options.amg_options))
                self.stats["amg_setups"] += 1
                self.stats["amg_setup_seconds"] += self.pre.setup_seconds
        self.active = active.copy()
        self.p = p
        rhs = p.T @ np.concatenate([st.rhs1, st.rhs2])
        x0 = np.concatenate([u1[ii], u2[ii][~active]])
        self.cg = PCG(self.mat, rhs, x0, self.pre)

    def iterate(self, budget, s_share):
        """One CG iteration; returns 0 when CG cannot proceed (at round-off)."""
        return 1 if self.cg.step() else 0

    def spill(self):
        """Free what the flux reconstruction does not need: matrices, hierarchy, prolongation.

        ``K_II``, ``A1_II`` (about 340 bytes per vertex together), and of the current
        step the reduced matrix, its AMG hierarchy, the prolongation ``P`` and the CG's
        right-hand side; :meth:`restore` rebuilds all of it bit for bit (the assembly,
        the products and the smoothed-aggregation setup are deterministic) when the
        iteration goes on (see :meth:`DecoupledCG.spill`).
        """
        st = self.system
        if st.k_ii is None:
            return
        st.k_ii = st.a1_ii = None
        if self.active is not None:
            self.mat = self.pre = self.p = None
            self.cg.a = self.cg.b = self.cg.m = None

    def restore(self):
        """Rebuild what :meth:`spill` freed (no-op when nothing was freed)."""
        st = self.system
        if st.k_ii is not None:
            return
        ii = st.interior
        st.a1_ii = submatrix(st.scene.weighted_stiffness(1), ii, ii)  # as GeneralStep makes it
        st.k_ii = st.reduced_stiffness()
        if self.active is not None:
            p = self.p = st.prolongation(self.active)
            self.mat = self.cg.a = threaded((p.T @ st.k_ii @ p).tocsr())
            self.cg.b = p.T @ np.concatenate([st.rhs1, st.rhs2])
            if self.chain is not None:
                self.pre = self.cg.m = self._geometric(self.mat, self.active, "spill")
            else:
                self.pre = self.cg.m = _resetup(self.mat, self.options, self.stats)

    def solve_exact(self):
        """Iterate to round-off; return the CG iterations done (all CGs)."""
        return self.cg.solve(EXACT_AMG_RTOL, 10 * self.options.max_inner)

    @property
    def iterations(self):
        """CG iterations of the current step (the gap CG on the decoupled path)."""
        return self.cg.iterations

    def at_roundoff(self):
        """Return True when the current solve is at round-off."""
        return self.cg.at_roundoff(EXACT_AMG_RTOL)

    def residual(self):
        """Relative CG residual, the predictor of eta_alg between checks."""
        return self.cg.relative_residual

    def true_relative_residual(self):
        """Return the true relative residual of the current solve (the largest over its CGs)."""
        return self.cg.true_residual_norm() / self.cg.b_norm

    def triple(self):
        """Full triple of the current CG iterate."""
        return self.system.triple(self.active, self.p @ self.cg.x)

    def energy_error_estimate(self) -> float:
        """Return the CG's estimate of the algebraic error in the energy norm (inf before a step).

        The reduced matrix's norm is the energy norm of ``(u1, u2)``
        (:meth:`fastmem.linalg.amg.PCG.error_estimate`; not a bound).
        """
        e = self.cg.error_estimate()
        return math.inf if e is None else math.sqrt(e)


def gap_matrix(a, active):
    """``keep A keep + diag(A) on the active set`` (``keep`` = inactive indicator), CSR.

    Bit for bit the matrix scipy makes of
    ``(diags(~active) @ a @ diags(~active) + diags(a.diagonal() * active)).tocsr()``
    for a canonical CSR ``a`` (sorted indices, no duplicates, a stored
    diagonal): the entries of ``a`` in inactive rows and columns and the
    diagonal of the active rows, in ``a``'s order, stored zeros dropped, the
    index dtype of ``a`` kept.  Built by one pass of masks over ``a``'s entries
    instead of three full temporaries of the matrix; from :data:`THREADED_ROWS`
    rows on, by two passes over row chunks in the kernel threads
    (:func:`fastmem.linalg.sparse.masked_gap`, the same arrays).
    """
    if a.shape[0] >= THREADED_ROWS:
        out = masked_gap(a, active)
        if out is not None:
            return out
    return _gap_matrix_numpy(a, active)


def _gap_matrix_numpy(a, active):
    """:func:`gap_matrix` by NumPy masks over the entries (small matrices, and the reference)."""
    n = a.shape[0]
    indptr, indices, data = a.indptr, a.indices, a.data
    inactive = ~active
    counts = np.diff(indptr)
    row_active = np.repeat(active, counts)  # bool per entry
    take = np.repeat(inactive, counts)
    take &= inactive[indices]
    take &= data != 0.0
    # the diagonal of the active rows (a.diagonal() keeps it even where it is zero:
    # scipy then drops it from the sum, as does the test of its value below)
    rows = np.repeat(np.arange(n, dtype=indices.dtype), counts)
    row_active &= indices == rows
    del rows
    row_active &= data != 0.0
    take |= row_active
    del row_active
    cum = np.cumsum(take, dtype=indptr.dtype)  # nnz fits a's index dtype
    new_ptr = np.zeros(n + 1, dtype=indptr.dtype)
    ends = indptr[1:]
    nz = ends > 0
    new_ptr[1:][nz] = cum[ends[nz] - 1]
    del cum
    out = sp.csr_matrix((data[take], indices[take], new_ptr), shape=a.shape, copy=False)
    out.has_sorted_indices = a.has_sorted_indices
    return out


def gap_delta(a, old, new):
    """``gap_matrix(a, new) - gap_matrix(a, old)`` on the only rows and columns it touches.

    Returns ``(index, delta)``: the sorted vertices whose rows or columns change (the
    vertices whose activity changed and their neighbours in ``a``) and the difference
    restricted to them, a CSR matrix of size ``len(index)``.  O(size of the change).
    """
    flipped = np.flatnonzero(old != new)
    index = np.union1d(flipped, a[flipped].indices)
    rows = a[index]  # the rows of index; their columns mapped into index (those inside)
    pos = np.searchsorted(index, rows.indices)
    pos[pos == index.size] = 0
    inside = index[pos] == rows.indices
    kept = np.concatenate([[0], np.cumsum(inside)])
    ptr = kept[rows.indptr].astype(rows.indptr.dtype)  # entries kept before each row
    sub = sp.csr_matrix(
        (rows.data[inside], pos[inside].astype(rows.indices.dtype), ptr),
        shape=(index.size, index.size),
    )
    sub.sort_indices()
    delta = gap_matrix(sub, new[index]) - gap_matrix(sub, old[index])
    delta.eliminate_zeros()
    return index, delta


class _WeakCall:
    """A bound method called through a weak reference to its object.

    The gap CG belongs to its :class:`DecoupledCG`; holding the preconditioner as a
    plain bound method made a reference cycle (CG -> method -> DecoupledCG -> CG), so
    a level's matrices, hierarchies and interpolation lived on until Python's cycle
    collector ran -- during the finer levels' solves and flux reconstructions
    (104-267 bytes per finest vertex measured in review).
    """

    def __init__(self, method):
        self._ref = weakref.WeakMethod(method)

    def __call__(self, r):
        return self._ref()(r)


class DecoupledCG:
    """CGs for the sum s (one for the level) and the gap w (one per step), docs/method.md §3.3.

    The gap system is the interior Laplacian with the rows and columns of the
    active set replaced by its diagonal (``w = 0`` there), of fixed size; its
    AMG setup is kept while the active set differs from the one it was built
    for in at most ``amg_reuse`` of the interior vertices, with the coarse
    operators updated to the current active set (:meth:`_update_w`; a stale
    hierarchy slowed CG down four-fold).
    """

    def __init__(self, system, options, stats, prolongation=None):
        self.system = system
        self.options = options
        self.stats = stats
        a = system.a_ii = threaded(system.a_ii)  # a view: CG products in the kernel threads
        self.a_ii = a
        self.diag = a.diagonal()
        # the Laplacian's preconditioner, built when first applied (the CG of s, or of w
        # while the active set is close to empty): on the finest level s usually needs no
        # iteration, and an unused hierarchy is a setup and ~120 bytes per vertex wasted.
        # On a level of nested iteration (``prolongation``: interpolation from the coarser
        # level, interior to interior) a two-grid cycle over the coarser level's operator
        #: the nested chain of the geometric multigrid (None: pyamg for the gap system)
        self.chain = prolongation if isinstance(prolongation, NestedChain) else None
        if self.chain is not None:
            self.pre_all = NestedMG(a, self.chain, stats, options=options.amg_options)
        elif prolongation is not None:
            self.pre_all = TwoGridLaplacian(a, prolongation, options.amg_options, stats)
        else:
            self.pre_all = LazyAMG(a, options.amg_options, stats)
        self.pre_w = self.pre_all
        self.setup_active = np.zeros(system.interior.size, dtype=bool)
        self.update_active = self.setup_active  # the active set the gap hierarchy is for
        self.cg_s = None
        self.cg_w = None
        self.s_done = False
        self.active = None
        self._rhs = None  # the masked right-hand side of the gap preconditioner (large)

    def start(self, active, u1, u2):
        """Set up the CG of the step with active set ``active``, warm-started at ``(u1, u2)``."""
        st = self.system
        ii = st.interior
        if self.cg_s is None:
            s0 = (st.mu1 * u1 + st.mu2 * u2)[ii]
            self.cg_s = PCG(self.a_ii, st.rhs_s, s0, self.pre_all, copy=False)
        self.cg_w = None  # the previous gap matrix and CG vectors: free them first
        mat = threaded(gap_matrix(self.a_ii, active))
        changed = int(np.count_nonzero(active != self.setup_active))
        if self.chain is not None:
            # geometric multigrid: coarse operators of the truncated interpolation; a new
            # active set recomputes the coarse rows near the vertices that changed
            # (NestedMG.update: the hierarchy a new build would give, bit for bit)
            if not active.any():
                self.pre_w = self.pre_all
            elif self.pre_w is self.pre_all:
                self.pre_w = self._gmg_w(mat, active)
            elif changed:
                self.pre_w.update(mat, active)
            self.setup_active = self.update_active = active.copy()
        elif changed > self.options.amg_reuse * active.size:
            self.pre_w = None  # free the old hierarchy before the new one is built
            if self.s_done:
                self._drop_all()
            self.pre_w = amg_preconditioner(mat, dict(self.options.amg_options))
            self.stats["amg_setups"] += 1
            self.stats["amg_setup_seconds"] += self.pre_w.setup_seconds
            self.setup_active = active.copy()
            self.update_active = self.setup_active
        elif (
            self.pre_w is not self.pre_all
            and self.pre_w.can_update
            and not np.array_equal(active, self.update_active)
        ):
            # a few thousand vertices changed: same prolongators, exact coarse operators
            self._update_w(mat, active)
        rhs, w0 = self._gap_start(active, u1, u2)
        self.active = active.copy()
        self.cg_w = PCG(mat, rhs, w0, _WeakCall(self._masked), copy=False)

    def _gap_start(self, active, u1, u2):
        """Return the gap CG's right-hand side and start (0 on ``active``)."""
        st = self.system
        ii = st.interior
        n = ii.size
        if (
            n < THREADED_ROWS
            or not plain_float64((st.rhs_w,), n)
            or not plain_float64((u1, u2), st.n)
        ):
            return np.where(active, 0.0, st.rhs_w), np.where(active, 0.0, (u1 - u2)[ii])
        rhs, w0 = np.empty(n), np.empty(n)
        _par.parallel_for(
            gap_start_range, n, read_only(ii), read_only(active), read_only(st.rhs_w),
            read_only(u1), read_only(u2), rhs, w0,
        )  # fmt: skip
        return rhs, w0

    def _gmg_w(self, mat, active, key="amg"):
        """Build the geometric multigrid of the gap matrix ``mat`` of ``active``."""
        pre = NestedMG(
            mat,
            self.chain,
            self.stats,
            base=self.a_ii,
            active=active,
            options=self.options.amg_options,
        )
        pre.build(key)
        return pre

    def _update_w(self, mat, active):
        """Galerkin update of the gap hierarchy to ``active`` (:meth:`AMGPreconditioner.update`)."""
        index, delta = gap_delta(self.a_ii, self.setup_active, active)
        seconds = self.pre_w.update(mat, index, delta)
        self.stats["amg_updates"] = self.stats.get("amg_updates", 0) + 1
        self.stats["amg_update_seconds"] = self.stats.get("amg_update_seconds", 0.0) + seconds
        self.update_active = active.copy()

    def spill(self):
        """Free the interior Laplacian, the gap matrix and the hierarchies during a flux.

        The flux needs only the mesh, the data and the triple.  Freed: the interior
        Laplacian and its diagonal, the gap matrix and the gap CG's right-hand side
        (about 150 bytes per vertex), and the AMG hierarchies (about 100 each, and
        after an update 16 more for the setup's coarse operators); all
        rebuilt bit for bit by :meth:`restore` (the matrices are assembled again, the
        smoothed-aggregation setup is deterministic), which the inexact step calls
        when the iteration goes on after the check
        (:class:`fastmem.solver.inexact.AdaptiveStep`).  On the accepted (last) check of a
        level nothing is rebuilt.
        """
        if self.a_ii is None:
            return
        self.a_ii = self.system.a_ii = self.pre_all.matrix = self.diag = None
        self._rhs = None
        if self.cg_s is not None:
            self.cg_s.a = None
        if self.cg_w is not None:
            self.cg_w.a = self.cg_w.b = None
        self._rebuild = (self.pre_all.built, self.pre_w is not self.pre_all)
        if self.chain is not None:
            self.chain.drop_cache()  # the coarse operators of the chain: formed again
        self.pre_all.release()
        if self._rebuild[1]:
            self.pre_w = None

    def restore(self):
        """Rebuild what :meth:`spill` freed (no-op when nothing was freed)."""
        if self.a_ii is not None:
            return
        a = self.system.a_ii = threaded(self.system.interior_laplacian())
        self.a_ii = self.pre_all.matrix = a
        self.diag = a.diagonal()
        if self.cg_s is not None:
            self.cg_s.a = a
        if self.cg_w is not None:
            self.cg_w.a = threaded(gap_matrix(a, self.active))
            self.cg_w.b = np.where(self.active, 0.0, self.system.rhs_w)
        rebuild_all, rebuild_w = self._rebuild
        if rebuild_all:
            self.pre_all.build("spill")
        if rebuild_w and self.chain is not None:
            same = self.cg_w is not None and np.array_equal(self.setup_active, self.active)
            mat = self.cg_w.a if same else gap_matrix(a, self.setup_active)
            self.pre_w = self._gmg_w(mat, self.setup_active, "spill")
        elif rebuild_w:
            # the hierarchy of the setup's active set (often the current one: its matrix)
            same = self.cg_w is not None and np.array_equal(self.setup_active, self.active)
            mat = self.cg_w.a if same else gap_matrix(a, self.setup_active)
            self.pre_w = _resetup(mat, self.options, self.stats)
            if not np.array_equal(self.update_active, self.setup_active):
                # the Galerkin update is relative to the setup: the same hierarchy again
                target = self.update_active
                mat = self.cg_w.a if np.array_equal(target, self.active) else gap_matrix(a, target)
                index, delta = gap_delta(a, self.setup_active, target)
                self.pre_w.update(mat, index, delta)

    def _s_finished(self):
        """Mark s done (at round-off): free its search vectors and, if unused, its hierarchy."""
        self.s_done = True
        self.cg_s.release()
        if self.pre_w is not self.pre_all:
            # used by nothing else: a two-grid cycle also drops its interpolation
            self._drop_all()

    def _drop_all(self):
        """Free the Laplacian's preconditioner once s is done and w has its own hierarchy.

        Nothing uses it again on this level (``pre_w`` never returns to it); a two-grid
        cycle also drops its interpolation.
        """
        self.pre_all.release(final=True)

    def _masked(self, r):
        # the hierarchy may belong to an older active set: keep w = 0 on the current one
        n = r.shape[0]
        if n < THREADED_ROWS or not plain_float64((r, self.diag), n):
            z = self.pre_w(np.where(self.active, 0.0, r))
            z[self.active] = r[self.active] / self.diag[self.active]
            return z
        # large: the same values from the kernel threads, the masked vector in a buffer
        # of the step (the cycle reads it during the call only)
        if self._rhs is None or self._rhs.shape[0] != n:
            self._rhs = np.empty(n)
        active, rr = self.active, read_only(r)
        _par.parallel_for(masked_rhs_range, n, active, rr, self._rhs)
        z = self.pre_w(self._rhs)
        if z is self._rhs or not plain_float64((z,), n) or not z.flags.writeable:
            z = np.array(z, dtype=np.float64)  # never hand out the buffer itself
        _par.parallel_for(active_diagonal_range, n, active, rr, read_only(self.diag), z)
        return z

    def iterate(self, budget, s_share):
        """One CG iteration on w, and one on s while s holds over half the budget.

        Returns the number of CG iterations done: 0 when neither CG can proceed.
        """
        done = 1 if self.cg_w.step() else 0
        if self.s_done or (done and s_share <= 0.5 * budget):
            return done
        if self.cg_s.relative_residual <= EXACT_AMG_RTOL:
            if self.cg_s.at_roundoff(EXACT_AMG_RTOL):
                self._s_finished()
                return done
            self.cg_s.restart()  # the recursive residual drifted: replace it
        if self.cg_s.step():
            return done + 1
        self._s_finished()  # stuck: at round-off
        return done

    def solve_exact(self):
        """Iterate to round-off; return the CG iterations done (all CGs)."""
        n = 0
        if not self.s_done:
            n += self.cg_s.solve(EXACT_AMG_RTOL, 10 * self.options.max_inner)
            self._s_finished()
        return n + self.cg_w.solve(EXACT_AMG_RTOL, 10 * self.options.max_inner)

    @property
    def iterations(self):
        """CG iterations of the current step (the gap CG on the decoupled path)."""
        return self.cg_w.iterations

    def at_roundoff(self):
        """Return True when the current solve is at round-off."""
        s_ok = self.s_done or self.cg_s.at_roundoff(EXACT_AMG_RTOL)
        return s_ok and self.cg_w.at_roundoff(EXACT_AMG_RTOL)

    def residual(self):
        """Relative CG residual of the gap, the predictor of eta_alg between checks."""
        return self.cg_w.relative_residual

    def true_relative_residual(self):
        """Return the true relative residual of the current solve (the largest over its CGs)."""
        return max(cg.true_residual_norm() / cg.b_norm for cg in (self.cg_s, self.cg_w))

    def triple(self):
        """Full triple of the current CG iterate."""
        st = self.system
        return st.triple(self.active, self.cg_s.x, self.cg_w.x)  # s: interior values

    def _squared_error(self, cg, done) -> float:
        if done:
            return 0.0
        e = cg.error_estimate()
        return math.inf if e is None else e

    def energy_error_estimate(self, s_part=None) -> float:
        """Return the CGs' estimate of the algebraic error in the energy norm (not a bound).

        ``mu1 |e1|_1^2 + mu2 |e2|_1^2 = (|e_s|_1^2 + mu1 mu2 |e_w|_1^2) / (mu1 + mu2)``
        for the errors of ``s`` and ``w`` in the Laplacian's norm, which the gap matrix's
        equals on the gap's error (0 on the active set); each from its CG
        (:meth:`fastmem.linalg.amg.PCG.error_estimate`; inf before its first step).
        ``s_part``: the part of ``s`` to take while its CG has made no step (its share
        of the guaranteed eta_alg, :meth:`s_share`: ``s`` often needs none).
        """
        st = self.system
        es = self._squared_error(self.cg_s, self.s_done)
        if math.isinf(es) and s_part is not None:
            es = s_part**2 * (st.mu1 + st.mu2)
        ew = self._squared_error(self.cg_w, False)
        return math.sqrt((es + st.mu1 * st.mu2 * ew) / (st.mu1 + st.mu2))

    def s_error_estimate(self) -> float:
        """Return the part of :meth:`energy_error_estimate` due to ``s`` (0 once ``s`` is done)."""
        st = self.system
        return math.sqrt(self._squared_error(self.cg_s, self.s_done) / (st.mu1 + st.mu2))

    def s_share(self, mass, c_f):
        """Return the part of eta_alg due to the residual of s: C_F ||R_s/B|| / sqrt(mu1 + mu2).

        ``mass``: the consistent mass matrix, or None on meshes where the norm comes from
        the element mass matrices (:func:`fastmem.estimators.terms.lumped_norm`).
        """
        st = self.system
        if mass is None:
            r = st._full(self.cg_s.r)  # 0 on the boundary
            norm = lumped_norm(st.scene, r)
            if norm is not None:
                return c_f * norm / math.sqrt(st.mu1 + st.mu2)
            mass = mass_matrix(st.scene)
        rho = np.zeros(st.n)
        rho[st.interior] = self.cg_s.r / st.b_int
        return c_f * math.sqrt(max(float(rho @ (mass @ rho)), 0.0) / (st.mu1 + st.mu2))


class DirectStep:
    """Every step solved by a sparse direct factorisation (method "exact")."""

    exact = True
    total_iterations = 0

    def __init__(self, system, options=None):
        self.system = system
        self.name = system.name
        self.stats = {}

    def solve(self, active, triple, check) -> StepReport:
        """Solve the step of ``active`` from ``triple`` and hand the result to ``check``."""
        release_warm(triple)
        check(self.system.solve(active), 0, True)
        return StepReport()

    def face_solve(self, active, warm):
        """Solve the step of ``active`` to round-off (safeguard face solve); return the triple."""
        return self.system.solve(active)

    def at_roundoff(self) -> bool:
        """Return True when the last solve reached round-off."""
        return True

    def true_relative_residual(self) -> float:
        """Return the true relative residual of the last solve."""
        return 0.0

    @property
    def factorizations(self) -> int:
        """Number of sparse factorisations so far."""
        return self.system.factorizations


class AMGStep:
    """Every step solved by AMG-preconditioned CG to round-off (method "exact-amg")."""

    exact = True

    def __init__(self, system, options, prolongation=None):
        self.name = system.name
        self.options = options
        self.stats = new_stats()
        self.decoupled = isinstance(system, DecoupledStep)
        if self.decoupled:
            self.cg = DecoupledCG(system, options, self.stats, prolongation)
        else:
            self.cg = GeneralCG(system, options, self.stats, prolongation)
        self.total_iterations = 0

    def face_solve(self, active, warm):
        """Solve the step of ``active`` to round-off (safeguard face solve); return the triple."""
        self.cg.start(active, warm[0], warm[1])
        self.total_iterations += self.cg.solve_exact()
        return self.cg.triple()

    def solve(self, active, triple, check) -> StepReport:
        """Solve the step of ``active`` from ``triple`` and hand the result to ``check``."""
        warm = (triple[0], triple[1])
        release_warm(triple)
        triple = self.face_solve(active, warm)
        del warm
        n = self.cg.iterations
        check(triple, n, False)
        return StepReport(iterations=n)

    def at_roundoff(self) -> bool:
        """Return True when the last solve reached round-off."""
        return self.cg.at_roundoff()

    def true_relative_residual(self) -> float:
        """Return the true relative residual of the last solve."""
        return self.cg.true_relative_residual()
