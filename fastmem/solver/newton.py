r"""Newton-min on one mesh: one loop for every method (docs/method.md §3.1, 3.4 and 6).

At step k the active (contact) set is read off the previous iterate,

.. math::

    \mathcal A^k = \{a \text{ interior} :
        \lambda^{k-1}_a > c\,(u^{k-1}_{1,a} - u^{k-1}_{2,a})\},

(a prolonged triple of nested iteration starts from
:func:`fastmem.solver.nested.warm_active_set` instead) and the linear step
(:mod:`fastmem.solver.steps`) imposes ``gap = 0`` on the active set and
``lambda = 0`` on the inactive set.  This layer owns, for all three methods:

- the **active-set update** and the **stopping rule**: with exact linear steps
  (``"exact"``, ``"exact-amg"``) Newton-min stops when the active set repeats
  (then ``min(gap, lambda) = 0`` and the residuals are at round-off); with
  ``"inexact"`` when the estimator criteria of docs/method.md §6 hold for a fresh
  ``eta_disc`` of the returned iterate (:class:`Checks`);
- the **safeguard**: an active set that comes back (cycling, possible when
  the stiffness matrix is not an M-matrix) or no progress for
  :data:`fastmem.solver.safeguard.STALL_STEPS` steps switches to the monotone
  active-set iteration of :mod:`fastmem.solver.safeguard`, or raises
  :class:`~fastmem.errors.CyclingError` with ``safeguard=False``;
- the **history rows** (:mod:`fastmem.solver.history`): :class:`Checks` evaluates the
  estimators of every iterate a linear step hands it and records one row.

Every iterate is a full triple ``(u1, u2, lam)`` with its residual vectors
``(R1, R2)``, the input of the a posteriori estimators.
"""

from __future__ import annotations

import hashlib
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import CyclingError, NumericalError
from ..estimators.bound import evaluate
from ..estimators.terms import check_totals, combine, global_terms, local_terms
from ..fem.residual import residuals
from ..kernels import rows as _kr
from .inexact import AdaptiveStep
from .linear import make_step
from .nested import warm_active_set
from .safeguard import merit_stalled, new_safeguard_record, run_safeguard
from .steps import AMGStep, DirectStep, release_warm

__all__ = ["ROUNDOFF_TOL", "Checks", "LevelOutcome", "complementarity", "newton_min"]

logger = logging.getLogger(__name__)

#: Relative residual (:func:`relative_residual`) expected of a direct solve at convergence.
ROUNDOFF_TOL = 1e-9


def complementarity(u1, u2, lam, interior):
    """Nodal complementarity function ``min(u1 - u2, lam)`` on interior vertices."""
    return np.minimum(u1[interior] - u2[interior], lam[interior])


def relative_residual(scene, u1, u2, lam, r1, r2) -> float:
    """``|(R1, R2)|`` relative to the size of the terms it is computed from.

    The scale is ``|(|A1| |u1| + |F1| + |B lam|, |A2| |u2| + |F2| + |B lam|)|``: round-off
    in ``R_i = F_i - A_i u_i -/+ B lam`` is relative to the terms, not to the loads alone
    (with ``F = 0`` and ``g > 0`` the loads vanish but ``A1 u1`` does not).
    """
    f1, f2 = scene.loads
    bl = np.abs(scene.mesh.lumped_mass * lam)
    t1 = abs(scene.weighted_stiffness(1)) @ np.abs(u1) + np.abs(f1) + bl
    t2 = abs(scene.weighted_stiffness(2)) @ np.abs(u2) + np.abs(f2) + bl
    scale = float(np.sqrt(t1 @ t1 + t2 @ t2)) + np.finfo(float).tiny
    return float(np.sqrt(r1 @ r1 + r2 @ r2)) / scale


def _active_key(active: np.ndarray) -> bytes:
    return hashlib.blake2b(np.packbits(active).tobytes(), digest_size=16).digest()


