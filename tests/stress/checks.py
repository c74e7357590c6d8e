"""Run one (case, variant) of the stress matrix and check everything that must hold.

:func:`run` never raises for a library failure: it returns a :class:`Record`
whose ``problems`` list says what went wrong (empty = the case passes).  The
tests assert that list is empty; the report prints it.

What is checked (docs/method.md §2, 3, 5, 6):

- outcome: ``converged=True``, or a documented ConvergenceError (CyclingError...)
  where the case allows it; never ``converged=False`` without an error, never
  an undocumented exception;
- no NaN or inf in the returned Result: nodal arrays, residuals, estimator
  totals and maps, timings, numeric parameters, history (where the history
  marks "not evaluated" by NaN, only there: ``eta`` and ``eta_disc`` of rows
  without a fresh flux reconstruction);
- exact solves (``exact``, ``exact-amg``): the scaled complementarity
  ``max_a |min(gap_a / U, lam_a / L)|`` (U, L the scales of u and lambda) and
  the normwise relative residual are at round-off, and the algebraic part of
  the bound is negligible (``eta_alg <= 1e-6 eta`` for exact, ``1e-3 eta`` for
  exact-amg, or a residual at 1e-13);
- no hang: a watchdog monitor aborts a solve after 60 s or 10000 history rows;
- ``inexact``: the stopping criteria hold for the returned triple
  (``eta_lin <= gamma_lin eta_disc``, ``eta_alg <= gamma_alg max(eta_disc, eta_lin)``);
- the attached estimate is the estimate of the returned triple (recomputed with
  :func:`fastmem.estimate`);
- manufactured cases: ``eta >= |||u - u_h|||`` (error with a degree-10 rule);
- the case's :class:`~tests.stress.cases.Expect` (contact-set size, mesh
  property, scaling of the solution).
"""

from __future__ import annotations

import math
import numbers
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

import fastmem as fm

from . import meshes
from .cases import VARIANTS, Case

#: Quadrature degree of the error integrals (>= 6 required by docs/method.md §7).
ERROR_DEGREE = 10
#: Round-off levels accepted for exact solves.
COMP_TOL = {"exact": 1e-9, "exact-amg": 1e-8}
RES_TOL = {"exact": 1e-10, "exact-amg": 1e-8}
#: An exact solve leaves no visible algebraic part in the bound: eta_alg <= ALG_TOL eta
#: (unless the normwise relative residual is at ROUNDOFF_RES, e.g. when eta itself is tiny).
#: exact-amg stops CG at a relative residual of 1e-12, which on ill-conditioned systems
#: (graded meshes, mu contrasts) leaves a small algebraic error: 0.1% of eta is accepted.
ALG_TOL = {"exact": 1e-6, "exact-amg": 1e-3}
ROUNDOFF_RES = 1e-13
#: Relative agreement of a scaled case with its scale = 1 reference (exact solves).
SCALE_TOL = 1e-6
#: Relative agreement of result.eta with a recomputed estimate of the same triple.
ESTIMATE_TOL = 1e-8
#: A solve still running after this wall time or this many history rows is a hang.
WATCHDOG_SECONDS = 60.0
WATCHDOG_ROWS = 10000


@dataclass
class Record:
    """Outcome of one (case, variant) run."""

    case: str
    variant: str
    mode: str
    outcome: str = ""
    error_class: str | None = None
    converged: bool | None = None
    n_newton: int | None = None
    safeguard: str = "-"
    eta: float | None = None
    error: float | None = None
    seconds: float = math.nan
    skipped: str | None = None
    problems: list = field(default_factory=list)
    info: dict = field(default_factory=dict)

    @property
    def effectivity(self) -> float | None:
        """``eta / error`` where the error is known."""
        if self.eta is None or not self.error:
            return None
        return self.eta / self.error

    def problem(self, msg: str) -> None:
        self.problems.append(msg)


# ------------------------------------------------------------------------------ helpers


def _nonfinite_leaves(obj, prefix=""):
    """Names of non-finite numbers inside nested dicts / lists / arrays."""
    bad = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            bad += _nonfinite_leaves(v, f"{prefix}{k}.")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            bad += _nonfinite_leaves(v, f"{prefix}{i}.")
    elif isinstance(obj, np.ndarray):
        if obj.dtype.kind in "fc" and not np.isfinite(obj).all():
            bad.append(prefix.rstrip(".") + f" ({int((~np.isfinite(obj)).sum())} entries)")
    elif isinstance(obj, numbers.Real) and not isinstance(obj, bool):
        if not math.isfinite(float(obj)):
            bad.append(prefix.rstrip(".") + f" = {obj}")
    return bad


