r"""The linear step of method "inexact": AMG-preconditioned CG stopped by the estimators.

docs/method.md §3.4 and 6.  Every inner (CG) iterate is mapped to a full
triple ``(u1, u2, lam)`` (``lam = 0`` on the inactive set, ``lam`` from the
first equation on the active set), its residuals ``R1, R2`` are formed and the
estimators are evaluated on it.  With :math:`\gamma_{alg}, \gamma_{lin}`
(default 0.1):

- inner stop: :math:`\eta_{alg} \le \gamma_{alg} \max(\eta_{disc}, \eta_{lin})`;
- outer stop: :math:`\eta_{lin} \le \gamma_{lin} \eta_{disc}` and the inner stop.

Cost control.  :math:`\eta_{alg}` and :math:`\eta_{lin}` are O(N) vector work
and are evaluated every ``check_every`` CG iterations.  :math:`\eta_{disc}`
needs the flux reconstruction; it is recomputed only when the cheap
components say that a stopping test could pass with the last known value
(the value of an earlier iterate of this level, or the coarser level's value
scaled by the mesh-size ratio).  A stop is only ever accepted with a fresh
:math:`\eta_{disc}` of the very iterate that is returned, so both criteria
hold for the returned triple exactly as recomputed from scratch.

The estimators and both criteria are evaluated by the Newton layer
(:class:`fastmem.solver.newton.Checks`, called at every check); this module decides
when to check: every ``check_every`` CG iterations, except while the
algebraic estimator predicted from the CG residual is still far above its
budget.  Method ``"exact-amg"`` (:class:`fastmem.solver.steps.AMGStep`) solves the
same systems to round-off instead.

Linear steps:

- general path: CG on the reduced SPD system :math:`P^T K P x = P^T (F - K u_B)`
  (docs/method.md §3.2), with a fresh AMG hierarchy whenever the active set changed
  (the system changes size);
- decoupled path: one CG for the sum ``s`` on the interior Laplacian
  (hierarchy built once, advanced only while its part of :math:`\eta_{alg}`
  exceeds half of the algebraic budget) and one CG per Newton step for the
  gap ``w`` on the fixed-size matrix that is the interior Laplacian with the
  rows and columns of the active set replaced by its diagonal (``w = 0``
  there).  Its AMG setup is kept while the active set has changed in at most
  ``amg_reuse`` (a fraction) of the interior vertices since the last setup
  (the coarse operators updated to each new active set), and redone otherwise.
"""

from __future__ import annotations

import logging
import math

from ..estimators.terms import BLOCK_SUM_TRIANGLES, friedrichs_constant, mass_matrix
from ..linalg.sparse import threaded
from ..memory import estimate_memory, meminfo_bytes, memory_limit, rss_bytes
from .history import ADAPTIVE_HISTORY_COLUMNS
from .steps import EXACT_AMG_RTOL, AMGStep, StepReport, release_warm

__all__ = [
    "ADAPTIVE_HISTORY_COLUMNS",
    "MAX_SKIP",
    "SKIP_MARGIN",
    "SPILL",
    "SPILL_FRACTION",
    "SPILL_MIN_TRIANGLES",
    "AdaptiveStep",
    "memory_pressure",
]

logger = logging.getLogger(__name__)

#: A check is skipped while the algebraic estimator predicted from the CG residual,
#: eta_alg(last check) * |r| / |r(last check)|, exceeds SKIP_MARGIN times the budget ...
SKIP_MARGIN = 1.5
#: ... but never for more than MAX_SKIP - 1 consecutive CG iterations.
MAX_SKIP = 4

#: Whether the inexact step spills (:meth:`AdaptiveStep.spill`): ``"auto"`` under memory
#: pressure (:func:`memory_pressure`) and on large decoupled meshes
#: (:data:`SPILL_MIN_TRIANGLES`), ``True`` always, ``False`` never.  Results are the
#: same bit for bit either way; spilling lowers the peak of the flux reconstructions and
#: costs a rebuild (assembly, products, AMG setups) after every check that does not end
#: the level (about 6-7 % of the general path's time at n = 512).
SPILL = "auto"

