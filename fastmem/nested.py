"""Nested iteration: coarser versions of a scene and the transfer of triples between meshes.

A mesh has a coarser version when it came from :meth:`Mesh.refine` (its
``parent``) or from a structured generator with an even number of cells
(:meth:`Mesh.coarser`).  The data move with it when they are constants or
callables; nodal arrays move only to a parent (its vertices come first in
the refined mesh) and per-triangle tensions to a parent as the mean over the
four children.  Triples are transferred by P1 interpolation at the fine
vertices, located in the coarse mesh with a bucket grid (Numba, O(N)).
"""

from __future__ import annotations

import logging
import math

import numpy as np
import scipy.sparse as sp

from .errors import MeshError
from .kernels import locate as _kl
from .scene import Scene

__all__ = ["coarse_scenes", "interpolation_matrix", "prolong_triple"]

logger = logging.getLogger(__name__)

#: Nested iteration stops coarsening below this many vertices.
NESTED_MIN_VERTICES = 1000


def interpolation_matrix(coarse, fine) -> sp.csr_matrix:
    """Sparse P1 interpolation ``I`` with ``(I v)_a = v_coarse(x_a)`` at the fine vertices."""
    v, t = coarse.vertices, coarse.triangles
    x0, x1, y0, y1 = coarse.bounding_box
    nb = max(1, int(math.sqrt(coarse.n_triangles / 2)))
    dx = (x1 - x0) / nb or 1.0
    dy = (y1 - y0) / nb or 1.0
    ptr, items = _kl.bucket_grid(v, t, nb, nb, x0, y0, dx, dy)
    tri, bary = _kl.locate_points(fine.vertices, v, t, ptr, items, nb, nb, x0, y0, dx, dy)
    if (tri < 0).any():
        k = int(np.flatnonzero(tri < 0)[0])
        raise MeshError(
            f"fine vertex {k} at {fine.vertices[k].tolist()} is outside the coarse mesh"
        )
    rows = np.repeat(np.arange(fine.n_vertices), 3)
    mat = sp.csr_matrix(
        (bary.ravel(), (rows, t[tri].ravel())), shape=(fine.n_vertices, coarse.n_vertices)
    )
    mat.eliminate_zeros()
    return mat


def _transfer_mu(mu, fine, coarse):
    if isinstance(mu, float):
        return mu
    if fine.parent is coarse:  # red refinement: children of t are 4t .. 4t+3
        return np.asarray(mu).reshape(-1, 4).mean(axis=1)
    return None


def _transfer_nodal(value, fine, coarse):
    if callable(value) or isinstance(value, float):
        return value
    if fine.parent is coarse:
        return np.asarray(value)[: coarse.n_vertices]
    return None


def coarse_scene(scene: Scene) -> Scene | None:
    """Return the same problem on the next coarser mesh, or None if there is none."""
    fine = scene.mesh
    coarse = fine.coarser()
    if coarse is None:
        return None
    mu = [_transfer_mu(m, fine, coarse) for m in (scene.mu1, scene.mu2)]
    data = [_transfer_nodal(d, fine, coarse) for d in (scene.f1, scene.f2, scene.g)]
    if any(x is None for x in mu + data):
        logger.info("nested iteration: the data of this scene cannot move to a coarser mesh")
        return None
    return Scene(
        coarse,
        mu=tuple(mu),
        f=(data[0], data[1]),
        g=data[2],
        active_c=scene.active_c,
        load_degree=scene.load_degree,
    )


def coarse_scenes(scene: Scene, min_vertices: int = NESTED_MIN_VERTICES) -> list:
    """Chain of coarser scenes, coarsest first, each with at least ``min_vertices``/4 vertices."""
    chain = []
    cur = scene
    while cur.mesh.n_vertices >= min_vertices:
        nxt = coarse_scene(cur)
        if nxt is None:
            break
        chain.append(nxt)
        cur = nxt
    return chain[::-1]


def prolong_triple(fine_scene: Scene, coarse_scene_: Scene, triple):
    """Interpolate a coarse triple onto the fine mesh; boundary values reset exactly."""
    mat = interpolation_matrix(coarse_scene_.mesh, fine_scene.mesh)
    u1, u2, lam = (mat @ x for x in triple)
    bnd = fine_scene.mesh.boundary_vertices
    u1[bnd] = fine_scene.boundary_values[bnd]
    u2[bnd] = 0.0
    lam[bnd] = 0.0
    return u1, u2, lam
