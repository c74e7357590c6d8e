r"""Newton-min (semismooth Newton, primal-dual active set) for the two-membrane problem.

At step k the active (contact) set is read off the previous iterate,

.. math::

    \mathcal A^k = \{a \text{ interior} :
        \lambda^{k-1}_a > c\,(u^{k-1}_{1,a} - u^{k-1}_{2,a})\},

and the linear step (:mod:`fastmem.linear`) imposes ``gap = 0`` on the active
set and ``lambda = 0`` on the inactive set.  With exact solves the iteration
stops when the active set repeats: then ``min(gap, lambda) = 0`` holds exactly
(on the active set ``gap = 0`` and ``lambda > 0``; on the inactive set
``lambda = 0`` and ``gap >= 0``) and the residuals are at round-off.  An
active set seen at an earlier step means the iteration cycles (possible when
the stiffness matrix is not an M-matrix): :class:`~fastmem.errors.CyclingError`.

Every iterate is a full triple ``(u1, u2, lam)`` with its residual vectors
``(R1, R2)``, the input of the a posteriori estimators.
"""

from __future__ import annotations

import hashlib
import logging
import time

import numpy as np

from .adaptive import ADAPTIVE_HISTORY_COLUMNS, AdaptiveOptions, newton_amg
from .amg import check_amg_options
from .config import blas_limits, get_threads
from .errors import CyclingError, InputTypeError, ParameterError
from .linear import make_step, residuals
from .loaddata import expect_estimates
from .nested import coarse_scenes, prolong_triple
from .result import Result, check_triple
from .safeguard import merit_stalled, new_safeguard_record, run_safeguard
from .scene import Scene

__all__ = ["HISTORY_COLUMNS", "METHODS", "complementarity", "solve"]

logger = logging.getLogger(__name__)

METHODS = ("inexact", "exact-amg", "exact")

#: Factor applied to the eta_disc predicted from coarser levels before the final level: the
#: prediction (eta_disc ~ h) overestimated by 18% on the default scene at n = 512, and an
#: overestimate costs one flux reconstruction more, an underestimate a CG iteration or two.
#: The outer (Newton) candidate test divides it out again (``hint_slack`` of newton_amg):
#: there an underestimate costs whole Newton steps (manufactured scene, n = 768: 2 steps).
HINT_SAFETY = 0.7

#: Nested iteration builds auxiliary coarse meshes for meshes without a coarser version.
AUXILIARY = True

#: Relative residual (:func:`_relative_residual`) expected of an exact solve at convergence.
ROUNDOFF_TOL = 1e-9

#: Columns of the per-step history of an exact Newton-min solve.
HISTORY_COLUMNS = ("k", "n_active", "n_changed", "comp_norm", "res_norm", "seconds", "safeguard")


def complementarity(u1, u2, lam, interior):
    """Nodal complementarity function ``min(u1 - u2, lam)`` on interior vertices."""
    return np.minimum(u1[interior] - u2[interior], lam[interior])


def _active_key(active: np.ndarray) -> bytes:
    return hashlib.blake2b(np.packbits(active).tobytes(), digest_size=16).digest()


def _check_initial(initial, mesh):
    if initial is None:
        return None
    return check_triple(mesh, initial, prefix="initial ")


_FLOAT_COLUMNS = ("comp_norm", "res_norm", "seconds")


def _history_arrays(rows, columns):
    """History lists to arrays: float64 for norms, estimators and times, int64 otherwise."""
    return {
        name: np.asarray(
            rows[name],
            dtype=np.float64 if name in _FLOAT_COLUMNS or name.startswith("eta") else np.int64,
        )
        for name in columns
    }


def _check_positive(name, value, integer=False, allow_zero=False):
    ok_type = (int, np.integer) if integer else (int, float, np.integer, np.floating)
    if isinstance(value, bool) or not isinstance(value, ok_type):
        kind = "an integer" if integer else "a number"
        raise ParameterError(f"{name} must be {kind}, got {value!r}")
    if not (np.isfinite(value) and (value >= 0 if allow_zero else value > 0)):
        bound = ">= 0" if allow_zero else "positive"
        raise ParameterError(f"{name} must be {bound}, got {value!r}")


