"""Nested iteration: coarser versions of a scene and the transfer of triples between meshes.

A mesh has a coarser version when it came from :meth:`Mesh.refine` (its
``parent``) or from a structured generator with an even number of cells
(:meth:`Mesh.coarser`).  The data move with it when they are constants or
callables; nodal arrays move only to a parent (its vertices come first in
the refined mesh) and per-triangle tensions to a parent as the mean over the
four children.  Triples are transferred by P1 interpolation at the fine
vertices.  Between two meshes of the structured generators (the coarse grid has
half the cells of the fine one) and from a parent to its red refinement, every
fine vertex is a coarse vertex or the midpoint of a coarse edge, so the weights
are known from the indices alone (O(N): NumPy, and from
:data:`KERNELS_FROM` fine vertices on the kernel threads, the same matrix); other
pairs locate the fine
vertices in the coarse mesh with a bucket grid (Numba, O(N)), whose kernels a
structured run thus never compiles.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp

from ..errors import FastmemError, MeshError
from ..fem.scene import Scene
from ..kernels import mg as _kmg
from ..kernels import pool as _par
from ..kernels.rows import warm_active_range
from ..linalg.sparse import THREADED_ROWS, plain_float64, read_only, threaded
from ..mesh.coarsen import coarse_mesh, inside, locate
from ..mesh.mesh import Mesh

__all__ = ["coarse_scenes", "interpolation_matrix", "prolong_triple", "warm_active_set"]

logger = logging.getLogger(__name__)

#: Nested iteration stops coarsening below this many vertices.
NESTED_MIN_VERTICES = 1000


def interpolation_matrix(coarse, fine) -> sp.csr_matrix:
    """Sparse P1 interpolation ``I`` with ``(I v)_a = v_coarse(x_a)`` at the fine vertices.

    Every fine vertex must lie in the coarse mesh (MeshError otherwise),
    except for auxiliary coarse meshes (:mod:`fastmem.mesh.coarsen`), which
    approximate a curved boundary from inside: there a fine vertex outside
    takes the value at the clipped barycentric coordinates of the nearest
    candidate triangle of its bucket, or of the nearest coarse vertex when
    its bucket holds no triangle.
    """
    mat = _nested_interpolation(coarse, fine)
    if mat is not None:
        return mat
    t = coarse.triangles
    tri, bary = locate(coarse, fine.vertices)
    if coarse._cache.get("auxiliary", False):
        lost = tri < 0
        cols = t[np.maximum(tri, 0)]
        if lost.any():
            from scipy.spatial import cKDTree  # lazy: scipy.spatial adds 0.12 s to import fastmem

            cols[lost] = cKDTree(coarse.vertices).query(fine.vertices[lost])[1][:, None]
            bary[lost] = (1.0, 0.0, 0.0)
    else:
        ok, tri = inside(coarse, fine.vertices)
        if not ok.all():
            k = int(np.flatnonzero(~ok)[0])
            raise MeshError(
                f"fine vertex {k} at {fine.vertices[k].tolist()} is outside the coarse mesh"
            )
        cols = t[tri]
    rows = np.repeat(np.arange(fine.n_vertices), 3)
    mat = sp.csr_matrix(
        (bary.ravel(), (rows, cols.ravel())), shape=(fine.n_vertices, coarse.n_vertices)
    )
    mat.eliminate_zeros()
    return mat


def _grid_indices(points, grid) -> tuple[np.ndarray, np.ndarray]:
    nx, ny, x0, x1, y0, y1 = grid
    i = np.rint((points[:, 0] - x0) * (nx / (x1 - x0))).astype(np.int64)
    j = np.rint((points[:, 1] - y0) * (ny / (y1 - y0))).astype(np.int64)
    return i, j


def _grid_columns(coarse, fine):
    """Return the two coarse vertices of each fine vertex of a grid twice as fine, or None.

    Returns ``(first, second)``, int64 (N_fine,): a fine vertex on a coarse vertex
    has ``second = -1``; one on the midpoint of a coarse edge (a side of a cell, or
    the diagonal of the cell it is the centre of) has its two end points.  None
    when the meshes are not of one grid family or a vertex is missing.
    """
    gc, gf = coarse._grid, fine._grid
    if gc is None or gf is None or gf != (2 * gc[0], 2 * gc[1], *gc[2:]):
        return None
    ncx, ncy = gc[0], gc[1]
    ci, cj = _grid_indices(coarse.vertices, gc)
    if ci.min() < 0 or cj.min() < 0 or ci.max() > ncx or cj.max() > ncy:
        return None
    vertex_at = np.full((ncy + 1) * (ncx + 1), -1, dtype=np.int64)
    vertex_at[cj * (ncx + 1) + ci] = np.arange(coarse.n_vertices)
    # each cell's diagonal, from its triangles: "slash" joins (i, j) and (i + 1, j + 1)
    ti, tj = ci[coarse.triangles], cj[coarse.triangles]
    i0, j0 = ti.min(axis=1), tj.min(axis=1)
    cell = j0 * ncx + i0
    has_low = ((ti == i0[:, None]) & (tj == j0[:, None])).any(axis=1)
    has_high = ((ti == i0[:, None] + 1) & (tj == j0[:, None] + 1)).any(axis=1)
    present = np.zeros(ncx * ncy, dtype=bool)
    present[cell] = True
    slash = np.zeros(ncx * ncy, dtype=bool)
    slash[cell[has_low & has_high]] = True
    i, j = _grid_indices(fine.vertices, gf)
    hi, hj, oi, oj = i // 2, j // 2, i % 2, j % 2
    centre = (oi == 1) & (oj == 1)
    c = np.minimum(hj, ncy - 1) * ncx + np.minimum(hi, ncx - 1)
    if not present[c[centre]].all():
        return None
    back = centre & ~slash[c]
    # first end point (i, j) or, on a "back" diagonal, (i + 1, j); second one step on
    a_i = hi + back
    b_i = np.where(back, hi, hi + oi)
    b_j = hj + oj
    first = vertex_at[np.minimum(hj, ncy) * (ncx + 1) + np.minimum(a_i, ncx)]
    second = vertex_at[np.minimum(b_j, ncy) * (ncx + 1) + np.minimum(b_i, ncx)]
    second[(oi == 0) & (oj == 0)] = -1
    if (first < 0).any() or ((second < 0) & ((oi == 1) | (oj == 1))).any():
        return None
    return first, second


#: Fine meshes of at least this many vertices get their nested interpolation from the
#: threaded kernels of :mod:`fastmem.kernels.mg` (the same matrix as the NumPy path of
#: smaller ones, which a default run's meshes take: it compiles none of them).
KERNELS_FROM = 65536


def _nested_interpolation(coarse, fine) -> sp.csr_matrix | None:
    """Interpolation onto a nested fine mesh from the indices alone, or None.

    A fine vertex is a coarse vertex (weight 1) or the midpoint of a coarse edge
    (weights 1/2, 1/2): the red refinement of ``coarse`` (``fine.parent``, vertex
    ``N + e`` on edge ``e``) and two meshes of a structured generator, one with
    twice the cells of the other (:attr:`Mesh._grid`).  Checked against the
    coordinates (None, and point location instead, if any vertex is off).
    Meshes of :data:`KERNELS_FROM` vertices and more: in the kernel threads.
    """
    if fine.n_vertices >= KERNELS_FROM:
        return _nested_interpolation_threaded(coarse, fine)
    if fine.parent is coarse:
        n = coarse.n_vertices
        first = np.concatenate([np.arange(n), coarse.edges[:, 0]])
        second = np.concatenate([np.full(n, -1), coarse.edges[:, 1]])
        if first.size != fine.n_vertices:
            return None
    else:
        cols = _grid_columns(coarse, fine)
        if cols is None:
            return None
        first, second = cols
    single = second < 0
    w = np.where(single, 1.0, 0.5)
    cv = coarse.vertices
    x = w[:, None] * (cv[first] + np.where(single[:, None], 0.0, cv[np.maximum(second, 0)]))
    if np.abs(x - fine.vertices).max(axis=1).max() > 1e-9 * coarse.diameters.min():
        return None
    two = ~single
    rows = np.concatenate([np.arange(fine.n_vertices), np.flatnonzero(two)])
    cols = np.concatenate([first, second[two]])
    return sp.csr_matrix(
        (np.concatenate([w, w[two]]), (rows, cols)), shape=(fine.n_vertices, coarse.n_vertices)
    )


def _nested_interpolation_threaded(coarse, fine) -> sp.csr_matrix | None:
    """:func:`_nested_interpolation` by the kernels of :mod:`fastmem.kernels.mg`.

    The coarse vertices of each fine vertex (a grid table of the coarse vertices and
    the cells' diagonals first, for two meshes of one grid), then a pass that counts
    each row's entries and checks the coordinates, a prefix sum and a fill pass: the
    matrix of the NumPy path, entry for entry (columns ascending, int32 indices).
    """
    nf = fine.n_vertices
    first = np.empty(nf, dtype=np.int64)
    second = np.empty(nf, dtype=np.int64)
    fail = np.zeros(1, dtype=np.int8)
    if fine.parent is coarse:
        n = coarse.n_vertices
        if n + coarse.edges.shape[0] != nf:
            return None
        _par.parallel_for(_kmg.red_pairs_range, nf, n, coarse.edges, first, second)
    else:
        gc, gf = coarse._grid, fine._grid
        if gc is None or gf is None or gf != (2 * gc[0], 2 * gc[1], *gc[2:]):
            return None
        ncx, ncy = int(gc[0]), int(gc[1])
        box = tuple(float(b) for b in gc[2:])
        vertex_at = np.full((ncy + 1) * (ncx + 1), -1, dtype=np.int64)
        cv = coarse.vertices
        _par.parallel_for(
            _kmg.grid_vertex_table_range, coarse.n_vertices, cv, ncx, ncy, *box, vertex_at, fail
        )
        if fail[0]:
            return None
        present = np.zeros(ncx * ncy, dtype=np.bool_)
        slash = np.zeros(ncx * ncy, dtype=np.bool_)
        _par.parallel_for(
            _kmg.grid_cells_range, coarse.n_triangles, cv, coarse.triangles, ncx, ncy, *box,
            present, slash,
        )  # fmt: skip
        _par.parallel_for(
            _kmg.grid_pairs_range, nf, fine.vertices, 2 * ncx, 2 * ncy, *box, ncx, ncy,
            vertex_at, present, slash, first, second, fail,
        )  # fmt: skip
        if fail[0]:
            return None
    counts = np.empty(nf, dtype=np.int32)
    tol = 1e-9 * coarse.diameters.min()
    _par.parallel_for(
        _kmg.pair_counts_range, nf, first, second, coarse.vertices, fine.vertices, tol,
        counts, fail,
    )  # fmt: skip
    if fail[0]:
        return None
    indptr = np.zeros(nf + 1, dtype=np.int32)  # nnz <= 2 N < 2**31 (INDEX_LIMIT)
    np.cumsum(counts, out=indptr[1:])
    indices = np.empty(int(indptr[-1]), dtype=np.int32)
    data = np.empty(indices.size)
    _par.parallel_for(_kmg.pair_fill_range, nf, first, second, indptr, indices, data)
    mat = sp.csr_matrix((data, indices, indptr), shape=(nf, coarse.n_vertices), copy=False)
    mat.has_sorted_indices = True
    return mat


def precompile() -> None:
    """Compile (or load) the threaded nested-interpolation kernels, with a solve's types.

    Meshes of :data:`KERNELS_FROM` vertices and more use them, which the tiny
    problem of :func:`fastmem.warm_up` is not: here two meshes of one grid and a red
    refinement take them.
    """
    fine = Mesh.square(4)
    _nested_interpolation_threaded(fine.coarser(), fine)
    coarse = Mesh.square(2)
    _nested_interpolation_threaded(coarse, coarse.refine())


def _transfer_mu(mu, fine, coarse, cmap):
    if isinstance(mu, float):
        return mu
    if cmap is not None:  # the fine triangle under each coarse centroid
        return np.asarray(mu)[cmap.triangle]
    if fine.parent is coarse:  # red refinement: children of t are 4t .. 4t+3
        return np.asarray(mu).reshape(-1, 4).mean(axis=1)
    # another coarser mesh of the domain (the structured generators): the fine triangle
    # under each coarse centroid, as for the auxiliary meshes.  The coarse levels only
    # give the initial guess; without them Newton-min moves the contact front about one
    # cell per step (checkerboard c = 1e-3: 39 steps at n = 256, 71 at n = 512)
    tri, _ = locate(fine, coarse.vertices[coarse.triangles].mean(axis=1))
    if (tri < 0).any():
        return None
    return np.asarray(mu)[tri]


def _transfer_nodal(value, fine, coarse, cmap):
    if callable(value) or isinstance(value, float):
        return value
    if cmap is not None:  # coarse vertices are fine vertices
        return np.asarray(value)[cmap.vertex]
    if fine.parent is coarse:
        return np.asarray(value)[: coarse.n_vertices]
    return None


def coarse_scene(scene: Scene, auxiliary: bool = False) -> Scene | None:
    """Return the same problem on the next coarser mesh, or None if there is none.

    With ``auxiliary``, a mesh without a coarser version (:meth:`Mesh.coarser`)
    gets an auxiliary one built from a subset of its vertices
    (:func:`fastmem.mesh.coarsen.coarse_mesh`).
    """
    fine = scene.mesh
    coarse = fine.coarser()
    cmap = None
    if coarse is None and auxiliary:
        cmap = coarse_mesh(fine)
        coarse = None if cmap is None else cmap.mesh
    if coarse is None:
        return None
    mu = [_transfer_mu(m, fine, coarse, cmap) for m in (scene.mu1, scene.mu2)]
    g = scene.g
    if cmap is not None and not (callable(g) or isinstance(g, float)):
        g = scene.boundary_values  # the validated values (zero inside), not raw entries
    data = [_transfer_nodal(d, fine, coarse, cmap) for d in (scene.f1, scene.f2, g)]
    if any(x is None for x in mu + data):
        logger.info("nested iteration: the data of this scene cannot move to a coarser mesh")
        return None
    try:
        return Scene(
            coarse,
            mu=tuple(mu),
            f=(data[0], data[1]),
            g=data[2],
            active_c=scene.active_c,
            load_degree=scene.load_degree,
            parallel_callables=scene.parallel_callables,
        )
    except FastmemError as exc:
        if cmap is None:
            raise
        logger.info("auxiliary coarse mesh: the data do not move to it (%s)", exc)
        return None


def coarse_scenes(
    scene: Scene, min_vertices: int = NESTED_MIN_VERTICES, auxiliary: bool = False
) -> list:
    """Chain of coarser scenes, coarsest first, each with at least ``min_vertices``/4 vertices.

    ``auxiliary``: continue with auxiliary coarse meshes where a mesh has no
    coarser version (see :func:`coarse_scene`).
    """
    chain = []
    cur = scene
    while cur.mesh.n_vertices >= min_vertices:
        nxt = coarse_scene(cur, auxiliary)
        if nxt is None:
            break
        chain.append(nxt)
        cur = nxt
    return chain[::-1]


def prolong_triple(fine_scene: Scene, coarse_scene_: Scene, triple, matrix=None):
    """Interpolate a coarse triple onto the fine mesh; boundary values reset exactly.

    ``matrix``: the :func:`interpolation_matrix` of the two meshes, if already built.
    """
    mat = interpolation_matrix(coarse_scene_.mesh, fine_scene.mesh) if matrix is None else matrix
    mat = threaded(mat)  # large: the products in the kernel threads (scipy's bits)
    u1, u2, lam = (mat @ x for x in triple)
    bnd = fine_scene.mesh.boundary_vertices
    u1[bnd] = fine_scene.boundary_values[bnd]
    u2[bnd] = 0.0
    lam[bnd] = 0.0
    return u1, u2, lam


def warm_active_set(scene: Scene, triple) -> np.ndarray:
    """First active set on a level from the triple prolonged from the coarser level.

    ``{a interior : kappa_a B_a lam_a > gap_a}`` (:attr:`Scene.active_weight`):
    a heuristic for the initial active set of Newton-min (PDAS may start from
    any set), chosen so that both sides are lengths, the term of lam in the
    gap equation against the gap (up to the factor ``A_aa``, about 4 on
    structured meshes, by which it changes the gap at its own vertex:
    dividing by it was measured too and cost 3 more Newton steps in total on
    the default scene at n = 512 and 1024).  ``scene.active_c`` is not
    used here.  The rule of docs/method.md §3.1 with c = 1 compares a pressure with a length;
    on a prolonged triple (where lam > 0 and gap > 0 overlap on the coarse
    front) it made every fine vertex with interpolated lam > 0 active and the
    next Newton steps retreat from the overshoot one layer at a time
    (manufactured scene, n = 1024: first eta_lin 1.8e-2 -> 1.1e-3, finest
    Newton steps 6 -> 5).  From the second step on both rules agree (gap = 0
    on the active set and lam = 0 on the inactive one after every step).
    """
    u1, u2, lam = triple
    ii = scene.mesh.interior_vertices
    weight = scene.active_weight
    if (
        ii.size >= THREADED_ROWS
        and plain_float64((u1, u2, lam), scene.mesh.n_vertices)
        and plain_float64((weight,), ii.size)
    ):  # one pass of the kernel threads, the same bits
        out = np.empty(ii.size, dtype=np.bool_)
        _par.parallel_for(
            warm_active_range, ii.size, read_only(ii), read_only(weight),
            read_only(u1), read_only(u2), read_only(lam), out,
        )  # fmt: skip
        return out
    return weight * lam[ii] > (u1[ii] - u2[ii])
