r"""Newton-min with AMG-preconditioned CG inner solves, stopped by the estimators.

MATH.md sections 3.4 and 6.  Every inner (CG) iterate is mapped to a full
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

Method ``"exact-amg"`` runs the same loop with inner solves to relative
residual 1e-12 and the exact stopping rule (the active set repeats): the
baseline for meshes too large for a direct solver.

Linear steps:

- general path: CG on the reduced SPD system :math:`P^T K P x = P^T (F - K u_B)`
  (MATH.md 3.2), with a fresh AMG hierarchy whenever the active set changed
  (the system changes size);
- decoupled path: one CG for the sum ``s`` on the interior Laplacian
  (hierarchy built once, advanced only while its part of :math:`\eta_{alg}`
  exceeds half of the algebraic budget) and one CG per Newton step for the
  gap ``w`` on the fixed-size matrix that is the interior Laplacian with the
  rows and columns of the active set replaced by its diagonal (``w = 0``
  there).  Its AMG hierarchy is reused while the active set has changed in
  at most ``amg_reuse`` (a fraction) of the interior vertices since the last
  setup, and rebuilt otherwise.
"""

from __future__ import annotations

import hashlib
import logging
import math
import time

import numpy as np
import scipy.sparse as sp

from .amg import PCG, amg_preconditioner
from .bound import evaluate
from .errors import CyclingError, NumericalError
from .estimators import combine, global_terms, local_terms
from .linear import DecoupledStep, GeneralStep, residuals
from .nested import warm_active_set
from .safeguard import merit_stalled, new_safeguard_record, run_safeguard

__all__ = ["ADAPTIVE_HISTORY_COLUMNS", "AdaptiveOptions", "newton_amg"]

logger = logging.getLogger(__name__)

#: Columns of the history of the AMG methods: one row per estimator evaluation.
ADAPTIVE_HISTORY_COLUMNS = (
    "level",
    "k",
    "inner",
    "inner_total",
    "n_active",
    "eta_disc",
    "eta_lin",
    "eta_alg",
    "eta",
    "fresh_disc",
    "seconds",
    "safeguard",
)

#: Relative residual of the inner solves of ``exact-amg``.
EXACT_AMG_RTOL = 1e-12


class AdaptiveOptions:
    """Parameters of the AMG methods (validated by :func:`fastmem.solve`)."""

    def __init__(
        self,
        gamma_alg=0.1,
        gamma_lin=0.1,
        max_inner=500,
        check_every=1,
        amg_options=None,
        amg_reuse=0.05,
        full_history=False,
        keep_iterates=False,
        safeguard=True,
    ):
        self.gamma_alg = gamma_alg
        self.gamma_lin = gamma_lin
        self.max_inner = max_inner
        self.check_every = check_every
        self.amg_options = amg_options
        self.amg_reuse = amg_reuse
        self.full_history = full_history
        self.keep_iterates = keep_iterates
        self.safeguard = safeguard


class _Evaluator:
    """Estimators of one scene: cheap components every check, the flux on demand."""

    def __init__(self, scene):
        self.scene = scene
        self.n_flux = 0
        self.flux_seconds = 0.0

    def cheap(self, u1, u2, lam, r1, r2):
        # no data oscillation here: it enters eta_disc only (added by evaluate() with the flux)
        local = local_terms(self.scene, u1, u2, lam, oscillation=False)
        glob = global_terms(self.scene, u1, u2, lam, r1, r2)
        m = self.scene.mesh.n_triangles
        zero = np.zeros(m)
        zeros = {**local, "eta_osc1": zero, "eta_osc2": zero}
        totals = combine(zero, zero, zeros, glob)["totals"]  # eta_lin, eta_alg need no flux
        return {"eta_lin": totals["eta_lin"], "eta_alg": totals["eta_alg"]}, local, glob

    def full(self, u1, u2, lam, r1, r2, local, glob):
        t0 = time.perf_counter()
        est = evaluate(self.scene, u1, u2, lam, r1, r2, local=local, glob=glob)
        self.n_flux += 1
        self.flux_seconds += time.perf_counter() - t0
        return est