#: ``"auto"`` spills when the memory guard's estimate of the solve on the step's mesh
#: (:func:`fastmem.memory.estimate_memory`) exceeds this fraction of the memory at hand.
SPILL_FRACTION = 0.5

#: ``"auto"`` also spills on the decoupled path from this many triangles on.  There a flux
#: check nearly always ends its level (every level of at least 2^18 triangles did in the
#: default, manufactured and adaptive runs of the benchmarks), so the rebuild is rarely
#: paid, and the flux then takes memory the process has just freed instead of new memory
#: (first default solve at n = 1024 on the 2-core VM: median 5.44 -> 4.58 s over 4 fresh
#: processes each, peak 1.39 -> 1.24 GB; docs/performance.md).  The general path keeps the
#: memory-pressure rule: its checks often do not end the level.
SPILL_MIN_TRIANGLES = 1 << 18


def memory_pressure(mesh, fraction=None, limit=None) -> bool:
    """Return True when a solve on ``mesh`` may come close to the memory the process can use.

    The memory guard's estimate of the peak (method ``"inexact"`` with the bound)
    against ``fraction`` (default :data:`SPILL_FRACTION`) of the smaller of the
    guard's limit (:func:`fastmem.memory.memory_limit` of ``limit``: the
    ``memory_limit`` of :func:`fastmem.solve`, else ``FASTMEM_MEMORY_LIMIT`` or the
    machine's memory; ``False`` disables it) and what the process could still reach
    (its resident memory plus the system's ``MemAvailable``; Linux only, ignored
    elsewhere).
    """
    fraction = SPILL_FRACTION if fraction is None else fraction
    need = estimate_memory(mesh.n_vertices, mesh.n_triangles, "inexact", True)
    room = [memory_limit(limit)[0]]
    avail = meminfo_bytes("MemAvailable")
    if avail is not None:
        room.append(avail + rss_bytes())
    room = [r for r in room if r]
    return bool(room) and need > fraction * min(room)


def _mass(scene):
    """Return the mass matrix for :meth:`DecoupledCG.s_share`, or None where it needs none.

    From :data:`fastmem.estimators.terms.BLOCK_SUM_TRIANGLES` triangles the norm comes
    from the element mass matrices (:func:`fastmem.estimators.terms.lumped_norm`): no
    assembled matrix (56 bytes per vertex) lives through the level.
    """
    if scene.mesh.n_triangles >= BLOCK_SUM_TRIANGLES:
        return None
    return threaded(mass_matrix(scene))


def _wants_spill(mesh, limit=None, decoupled=False) -> bool:
    if SPILL == "auto":
        if decoupled and mesh.n_triangles >= SPILL_MIN_TRIANGLES:
            return True
        return memory_pressure(mesh, limit=limit)
    return bool(SPILL)