def solve(
    scene: Scene,
    method: str = "inexact",
    path: str = "auto",
    *,
    max_newton: int = 1000,
    initial=None,
    monitor=None,
    blas_threads: int | None = None,
    estimate: bool = False,
    gamma_alg: float = 0.1,
    gamma_lin: float = 0.1,
    max_inner: int = 500,
    check_every: int = 1,
    amg_options: dict | None = None,
    amg_reuse: float = 0.05,
    nested: bool | str = "auto",
    full_history: bool = False,
    keep_iterates: bool = False,
    safeguard: bool = True,
) -> Result:
    """Solve the discrete two-membrane contact problem with Newton-min.

    Parameters
    ----------
    scene : Scene
        The problem.
    method : {"inexact", "exact-amg", "exact"}
        ``"inexact"`` (default): AMG-preconditioned CG inner solves stopped
        by the estimators (MATH.md section 6, :mod:`fastmem.adaptive`): the
        inner iteration stops when ``eta_alg <= gamma_alg * max(eta_disc,
        eta_lin)``, Newton-min when also ``eta_lin <= gamma_lin * eta_disc``.
        ``"exact-amg"``: the same loop with inner solves to relative residual
        1e-12, stopping when the active set repeats (the exact baseline for
        large meshes).  ``"exact"``: every step solved by a sparse direct
        solver (small meshes).
    path : {"auto", "general", "decoupled"}
        Linear-step formulation; "auto" takes "decoupled" for constant mu.
    max_newton : int
        Maximum number of Newton-min steps (per level).  Reaching it returns
        a Result with ``converged=False`` and logs a warning.
    initial : tuple (u1, u2, lam) of ndarray, optional
        Initial iterate; its active set starts the iteration (and it is the
        warm start of the AMG methods).  Default: see ``nested``.
    monitor : callable, optional
        Called with each history row (a dict) as soon as it is recorded.
    blas_threads : int, optional
        BLAS threads during the solve (default :func:`fastmem.get_threads`).
    estimate : bool
        Attach the guaranteed a posteriori error bound of the returned triple
        (:func:`fastmem.estimate`).  ``"inexact"`` computes it anyway (its
        stopping test needs it) and always attaches it; the other methods
        reconstruct no flux without ``estimate=True``.
    gamma_alg, gamma_lin : float
        Stopping parameters of ``"inexact"`` (default 0.1 each).
    max_inner : int
        Maximum CG iterations per Newton step (``"inexact"``; ``"exact-amg"``
        allows ten times as many).
    check_every : int
        Evaluate the cheap estimators every ``check_every`` CG iterations.
    amg_options : dict, optional
        Options of :func:`pyamg.smoothed_aggregation_solver` (plus ``cycle``);
        default :data:`fastmem.amg.AMG_DEFAULTS` (pyamg's defaults, V-cycles).
    amg_reuse : float
        Decoupled path: reuse the gap system's AMG hierarchy while the active
        set differs from the one it was built for in at most this fraction of
        the interior vertices (0: rebuild whenever it changed).
    nested : bool or "auto"
        AMG methods without ``initial``: solve on the chain of coarser meshes
        (:meth:`Mesh.coarser`, down to about 1000 vertices) and prolong each
        solution as the initial iterate of the next level.  A mesh without a
        coarser version (read from a file, built from arrays) gets auxiliary
        coarse meshes from subsets of its vertices (:mod:`fastmem.coarsen`).
        "auto": when a coarser mesh exists or can be built and the data can
        move to it; otherwise the iteration starts from the unconstrained
        problem.  ``False``: always the unconstrained start.
    full_history : bool
        Reconstruct the flux at every history row, so that every row carries
        the guaranteed bound ``eta`` (costly; for studies and tests).
    keep_iterates : bool
        Keep the triple of every history row in ``result.iterates``.
    safeguard : bool
        When Newton-min cycles (an active set comes back) or stalls (no new
        smallest ``||min(gap, lam)||`` in
        :data:`fastmem.safeguard.STALL_STEPS` steps), switch
        to the monotone feasible active-set iteration of
        :mod:`fastmem.safeguard` (exact face solves, energy decreasing at
        every step) until it reaches the KKT point or its working set
        settles, then resume Newton-min.  Uses are booked in
        ``result.parameters["solver"]["safeguard"]`` and in the history
        column ``safeguard``.  ``False``: cycling raises
        :class:`~fastmem.errors.CyclingError`.

    Returns
    -------
    Result

    Raises
    ------
    CyclingError
        With ``safeguard=False``: when an active set repeats an earlier one.
    """
    if not isinstance(scene, Scene):
        raise InputTypeError(f"scene must be a fastmem.Scene, got {type(scene).__name__}")
    for name, flag in (
        ("estimate", estimate),
        ("full_history", full_history),
        ("keep_iterates", keep_iterates),
        ("safeguard", safeguard),
    ):
        if not isinstance(flag, (bool, np.bool_)):
            raise InputTypeError(f"{name} must be True or False, got {flag!r}")
    if method not in METHODS:
        raise ParameterError(f"method must be one of {METHODS}, got {method!r}")
    _check_positive("max_newton", max_newton, integer=True)
    _check_positive("max_inner", max_inner, integer=True)
    _check_positive("check_every", check_every, integer=True)
    _check_positive("gamma_alg", gamma_alg)
    _check_positive("gamma_lin", gamma_lin)
    _check_positive("amg_reuse", amg_reuse, allow_zero=True)
    if monitor is not None and not callable(monitor):
        raise InputTypeError(f"monitor must be a callable taking one row, got {monitor!r}")
    if not (isinstance(nested, (bool, np.bool_)) or (isinstance(nested, str) and nested == "auto")):
        raise ParameterError(f"nested must be True, False or 'auto', got {nested!r}")
    nested = nested if isinstance(nested, str) else bool(nested)
    amg_opts = check_amg_options(amg_options)
    if path not in ("auto", "general", "decoupled"):
        raise ParameterError(f"path must be 'auto', 'general' or 'decoupled', got {path!r}")
    if path == "decoupled" and not scene.constant_mu:
        raise ParameterError(
            "path='decoupled' needs constant mu1 and mu2; this scene has per-triangle "
            "values (use path='general' or 'auto')"
        )
    mesh = scene.mesh
    init = _check_initial(initial, mesh)
    timings = {}
    t_start = time.perf_counter()
    with blas_limits(blas_threads):
        t0 = time.perf_counter()
        if estimate or method == "inexact":  # one evaluation of callable loads for all uses
            expect_estimates(scene)
        _ = scene.loads, scene.weighted_stiffness(1), scene.weighted_stiffness(2)
        timings["assembly"] = time.perf_counter() - t0
        if method == "exact":
            t0 = time.perf_counter()
            step = make_step(scene, path)
            timings["setup"] = time.perf_counter() - t0
            result = _newton(
                scene, step, method, max_newton, init, monitor, timings, bool(safeguard)
            )
            if estimate:
                from .bound import estimate as _estimate

                t0 = time.perf_counter()
                result.estimate = _estimate(
                    scene, result.u1, result.u2, result.lam, result.r1, result.r2
                )
                timings["estimate"] = time.perf_counter() - t0
        else:
            opts = AdaptiveOptions(
                gamma_alg=float(gamma_alg),
                gamma_lin=float(gamma_lin),
                max_inner=int(max_inner),
                check_every=int(check_every),
                amg_options=amg_opts,
                amg_reuse=float(amg_reuse),
                full_history=bool(full_history),
                keep_iterates=bool(keep_iterates),
                safeguard=bool(safeguard),
            )
            result = _solve_amg(
                scene, method, path, opts, max_newton, init, nested, monitor, estimate, timings
            )
    timings["total"] = time.perf_counter() - t_start
    return result


