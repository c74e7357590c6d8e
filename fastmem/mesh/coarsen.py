"""Auxiliary coarse meshes for nested iteration on meshes that did not come from refinement.

A mesh read from a file (gmsh, meshio) or built from arrays has no coarser
version to start Newton-min from, and from the unconstrained start the contact
front moves about one cell per Newton step.  :func:`coarse_mesh` builds a
coarser mesh of the same domain from a subset of its vertices:

1. the vertices are taken greedily as a maximal independent set of the vertex
   graph (Numba, O(N)): corners of the boundary first, then the other boundary
   vertices, then the interior; about one vertex in four, spaced two to three
   fine edges apart, graded like the fine mesh (corners are always kept, even
   when two of them are neighbours);
2. the taken vertices are triangulated by Delaunay (scipy / Qhull,
   O(N log N); the most expensive step: about 1 s for 66k points here);
3. triangles whose centroid or an edge midpoint lies outside the fine mesh
   (holes, re-entrant corners, gaps between parts: the convex hull of a
   non-convex domain) and slivers are dropped.

The coarse domain approximates the fine one: a curved boundary by an
inscribed polygon, and a triangle may still bridge a notch narrower than its
edges.

The coarse vertices are fine vertices, so nodal data restrict by index; a
per-triangle tension takes the value of the fine triangle under the coarse
centroid; boundary values come from the validated boundary values of g.
The coarse mesh only provides an initial guess: any failure (too few
vertices taken, a triangulation the mesh checks refuse, an error in Qhull)
gives None and the solver starts from the unconstrained problem as before.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from ..errors import FastmemError
from ..kernels import coarsen as _kc
from ..kernels import locate as _kl
from .mesh import Mesh
from .pattern import csr_structure

__all__ = ["CoarseMap", "coarse_mesh", "inside", "locate"]

logger = logging.getLogger(__name__)

#: A boundary vertex whose two boundary edges turn by more than this angle is a corner
#: (always kept, so that the coarse domain keeps the corners of the fine one).
CORNER_ANGLE_DEG = 20.0

#: Coarsening that keeps more than this fraction of the vertices is not worth a level.
MAX_RATIO = 0.6


class CoarseMap:
    """An auxiliary coarse mesh with its relation to the fine mesh it came from.

    Attributes
    ----------
    mesh : Mesh
        The coarse mesh.
    vertex : ndarray of int64, shape (N_coarse,)
        Fine vertex of each coarse vertex (same coordinates).
    triangle : ndarray of int64, shape (M_coarse,)
        Fine triangle containing the centroid of each coarse triangle.
    """

    def __init__(self, mesh, vertex, triangle):
        self.mesh = mesh
        self.vertex = vertex
        self.triangle = triangle


def locate(mesh, points):
    """Triangle of ``mesh`` containing each point, and its barycentric coordinates.

    A bucket grid of ``mesh`` is built for the call (not kept: the fine mesh
    may have millions of triangles).  A point inside no triangle gets the
    candidate of its bucket that it is closest to in barycentric terms, with
    clipped coordinates, or ``tri = -1`` when its bucket holds no triangle;
    see :func:`fastmem.kernels.locate.locate_points`.
    """
    x0, x1, y0, y1 = mesh.bounding_box
    nb = max(1, int(math.sqrt(mesh.n_triangles / 2)))
    dx = (x1 - x0) / nb or 1.0
    dy = (y1 - y0) / nb or 1.0
    ptr, items = _kl.bucket_grid(mesh.vertices, mesh.triangles, nb, nb, x0, y0, dx, dy)
    pts = np.ascontiguousarray(points, dtype=np.float64)
    return _kl.locate_points(pts, mesh.vertices, mesh.triangles, ptr, items, nb, nb, x0, y0, dx, dy)


def inside(mesh, points) -> tuple[np.ndarray, np.ndarray]:
    """Mask of the points inside ``mesh`` (to round-off) and their triangles (-1 outside)."""
    tri, bary = locate(mesh, points)
    found = tri >= 0
    k = np.maximum(tri, 0)
    back = np.einsum("pk,pkd->pd", bary, mesh.vertices[mesh.triangles[k]])
    ok = found & (np.linalg.norm(back - points, axis=1) <= 1e-9 * mesh.diameters[k])
    return ok, np.where(ok, tri, -1)


def _corners(mesh) -> np.ndarray:
    """Boundary vertices where the boundary turns (or that do not have two boundary edges)."""
    edges = mesh.edges[mesh.boundary_edges]  # (B, 2)
    a = np.concatenate([edges[:, 0], edges[:, 1]])
    b = np.concatenate([edges[:, 1], edges[:, 0]])
    order = np.argsort(a, kind="stable")
    a, b = a[order], b[order]
    counts = np.bincount(a, minlength=mesh.n_vertices)
    bnd = np.flatnonzero(counts > 0)
    start = np.concatenate([[0], np.cumsum(counts[bnd])[:-1]])
    regular = counts[bnd] == 2
    v = mesh.vertices
    p = v[b[start[regular]]] - v[bnd[regular]]
    q = v[b[start[regular] + 1]] - v[bnd[regular]]
    cos = (p * q).sum(axis=1) / (np.linalg.norm(p, axis=1) * np.linalg.norm(q, axis=1))
    straight = cos < -math.cos(math.radians(CORNER_ANGLE_DEG))
    corner = np.ones(bnd.size, dtype=bool)
    corner[np.flatnonzero(regular)[straight]] = False
    return bnd[corner]


def coarse_mesh(mesh) -> CoarseMap | None:
    """Coarser mesh of (nearly) the same domain from about a quarter of the vertices, or None.

    See the module docstring for the construction.  Never raises: any failure
    is logged and gives None (the caller then starts from the unconstrained
    problem).
    """
    try:
        return _coarse_mesh(mesh)
    except Exception as exc:  # an initial guess is optional: never fail the solve for it
        logger.info("auxiliary coarse mesh not built: %s: %s", type(exc).__name__, exc)
        return None


def _coarse_mesh(mesh):

    indptr, indices, _ = csr_structure(mesh)
    corners = _corners(mesh)
    bnd = mesh.boundary_vertex_mask.copy()
    bnd[corners] = False
    order = np.concatenate([corners, np.flatnonzero(bnd), mesh.interior_vertices])
    taken = _kc.independent_set(indptr, indices, order.astype(np.int64))
    taken[corners] = True  # two neighbouring corners both stay (then not independent)
    keep = np.flatnonzero(taken)
    if keep.size < 3 or keep.size > MAX_RATIO * mesh.n_vertices:
        return None
    pts = mesh.vertices[keep]
    from scipy.spatial import Delaunay  # lazy: scipy.spatial adds 0.12 s to import fastmem

    tri = Delaunay(pts).simplices.astype(np.int64)
    # keep a triangle when its centroid and its edge midpoints lie in the fine mesh
    # (drops the convex hull over re-entrant corners, holes and gaps between parts)
    corner_pts = pts[tri]  # (T, 3, 2)
    probes = [corner_pts.mean(axis=1)] + [
        0.5 * (corner_pts[:, a] + corner_pts[:, b]) for a, b in ((0, 1), (1, 2), (2, 0))
    ]
    ok, fine_tri = inside(mesh, np.concatenate(probes))  # one bucket grid for all probes
    nt = tri.shape[0]
    ok = ok.reshape(4, nt).all(axis=0)
    fine_tri = fine_tri[:nt]
    e1 = corner_pts[:, 1] - corner_pts[:, 0]
    e2 = corner_pts[:, 2] - corner_pts[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    diam2 = np.maximum.reduce([(e1**2).sum(1), (e2**2).sum(1), ((e2 - e1) ** 2).sum(1)])
    ok &= area > 1e-6 * diam2  # no slivers
    tri, fine_tri = tri[ok], fine_tri[ok]
    if tri.shape[0] == 0:
        return None
    used = np.zeros(keep.size, dtype=bool)
    used[tri.ravel()] = True
    renum = np.cumsum(used) - 1
    try:
        coarse = Mesh(pts[used], renum[tri])
    except FastmemError as exc:
        logger.info("auxiliary coarse mesh refused by the mesh checks: %s", exc)
        return None
    coarse._cache["auxiliary"] = True  # interpolation from it may extrapolate
    return CoarseMap(coarse, keep[used], fine_tri)