def nonfinite_fields(result) -> list[str]:
    """Every NaN / inf in a Result (see the module docstring for the history rule)."""
    bad = []
    for name in ("u1", "u2", "lam", "r1", "r2"):
        arr = getattr(result, name)
        if not np.isfinite(arr).all():
            bad.append(f"{name} ({int((~np.isfinite(arr)).sum())} entries)")
    hist = dict(result.history)
    fresh = hist.get("fresh_disc")
    for name in ("eta", "eta_disc"):
        if fresh is not None and name in hist:
            col = np.asarray(hist.pop(name), dtype=float)
            evaluated = np.asarray(fresh) != 0
            if np.isinf(col).any() or not np.isfinite(col[evaluated]).all():
                bad.append(f"history.{name} (non-finite in evaluated rows)")
    bad += _nonfinite_leaves(hist, "history.")
    if result.estimate is not None:
        bad += _nonfinite_leaves(result.estimate.totals, "estimate.")
        bad += _nonfinite_leaves(result.estimate.maps, "estimate.maps.")
    bad += _nonfinite_leaves(result.timings, "timings.")
    bad += _nonfinite_leaves(result.parameters, "parameters.")
    return bad


def scaled_complementarity(scene, u1, u2, lam) -> float:
    """``max_a |min(gap_a / U, lam_a / L)|`` over interior vertices (0 at a KKT point)."""
    mesh = scene.mesh
    ii = mesh.interior_vertices
    if ii.size == 0:
        return 0.0
    b = mesh.lumped_mass[ii]
    f1, f2 = scene.loads
    tiny = np.finfo(float).tiny
    u_scale = max(np.abs(u1).max(), np.abs(u2).max(), tiny)
    l_scale = max(np.abs(lam).max(), np.abs(f1[ii] / b).max(), np.abs(f2[ii] / b).max(), tiny)
    gap = (u1 - u2)[ii] / u_scale
    return float(np.abs(np.minimum(gap, lam[ii] / l_scale)).max())


def relative_residual(scene, u1, u2, lam) -> float:
    """``||(R1, R2)|| / (sum of the norms of the terms of R)`` (normwise backward error)."""
    from fastmem.fem.residual import residuals

    r1, r2 = residuals(scene, u1, u2, lam)
    f1, f2 = scene.loads
    ii = scene.mesh.interior_vertices
    bl = (scene.mesh.lumped_mass * lam)[ii]
    terms = np.linalg.norm(f1[ii]) + np.linalg.norm(f2[ii]) + 2 * np.linalg.norm(bl)
    for i, u in ((1, u1), (2, u2)):
        a = abs(scene.weighted_stiffness(i))
        terms += np.linalg.norm((a @ np.abs(u))[ii])
    return float(np.hypot(np.linalg.norm(r1), np.linalg.norm(r2)) / max(terms, 1e-300))


def safeguard_summary(params) -> str:
    """The safeguard bookkeeping of a result, for the report ("-" when not recorded)."""
    rec = params.get("solver", {}).get("safeguard")
    if rec is None:
        return "-"
    if not rec.get("uses"):
        return "no"
    kkt = sum(bool(x) for x in rec.get("reached_kkt", []))
    trig = ", ".join(rec.get("triggers", []))
    return f"{rec['uses']}x, {rec['steps']} steps, KKT {kkt}/{rec['uses']} ({trig})"


def stop_reason(result) -> str:
    reason = result.parameters.get("solver", {}).get("stop_reason")
    if reason:
        return reason
    return "active set settled" if result.converged else f"max_newton reached ({result.n_newton})"


class Hang(Exception):
    """Raised by the :class:`Watchdog` monitor: the solve does not come back."""