def _merge_safeguard(records):
    """Sum the per-level safeguard bookkeeping into one record."""
    total = new_safeguard_record()
    for lev, rec in enumerate(records):
        for name in ("uses", "steps", "seconds"):
            total[name] += rec[name]
        total["triggers"] += [f"level {lev}: {t}" for t in rec["triggers"]]
        total["reached_kkt"] += rec["reached_kkt"]
    return total


def _solve_amg(scene, method, path, opts, max_newton, init, nested, monitor, estimate, timings):
    """Nested iteration over the coarse chain, then the AMG Newton-min on ``scene``."""
    from .bound import evaluate

    chain = []
    if init is None and nested is not False:
        t0 = time.perf_counter()
        chain = coarse_scenes(scene, auxiliary=AUXILIARY)
        timings["coarsening"] = time.perf_counter() - t0
        if nested is True and not chain:
            logger.warning("nested=True but this mesh has no usable coarser version")
    levels = chain + [scene]
    rows = {name: [] for name in ADAPTIVE_HISTORY_COLUMNS}
    level_info = []
    iterates = []
    triple = init
    disc_hint = None
    t_solve = time.perf_counter()
    out = None
    for lev, sc in enumerate(levels):
        t0 = time.perf_counter()
        if lev > 0:
            triple = prolong_triple(sc, levels[lev - 1], triple)
            h_ratio = sc.mesh.diameters.max() / levels[lev - 1].mesh.diameters.max()
            disc_hint = None if out["eta_disc"] is None else out["eta_disc"] * h_ratio
        # intermediate levels only make initial guesses: no flux there (see newton_amg)
        certify = lev == 0 or lev == len(levels) - 1
        if certify and (estimate or method == "inexact"):
            expect_estimates(sc)  # before the step's load vectors: one pass over the data
        step = make_step(sc, path)
        slack = 1.0
        if certify and disc_hint is not None:
            # a hint above the true value triggers a flux too early (a wasted one) ...
            disc_hint *= HINT_SAFETY
            # ... but the outer test must not miss a stop that the true value allows
            slack = 1.0 / HINT_SAFETY
        out = newton_amg(
            sc,
            step,
            method,
            opts,
            max_newton,
            triple,
            monitor,
            lev,
            disc_hint,
            rows,
            certify,
            hint_slack=slack,
            prolonged=lev > 0,
        )
        triple = (out["u1"], out["u2"], out["lam"])
        iterates.extend(out["iterates"])
        info = {
            "level": lev,
            "n_vertices": sc.mesh.n_vertices,
            "newton": out["n_newton"],
            "inner": out["inner"],
            "converged": out["converged"],
            "seconds": time.perf_counter() - t0,
            **{k: v for k, v in out["stats"].items()},
        }
        level_info.append(info)
        logger.info(
            "level %d (%d vertices): %d Newton steps, %d inner iterations, %.2fs",
            lev,
            sc.mesh.n_vertices,
            out["n_newton"],
            out["inner"],
            info["seconds"],
        )
    timings["solve"] = time.perf_counter() - t_solve
    est = out["estimate"]
    if est is None and (estimate or method == "inexact"):
        t0 = time.perf_counter()
        est = evaluate(
            scene, out["u1"], out["u2"], out["lam"], out["r1"], out["r2"], out["local"], out["glob"]
        )
        timings["estimate"] = time.perf_counter() - t0
    history = _history_arrays(rows, ADAPTIVE_HISTORY_COLUMNS)
    mesh = scene.mesh
    params = scene.parameters()
    params["solver"] = {
        "method": method,
        "path": step.name,
        "max_newton": max_newton,
        "gamma_alg": opts.gamma_alg,
        "gamma_lin": opts.gamma_lin,
        "max_inner": opts.max_inner,
        "check_every": opts.check_every,
        "amg_reuse": opts.amg_reuse,
        "amg_options": {k: repr(v) for k, v in opts.amg_options.items()},
        "nested_levels": len(levels),
        "levels": level_info,
        "stop_reason": out["reason"],
        "safeguard": _merge_safeguard([info["safeguard"] for info in level_info]),
        "threads": get_threads(),
    }
    result = Result(
        mesh=mesh,
        u1=out["u1"],
        u2=out["u2"],
        lam=out["lam"],
        r1=out["r1"],
        r2=out["r2"],
        active=out["active"],
        history=history,
        timings=timings,
        parameters=params,
        converged=out["converged"],
        n_newton=out["n_newton"],
        method=method,
        path=step.name,
        estimate=est,
    )
    if opts.keep_iterates:
        result.iterates = iterates
    return result


