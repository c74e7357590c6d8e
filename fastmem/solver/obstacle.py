r"""Newton-min (primal-dual active set) for the obstacle family, with nested iteration.

One Newton-min step on an :class:`~fastmem.fem.obstacle.Obstacle` fixes
``u = psi`` on the lower active set, ``u = chi`` on the upper one, and solves
the interior Laplacian on the rest (docs/obstacle.md §2.1).  The system is
the *masked* one of the decoupled membrane path (:func:`fastmem.solver.steps.gap_matrix`:
the rows and columns of the active set replaced by their diagonal), of fixed
size, so that an AMG hierarchy carries over from step to step and a CG
iterate keeps ``u`` exactly on the obstacles at active vertices: the
algebraic residual of an inexact step lives on the inactive set.

Methods, as for the membranes:

``"exact"``
    sparse direct factorisation of every step;
``"exact-amg"``
    AMG-preconditioned CG to round-off;
``"inexact"``
    AMG-CG stopped by the estimators (docs/obstacle.md §6): the inner
    iteration stops when ``eta_alg <= gamma_alg max(eta_disc, eta_lin)``,
    Newton-min when in addition ``eta_lin <= gamma_lin eta_disc``, with
    ``eta_disc`` evaluated only when a test could pass and a stop accepted
    only with a fresh one.

Nested iteration (``nested="auto"``) solves the same problem on the chain of
coarser meshes (:meth:`fastmem.mesh.mesh.Mesh.coarser`) first and prolongs
each solution as the next level's initial iterate.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from ..errors import NumericalError, ParameterError
from ..estimators import obstacle as _est
from ..fem.obstacle import Obstacle
from ..linalg.amg import PCG, amg_preconditioner, check_amg_options
from ..linalg.direct import factorize
from ..linalg.sparse import submatrix, threaded
from .nested import NESTED_MIN_VERTICES, interpolation_matrix
from .steps import EXACT_AMG_RTOL, gap_delta, gap_matrix

#: Relative residual of the CG solves on the coarse levels of nested iteration (inexact)
COARSE_RTOL = 1e-8

__all__ = ["ObstacleLevel", "coarse_problem", "newton_min_obstacle", "solve_obstacle_levels"]

logger = logging.getLogger(__name__)


@dataclass
class ObstacleLevel:
    """What one mesh of nested iteration produced."""

    problem: Obstacle
    u: np.ndarray
    lam: np.ndarray
    estimate: object
    steps: int
    inner: int
    converged: bool
    seconds: float
    rows: dict


# ----------------------------------------------------------------- coarse problems
def _transfer(value, fine, coarse):
    if value is None or callable(value) or isinstance(value, float):
        return value, True
    if fine.parent is coarse:  # refinement keeps the coarse vertices first
        return np.asarray(value)[: coarse.n_vertices], True
    return None, False


def coarse_problem(problem: Obstacle) -> Obstacle | None:
    """Return the same problem on the next coarser mesh, or None when there is none.

    Constant and callable data move to any coarser mesh; nodal data only to the
    parent of a refined mesh; per-triangle tensions to the parent (mean of the
    four children).
    """
    fine = problem.mesh
    coarse = fine.coarser()
    if coarse is None:
        return None
    mu = problem.mu
    if not isinstance(mu, float):
        if fine.parent is not coarse or fine.n_triangles != 4 * coarse.n_triangles:
            return None
        mu = np.asarray(mu).reshape(-1, 4).mean(axis=1)
    moved = {}
    for name in ("f", "g", "lower", "upper"):
        val, ok = _transfer(getattr(problem, name), fine, coarse)
        if not ok:
            return None
        moved[name] = val
    return Obstacle(
        coarse,
        mu=mu,
        f=moved["f"],
        g=moved["g"],
        lower=moved["lower"],
        upper=moved["upper"],
        active_c=problem.active_c,
        load_degree=problem.load_degree,
        sub_levels=problem.sub_levels,
        parallel_callables=problem.parallel_callables,
    )


def _chain(problem, nested):
    if nested is False:
        return [problem]
    chain = []
    cur = problem
    while cur.mesh.n_vertices >= NESTED_MIN_VERTICES:
        nxt = coarse_problem(cur)
        if nxt is None:
            break
        chain.append(nxt)
        cur = nxt
    if nested is True and not chain:
        logger.warning("nested=True but this mesh has no usable coarser version")
    return chain[::-1] + [problem]


# ----------------------------------------------------------------- one level
class _System:
    """The interior system of one mesh: ``mu A_II``, the load and the obstacle targets."""

    def __init__(self, problem: Obstacle):
        mesh = problem.mesh
        self.problem = problem
        self.ii = mesh.interior_vertices
        a = problem.weighted
        # the interior block in the kernel threads on large meshes (scipy's a[ii][:, ii],
        # entry for entry), and the boundary term from one product: the same row sums
        self.a_ii = threaded(submatrix(a, self.ii, self.ii))
        self.a_ii.sort_indices()
        gb = problem.boundary_values
        self.b = problem.load[self.ii] - (a @ gb)[self.ii]
        self.diag = self.a_ii.diagonal()
        n = self.ii.size
        self.psi = problem.psi[self.ii] if problem.psi is not None else np.full(n, -np.inf)
        self.chi = problem.chi[self.ii] if problem.chi is not None else np.full(n, np.inf)
        self.scale = problem.active_scale[self.ii]
        self.coordinates = mesh.vertices[self.ii]

    def sets(self, u_i, lam_i):
        """Active sets ``(lower, upper)`` of an iterate (docs/obstacle.md §2.1)."""
        with np.errstate(invalid="ignore"):
            lo = lam_i - self.scale * (u_i - self.psi) > 0
            up = -lam_i - self.scale * (self.chi - u_i) > 0
        return lo, up & ~lo

    def masked(self, lo, up):
        act = lo | up
        target = np.where(lo, self.psi, np.where(up, self.chi, 0.0))
        rhs = self.b - self.a_ii @ np.where(act, target, 0.0)
        rhs[act] = self.diag[act] * target[act]
        return gap_matrix(self.a_ii, act), rhs, act, target

    def full(self, x_i):
        u = np.array(self.problem.boundary_values)
        u[self.ii] = x_i
        return u

    def multiplier(self, u, act):
        """``lam_a = ((mu A u)_a - F_a) / B_a`` on the active set, 0 elsewhere."""
        p = self.problem
        mesh = p.mesh
        lam = np.zeros(mesh.n_vertices)
        full = (p.weighted @ u - p.load)[self.ii] / mesh.lumped_mass[self.ii]
        lam[self.ii] = np.where(act, full, 0.0)
        return lam


class _AMG:
    """The masked system's AMG hierarchy, kept while the active set changes little."""

    def __init__(self, system, options):
        self.system = system
        self.options = options
        self.pre = None
        self.setup_act = None
        self.update_act = None
        self.setups = 0

    def prepare(self, mat, act):
        sysm = self.system
        changed = (
            act.size if self.setup_act is None else int(np.count_nonzero(act != self.setup_act))
        )
        if self.pre is None or changed > self.options["amg_reuse"] * act.size:
            self.pre = None
            self.pre = amg_preconditioner(mat, dict(self.options["amg_options"]))
            self.setups += 1
            self.setup_act = act.copy()
            self.update_act = self.setup_act
        elif self.pre.can_update and not np.array_equal(act, self.update_act):
            index, delta = gap_delta(sysm.a_ii, self.setup_act, act)
            self.pre.update(mat, index, delta)
            self.update_act = act.copy()
        diag = sysm.diag
        pre = self.pre

        def apply(r):
            z = pre(np.where(act, 0.0, r))
            z[act] = r[act] / diag[act]
            return z

        return apply