class _GeneralInner:
    """Inner CG on the reduced SPD system of one active set (general path)."""

    def __init__(self, step: GeneralStep, options, stats):
        self.step = step
        self.options = options
        self.stats = stats
        self.active = None

    def start(self, active, u1, u2):
        st = self.step
        ii = st.interior
        p = st.prolongation(active)
        if self.active is None or not np.array_equal(active, self.active):
            mat = (p.T @ st.k_ii @ p).tocsr()
            self.pre = amg_preconditioner(mat, self.options.amg_options)
            self.stats["amg_setups"] += 1
            self.stats["amg_setup_seconds"] += self.pre.setup_seconds
            self.mat = mat
        self.active = active.copy()
        self.p = p
        rhs = p.T @ np.concatenate([st.rhs1, st.rhs2])
        x0 = np.concatenate([u1[ii], u2[ii][~active]])
        self.cg = PCG(self.mat, rhs, x0, self.pre)

    def iterate(self, budget, s_share):
        """One CG iteration; returns 0 when CG cannot proceed (at round-off)."""
        return 1 if self.cg.step() else 0

    def solve_exact(self):
        return self.cg.solve(EXACT_AMG_RTOL, 10 * self.options.max_inner)

    @property
    def iterations(self):
        return self.cg.iterations

    def at_roundoff(self):
        return self.cg.at_roundoff(EXACT_AMG_RTOL)

    def residual(self):
        """Relative CG residual, the predictor of eta_alg between checks."""
        return self.cg.relative_residual

    def true_relative_residual(self):
        return self.cg.true_residual_norm() / self.cg.b_norm

    def triple(self):
        return self.step.triple(self.active, self.p @ self.cg.x)


class _DecoupledInner:
    """Inner CGs for the sum s (persistent) and the gap w (per Newton step)."""

    def __init__(self, step: DecoupledStep, options, stats):
        self.step = step
        self.options = options
        self.stats = stats
        a = step.a_ii
        self.a_ii = a
        self.diag = a.diagonal()
        self.pre_all = amg_preconditioner(a, options.amg_options)
        stats["amg_setups"] += 1
        stats["amg_setup_seconds"] += self.pre_all.setup_seconds
        self.pre_w = self.pre_all
        self.setup_active = np.zeros(step.interior.size, dtype=bool)
        self.cg_s = None
        self.s_done = False

    def start(self, active, u1, u2, s0=None):
        st = self.step
        ii = st.interior
        if self.cg_s is None:
            s_init = st.mu1 * u1 + st.mu2 * u2 if s0 is None else s0
            self.cg_s = PCG(self.a_ii, st.rhs_s, s_init[ii], self.pre_all)
        inactive = ~active
        # the gap system: Laplacian with the active rows/columns replaced by the diagonal
        keep = inactive.astype(np.float64)
        dk = sp.diags(keep)
        mat = (dk @ self.a_ii @ dk + sp.diags(self.diag * active)).tocsr()
        changed = int(np.count_nonzero(active != self.setup_active))
        if changed > self.options.amg_reuse * active.size:
            self.pre_w = amg_preconditioner(mat, self.options.amg_options)
            self.stats["amg_setups"] += 1
            self.stats["amg_setup_seconds"] += self.pre_w.setup_seconds
            self.setup_active = active.copy()
        rhs = np.where(active, 0.0, st.rhs_w)
        w0 = np.where(active, 0.0, (u1 - u2)[ii])
        self.active = active.copy()
        self.cg_w = PCG(mat, rhs, w0, self._masked)

    def _masked(self, r):
        # the hierarchy may belong to an older active set: keep w = 0 on the current one
        z = self.pre_w(np.where(self.active, 0.0, r))
        z[self.active] = r[self.active] / self.diag[self.active]
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
                self.s_done = True
                return done
            self.cg_s.restart()  # the recursive residual drifted: replace it
        if self.cg_s.step():
            return done + 1
        self.s_done = True  # stuck: at round-off
        return done

    def solve_exact(self):
        n = 0
        if not self.s_done:
            n += self.cg_s.solve(EXACT_AMG_RTOL, 10 * self.options.max_inner)
            self.s_done = True
        return n + self.cg_w.solve(EXACT_AMG_RTOL, 10 * self.options.max_inner)

    @property
    def iterations(self):
        return self.cg_w.iterations

    def at_roundoff(self):
        s_ok = self.s_done or self.cg_s.at_roundoff(EXACT_AMG_RTOL)
        return s_ok and self.cg_w.at_roundoff(EXACT_AMG_RTOL)

    def residual(self):
        """Relative CG residual of the gap, the predictor of eta_alg between checks."""
        return self.cg_w.relative_residual

    def true_relative_residual(self):
        return max(cg.true_residual_norm() / cg.b_norm for cg in (self.cg_s, self.cg_w))

    def s_full(self):
        return self.step._full(self.cg_s.x, self.step.s_boundary)

    def triple(self):
        return self.step.triple(self.active, self.s_full(), self.cg_w.x)

    def s_share(self, mass, c_f):
        """Return the part of eta_alg due to the residual of s: C_F ||R_s/B|| / sqrt(mu1 + mu2)."""
        st = self.step
        rho = np.zeros(st.n)
        rho[st.interior] = self.cg_s.r / st.b_int
        return c_f * math.sqrt(max(float(rho @ (mass @ rho)), 0.0) / (st.mu1 + st.mu2))


