r"""The obstacle family's solve: one mesh, or to a guaranteed tolerance by refinement.

:func:`solve_obstacle` is what :func:`fastmem.solve` runs for an
:class:`~fastmem.fem.obstacle.Obstacle`.  Without ``tol``/``rtol`` it solves
the given mesh (nested iteration over its coarser versions); with one it runs
SOLVE -> ESTIMATE -> MARK -> REFINE (Dörfler marking of the indicators of
docs/obstacle.md §6, newest-vertex bisection), each mesh started from the
previous solution prolonged exactly, until the guaranteed bound of the
returned iterate meets the tolerance.  Intermediate meshes are solved only as
tightly as the marking needs: their inexact solves stop with the same
``gamma`` rules; the bound of the returned iterate is always a fresh,
guaranteed one.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from ..estimators import obstacle as _est
from ..fem.obstacle import Obstacle
from ..io.result import Estimate, ObstacleResult
from ..mesh.refine import dorfler_mark, refine_marked
from ..solver.obstacle import newton_min_obstacle, solve_obstacle_levels
from .loop import ensure_growth

__all__ = ["ADAPTIVITY_COLUMNS", "refine_problem", "solve_obstacle"]

logger = logging.getLogger(__name__)

#: Columns of ``result.adaptivity`` (those of :data:`fastmem.adapt.loop.ADAPTIVITY_COLUMNS`
#: but ``cg_stop``: every mesh's solve here stops by its own criterion).
ADAPTIVITY_COLUMNS = (
    "level",
    "n_vertices",
    "n_triangles",
    "eta",
    "eta_disc",
    "eta_lin",
    "eta_alg",
    "energy_norm",
    "target",
    "marked_fraction",
    "newton",
    "inner",
    "solve_seconds",
    "refine_seconds",
)


def refine_problem(problem: Obstacle, mesh, refinement) -> Obstacle:
    """Move an obstacle problem to a refined mesh (nodal data interpolated, callables kept)."""

    def nodal(value):
        if value is None or callable(value) or isinstance(value, float):
            return value
        return refinement.prolong(np.asarray(value))

    mu = problem.mu
    if not isinstance(mu, float):
        mu = refinement.inherit(mu)
    g = problem.g
    if not (callable(g) or isinstance(g, float)):
        g = refinement.prolong(problem.boundary_values)
    return Obstacle(
        mesh,
        mu=mu,
        f=nodal(problem.f),
        g=g,
        lower=nodal(problem.lower),
        upper=nodal(problem.upper),
        active_c=problem.active_c,
        load_degree=problem.load_degree,
        sub_levels=problem.sub_levels,
        parallel_callables=problem.parallel_callables,
    )


def energy_norm(problem, u) -> float:
    """``|||u_h||| = (u^T mu A u)^(1/2)``."""
    return math.sqrt(max(float(u @ (problem.weighted @ u)), 0.0))


def _as_estimate(est) -> Estimate:
    totals = {"eta": est.eta, "eta_I": est.eta_I, "eta_II": est.eta_II}
    totals.update(est.components)
    totals.update({k: float(v) for k, v in est.terms.items()})
    totals["guaranteed"] = float(est.guaranteed)
    totals["case_ii"] = float(est.case == "ii")
    return Estimate(totals=totals, maps={"eta_K": est.indicators})


def _history(rows) -> dict:
    out = {}
    for k, v in rows.items():
        arr = np.asarray(v)
        out[k] = arr.astype(np.float64) if arr.dtype.kind == "f" else arr.astype(np.int64)
    return out


def _result(problem, level, options, rows, timings, adaptivity=None, extra=None):
    est = level.estimate
    mesh = problem.mesh
    n = mesh.n_vertices
    r = _est.residual(problem, level.u, level.lam)
    act = np.zeros(n, dtype=bool)
    act[mesh.interior_vertices] = level.lam[mesh.interior_vertices] != 0.0
    parameters = problem.parameters()
    parameters["solver"] = {
        "method": options["method"],
        "gamma_alg": options["gamma_alg"],
        "gamma_lin": options["gamma_lin"],
        "nested": str(options["nested"]),
    }
    if est is not None:
        parameters["estimate"] = {"guaranteed": est.guaranteed, "case": est.case}
        if est.reason:
            parameters["estimate"]["reason"] = est.reason
    if extra:
        parameters["adaptivity"] = extra
    return ObstacleResult(
        mesh=mesh,
        u1=level.u,
        u2=np.zeros(n),
        lam=level.lam,
        r1=r,
        r2=np.zeros(n),
        active=act,
        history=_history(rows),
        timings=timings,
        parameters=parameters,
        converged=bool(level.converged),
        n_newton=int(level.steps),
        method=options["method"],
        path="obstacle",
        estimate=None if est is None else _as_estimate(est),
        adaptivity=adaptivity,
        lower=problem.psi,
        upper=problem.chi,
    )


def solve_obstacle(problem: Obstacle, options: dict, initial=None) -> ObstacleResult:
    """Solve ``problem`` (see the module docstring); ``options`` from :func:`fastmem.solve`."""
    timings = {}
    t0 = time.perf_counter()
    _ = problem.load, problem.weighted
    timings["assembly"] = time.perf_counter() - t0
    adapt = options.get("adapt")
    if adapt is None:
        t1 = time.perf_counter()
        levels = solve_obstacle_levels(problem, options, initial)
        timings["solve"] = time.perf_counter() - t1
        timings["total"] = time.perf_counter() - t0
        return _result(problem, levels[-1], options, levels[-1].rows, timings)
    return _solve_to_tolerance(problem, options, initial, timings, t0)


def _solve_to_tolerance(problem, options, initial, timings, t0):
    tol, rtol, theta = (options["adapt"][k] for k in ("tol", "rtol", "theta"))
    min_growth = options["adapt"].get("min_growth", 1.0)
    bisections = options["adapt"].get("bisections", 1)
    max_vertices = options["adapt"]["max_vertices"]
    max_levels = options["adapt"]["max_levels"]
    budget = options["adapt"]["time_budget"]
    monitor = options["adapt"].get("level_monitor")
    table = {k: [] for k in ADAPTIVITY_COLUMNS}
    rows = {}
    opts = dict(options)
    opts["estimate"] = True
    level = None
    u = lam = None  # the previous mesh's solution, prolonged
    stop_reason = "max_levels"
    converged = False
    for lev in range(max_levels):
        t1 = time.perf_counter()
        if lev == 0:
            levels = solve_obstacle_levels(problem, opts, initial)
            level = levels[-1]
            rows = level.rows
        else:
            hint = None
            level = newton_min_obstacle(problem, opts, u, lam, level=lev, disc_hint=hint, rows=rows)
        est = level.estimate
        energy = energy_norm(problem, level.u)
        target = min(
            tol if tol is not None else math.inf,
            rtol * energy if rtol is not None else math.inf,
        )
        seconds = time.perf_counter() - t1
        row = {
            "level": lev,
            "n_vertices": problem.mesh.n_vertices,
            "n_triangles": problem.mesh.n_triangles,
            "eta": est.eta,
            "eta_disc": est.eta_disc,
            "eta_lin": est.eta_lin,
            "eta_alg": est.eta_alg,
            "energy_norm": energy,
            "target": target,
            "marked_fraction": 0.0,
            "newton": level.steps,
            "inner": level.inner,
            "solve_seconds": seconds,
            "refine_seconds": 0.0,
        }
        if est.eta <= target:
            converged, stop_reason = True, "tolerance"
        elif problem.mesh.n_vertices * max(1.3, min_growth) > max_vertices:
            stop_reason = "max_vertices"
        elif budget is not None and time.perf_counter() - t0 + 1.5 * seconds > budget:
            stop_reason = "time_budget"
        if converged or stop_reason in ("max_vertices", "time_budget") or lev == max_levels - 1:
            _append(table, row, monitor)
            break
        t2 = time.perf_counter()
        eta2 = est.indicators**2
        marked = ensure_growth(
            problem.mesh, eta2, dorfler_mark(eta2, theta), min_growth, bisections
        )
        row["marked_fraction"] = float(marked.mean())
        new_mesh, refinement = refine_marked(problem.mesh, marked, bisections=bisections)
        new_problem = refine_problem(problem, new_mesh, refinement)
        u = refinement.prolong(level.u)
        lam = refinement.prolong(level.lam)
        bnd = new_mesh.boundary_vertices
        u[bnd] = new_problem.boundary_values[bnd]
        lam[bnd] = 0.0
        problem = new_problem
        row["refine_seconds"] = time.perf_counter() - t2
        _append(table, row, monitor)
    timings["solve"] = time.perf_counter() - t0 - timings["assembly"]
    timings["total"] = time.perf_counter() - t0
    adaptivity = {
        k: np.asarray(v, dtype=np.int64 if k in _INT_COLUMNS else np.float64)
        for k, v in table.items()
    }
    extra = {"stop_reason": stop_reason, "tol": tol, "rtol": rtol, "theta": theta}
    extra["min_growth"] = min_growth
    extra["bisections"] = bisections
    level.converged = level.converged and converged
    return _result(problem, level, options, rows, timings, adaptivity, extra)


_INT_COLUMNS = ("level", "n_vertices", "n_triangles", "newton", "inner")


def _append(table, row, monitor):
    for k in ADAPTIVITY_COLUMNS:
        table[k].append(row[k])
    if monitor is not None:
        monitor(dict(row))
