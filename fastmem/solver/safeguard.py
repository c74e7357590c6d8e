r"""Safeguard of Newton-min: a monotone feasible active-set iteration on the energy.

Plain Newton-min (primal-dual active set) converges in finitely many steps
when the stiffness matrix is an M-matrix, but it may cycle, or wander without
reducing ``||min(gap, lam)||``, when it is not (obtuse or badly perturbed
triangles, docs/method.md §3).  The discrete problem is a strictly convex
quadratic programme,

.. math::  \min_{u_1, u_2} J(u_1, u_2) = \tfrac12 u_1^T A_1 u_1 + \tfrac12 u_2^T A_2 u_2
           - F_1^T u_1 - F_2^T u_2 \quad\text{s.t.}\quad u_{1,a} - u_{2,a} \ge 0
           \ (a \text{ interior}),

whose KKT conditions, with the multiplier :math:`B\lambda`, are exactly the
Newton-min equations.  The safeguard therefore keeps a *feasible* iterate
``x`` and decreases ``J`` at every step, which excludes cycling:

1. ``z`` = minimiser of ``J`` on the face ``gap = 0`` on the working set
   :math:`\mathcal W` (one Newton-min linear step with active set
   :math:`\mathcal W`, so the existing exact or AMG solvers are reused);
2. if ``z`` is feasible it becomes the iterate; if its multipliers are
   non-negative on :math:`\mathcal W` it is the solution (KKT), otherwise
   the vertices with negative multipliers leave :math:`\mathcal W` (all of
   them; only the most negative one after a step that made no progress, the
   classical rule that guarantees a strict decrease);
3. if ``z`` is infeasible, a projected search along ``d = z - x``: the trial
   point ``P(x + t d)`` (``P`` sets ``u_1 = u_2`` to their diagonally weighted
   mean where the gap is negative) is accepted at the first ``t = 1, 1/2,
   ...`` with the Armijo decrease ``J(P(x + t d)) <= J(x) - 2 sigma t (J(x) -
   J(z))``; if none passes, the feasible step to the first blocking vertex
   (a decrease by convexity).  The working set becomes ``{gap = 0}``.

Why this safeguard rather than a damped Fischer-Burmeister Newton method: it
needs only the face solves Newton-min already has (no new non-symmetric
Jacobian systems, both linear-step paths and all three methods work
unchanged), its merit is the energy (monotone, no smoothing parameter), and a
feasible iterate at every step gives a meaningful triple even when it is
stopped early.  Projection lets many vertices enter the working set in one
step, so it does not crawl one vertex at a time like a textbook active-set
method.  Newton-min resumes from the safeguard's result (for exact face
solves that result is already the solution).
"""

from __future__ import annotations

import logging
import time

import numpy as np

__all__ = ["STALL_STEPS", "SafeguardOutcome", "merit_stalled", "monotone_active_set"]

logger = logging.getLogger(__name__)

#: Newton-min steps without a new smallest ``||min(gap, lam)||`` that trigger the safeguard.
STALL_STEPS = 8
#: Armijo constant of the projected search.
ARMIJO_SIGMA = 1e-4
#: Halvings of the projected search before the blocking step is taken.
MAX_HALVINGS = 20


class SafeguardOutcome:
    """What :func:`monotone_active_set` returns.

    Attributes
    ----------
    u1, u2, lam : ndarray
        The last face minimiser (the solution when ``converged``).
    active : ndarray of bool
        Working set on the interior vertices, the active set Newton-min
        resumes with.
    converged : bool
        The KKT conditions hold (feasible face minimiser, ``lam >= 0``).
    steps : int
        Face solves performed.
    energies : list of float
        Energy of the feasible iterate after each step (non-increasing).
    """

    def __init__(self, u1, u2, lam, active, converged, steps, energies):
        self.u1, self.u2, self.lam = u1, u2, lam
        self.active = active
        self.converged = converged
        self.steps = steps
        self.energies = energies


def _energy_tools(scene):
    mesh = scene.mesh
    ii = mesh.interior_vertices
    a1 = scene.weighted_stiffness(1)
    a2 = scene.weighted_stiffness(2)
    f1, f2 = scene.loads
    w1 = a1.diagonal()[ii]
    w2 = a2.diagonal()[ii]
    wsum = w1 + w2

    def energy(v1, v2):
        return float(0.5 * (v1 @ (a1 @ v1)) + 0.5 * (v2 @ (a2 @ v2)) - f1 @ v1 - f2 @ v2)

    def project(v1, v2):
        """Nearest feasible point in the diagonally weighted norm (u1 = u2 where gap < 0)."""
        gap = v1[ii] - v2[ii]
        neg = gap < 0.0
        if not neg.any():
            return v1, v2
        v1 = v1.copy()
        v2 = v2.copy()
        idx = ii[neg]
        mean = (w1[neg] * v1[idx] + w2[neg] * v2[idx]) / wsum[neg]
        v1[idx] = mean
        v2[idx] = mean
        return v1, v2

    return energy, project