#: A check is skipped while the algebraic estimator predicted from the CG residual,
#: eta_alg(last check) * |r| / |r(last check)|, exceeds SKIP_MARGIN times the budget ...
SKIP_MARGIN = 1.5
#: ... but never for more than MAX_SKIP - 1 consecutive CG iterations.
MAX_SKIP = 4


def _skip_check(last_check, i, inner, budget, options):
    """Return True when the inner criterion cannot plausibly hold yet (skip the check)."""
    if last_check is None or options.full_history or i >= options.max_inner:
        return False
    i_c, eta_c, res_c = last_check
    if i - i_c >= MAX_SKIP or res_c <= 0.0 or inner.residual() <= EXACT_AMG_RTOL:
        return False
    return eta_c * inner.residual() / res_c > SKIP_MARGIN * budget


def _active_key(active):
    return hashlib.blake2b(np.packbits(active).tobytes(), digest_size=16).digest()


def newton_amg(
    scene,
    step,
    method,
    options,
    max_newton,
    init,
    monitor,
    level,
    disc_hint,
    rows,
    certify=True,
    hint_slack=1.0,
    prolonged=False,
):
    """Newton-min on one mesh with AMG-CG inner solves (``inexact`` or ``exact-amg``).

    Parameters
    ----------
    scene, step :
        The problem and its linear-step object (general or decoupled).
    method : {"inexact", "exact-amg"}
    options : AdaptiveOptions
    max_newton : int
    init : tuple or None
        Initial triple (warm start and first active set); None for the
        unconstrained start.
    monitor : callable or None
        Called with each history row.
    level : int
        Level number (nested iteration) written to the history.
    disc_hint : float or None
        Predicted eta_disc on this mesh (from a coarser level), used only to
        decide when a fresh value is worth computing.
    rows : dict of lists
        History columns to append to (shared across levels).
    certify : bool
        Accept a stop only with a fresh eta_disc of the returned iterate
        (default).  ``False`` (intermediate levels of nested iteration, whose
        solutions only serve as initial guesses): the stopping tests use
        ``disc_hint`` and no flux is reconstructed, unless no hint exists.
    hint_slack : float
        ``disc_hint`` may underestimate eta_disc by up to this factor (the
        caller scaled it down so that the inner candidate test does not waste
        a flux).  Until a fresh value exists, the outer candidate test uses
        ``hint_slack * disc_hint``, so that a step whose ``eta_lin`` already
        meets the outer criterion with the true eta_disc is checked instead
        of followed by a needless Newton step.
    prolonged : bool
        ``init`` was prolonged from a coarser level: its first active set is
        :func:`fastmem.nested.warm_active_set` (else the rule of MATH.md 3.1).

    Returns
    -------
    dict
        ``u1, u2, lam, r1, r2, active, estimate`` (an Estimate of the returned
        triple when one was computed), ``converged``, ``n_newton``,
        ``inner`` (CG iterations of this level), ``stats``, ``reason``,
        ``iterates`` (list of triples per history row if asked).
    """
    from .estimators import _mass_matrix, friedrichs_constant

    mesh = scene.mesh
    interior = mesh.interior_vertices
    exact = method == "exact-amg"
    stats = {"amg_setups": 0, "amg_setup_seconds": 0.0, "checks": 0, "skipped_checks": 0}
    ev = _Evaluator(scene)
    mass = _mass_matrix(scene)
    c_f = friedrichs_constant(mesh)
    decoupled = isinstance(step, DecoupledStep)
    inner = (_DecoupledInner if decoupled else _GeneralInner)(step, options, stats)
    g_alg, g_lin = options.gamma_alg, options.gamma_lin
    if init is None:
        u1 = scene.boundary_values.copy()
        u2 = np.zeros(mesh.n_vertices)
        lam = np.zeros(mesh.n_vertices)
        active = np.zeros(interior.size, dtype=bool)
    else:
        u1, u2, lam = init
        active = warm_active_set(scene, init) if prolonged else scene.active_rule(u1, u2, lam)
    disc_known = disc_hint
    disc_fresh = False  # disc_known is a hint until the first flux of this level
    level_start = rows["inner_total"][-1] if rows["inner_total"] else 0
    inner_total = level_start
    iterates = []
    converged = False
    reason = ""
    last = None
    k = 0
    t_level = time.perf_counter()

    def record(k, i, n_act, vals, disc, eta, fresh, triple, safeguard=0):
        row = {
            "level": level,
            "k": k,
            "inner": i,
            "inner_total": inner_total,
            "n_active": n_act,
            "eta_disc": disc if disc is not None else math.nan,
            "eta_lin": vals["eta_lin"],
            "eta_alg": vals["eta_alg"],
            "eta": eta,
            "fresh_disc": int(fresh),
            "seconds": time.perf_counter() - t_level,
            "safeguard": safeguard,
        }
        for name in ADAPTIVE_HISTORY_COLUMNS:
            rows[name].append(row[name])
        if options.keep_iterates:
            iterates.append(tuple(np.array(x, copy=True) for x in triple))
        if monitor is not None:
            monitor(row)

    seen = {}
    tracker = [math.inf, 0]
    guard = new_safeguard_record()
    hit_max = 0  # consecutive Newton steps whose inner solve reached max_inner
    k = 0
    while k < max_newton:
        k += 1
        key = _active_key(active)
        seen[key] = seen.get(key, 0) + 1
        # exact-amg cycles like exact Newton-min; inexact steps may revisit a set
        # legitimately (the warm start differs), but not again and again
        changed = k > 1 and not np.array_equal(active, inner.active)
        cycles = changed and seen[key] > (1 if exact else 2)
        stalled = False
        if changed and k > 2:
            gap = (u1 - u2)[interior]
            merit = float(np.linalg.norm(np.minimum(gap, lam[interior])))
            stalled = merit_stalled(tracker, merit, inner.active, active)
        if cycles and not options.safeguard:
            raise CyclingError(
                f"{method} Newton-min cycles on level {level}: the active set of step {k} "
                f"({int(active.sum())} vertices) was already used {seen[key] - 1} time(s); the "
                "stiffness matrix is probably not an M-matrix (obtuse angles). Use "
                "safeguard=True or another mesh.",
                history={n: np.asarray(v) for n, v in rows.items()},
            )
        if (cycles or stalled) and options.safeguard:
            warm = [u1, u2]

            def face_solve(act, warm=warm):
                nonlocal inner_total
                inner.start(act, warm[0], warm[1])
                inner_total += inner.solve_exact()
                v1, v2, lm = inner.triple()
                warm[0], warm[1] = v1, v2
                return v1, v2, lm

            def on_step(kk, act, triple, disc=disc_known):
                v1, v2, lm = triple
                q1, q2 = residuals(scene, v1, v2, lm)
                vals, _, _ = ev.cheap(v1, v2, lm, q1, q2)
                record(kk, 0, int(act.sum()), vals, disc, math.nan, False, triple, 1)

            outcome = run_safeguard(
                scene,
                face_solve,
                (u1, u2),
                k - 1,
                max_newton - k + 1,
                guard,
                "cycle" if cycles else "stall",
                on_step,
            )
            k += outcome.steps - 1
            u1, u2, lam = outcome.u1, outcome.u2, outcome.lam
            active = outcome.active
            seen = {_active_key(active): 1}
            tracker = [math.inf, 0]
            if k >= max_newton:
                reason = f"max_newton = {max_newton} reached (in the safeguard)"
                r1, r2 = residuals(scene, u1, u2, lam)
                vals, local, glob = ev.cheap(u1, u2, lam, r1, r2)
                last = (u1, u2, lam, r1, r2, None, local, glob)
                break
            k += 1
        inner.start(active, u1, u2)
        n_act = int(active.sum())
        i0 = inner.iterations
        if exact:
            inner_total += inner.solve_exact()
            u1, u2, lam = inner.triple()
            r1, r2 = residuals(scene, u1, u2, lam)
            vals, local, glob = ev.cheap(u1, u2, lam, r1, r2)
            est = None
            if options.full_history:
                est = ev.full(u1, u2, lam, r1, r2, local, glob)
            record(
                k,
                inner.iterations - i0,
                n_act,
                vals,
                None if est is None else est.totals["eta_disc"],
                math.nan if est is None else est.eta,
                est is not None,
                (u1, u2, lam),
            )
            last = (u1, u2, lam, r1, r2, est, local, glob)
            new_active = scene.active_rule(u1, u2, lam)
            if np.array_equal(new_active, active):
                if inner.at_roundoff():
                    converged = True
                    reason = "active set settled"
                else:
                    reason = (
                        "active set settled, but CG stopped above round-off (true "
                        f"residual {inner.true_relative_residual():.1e} relative): the "
                        "linear steps are not exact (ill-conditioned system)"
                    )
                break
            active = new_active
            continue
        # ---- inexact: CG iterations with estimator checks
        inner_ok = False
        outer_ok = False
        budget = math.inf
        s_share = math.inf
        last_check = None  # (i, eta_alg, CG residual) at the last check of this step
        while True:
            done = inner.iterate(budget, s_share)
            inner_total += done
            i = inner.iterations - i0
            stuck = done == 0  # CG cannot proceed: check now, the solve is at round-off
            if not stuck and i % options.check_every and i < options.max_inner:
                continue
            if not stuck and _skip_check(last_check, i, inner, budget, options):
                stats["skipped_checks"] += 1
                continue
            stats["checks"] += 1
            u1, u2, lam = inner.triple()
            r1, r2 = residuals(scene, u1, u2, lam)
            vals, local, glob = ev.cheap(u1, u2, lam, r1, r2)
            if decoupled:
                s_share = inner.s_share(mass, c_f)
            eta_lin, eta_alg = vals["eta_lin"], vals["eta_alg"]
            if not (math.isfinite(eta_lin) and math.isfinite(eta_alg)):
                raise NumericalError(
                    f"{method} Newton-min step {k} on level {level}: the estimators are not "
                    f"finite (eta_lin = {eta_lin}, eta_alg = {eta_alg}); the data are "
                    "probably beyond what float64 resolves (check mu, f and g)"
                )
            roundoff = stuck or inner.at_roundoff()
            last_check = (i, eta_alg, inner.residual())
            est = None
            want_fresh = options.full_history or disc_known is None
            if not want_fresh and certify:
                cand_inner = roundoff or eta_alg <= g_alg * max(disc_known, eta_lin)
                slack = 1.0 if disc_fresh else hint_slack
                cand_outer = eta_lin <= g_lin * slack * disc_known
                want_fresh = cand_inner and cand_outer
            disc = disc_known
            if want_fresh:
                est = ev.full(u1, u2, lam, r1, r2, local, glob)
                disc = disc_known = est.totals["eta_disc"]
                disc_fresh = True
            budget = g_alg * max(disc, eta_lin)
            # a solve at round-off meets the criterion even when eta_disc = eta_lin = 0
            inner_ok = eta_alg <= budget or roundoff
            outer_ok = (est is not None or not certify) and inner_ok and eta_lin <= g_lin * disc
            record(
                k,
                i,
                n_act,
                vals,
                disc,
                est.eta if est is not None else math.nan,
                est is not None,
                (u1, u2, lam),
            )
            last = (u1, u2, lam, r1, r2, est, local, glob)
            if inner_ok and (est is not None or not certify or eta_lin > g_lin * disc):
                break  # the step is accurate enough (and cannot be the last one, or is checked)
            if i >= options.max_inner:
                logger.warning(
                    "inexact Newton-min step %d: %d CG iterations without meeting the "
                    "algebraic criterion (eta_alg %.3e > %.3e)",
                    k,
                    i,
                    eta_alg,
                    budget,
                )
                break
        if outer_ok:
            converged = True
            reason = "estimator criteria met"
            break
        hit_max = hit_max + 1 if i >= options.max_inner else 0
        if hit_max >= 2:
            reason = (
                f"two consecutive Newton steps reached max_inner = {options.max_inner} CG "
                "iterations without meeting the algebraic criterion (ill-conditioned system?)"
            )
            break
        active = scene.active_rule(u1, u2, lam)
    else:
        reason = f"max_newton = {max_newton} reached"
    if not converged:
        logger.warning(
            "%s Newton-min stopped without meeting its criteria on level %d: %s",
            method,
            level,
            reason or "criteria not met",
        )
    u1, u2, lam, r1, r2, est, _, _ = last
    full_active = np.zeros(mesh.n_vertices, dtype=bool)
    full_active[interior] = inner.active
    stats["safeguard"] = guard
    stats["flux_evaluations"] = ev.n_flux
    stats["flux_seconds"] = ev.flux_seconds
    if decoupled:
        stats["s_iterations"] = inner.cg_s.iterations
    return {
        "u1": u1,
        "u2": u2,
        "lam": lam,
        "r1": r1,
        "r2": r2,
        "active": full_active,
        "estimate": est,
        "local": last[6],
        "glob": last[7],
        "converged": converged,
        "reason": reason,
        "n_newton": k,
        "inner": inner_total - level_start,
        "stats": stats,
        "iterates": iterates,
        "eta_disc": disc_known,
    }