class Watchdog:
    """A ``monitor`` for :func:`fastmem.solve` that aborts a solve looping without end.

    fastmem calls the monitor with every history row; after ``max_seconds``
    of wall time or ``max_rows`` rows it raises :class:`Hang`, which
    propagates out of ``solve`` (a hang becomes a reported problem instead
    of a stuck test run).
    """

    def __init__(self, max_seconds=WATCHDOG_SECONDS, max_rows=WATCHDOG_ROWS):
        self.max_seconds = max_seconds
        self.max_rows = max_rows
        self.rows = 0
        self.t0 = time.perf_counter()
        self.last = None

    def __call__(self, row):
        self.rows += 1
        self.last = row
        elapsed = time.perf_counter() - self.t0
        if self.rows > self.max_rows or elapsed > self.max_seconds:
            raise Hang(
                f"solve still running after {self.rows} history rows and {elapsed:.1f} s; "
                f"last row {_short_row(row)}"
            )


def _short_row(row):
    keep = ("level", "k", "inner", "inner_total", "n_active", "eta_disc", "eta_lin", "eta_alg")
    return {
        k: (float(f"{v:.4g}") if isinstance(v, float) else v) for k, v in row.items() if k in keep
    }


def _solve(built, variant, watchdog=None):
    method, extra = VARIANTS[variant]
    opts = {**built.solve_options, **extra}
    t0 = time.perf_counter()
    result = fm.solve(
        built.scene, method=method, estimate=True, monitor=watchdog or Watchdog(), **opts
    )
    return result, time.perf_counter() - t0


# ------------------------------------------------------------------------------ the run


def run(case: Case, variant: str, mode: str = "fast") -> Record:
    """Build, solve and check one (case, variant); never raises for library failures."""
    rec = Record(case.name, variant, mode)
    exp = case.expect
    if exp.needs_gmsh:
        ok, why = meshes.gmsh_available()
        if not ok:
            rec.skipped = why
            rec.outcome = "skipped"
            return rec
    built = case.build(mode)
    scene, mesh = built.scene, built.scene.mesh
    rec.info["vertices"] = mesh.n_vertices
    if exp.non_m_matrix:
        npos = meshes.positive_offdiagonals(mesh)
        rec.info["positive_offdiag"] = npos
        if npos == 0:
            rec.problem("mesh: expected positive off-diagonal stiffness entries, found none")
    if exp.min_aspect is not None:
        asp = meshes.max_aspect_ratio(mesh)
        rec.info["aspect"] = asp
        if asp < exp.min_aspect:
            rec.problem(f"mesh: aspect ratio {asp:.3g} < {exp.min_aspect:.3g}")

    method, extra = VARIANTS[variant]
    allowed = (not exp.must_converge) or extra.get("safeguard") is False
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", fm.errors.FastmemWarning)
            result, rec.seconds = _solve(built, variant)
    except fm.errors.ConvergenceError as err:
        rec.error_class = type(err).__name__
        rec.outcome = f"{rec.error_class}"
        rec.info["message"] = str(err)
        if not allowed:
            rec.problem(f"raised {rec.error_class} on a case that must converge: {err}")
        hist = getattr(err, "history", None)
        if hist is not None:
            bad = _nonfinite_leaves(dict(hist), "error.history.")
            bad = [b for b in bad if not b.startswith(("error.history.eta ", "error.history.eta_"))]
            if bad:
                rec.problem(f"non-finite values in the error's history: {bad}")
        return rec
    except Hang as err:
        rec.error_class = "Hang"
        rec.outcome = "hang (aborted by the watchdog)"
        rec.problem(f"the solver does not return: {err}")
        return rec
    except Exception as err:  # noqa: BLE001 - anything else is a finding
        rec.error_class = type(err).__name__
        rec.outcome = f"{rec.error_class} (undocumented)"
        rec.problem(f"unexpected exception {type(err).__name__}: {err}")
        return rec

    rec.converged = bool(result.converged)
    rec.n_newton = int(result.n_newton)
    rec.safeguard = safeguard_summary(result.parameters)
    rec.outcome = "converged" if result.converged else f"not converged: {stop_reason(result)}"
    if not result.converged:
        rec.problem(f"returned converged=False without an error ({stop_reason(result)})")
    bad = nonfinite_fields(result)
    if bad:
        rec.problem(f"NaN/inf in the result: {bad}")
    if result.estimate is None:
        rec.problem("no estimate attached although estimate=True")
        return rec
    rec.eta = result.eta
    tot = result.estimate.totals
    interior = mesh.interior_vertices
    n_act = int(np.count_nonzero(result.active[interior]))
    rec.info.update(n_active=n_act, n_interior=int(interior.size))
    u1, u2, lam = result.u1, result.u2, result.lam
    if not all(np.isfinite(x).all() for x in (u1, u2, lam)):
        return rec  # already reported; the checks below would only repeat it

    comp = scaled_complementarity(scene, u1, u2, lam)
    res = relative_residual(scene, u1, u2, lam)
    rec.info.update(comp=comp, res=res)
    for k in ("eta_disc", "eta_lin", "eta_alg"):
        rec.info[k] = float(tot[k])
    if method in COMP_TOL and result.converged:
        if not comp <= COMP_TOL[method]:
            rec.problem(f"complementarity {comp:.3e} > {COMP_TOL[method]:.0e} at convergence")
        if not res <= RES_TOL[method]:
            rec.problem(f"relative residual {res:.3e} > {RES_TOL[method]:.0e} at convergence")
        e_alg = float(tot["eta_alg"])
        if not (e_alg <= ALG_TOL[method] * float(tot["eta"]) or res <= ROUNDOFF_RES):
            rec.problem(
                f"converged with exact solves but eta_alg = {e_alg:.3e} is "
                f"{e_alg / float(tot['eta']):.1e} of eta (> {ALG_TOL[method]:.0e}): the linear "
                "solve was not exact"
            )
    if method == "inexact" and result.converged:
        g_alg = result.parameters["solver"]["gamma_alg"]
        g_lin = result.parameters["solver"]["gamma_lin"]
        e_disc, e_lin, e_alg = (float(tot[k]) for k in ("eta_disc", "eta_lin", "eta_alg"))
        slack = 1.0 + 1e-12
        if not e_lin <= g_lin * e_disc * slack:
            rec.problem(f"converged but eta_lin {e_lin:.3e} > gamma_lin eta_disc {e_disc:.3e}")
        if not (e_alg <= g_alg * max(e_disc, e_lin) * slack or res <= 1e-10):
            rec.problem(
                f"converged but eta_alg {e_alg:.3e} > gamma_alg max(eta_disc, eta_lin) "
                f"(relative residual {res:.1e})"
            )

    again = fm.estimate(scene, u1, u2, lam)
    if not abs(again.eta - rec.eta) <= ESTIMATE_TOL * max(abs(again.eta), 1e-300):
        rec.problem(f"attached eta {rec.eta:.6e} != recomputed eta {again.eta:.6e}")
    if not (math.isfinite(rec.eta) and rec.eta >= 0):
        rec.problem(f"eta = {rec.eta}")

    if built.exact is not None:
        rec.error = float(built.exact.energy_error(mesh, u1, u2, degree=ERROR_DEGREE))
        if not rec.eta >= rec.error:
            rec.problem(
                f"bound violated: eta {rec.eta:.6e} < error {rec.error:.6e} "
                f"(effectivity {rec.eta / rec.error:.4f})"
            )

    if exp.n_active is not None and result.converged:
        want = {"none": 0, "one": 1, "all": int(interior.size)}[exp.n_active]
        if n_act != want:
            rec.problem(f"contact set has {n_act} interior vertices, expected {want}")

    if exp.scale is not None and built.reference is not None:
        _check_scaling(rec, built, variant, result, exp.scale)
    return rec