def _check_row(rows, **values):
    for k, v in values.items():
        rows.setdefault(k, []).append(v)


def newton_min_obstacle(problem, options, u, lam, level=0, disc_hint=None, rows=None):
    """Newton-min on one mesh from ``(u, lam)``; returns an :class:`ObstacleLevel`.

    ``options``: the dict built by :func:`fastmem.pipeline.solve` (method,
    max_newton, gamma_alg, gamma_lin, max_inner, check_every, amg_options,
    amg_reuse, estimate, monitor).
    """
    t0 = time.perf_counter()
    method = options["method"]
    sysm = _System(problem)
    rows = {} if rows is None else rows
    ii = sysm.ii
    lo, up = sysm.sets(u[ii], lam[ii])
    amg = _AMG(sysm, options) if method != "exact" else None
    seen = {}
    est = None
    eta_disc = disc_hint
    converged = False
    inner_total = 0
    total = rows["inner_total"][-1] if rows.get("inner_total") else 0
    k = 0
    x = u[ii].copy()
    for k in range(1, options["max_newton"] + 1):
        key = (lo.tobytes(), up.tobytes())
        if key in seen and seen[key] != k - 1:
            logger.warning(
                "Newton-min revisited the active set of step %d at step %d", seen[key], k
            )
        seen[key] = k
        mat, rhs, act, target = sysm.masked(lo, up)
        x = np.where(act, target, x)
        inner = 0
        est = None
        if method == "exact":
            x = factorize(mat, sysm.coordinates).solve(rhs) if mat.shape[0] else x
        else:
            pre = amg.prepare(threaded(mat), act)
            cg = PCG(threaded(mat), rhs, x, pre)
            if method in ("exact-amg", "coarse"):
                rtol = EXACT_AMG_RTOL if method == "exact-amg" else COARSE_RTOL
                inner = cg.solve(rtol, options["max_inner"])
                x = cg.x
            else:
                x, inner, est, eta_disc = _inexact_solve(
                    problem, sysm, cg, act, options, eta_disc, (lo, up)
                )
        inner_total += inner
        u = sysm.full(x)
        lam = sysm.multiplier(u, act)
        nlo, nup = sysm.sets(u[ii], lam[ii])
        same = np.array_equal(nlo, lo) and np.array_equal(nup, up)
        if method == "inexact":
            stop = False
            if est is not None:  # a fresh eta_disc: the Newton test may pass
                c = est.components
                stop = (
                    c["eta_lin"] <= options["gamma_lin"] * c["eta_disc"]
                    and c["eta_alg"] <= options["gamma_alg"] * c["eta_disc"]
                )
        else:
            stop = same
        total += inner
        _check_row(
            rows,
            level=level,
            k=k,
            inner=inner,
            inner_total=total,
            n_active=int(lo.sum() + up.sum()),
            n_changed=int(np.count_nonzero(nlo != lo) + np.count_nonzero(nup != up)),
            eta_disc=np.nan if est is None else est.eta_disc,
            eta_lin=np.nan if est is None else est.eta_lin,
            eta_alg=np.nan if est is None else est.eta_alg,
            eta=np.nan if est is None else est.eta,
            fresh_disc=int(est is not None),
            seconds=time.perf_counter() - t0,
            n_vertices=problem.mesh.n_vertices,
            active_lower=int(lo.sum()),
            active_upper=int(up.sum()),
        )
        if options.get("monitor") is not None:
            options["monitor"]({k2: v[-1] for k2, v in rows.items()})
        lo, up = nlo, nup
        if stop:
            converged = True
            break
    if not converged:
        logger.warning(
            "Newton-min on %d vertices stopped after max_newton = %d steps without converging",
            problem.mesh.n_vertices,
            options["max_newton"],
        )
    if method not in ("inexact", "coarse") and options["estimate"] and options.get("final", True):
        est = _est.estimate(problem, u, lam)
    return ObstacleLevel(
        problem, u, lam, est, k, inner_total, converged, time.perf_counter() - t0, rows
    )