def make_linear_step(scene, options, prolongation=None):
    """Build the linear step of ``options.newton.method`` (:mod:`fastmem.solver.steps`).

    ``prolongation``: interpolation from the coarser level of nested iteration,
    interior vertices to interior vertices (the decoupled CG's two-grid cycle for
    the sum, :class:`fastmem.linalg.amg.TwoGridLaplacian`); None: none.
    """
    system = make_step(scene, options.newton.path)
    method = options.newton.method
    if method == "exact":
        return DirectStep(system)
    if method == "exact-amg":
        return AMGStep(system, options.inner, prolongation)
    return AdaptiveStep(
        system, options.inner, check_all=options.record.full_history, prolongation=prolongation
    )


@dataclass
class Verdict:
    """The estimators' answer to one check of a linear step."""

    eta_alg: float
    budget: float = math.inf  # the inner criterion: eta_alg <= budget
    stop_inner: bool = True
    outer_ok: bool = False


@dataclass
class Last:
    """The last checked iterate of a level and what was computed on it."""

    u1: np.ndarray
    u2: np.ndarray
    lam: np.ndarray
    r1: np.ndarray
    r2: np.ndarray
    estimate: object
    local: dict | None  # None: the checks formed no map (evaluate() forms them)
    glob: dict


class Checks:
    """Estimators of the iterates of one level, the stopping criteria and the history rows.

    Called by a linear step as ``check(triple, inner_iterations, roundoff)``
    for every iterate it wants judged.  The flux (``eta_disc``) is
    reconstructed only when a criterion needs a fresh value (docs/method.md §6), or
    at every row with ``full_history``.
    """

    def __init__(self, scene, options, step, level, rows, certify, disc_hint, hint_slack):
        self.scene = scene
        self.newton, self.record = options.newton, options.record
        self.g_alg = options.inner.gamma_alg
        # the inner criterion from the CG's own error estimate too (the adaptive loop's
        # intermediate meshes, fastmem.adapt.loop.INTERMEDIATE_ALG)
        self.cg_decides = options.inner.alg_estimate == "cg" and isinstance(step, AdaptiveStep)
        self.step = step
        self.level = level
        self.rows = rows
        self.certify = certify
        self.hint_slack = hint_slack
        self.disc_known = disc_hint
        self.disc_fresh = False  # disc_known is a hint until the first flux of this level
        self.level_start = rows["inner_total"][-1] if rows["inner_total"] else 0
        self.interior = scene.mesh.interior_vertices
        self.n_flux = 0
        self.flux_seconds = 0.0
        self.iterates = []
        self.last = None
        self.verdict = None
        self.k = 0
        self.active = None
        self.t_level = time.perf_counter()
        # called before each flux reconstruction (AdaptiveStep.spill; it restores itself)
        self.before_flux = step.spill if isinstance(step, AdaptiveStep) else None

    def _cheap(self, u1, u2, lam, r1, r2):
        # eta_lin, eta_alg need no flux and no per-triangle map: on large meshes one pass
        # of sums (the maps, if a flux follows, are formed by evaluate(), local=None)
        quick = check_totals(self.scene, u1, u2, lam, r1, r2)
        if quick is not None:
            eta_lin, eta_alg, glob = quick
            return eta_lin, eta_alg, None, glob
        # no data oscillation here: it enters eta_disc only (added by evaluate() with the flux)
        local = local_terms(self.scene, u1, u2, lam, oscillation=False)
        glob = global_terms(self.scene, u1, u2, lam, r1, r2)
        zero = np.zeros(self.scene.mesh.n_triangles)
        zeros = {**local, "eta_osc1": zero, "eta_osc2": zero}
        totals = combine(zero, zero, zeros, glob)["totals"]  # eta_lin, eta_alg need no flux
        return totals["eta_lin"], totals["eta_alg"], local, glob

    def _flux(self, last):
        t0 = time.perf_counter()
        if self.before_flux is not None:  # the inexact step frees what the flux does not need
            self.before_flux()
        u = (last.u1, last.u2, last.lam, last.r1, last.r2)
        last.estimate = evaluate(self.scene, *u, local=last.local, glob=last.glob)
        self.n_flux += 1
        self.flux_seconds += time.perf_counter() - t0
        return last.estimate.totals["eta_disc"]

    def __call__(self, triple, inner, roundoff, safeguard=0) -> Verdict:
        """Judge one iterate: residuals, estimators, criteria; record its history row."""
        self.last = None  # the previous iterate's vectors and estimator maps: free them first
        u1, u2, lam = triple
        r1, r2 = residuals(self.scene, u1, u2, lam)
        eta_lin, eta_alg, local, glob = self._cheap(u1, u2, lam, r1, r2)
        last = self.last = Last(u1, u2, lam, r1, r2, None, local, glob)
        verdict = Verdict(eta_alg)
        if self.newton.exact or safeguard:
            disc = self._flux(last) if self.record.full_history and not safeguard else None
            if safeguard:
                disc = self.disc_known
        else:
            decides = eta_alg
            if self.cg_decides:  # the smaller; the history keeps the guaranteed eta_alg
                decides = min(eta_alg, self.step.error_estimate())
            verdict, disc = self._criteria(last, eta_lin, decides, roundoff)
        self._row(last, inner, disc, eta_lin, eta_alg, safeguard)
        self.verdict = verdict
        return verdict

    def _criteria(self, last, eta_lin, eta_alg, roundoff):
        """Inner and outer criteria of docs/method.md §6, with a fresh eta_disc only when needed."""
        if not (math.isfinite(eta_lin) and math.isfinite(eta_alg)):
            raise NumericalError(
                f"inexact Newton-min step {self.k} on level {self.level}: the estimators are "
                f"not finite (eta_lin = {eta_lin}, eta_alg = {eta_alg}); the data are "
                "probably beyond what float64 resolves (check mu, f and g)"
            )
        g_alg, g_lin, known = self.g_alg, self.newton.gamma_lin, self.disc_known
        want_fresh = self.record.full_history or known is None
        if not want_fresh and self.certify:
            cand_inner = roundoff or eta_alg <= g_alg * max(known, eta_lin)
            slack = 1.0 if self.disc_fresh else self.hint_slack
            want_fresh = cand_inner and eta_lin <= g_lin * slack * known
        if want_fresh:
            self.disc_known = self._flux(last)
            self.disc_fresh = True
        disc = self.disc_known
        fresh = last.estimate is not None
        budget = g_alg * max(disc, eta_lin)
        # a solve at round-off meets the criterion even when eta_disc = eta_lin = 0
        inner_ok = eta_alg <= budget or roundoff
        checked = fresh or not self.certify
        return Verdict(
            eta_alg,
            budget,
            stop_inner=inner_ok and (checked or eta_lin > g_lin * disc),
            outer_ok=checked and inner_ok and eta_lin <= g_lin * disc,
        ), disc

    def _row(self, last, inner, disc, eta_lin, eta_alg, safeguard):
        u1, u2, lam = last.u1, last.u2, last.lam
        est = last.estimate
        changed, comp_sq = _kr.row_measures(
            u1, u2, lam, self.interior, self.active, self.scene.active_c
        )
        row = {
            "level": self.level,
            "k": self.k,
            "inner": inner,
            "inner_total": self.level_start + self.step.total_iterations,
            "n_active": int(self.active.sum()),
            "n_changed": int(changed),
            "comp_norm": math.sqrt(comp_sq),
            "res_norm": float(np.sqrt(last.r1 @ last.r1 + last.r2 @ last.r2)),
            "eta_disc": math.nan if disc is None else disc,
            "eta_lin": eta_lin,
            "eta_alg": eta_alg,
            "eta": math.nan if est is None else est.eta,
            "fresh_disc": int(est is not None),
            "seconds": time.perf_counter() - self.t_level,
            "safeguard": safeguard,
        }
        for name, value in row.items():
            self.rows[name].append(value)
        if self.record.keep_iterates:
            self.iterates.append(tuple(np.array(x, copy=True) for x in (u1, u2, lam)))
        if self.record.monitor is not None:
            self.record.monitor(row)


