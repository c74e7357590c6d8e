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

from dataclasses import dataclass

import numpy as np
import pyamg
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from ..errors import NumericalError, ParameterError
from ..kernels.bilu import bilu0_factor, bilu0_solve

__all__ = [
    "AMG_OPTIONS",
    "LINEAR_SOLVERS",
    "LinearSolve",
    "gmres",
    "preconditioner",
    "pressure_stages",
]

#: The inner solvers: ``direct`` (SuperLU), ``ilu`` (GMRES with ILU), ``cpr`` (GMRES with CPR-AMG).
LINEAR_SOLVERS = ("direct", "ilu", "cpr")


@dataclass
class LinearSolve:
    """What one linear solve did."""

    iterations: int = 0
    residual: float = 0.0  # relative residual of the scaled system
    stopped_by: str = ""


def block_ilu(a: sp.csr_matrix):
    """Block ILU(0) of ``a`` with the 3 x 3 blocks of the cells; return ``apply(r)``.

    The pattern is the cell graph's (no fill), every cell's diagonal block is
    inverted exactly: the preconditioner of reservoir simulators
    (:mod:`fastmem.kernels.bilu`).  SuperLU's ILU without pivoting lost
    accuracy as the gas spread (169 GMRES iterations on the 2D section after 6
    steps, where this needs a few), and with COLAMD and pivoting it filled in
    almost to a full LU and then failed as "singular" at 25,500 cells.
    """
    bsr = a.tobsr(blocksize=(3, 3))
    bsr.sort_indices()
    indptr = bsr.indptr.astype(np.int64)
    indices = bsr.indices.astype(np.int64)
    blocks = np.ascontiguousarray(bsr.data, dtype=float)
    diag_pos, inv_diag, singular = bilu0_factor(indptr, indices, blocks)
    if singular >= 0:
        raise NumericalError(
            f"block ILU(0) met a singular pivot block at cell {singular}: use "
            "linear_solver='direct'"
        )

    def apply(r):
        return bilu0_solve(indptr, indices, blocks, diag_pos, inv_diag, np.ascontiguousarray(r))

    return apply


#: Options of the AMG hierarchies of CPR: smoothed aggregation whose prolongation
#: smoother bounds the spectral radius row by row ("local") instead of estimating
#: it by Arnoldi (that estimate was 4.4 s of 28.5 s on the 25,500-cell section).
AMG_OPTIONS = {
    "max_coarse": 50,
    "smooth": ("jacobi", {"omega": 4.0 / 3.0, "weighting": "local"}),
}


def pressure_stages(a: sp.csr_matrix, n_cells: int, row_scales=None):
    """CPR's stage one: an AMG hierarchy for the pressure and one for the dissolved fraction.

    The pressure block of the water rows (water is incompressible: a
    Laplacian in ``P``) and the ``chi`` block of the hydrogen rows (Fick
    diffusion: ``D dt / h^2`` is 1e4 on the benchmark's cells).  The row
    scales that made ``a`` dimensionless are undone on each block, so that it
    is symmetric again (the two-point Laplacian) for smoothed aggregation.
    """
    stages = []
    for row_offset, col in ((1, 1), (2, 2)):
        rows = 3 * np.arange(n_cells) + row_offset  # cell rows are ordered min, water, hydrogen
        cols = 3 * np.arange(n_cells) + col  # unknowns S, P, chi
        weight = np.ones(n_cells) if row_scales is None else np.asarray(row_scales)[rows]
        a_rows = a[rows].tocsr()
        block = (sp.diags(weight) @ a_rows[:, cols]).tocsr()
        ml = pyamg.smoothed_aggregation_solver(block, **AMG_OPTIONS)
        stages.append((rows, cols, weight, ml, a_rows))
    return stages


def preconditioner(kind: str, a: sp.csr_matrix, n_cells: int, row_scales=None, stages=None):
    """Return ``apply(r)`` approximating ``a^{-1} r`` for ``kind`` in ``('ilu', 'cpr')``.

    ``row_scales`` (3N,) are the factors that scaled ``a``'s rows
    (:func:`pressure_stages`); ``stages``, hierarchies of an earlier Newton
    step of the same time step, are used instead of new ones (the blocks
    change little within a step).  ``apply.stages`` holds the ones used.
    """
    ilu = block_ilu(a)
    if kind == "ilu":
        return ilu
    if kind != "cpr":
        raise ParameterError(f"preconditioner must be 'ilu' or 'cpr', got {kind!r}")
    if stages is None:
        stages = pressure_stages(a, n_cells, row_scales)

    def apply(r):
        x1 = np.zeros_like(r)
        for rows, cols, weight, ml, a_rows in stages:
            rest = r[rows] - a_rows @ x1  # only the rows this stage solves
            x1[cols] += ml.solve(weight * rest, tol=1e-30, maxiter=1, cycle="V")
        return x1 + ilu(r - a @ x1)

    apply.stages = stages
    return apply


def gmres(a, b, apply_m, *, rtol=1e-10, maxiter=500, restart=60, every=None, check=None, drop=1.0):
    """Right-preconditioned restarted GMRES from ``x = 0``.

    Stops when the residual norm is below ``rtol * |b|``, after ``maxiter``
    iterations, or when ``check(x, k)`` returns True; ``check`` is called with
    the iterate every ``every`` iterations, and only once the relative
    residual has fallen below ``drop`` times its value at the last check
    (``drop = 1``: every ``every`` iterations; ``drop = 0.5``: each check
    after a halving, which spares most checks when GMRES converges slowly).
    Returns ``(x, LinearSolve)``.
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
    last = 1.0 / drop if drop > 0 else np.inf  # the first check is never skipped
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
            elif check is not None and every and total % every == 0 and res <= drop * last:
                last = res
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