def _relative_residual(scene, u1, u2, lam, r1, r2) -> float:
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


def _newton(scene, step, method, max_newton, init, monitor, timings, use_safeguard=True):
    mesh = scene.mesh
    interior = mesh.interior_vertices
    if init is None:
        active = np.zeros(interior.size, dtype=bool)
    else:
        u1, u2, lam = init
        active = scene.active_rule(u1, u2, lam)
    seen = {_active_key(active): 0}
    rows = {name: [] for name in HISTORY_COLUMNS}
    converged = False
    t_solve = time.perf_counter()
    guard = new_safeguard_record()
    tracker = [np.inf, 0]

    def record(row):
        for name in HISTORY_COLUMNS:
            rows[name].append(row[name])
        if monitor is not None:
            monitor(row)

    t_row = [time.perf_counter()]

    def safeguard_row(kk, act, triple):
        v1, v2, lm = triple
        q1, q2 = residuals(scene, v1, v2, lm)
        now = time.perf_counter()
        record(
            {
                "k": kk,
                "n_active": int(act.sum()),
                "n_changed": int(np.count_nonzero(scene.active_rule(v1, v2, lm) != act)),
                "comp_norm": float(np.linalg.norm(complementarity(v1, v2, lm, interior))),
                "res_norm": float(np.sqrt(q1 @ q1 + q2 @ q2)),
                "seconds": now - t_row[0],
                "safeguard": 1,
            }
        )
        t_row[0] = now

    k = 0
    while k < max_newton:
        k += 1
        t0 = t_row[0] = time.perf_counter()
        u1, u2, lam = step.solve(active)
        r1, r2 = residuals(scene, u1, u2, lam)
        new_active = scene.active_rule(u1, u2, lam)
        n_changed = int(np.count_nonzero(new_active != active))
        row = {
            "k": k,
            "n_active": int(active.sum()),
            "n_changed": n_changed,
            "comp_norm": float(np.linalg.norm(complementarity(u1, u2, lam, interior))),
            "res_norm": float(np.sqrt(r1 @ r1 + r2 @ r2)),
            "seconds": time.perf_counter() - t0,
            "safeguard": 0,
        }
        record(row)
        logger.info(
            "newton %d: |A|=%d changed=%d |min(gap,lam)|=%.3e |R|=%.3e",
            k,
            row["n_active"],
            n_changed,
            row["comp_norm"],
            row["res_norm"],
        )
        if n_changed == 0:
            converged = True
            break
        key = _active_key(new_active)
        # the first step starts from the unconstrained solution: its merit is no reference
        stalled = k > 1 and merit_stalled(tracker, row["comp_norm"], active, new_active)
        cycles = key in seen
        if (cycles or stalled) and use_safeguard and k < max_newton:
            trigger = "cycle" if cycles else "stall"
            outcome = run_safeguard(
                scene, step.solve, (u1, u2), k, max_newton - k, guard, trigger, safeguard_row
            )
            k += outcome.steps
            u1, u2, lam = outcome.u1, outcome.u2, outcome.lam
            r1, r2 = residuals(scene, u1, u2, lam)
            active = outcome.active
            if outcome.converged:  # exact face solves: the KKT point is the solution
                converged = True
                break
            seen = {_active_key(active): k}
            tracker = [np.inf, 0]
            continue
        if cycles:
            history = {n: np.asarray(v) for n, v in rows.items()}
            raise CyclingError(
                f"Newton-min cycles: the active set of step {k + 1} ({int(new_active.sum())} "
                f"vertices) equals the one of step {seen[key] + 1}; the stiffness matrix is "
                "probably not an M-matrix (obtuse angles). Use safeguard=True or another mesh.",
                history=history,
            )
        seen[key] = k
        active = new_active
    timings["solve"] = time.perf_counter() - t_solve
    res_rel = _relative_residual(scene, u1, u2, lam, r1, r2)
    if converged and res_rel > ROUNDOFF_TOL:
        logger.warning(
            "Newton-min: the active set settled but the relative residual is %.2e, above "
            "round-off (%.0e): the linear solves are inaccurate (ill-conditioned data?)",
            res_rel,
            ROUNDOFF_TOL,
        )
    if not converged:
        logger.warning(
            "Newton-min did not converge in %d steps (active set still changing by %d vertices)",
            max_newton,
            n_changed,
        )
    history = _history_arrays(rows, HISTORY_COLUMNS)
    params = scene.parameters()
    params["solver"] = {
        "method": method,
        "path": step.name,
        "max_newton": max_newton,
        "factorizations": step.factorizations,
        "relative_residual": res_rel,
        "safeguard": guard,
        "threads": get_threads(),
    }
    full_active = np.zeros(mesh.n_vertices, dtype=bool)
    full_active[interior] = active
    return Result(
        mesh=mesh,
        u1=u1,
        u2=u2,
        lam=lam,
        r1=r1,
        r2=r2,
        active=full_active,
        history=history,
        timings=timings,
        parameters=params,
        converged=converged,
        n_newton=k,
        method=method,
        path=step.name,
    )