def monotone_active_set(scene, face_solve, u1, u2, max_steps, on_step=None):
    """Run the safeguard from ``(u1, u2)`` (projected onto the feasible set first).

    Parameters
    ----------
    scene : Scene
    face_solve : callable
        ``face_solve(active) -> (u1, u2, lam)``: the Newton-min linear step,
        solved exactly (to round-off), for the active set ``active`` (bool
        over the interior vertices).
    u1, u2 : ndarray
        Starting point (any; it is projected).
    max_steps : int
        Maximum number of face solves.
    on_step : callable, optional
        Called after each face solve as ``on_step(step, active, (u1, u2, lam))``.

    Returns
    -------
    SafeguardOutcome
    """
    ii = scene.mesh.interior_vertices
    energy, project = _energy_tools(scene)
    x1, x2 = project(np.asarray(u1, dtype=float), np.asarray(u2, dtype=float))
    j_x = energy(x1, x2)
    energies = [j_x]
    active = (x1[ii] - x2[ii]) <= 0.0
    j_release = None  # energy when vertices were last released
    z1 = z2 = lam = None
    converged = False
    step = 0
    for step in range(1, max_steps + 1):
        z1, z2, lam = face_solve(active)
        if on_step is not None:
            on_step(step, active, (z1, z2, lam))
        gap_z = z1[ii] - z2[ii]
        u_scale = max(float(np.abs(z1).max()), float(np.abs(z2).max()), np.finfo(float).tiny)
        tol_gap = 1e-11 * u_scale
        j_z = energy(z1, z2)
        if np.all(gap_z[~active] >= -tol_gap):
            tiny = 1e-14 * max(abs(j_x), abs(j_z), np.finfo(float).tiny)
            stuck = j_release is not None and j_z >= j_release - tiny
            x1, x2, j_x = z1, z2, min(j_z, j_x)
            energies.append(j_x)
            lam_i = lam[ii]
            lam_tol = 1e-10 * max(float(np.abs(lam_i).max()), np.finfo(float).tiny)
            neg = active & (lam_i < -lam_tol)
            if not neg.any():
                converged = True
                break
            # the last release bought nothing: the classical one-at-a-time rule this time
            if stuck:
                neg = np.zeros_like(neg)
                neg[np.argmin(np.where(active, lam_i, np.inf))] = True
            active = active & ~neg
            j_release = j_x
            continue
        d1, d2 = z1 - x1, z2 - x2
        decrease = max(j_x - j_z, 0.0)
        t = 1.0
        accepted = False
        for _ in range(MAX_HALVINGS):
            y1, y2 = project(x1 + t * d1, x2 + t * d2)
            j_y = energy(y1, y2)
            if j_y <= j_x - 2.0 * ARMIJO_SIGMA * t * decrease:
                accepted = True
                break
            t *= 0.5
        if not accepted:
            # feasible step to the first blocking vertex: J decreases by convexity
            gap_x = x1[ii] - x2[ii]
            gap_d = d1[ii] - d2[ii]
            block = (~active) & (gap_d < 0.0)
            ratios = gap_x[block] / -gap_d[block]
            t = float(min(1.0, max(0.0, ratios.min()))) if ratios.size else 1.0
            y1, y2 = project(x1 + t * d1, x2 + t * d2)
            j_y = energy(y1, y2)
        x1, x2, j_x = y1, y2, min(j_y, j_x)
        energies.append(j_x)
        new_active = (x1[ii] - x2[ii]) <= tol_gap
        if not accepted and t == 0.0:
            # degenerate: add the blocking vertices without moving
            new_active |= block & (gap_x <= tol_gap)
        active = active | new_active if not accepted else new_active
    logger.info(
        "safeguard: %d face solves, %s, energy %.6e -> %.6e",
        step,
        "KKT point reached" if converged else "stopped before the KKT point",
        energies[0],
        energies[-1],
    )
    return SafeguardOutcome(z1, z2, lam, active, converged, step, energies)


def merit_stalled(tracker, merit, old_active=None, new_active=None) -> bool:
    """Update ``tracker = [best, steps_since_best]`` with ``merit``; True after a stall.

    A stall is :data:`STALL_STEPS` consecutive Newton-min steps without
    progress.  Progress is a new smallest ``||min(gap, lam)||``, or (when the
    active sets are given) a monotone change of the active set (the new set
    strictly contains, or is strictly contained in, the old one): a contact
    front that moves one cell per step does not reduce the merit function
    but cannot cycle either (the stress case "criss-cross crawl" at aspect
    ratio 128 triggered the safeguard needlessly before this rule).
    """
    monotone = False
    if old_active is not None and new_active is not None:
        grew = np.all(new_active >= old_active)
        shrank = np.all(new_active <= old_active)
        monotone = bool(grew or shrank) and not np.array_equal(old_active, new_active)
    if merit < tracker[0] or monotone:
        tracker[0], tracker[1] = min(merit, tracker[0]), 0
    else:
        tracker[1] += 1
    return tracker[1] >= STALL_STEPS


def new_safeguard_record() -> dict:
    """Empty bookkeeping of safeguard uses (stored in ``parameters["solver"]["safeguard"]``)."""
    return {"uses": 0, "steps": 0, "seconds": 0.0, "triggers": [], "reached_kkt": []}


def run_safeguard(scene, face_solve, start, k, max_steps, record, trigger, on_step=None):
    """Switch from Newton-min (at step ``k``) to :func:`monotone_active_set` and book it.

    ``trigger`` is ``"cycle"`` (an active set came back) or ``"stall"`` (no
    new smallest ``||min(gap, lam)||`` for :data:`STALL_STEPS` steps);
    ``on_step(k_global, active, triple)`` is called after each face solve
    with the global step number.
    """
    logger.warning(
        "Newton-min %s at step %d: switching to the monotone safeguard",
        "cycles" if trigger == "cycle" else "stalls",
        k,
    )
    t0 = time.perf_counter()
    callback = None if on_step is None else (lambda s, act, tri: on_step(k + s, act, tri))
    outcome = monotone_active_set(scene, face_solve, start[0], start[1], max_steps, callback)
    record["uses"] += 1
    record["steps"] += outcome.steps
    record["seconds"] += time.perf_counter() - t0
    record["triggers"].append(f"{trigger} at step {k}")
    record["reached_kkt"].append(bool(outcome.converged))
    return outcome
