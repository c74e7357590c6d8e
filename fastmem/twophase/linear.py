"""Linear solvers of the Newton-min steps: direct, GMRES with ILU, GMRES with CPR-AMG.

The Newton-min system is scaled first (rows by the storage of a unit change,
columns by the unknowns' units, :meth:`fastmem.twophase.model.Problem.row_scales`)
so that every solver sees a dimensionless matrix.  GMRES is ours (restarted,
right-preconditioned, Givens rotations) because the adaptive strategy needs
the iterate every ``nu`` iterations to evaluate its estimators; SciPy's
``gmres`` only hands it out at restarts.

CPR ("constrained pressure residual") is the two-stage preconditioner of
reservoir simulators: stage one solves the pressure block of the water
equations (an M-matrix: water is incompressible, so those rows are a
Laplacian in ``P``) by one algebraic-multigrid V-cycle (pyamg), stage two
applies ILU to the whole system on what is left.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import pyamg
import scipy.sparse as sp
from scipy.sparse.linalg import spilu, splu

from ..errors import NumericalError, ParameterError

__all__ = ["LINEAR_SOLVERS", "LinearSolve", "gmres", "preconditioner"]

#: The inner solvers: ``direct`` (SuperLU), ``ilu`` (GMRES with ILU), ``cpr`` (GMRES with CPR-AMG).
LINEAR_SOLVERS = ("direct", "ilu", "cpr")


@dataclass
class LinearSolve:
    """What one linear solve did."""

    iterations: int = 0
    residual: float = 0.0  # relative residual of the scaled system
    stopped_by: str = ""


def preconditioner(kind: str, a: sp.csr_matrix, n_cells: int):
    """Return ``apply(r)`` approximating ``a^{-1} r`` for ``kind`` in ``('ilu', 'cpr')``."""
    csc = a.tocsc()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            ilu = spilu(
                csc, drop_tol=1e-4, fill_factor=10.0, permc_spec="NATURAL", diag_pivot_thresh=0.0
            )
        except RuntimeError as exc:
            raise NumericalError(f"ILU of the Newton-min matrix failed: {exc}") from exc
    if kind == "ilu":
        return ilu.solve
    if kind != "cpr":
        raise ParameterError(f"preconditioner must be 'ilu' or 'cpr', got {kind!r}")
    rows = 3 * np.arange(n_cells) + 1  # water rows (cell rows ordered min, water, hydrogen)
    cols = rows + 1  # pressure columns
    app = a[rows][:, cols].tocsr()
    ml = pyamg.smoothed_aggregation_solver(app, max_coarse=50)

    def apply(r):
        x1 = np.zeros_like(r)
        x1[cols] = ml.solve(r[rows], tol=1e-30, maxiter=1, cycle="V")
        return x1 + ilu.solve(r - a @ x1)

    return apply


def gmres(a, b, apply_m, *, rtol=1e-10, maxiter=500, restart=60, every=None, check=None):
    """Right-preconditioned restarted GMRES from ``x = 0``.

    Stops when the residual norm is below ``rtol * |b|``, after ``maxiter``
    iterations, or when ``check(x, k)`` returns True; ``check`` is called with
    the iterate every ``every`` iterations.  Returns ``(x, LinearSolve)``.
    """
    n = b.size
    x = np.zeros(n)
    bnorm = float(np.linalg.norm(b))
    stats = LinearSolve()
    if bnorm == 0.0:
        stats.stopped_by = "zero right-hand side"
        return x, stats
    r = b.copy()
    total = 0
    while True:
        beta = float(np.linalg.norm(r))
        m = restart
        v = np.zeros((m + 1, n))
        z = np.zeros((m, n))
        h = np.zeros((m + 1, m))
        cs = np.zeros(m)
        sn = np.zeros(m)
        g = np.zeros(m + 1)
        g[0] = beta
        v[0] = r / beta
        j_done = 0
        stop = ""
        for j in range(m):
            z[j] = apply_m(v[j])
            w = a @ z[j]
            for i in range(j + 1):  # modified Gram-Schmidt
                h[i, j] = w @ v[i]
                w -= h[i, j] * v[i]
            h[j + 1, j] = float(np.linalg.norm(w))
            breakdown = h[j + 1, j] == 0.0  # the Krylov space is invariant: x is exact
            if not breakdown:
                v[j + 1] = w / h[j + 1, j]
            for i in range(j):
                t = cs[i] * h[i, j] + sn[i] * h[i + 1, j]
                h[i + 1, j] = -sn[i] * h[i, j] + cs[i] * h[i + 1, j]
                h[i, j] = t
            rho = np.hypot(h[j, j], h[j + 1, j])
            cs[j], sn[j] = (1.0, 0.0) if rho == 0 else (h[j, j] / rho, h[j + 1, j] / rho)
            h[j, j] = rho
            h[j + 1, j] = 0.0
            g[j + 1] = -sn[j] * g[j]
            g[j] = cs[j] * g[j]
            total += 1
            j_done = j + 1
            res = abs(g[j + 1]) / bnorm
            if res <= rtol:
                stop = "rtol"
            elif total >= maxiter:
                stop = "maxiter"
            elif check is not None and every and total % every == 0:
                if check(x + _update(h, g, z, j_done), total):
                    stop = "estimators"
            if stop or breakdown:
                break
        x = x + _update(h, g, z, j_done)
        r = b - a @ x
        stats.iterations = total
        stats.residual = float(np.linalg.norm(r)) / bnorm
        if stop or stats.residual <= rtol:
            stats.stopped_by = stop or "rtol"
            return x, stats


def _update(h, g, z, j):
    """``Z_j y`` with ``y`` the least-squares solution of the Hessenberg system."""
    y = np.linalg.solve(np.triu(h[:j, :j]), g[:j]) if j else np.zeros(0)
    return y @ z[:j]


def direct(a, b):
    """SuperLU solve of the scaled system; raises NumericalError on a singular matrix."""
    try:
        return splu(a.tocsc()).solve(b)
    except RuntimeError as exc:
        raise NumericalError(f"the Newton-min matrix is singular: {exc}") from exc
