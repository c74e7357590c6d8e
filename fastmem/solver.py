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

from .config import blas_limits, get_threads
from .errors import CyclingError, InputTypeError, ParameterError
from .linear import make_step, residuals
from .result import Result, check_triple
from .scene import Scene

__all__ = ["HISTORY_COLUMNS", "METHODS", "complementarity", "solve"]

logger = logging.getLogger(__name__)

METHODS = ("exact",)

#: Relative residual ||R|| / ||(F1, F2, B lam)|| expected of an exact solve at convergence.
ROUNDOFF_TOL = 1e-9

#: Columns of the per-step history of an exact Newton-min solve.
HISTORY_COLUMNS = ("k", "n_active", "n_changed", "comp_norm", "res_norm", "seconds")


def complementarity(u1, u2, lam, interior):
    """Nodal complementarity function ``min(u1 - u2, lam)`` on interior vertices."""
    return np.minimum(u1[interior] - u2[interior], lam[interior])


def _active_key(active: np.ndarray) -> bytes:
    return hashlib.blake2b(np.packbits(active).tobytes(), digest_size=16).digest()


def _check_initial(initial, mesh):
    if initial is None:
        return None
    return check_triple(mesh, initial, prefix="initial ")


def solve(
    scene: Scene,
    method: str = "exact",
    path: str = "auto",
    *,
    max_newton: int = 1000,
    initial=None,
    monitor=None,
    blas_threads: int | None = None,
    estimate: bool = False,
) -> Result:
    """Solve the discrete two-membrane contact problem with Newton-min.

    Parameters
    ----------
    scene : Scene
        The problem.
    method : {"exact"}
        ``"exact"``: every linear step is solved by a sparse direct solver.
    path : {"auto", "general", "decoupled"}
        Linear-step formulation; "auto" takes "decoupled" for constant mu.
    max_newton : int
        Maximum number of Newton-min steps.  Reaching it returns a Result with
        ``converged=False`` and logs a warning.
    initial : tuple (u1, u2, lam) of ndarray, optional
        Initial iterate; its active set starts the iteration.  Default: the
        unconstrained problem is the first step (empty active set).
    monitor : callable, optional
        Called with each history row (a dict) as soon as it is recorded.
    blas_threads : int, optional
        BLAS threads during the solve (default :func:`fastmem.get_threads`).
    estimate : bool
        Attach the guaranteed a posteriori error bound of the returned triple
        (:func:`fastmem.estimate`; costs one flux reconstruction).  Without it
        no flux is reconstructed.

    Returns
    -------
    Result

    Raises
    ------
    CyclingError
        When an active set repeats an earlier, different one.
    """
    if not isinstance(scene, Scene):
        raise InputTypeError(f"scene must be a fastmem.Scene, got {type(scene).__name__}")
    if not isinstance(estimate, (bool, np.bool_)):
        raise InputTypeError(f"estimate must be True or False, got {estimate!r}")
    if method not in METHODS:
        raise ParameterError(f"method must be one of {METHODS}, got {method!r}")
    if (
        isinstance(max_newton, bool)
        or not isinstance(max_newton, (int, np.integer))
        or (max_newton < 1)
    ):
        raise ParameterError(f"max_newton must be a positive integer, got {max_newton!r}")
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
        _ = scene.loads, scene.weighted_stiffness(1), scene.weighted_stiffness(2)
        timings["assembly"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        step = make_step(scene, path)
        timings["setup"] = time.perf_counter() - t0
        result = _newton(scene, step, method, max_newton, init, monitor, timings)
        if estimate:
            from .bound import estimate as _estimate

            t0 = time.perf_counter()
            result.estimate = _estimate(
                scene, result.u1, result.u2, result.lam, result.r1, result.r2
            )
            timings["estimate"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    return result


def _newton(scene, step, method, max_newton, init, monitor, timings):
    mesh = scene.mesh
    interior = mesh.interior_vertices
    c = scene.active_c
    if init is None:
        active = np.zeros(interior.size, dtype=bool)
    else:
        u1, u2, lam = init
        active = lam[interior] > c * (u1[interior] - u2[interior])
    seen = {_active_key(active): 0}
    rows = {name: [] for name in HISTORY_COLUMNS}
    converged = False
    t_solve = time.perf_counter()
    k = 0
    for k in range(1, max_newton + 1):
        t0 = time.perf_counter()
        u1, u2, lam = step.solve(active)
        r1, r2 = residuals(scene, u1, u2, lam)
        new_active = lam[interior] > c * (u1[interior] - u2[interior])
        n_changed = int(np.count_nonzero(new_active != active))
        row = {
            "k": k,
            "n_active": int(active.sum()),
            "n_changed": n_changed,
            "comp_norm": float(np.linalg.norm(complementarity(u1, u2, lam, interior))),
            "res_norm": float(np.sqrt(r1 @ r1 + r2 @ r2)),
            "seconds": time.perf_counter() - t0,
        }
        for name in HISTORY_COLUMNS:
            rows[name].append(row[name])
        logger.info(
            "newton %d: |A|=%d changed=%d |min(gap,lam)|=%.3e |R|=%.3e",
            k,
            row["n_active"],
            n_changed,
            row["comp_norm"],
            row["res_norm"],
        )
        if monitor is not None:
            monitor(row)
        if n_changed == 0:
            converged = True
            break
        key = _active_key(new_active)
        if key in seen:
            history = {n: np.asarray(v) for n, v in rows.items()}
            raise CyclingError(
                f"Newton-min cycles: the active set of step {k + 1} ({int(new_active.sum())} "
                f"vertices) equals the one of step {seen[key] + 1}; the stiffness matrix is "
                "probably not an M-matrix (obtuse angles). Try another mesh.",
                history=history,
            )
        seen[key] = k
        active = new_active
    timings["solve"] = time.perf_counter() - t_solve
    f1, f2 = scene.loads
    b = mesh.lumped_mass
    scale = np.sqrt(f1 @ f1 + f2 @ f2 + 2 * (b * lam) @ (b * lam)) + np.finfo(float).tiny
    res_rel = float(np.sqrt(r1 @ r1 + r2 @ r2) / scale)
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
    history = {
        name: np.asarray(
            rows[name],
            dtype=np.float64 if name in ("comp_norm", "res_norm", "seconds") else np.int64,
        )
        for name in HISTORY_COLUMNS
    }
    params = scene.parameters()
    params["solver"] = {
        "method": method,
        "path": step.name,
        "max_newton": max_newton,
        "factorizations": step.factorizations,
        "relative_residual": res_rel,
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