@dataclass
class LevelOutcome:
    """What :func:`newton_min` returns for one mesh."""

    last: Last
    active: np.ndarray  # the active set of the last linear step, over all vertices
    converged: bool
    reason: str
    n_newton: int
    inner: int  # CG iterations on this level
    stats: dict = field(default_factory=dict)
    iterates: list = field(default_factory=list)
    eta_disc: float | None = None  # last known eta_disc (a hint for the next level)
    path: str = ""


class _Safeguard:
    """Face solves of the safeguard through the linear step, rows booked as safeguard rows."""

    def __init__(self, scene, step, checks, record):
        self.scene, self.step, self.checks, self.record = scene, step, checks, record
        self.last_active = None

    def run(self, u1, u2, k_done, max_steps, trigger):
        warm = [u1, u2]

        def face_solve(act):
            self.last_active = act
            v = self.step.face_solve(act, warm)
            warm[0], warm[1] = v[0], v[1]
            return v

        def on_step(kk, act, triple):
            self.checks.k, self.checks.active = kk, act
            self.checks(triple, 0, True, safeguard=1)

        args = (self.scene, face_solve, (u1, u2), k_done, max_steps, self.record, trigger)
        return run_safeguard(*args, on_step)


def _cycling_error(method, level, k, active, uses, rows):
    return CyclingError(
        f"{method} Newton-min cycles on level {level}: the active set of step {k} "
        f"({int(active.sum())} vertices) was already used {uses} time(s); the stiffness "
        "matrix is probably not an M-matrix (obtuse angles). Use safeguard=True or another mesh.",
        history={n: np.asarray(v) for n, v in rows.items()},
    )