def _inexact_solve(problem, sysm, cg, act, options, eta_disc, current):
    """CG on the masked system stopped by the estimators; returns (x, its, est, eta_disc).

    Every ``check_every`` iterations the cheap terms (``eta_alg`` and a lower
    bound of ``eta_lin``) are evaluated.  The inner stop
    ``eta_alg <= gamma_alg max(eta_disc, eta_lin)`` is tried with the last
    ``eta_disc`` known (of the previous step or level); the flux is
    reconstructed (a fresh ``eta_disc``, ``est`` returned) only when the
    Newton test ``eta_lin <= gamma_lin eta_disc`` could pass as well, so that a
    step that cannot be the last costs no flux.  ``est`` is None otherwise.

    Without any ``eta_disc`` yet (the finest level after coarse levels solved
    without estimates), the inner stop uses ``eta_lin`` alone (stricter) while
    the iterate's active sets differ from the ``current`` ones (the Newton test
    cannot pass then); once they agree, the flux is reconstructed and the tests
    above apply.
    """
    g_alg = options["gamma_alg"]
    g_lin = options["gamma_lin"]
    every = options["check_every"]
    start = cg.iterations
    while True:
        for _ in range(every):
            if not cg.step():
                break
        its = cg.iterations - start
        u = sysm.full(cg.x)
        lam = sysm.multiplier(u, act)
        r = _est.residual(problem, u, lam)
        cheap = _est.cheap_terms(problem, u, lam, r)
        eta_lin = cheap["eta_eps"] + 2.0 * cheap["D_nc"]  # c_lin needs the pieces: a lower bound
        eta_alg = cheap["eta_alg"]
        done = cg.stuck or its >= options["max_inner"] or cg.at_roundoff(EXACT_AMG_RTOL)
        if eta_disc is None:
            lo, up = sysm.sets(cg.x, lam[sysm.ii])
            settled = np.array_equal(lo, current[0]) and np.array_equal(up, current[1])
            if not (done or settled):
                if eta_alg <= g_alg * eta_lin:
                    return cg.x, its, None, eta_disc  # the active set still moves: no flux
                continue
        elif not (done or eta_alg <= g_alg * max(eta_disc, eta_lin)):
            continue
        elif not done and eta_lin > g_lin * eta_disc:
            return cg.x, its, None, eta_disc  # this step cannot be the last: no flux
        est = _est.estimate(problem, u, lam, r, cheap)
        eta_disc = est.eta_disc
        if done or est.eta_alg <= g_alg * max(est.eta_disc, est.eta_lin):
            return cg.x, its, est, eta_disc


