"""The discrete residual of a triple: what the P1 equations leave over (docs/method.md §2)."""

from __future__ import annotations

from ..linalg.sparse import threaded

__all__ = ["residuals"]


def residuals(scene, u1, u2, lam):
    """Algebraic residuals ``R1 = F1 - A1 u1 + B lam``, ``R2 = F2 - A2 u2 - B lam``.

    Zero at boundary vertices (docs/method.md §2).

    Returns
    -------
    r1, r2 : ndarray of shape (N,)
    """
    f1, f2 = scene.loads
    b = scene.mesh.lumped_mass
    # products in the kernel threads (the same numbers as scipy's, fastmem.linalg.sparse.threaded)
    r1 = f1 - threaded(scene.weighted_stiffness(1)) @ u1 + b * lam
    r2 = f2 - threaded(scene.weighted_stiffness(2)) @ u2 - b * lam
    bnd = scene.mesh.boundary_vertex_mask
    r1[bnd] = 0.0
    r2[bnd] = 0.0
    return r1, r2