def newton_min(
    scene,
    options,
    init=None,
    *,
    level=0,
    rows,
    certify=True,
    disc_hint=None,
    hint_slack=1.0,
    prolonged=False,
    prolongation=None,
) -> LevelOutcome:
    """Newton-min on one mesh, for any method; appends its history rows to ``rows``.

    Parameters
    ----------
    scene : Scene
    options : SolveOptions
    init : tuple (u1, u2, lam) or None
        Initial triple (warm start and first active set); None: the
        unconstrained start (empty active set).
    level : int
        Level number (nested iteration) written to the history.
    rows : dict of lists
        History columns (:func:`fastmem.solver.history.new_history`), shared by the levels.
    certify : bool
        ``"inexact"``: accept a stop only with a fresh eta_disc of the returned
        iterate (default).  ``False`` (intermediate levels of nested
        iteration, whose solutions only serve as initial guesses): the tests
        use ``disc_hint`` and no flux is reconstructed unless no hint exists.
    disc_hint : float or None
        Predicted eta_disc on this mesh (from a coarser level), used only to
        decide when a fresh value is worth computing.
    hint_slack : float
        ``disc_hint`` may underestimate eta_disc by up to this factor: until a
        fresh value exists the outer candidate test uses ``hint_slack *
        disc_hint``, so that a step already meeting the outer criterion is
        checked instead of followed by a needless Newton step.
    prolonged : bool
        ``init`` was prolonged from a coarser level: its first active set is
        :func:`fastmem.solver.nested.warm_active_set` (else the rule of docs/method.md §3.1).
    prolongation : sparse matrix, a list holding one, or None
        Interpolation from the coarser level, interior to interior vertices
        (:func:`make_linear_step`); a list is emptied, so that the linear step
        holds the only reference and frees it when done.
    """
    no = options.newton
    if isinstance(prolongation, list):  # handed over: the step becomes its only owner
        prolongation = prolongation.pop() if prolongation else None
    step = make_linear_step(scene, options, prolongation)
    prolongation = None
    checks = Checks(scene, options, step, level, rows, certify, disc_hint, hint_slack)
    guard = new_safeguard_record()
    safe = _Safeguard(scene, step, checks, guard)
    mesh = scene.mesh
    if init is None:
        u1, u2, lam = (
            scene.boundary_values.copy(),
            np.zeros(mesh.n_vertices),
            np.zeros(mesh.n_vertices),
        )
        active = np.zeros(mesh.interior_vertices.size, dtype=bool)
    else:
        u1, u2, lam = init
        active = warm_active_set(scene, init) if prolonged else scene.active_rule(u1, u2, lam)
        release_warm(init)  # handed over as a list (solve_levels): the caller keeps no reference
        init = None
    seen, tracker, solved = {}, [math.inf, 0], None
    converged, reason, hit_max, k = False, "", 0, 0
    while k < no.max_newton:
        k += 1
        key = _active_key(active)
        seen[key] = seen.get(key, 0) + 1
        # exact steps cycle when a set comes back; inexact steps may revisit a set
        # legitimately (the warm start differs), but not again and again
        changed = solved is not None and not np.array_equal(active, solved)
        cycles = changed and seen[key] > (1 if step.exact else 2)
        stalled = False
        if changed and k > 2:
            merit = float(np.linalg.norm(complementarity(u1, u2, lam, mesh.interior_vertices)))
            stalled = merit_stalled(tracker, merit, solved, active)
        if cycles and not no.safeguard:
            raise _cycling_error(no.method, level, k, active, seen[key] - 1, rows)
        if (cycles or stalled) and no.safeguard:
            out = safe.run(u1, u2, k - 1, no.max_newton - k + 1, "cycle" if cycles else "stall")
            k += out.steps - 1
            u1, u2, lam, active, solved = out.u1, out.u2, out.lam, out.active, safe.last_active
            seen, tracker = {_active_key(active): 1}, [math.inf, 0]
            if out.converged and step.exact:  # exact face solves: the KKT point is the solution
                converged, reason = True, "the safeguard reached the KKT point"
                break
            if k >= no.max_newton:
                reason = f"max_newton = {no.max_newton} reached (in the safeguard)"
                break
            k += 1
        checks.k, checks.active, solved = k, active, active
        # the warm start is handed over (the step empties the list once started from it):
        # no reference here keeps the previous iterate alive during the estimators (nor
        # its residuals and estimator maps through ``last``: 72 bytes per vertex that sat
        # under the next step's flux reconstruction)
        warm = [u1, u2, lam]
        u1 = u2 = lam = last = None
        report = step.solve(active, warm, checks)
        del warm
        last = checks.last
        u1, u2, lam = last.u1, last.u2, last.lam
        if step.exact:
            new_active = scene.active_rule(u1, u2, lam)
            if np.array_equal(new_active, active):
                converged, reason = _settled(step)
                break
            active = new_active
            continue
        if checks.verdict.outer_ok:
            converged, reason = True, "estimator criteria met"
            break
        hit_max = hit_max + 1 if report.hit_max else 0
        if hit_max >= 2:
            reason = (
                f"two consecutive Newton steps reached max_inner = {options.inner.max_inner} CG "
                "iterations without meeting the algebraic criterion (ill-conditioned system?)"
            )
            break
        active = scene.active_rule(u1, u2, lam)
    else:
        reason = f"max_newton = {no.max_newton} reached"
    return _finish(scene, options, step, checks, guard, solved, converged, reason, k)