def _initial(problem):
    """Return the clamp of ``u = 0`` (``g`` on the boundary) and ``lam = 0``."""
    u = np.array(problem.boundary_values)
    ii = problem.mesh.interior_vertices
    inner = np.zeros(ii.size)
    if problem.psi is not None:
        inner = np.maximum(inner, problem.psi[ii])
    if problem.chi is not None:
        inner = np.minimum(inner, problem.chi[ii])
    u[ii] = inner
    return u, np.zeros(problem.mesh.n_vertices)


def solve_obstacle_levels(problem, options, initial=None):
    """Nested iteration over the coarse chain, then Newton-min on ``problem``.

    Returns the list of :class:`ObstacleLevel`, coarsest first.
    """
    if initial is not None:
        u, lam = (np.array(v, dtype=np.float64) for v in initial)
        n = problem.mesh.n_vertices
        if u.shape != (n,) or lam.shape != (n,):
            raise ParameterError(
                f"initial must be a pair (u, lam) of arrays of shape ({n},), got "
                f"{u.shape} and {lam.shape}"
            )
        if not (np.isfinite(u).all() and np.isfinite(lam).all()):
            raise ParameterError("initial contains NaN or inf")
        u[problem.mesh.boundary_vertices] = problem.boundary_values[problem.mesh.boundary_vertices]
        chain = [problem]
    else:
        chain = _chain(problem, options["nested"])
        u, lam = _initial(chain[0])
    levels = []
    rows = {}
    hint = None
    for lev, pr in enumerate(chain):
        if lev > 0:
            prev = chain[lev - 1]
            mat = interpolation_matrix(prev.mesh, pr.mesh)
            u, lam = mat @ u, mat @ lam
            bnd = pr.mesh.boundary_vertices
            u[bnd] = pr.boundary_values[bnd]
            lam[bnd] = 0.0
            est = levels[-1].estimate
            hint = None if est is None else 0.5 * est.eta_disc  # rate 1 in h
        opts = dict(options)
        opts["final"] = lev == len(chain) - 1
        if options["method"] == "inexact" and not opts["final"]:
            # a coarse level only provides the initial iterate of the next one: its
            # linear steps to COARSE_RTOL, Newton-min until the active set repeats, no
            # estimate (docs/obstacle.md §11)
            opts["method"] = "coarse"
        out = newton_min_obstacle(pr, opts, u, lam, level=lev, disc_hint=hint, rows=rows)
        if not np.isfinite(out.u).all():
            raise NumericalError("Newton-min produced NaN or inf")
        u, lam = out.u, out.lam
        levels.append(out)
    return levels


def check_obstacle_options(method, amg_options, amg_reuse):
    """Validate what only the obstacle solver reads; returns the AMG options dict."""
    if method not in ("inexact", "exact-amg", "exact"):
        raise ParameterError(
            f"method must be one of 'inexact', 'exact-amg', 'exact', got {method!r}"
        )
    return check_amg_options(amg_options)
