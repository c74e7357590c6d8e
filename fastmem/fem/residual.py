"""The discrete residual of a triple: what the P1 equations leave over (docs/method.md §2)."""

from __future__ import annotations

import numpy as np

from ..kernels import pool as _par
from ..kernels.smooth import residual_pair_range
from ..linalg.sparse import THREADED_ROWS, as_unsigned, plain_float64, read_only, threaded

__all__ = ["residuals"]


def residuals(scene, u1, u2, lam):
    """Algebraic residuals ``R1 = F1 - A1 u1 + B lam``, ``R2 = F2 - A2 u2 - B lam``.

    Zero at boundary vertices (docs/method.md §2).  On meshes of
    :data:`~fastmem.linalg.sparse.THREADED_ROWS` vertices and more whose two
    matrices share the pattern arrays (those of the mesh's stiffness pattern, for
    constant and per-triangle tensions), one pass of the kernel threads
    (:func:`fastmem.kernels.smooth.residual_pair_range`) gives the same bits.

    Returns
    -------
    r1, r2 : ndarray of shape (N,)
    """
    f1, f2 = scene.loads
    b = scene.mesh.lumped_mass
    a1, a2 = scene.weighted_stiffness(1), scene.weighted_stiffness(2)
    bnd = scene.mesh.boundary_vertex_mask
    fused = _fused(a1, a2, u1, u2, lam, f1, f2, b, bnd)
    if fused is not None:
        return fused
    # products in the kernel threads (the same numbers as scipy's, fastmem.linalg.sparse.threaded)
    r1 = f1 - threaded(a1) @ u1 + b * lam
    r2 = f2 - threaded(a2) @ u2 - b * lam
    r1[bnd] = 0.0
    r2[bnd] = 0.0
    return r1, r2


def _fused(a1, a2, u1, u2, lam, f1, f2, b, bnd):
    """Both residuals from one pass over the shared pattern, or None where it does not apply."""
    n = a1.shape[0]
    vectors = (u1, u2, lam, f1, f2)
    if (
        n < THREADED_ROWS
        or not _same_memory(a1.indices, a2.indices)
        or not _same_memory(a1.indptr, a2.indptr)
        or a1.indices.dtype not in (np.int32, np.int64)
        or a1.indptr.dtype != a1.indices.dtype
        or not all(m.dtype == np.float64 and m.data.flags.c_contiguous for m in (a1, a2))
        or not plain_float64(vectors, n)
    ):
        return None
    return fused_residuals(a1, a2, u1, u2, lam, f1, f2, b, bnd)


def fused_residuals(a1, a2, u1, u2, lam, f1, f2, b, bnd):
    """Run the kernel pass of :func:`residuals` (two matrices of one pattern), at any size.

    (:func:`fastmem.warm_up` compiles it on a tiny mesh.)
    """
    n = a1.shape[0]
    u1, u2, lam, f1, f2 = (read_only(np.ascontiguousarray(x)) for x in (u1, u2, lam, f1, f2))
    r1 = np.empty(n)
    r2 = np.empty(n)
    _par.parallel_for(
        residual_pair_range, n, as_unsigned(a1.indptr), as_unsigned(a1.indices), a1.data, a2.data,
        u1, u2, lam, f1, f2, b, bnd, r1, r2,
    )  # fmt: skip
    return r1, r2


def _same_memory(x, y) -> bool:
    """Tell whether two arrays are views of the same elements (so hold the same values)."""
    return x is y or (
        x.shape == y.shape
        and x.dtype == y.dtype
        and x.strides == y.strides
        and x.ctypes.data == y.ctypes.data
    )