def _settled(step):
    """Converged and the reason, once the active set of an exact step repeats."""
    if step.at_roundoff():
        return True, "active set settled"
    return False, (
        "active set settled, but CG stopped above round-off (true residual "
        f"{step.true_relative_residual():.1e} relative): the linear steps are not exact "
        "(ill-conditioned system)"
    )


def _finish(scene, options, step, checks, guard, solved, converged, reason, k) -> LevelOutcome:
    """Book the level: warnings, statistics, the active set of the last step."""
    last = checks.last
    stats = dict(step.stats)
    if isinstance(step, DirectStep):
        stats["factorizations"] = step.factorizations
        res = relative_residual(scene, last.u1, last.u2, last.lam, last.r1, last.r2)
        stats["relative_residual"] = res
        if converged and res > ROUNDOFF_TOL:
            logger.warning(
                "Newton-min: the active set settled but the relative residual is %.2e, above "
                "round-off (%.0e): the linear solves are inaccurate (ill-conditioned data?)",
                res,
                ROUNDOFF_TOL,
            )
    if not converged:
        logger.warning(
            "%s Newton-min did not converge on level %d (stopped without meeting its criteria): %s",
            options.newton.method,
            checks.level,
            reason or "criteria not met",
        )
    if getattr(step, "decoupled", False):
        stats["s_iterations"] = step.cg.cg_s.iterations
    stats.update(safeguard=guard, flux_evaluations=checks.n_flux, flux_seconds=checks.flux_seconds)
    active = np.zeros(scene.mesh.n_vertices, dtype=bool)
    active[scene.mesh.interior_vertices] = solved
    return LevelOutcome(
        last=last,
        active=active,
        converged=converged,
        reason=reason,
        n_newton=k,
        inner=step.total_iterations,
        stats=stats,
        iterates=checks.iterates,
        eta_disc=checks.disc_known,
        path=step.name,
    )