def _check_scaling(rec, built, variant, result, s):
    """A scaled scene's solution, lambda and eta are ``s`` times those of the reference."""
    ref_built = built.reference()
    try:
        ref, _ = _solve(ref_built, variant)
    except (fm.errors.FastmemError, Hang) as err:
        rec.problem(f"scaling reference raised {type(err).__name__}: {err}")
        return
    rel = {}
    for name in ("u1", "u2", "lam"):
        a, b = getattr(result, name) / s, getattr(ref, name)
        rel[name] = float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))
    rel["eta"] = abs(result.eta / s - ref.eta) / ref.eta
    rec.info["scale_dev"] = max(rel.values())
    same_active = bool(np.array_equal(result.active, ref.active))
    rec.info["scale_same_active"] = same_active
    if VARIANTS[variant][0] == "inexact":  # adaptive stops are scale-invariant too, but loosely
        tol, need_same = 1e-3, False
    else:
        tol, need_same = SCALE_TOL, True
    if need_same and not same_active:
        rec.problem("scaled case: contact set differs from the scale = 1 reference")
    worst = max(rel, key=rel.get)
    if not rel[worst] <= tol:
        rec.problem(
            f"scaled case: {worst} / {s:g} deviates from the scale = 1 reference by "
            f"{rel[worst]:.2e} (relative, tolerance {tol:.0e})"
        )