class AdaptiveStep(AMGStep):
    """CG iterations of one Newton-min step, checked by the estimators until the step may stop.

    ``check_all`` (``full_history``): check after every ``check_every``
    iterations, never skip.
    """

    exact = False

    def __init__(self, system, options, check_all=False, prolongation=None):
        super().__init__(system, options, prolongation)
        self.check_all = check_all
        #: the CGs' own error estimate steers them too (``alg_estimate="cg"``)
        self.cg_estimate = options.alg_estimate == "cg"
        if self.decoupled:  # the share of s in eta_alg steers its CG
            self.mass = _mass(system.scene)
            self.c_f = friedrichs_constant(system.scene.mesh)
        self.spilling = _wants_spill(system.scene.mesh, options.memory_limit, self.decoupled)
        self.stats["spill"] = self.spilling

    def spill(self):
        """Before a flux reconstruction: free what it does not need (when :data:`SPILL` says so).

        The CG's matrices, AMG hierarchies and recomputable vectors
        (:meth:`fastmem.solver.steps.DecoupledCG.spill`,
        :meth:`fastmem.solver.steps.GeneralCG.spill`),
        the consistent mass matrix (56 bytes per vertex) and the stiffness matrices
        (``A``, ``mu_i A``: 60-90 bytes per vertex each) cached on the scene, which the
        scene assembles again on their next use.  Called by
        :class:`fastmem.solver.newton.Checks` right before it reconstructs the flux;
        :meth:`restore` rebuilds all of it bit for bit when the level goes on, so only
        the memory peak and the time change, not a result.  With :data:`SPILL`
        ``"auto"`` nothing is freed on a mesh below :data:`SPILL_MIN_TRIANGLES` (or on
        the general path) without memory pressure (:func:`memory_pressure`).
        """
        if not self.spilling:
            return
        self.cg.spill()
        if self.decoupled:
            self.mass = None
        cache = self.cg.system.scene._cache
        for key in ("M", "A", "A1", "A2"):
            cache.pop(key, None)

    def restore(self):
        """Rebuild what :meth:`spill` freed (no-op when nothing was freed)."""
        self.cg.restore()
        if self.decoupled and self.mass is None:
            self.mass = _mass(self.cg.system.scene)

    def error_estimate(self) -> float:
        """Return the CGs' estimate of the algebraic error in the energy norm (not a bound).

        :meth:`fastmem.solver.steps.DecoupledCG.energy_error_estimate`, with the
        guaranteed share of ``s`` while its CG has made no step;
        :meth:`fastmem.solver.steps.GeneralCG.energy_error_estimate`.
        """
        if not self.decoupled:
            return self.cg.energy_error_estimate()
        cg, s_part = self.cg, None
        if cg.cg_s is not None and cg.cg_s.error_estimate() is None and not cg.s_done:
            s_part = cg.s_share(self.mass, self.c_f)
        return cg.energy_error_estimate(s_part)

    def _skip(self, last, i, budget):
        """Return True when the inner criterion cannot plausibly hold yet (skip the check).

        The prediction: ``eta_alg`` of the last check scaled by the CG residual since;
        with ``alg_estimate="cg"``, the CG's own error estimate where it has one (it
        needs no check to be formed).
        """
        if last is None or self.check_all or i >= self.options.max_inner:
            return False
        i_c, eta_c, res_c = last
        if i - i_c >= MAX_SKIP or res_c <= 0.0 or self.cg.residual() <= EXACT_AMG_RTOL:
            return False
        if self.cg_estimate:
            estimate = self.error_estimate()
            if math.isfinite(estimate):
                return estimate > SKIP_MARGIN * budget
        return eta_c * self.cg.residual() / res_c > SKIP_MARGIN * budget

    def solve(self, active, triple, check) -> StepReport:
        """CG iterations from ``triple``, checked until ``check`` lets the step stop."""
        cg, opts = self.cg, self.options
        cg.start(active, triple[0], triple[1])
        release_warm(triple)  # a handed-over warm start is freed here (fastmem.solver.steps)
        del triple
        i0 = cg.iterations
        budget = s_share = math.inf
        last = None  # (i, eta_alg, CG residual) at the last check of this step
        while True:
            done = cg.iterate(budget, s_share)
            self.total_iterations += done
            i = cg.iterations - i0
            stuck = done == 0  # CG cannot proceed: check now, the solve is at round-off
            if not stuck and i % opts.check_every and i < opts.max_inner:
                continue
            if not stuck and self._skip(last, i, budget):
                self.stats["skipped_checks"] += 1
                continue
            self.stats["checks"] += 1
            verdict = check(cg.triple(), i, stuck or cg.at_roundoff())
            if not verdict.outer_ok:  # the level goes on: rebuild what a flux spilled
                self.restore()
            last = (i, verdict.eta_alg, cg.residual())
            budget = verdict.budget
            if verdict.stop_inner:
                break
            if self.decoupled:
                s_share = cg.s_share(self.mass, self.c_f)
                if self.cg_estimate:  # the smaller of the two (Checks: the same)
                    s_share = min(s_share, cg.s_error_estimate())
            if i >= opts.max_inner:
                logger.warning(
                    "inexact linear step: %d CG iterations without meeting the algebraic "
                    "criterion (eta_alg %.3e > %.3e)",
                    i,
                    verdict.eta_alg,
                    budget,
                )
                break
        return StepReport(iterations=i, hit_max=i >= opts.max_inner)
