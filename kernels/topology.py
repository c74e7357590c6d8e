"""Edges of a triangle mesh in one pass: the connectivity that ``Mesh`` caches.

Half-edge ``h = 3 k + i`` is local edge ``i`` of triangle ``k``, from vertex
``t[k, (i + 1) % 3]`` to ``t[k, (i + 2) % 3]``.  The edges are the distinct
vertex pairs ``(lo, hi)``, ``lo < hi``, numbered in lexicographic order, and
the triangles of an edge are listed in the order of their half-edges: the
same numbering as a stable sort of the keys ``lo * N + hi`` would give, found
by a counting sort on ``lo`` (O(N + M)) and an insertion sort by ``hi`` inside
each vertex's bucket (a vertex's degree), instead of an O(M log M) sort and a
dozen passes over (3M,) arrays.

Index dtypes: the half-edge arrays of the pass and the returned ``edges``
are int32 (``counts`` and ``forward``: int8, saturated) (half the memory of int64: the pass holds
12 bytes per half-edge, about 72 per vertex, the retained ``edges`` 24 instead
of 48), and so are ``tri_edges`` and ``edge_triangles`` (24 instead of 48 bytes per
vertex each), so the caller must keep ``3 M`` and ``n`` below ``2**31``
(:data:`fastmem.mesh.mesh.INDEX_LIMIT` checks it).  The patch arrays of
:func:`vertex_patches` are int32 (triangles) and int8 (local index 0, 1, 2).
"""

import contextlib

import numba
import numpy as np

from ._jit import jit
from .pool import GRAIN, n_threads, parallel_for, ranges, run_ranges, zeros

__all__ = [
    "edge_topology",
    "lumped_mass",
    "rectangle_triangles",
    "refined_edge_topology",
    "triangle_checks",
    "vertex_patch_ptr",
    "vertex_patches",
]

#: saturation value of the int8 ``counts`` and ``forward`` of :func:`edge_topology`
COUNT_CAP = 127

#: Meshes of fewer triangles take NumPy paths that give the same arrays (vectorised
#: sorts and counts): on them the kernels' compile time (about 2 s for the eight
#: kernels, on the first run after an install) is far above their run time (a few
#: milliseconds either way at 32,768 triangles, the default ``fastmem run``).  The
#: P1 pattern, its position map and the stiffness and mass matrices follow the same
#: threshold (:mod:`fastmem.kernels.sparsity`, :mod:`fastmem.kernels.assembly`).
NUMPY_BELOW = 65536


def _small(m) -> bool:
    return m < NUMPY_BELOW


#: set by :func:`numpy_paths` (tests): small meshes take the NumPy paths of the pattern
#: and matrices even where their kernels are in the process
_PREFER_NUMPY = False


def numpy_path(m, kernel) -> bool:
    """Whether a mesh of ``m`` triangles builds its P1 pattern or matrices with NumPy.

    Small meshes (:data:`NUMPY_BELOW`) do, unless ``kernel`` (the Numba kernel of the
    other path) is in the process already: then it costs no compilation and runs about
    ten times faster (an adaptive loop after ``fastmem.warm_up(adaptive=True)``
    assembles its small meshes with it).  Both paths give the same bits.
    """
    return m < NUMPY_BELOW and (_PREFER_NUMPY or not getattr(kernel, "signatures", None))


@contextlib.contextmanager
def numpy_paths():
    """Within the block every mesh takes the NumPy paths, whatever its size (tests)."""
    global NUMPY_BELOW, _PREFER_NUMPY
    saved = NUMPY_BELOW, _PREFER_NUMPY
    NUMPY_BELOW, _PREFER_NUMPY = 2**62, True
    try:
        yield
    finally:
        NUMPY_BELOW, _PREFER_NUMPY = saved


@contextlib.contextmanager
def kernel_paths():
    """Within the block every mesh takes the kernels, whatever its size.

    For :func:`fastmem.warm_up` with ``large``: it compiles the kernels on a tiny
    mesh, with the argument types a large mesh passes.
    """
    global NUMPY_BELOW
    saved, NUMPY_BELOW = NUMPY_BELOW, 0
    try:
        yield
    finally:
        NUMPY_BELOW = saved


def edge_topology(t, n, patches=None):
    """Edges, triangle edges and edge triangles of the triangles ``t`` (M, 3) over ``n`` vertices.

    The edges of lower end point ``v`` are read from the vertex patch of ``v``
    (``patches = (patch_ptr, patch_triangles, patch_local)`` of
    :func:`vertex_patches`, computed here when not given; ``Mesh`` passes its own):
    the half-edges ``3 k + j`` of its triangles ``k`` (ascending) that leave ``v``
    towards a higher vertex, insertion-sorted by that vertex.  No half-edge
    arrays: the former counting sort held 12 bytes per half-edge (1.2 GB at
    n = 4096, memory first-touched for a temporary).  A wrapper around the Numba
    kernels :func:`_count_edges` and :func:`_number_edges`, both over vertex
    ranges in threads (:mod:`._par`; the same arrays for any thread count and
    split); the arrays are allocated here, so that the kernels compile no
    allocation code.  ``t`` must not repeat a vertex inside a triangle (``Mesh``
    refuses such triangles first).

    Returns
    -------
    edges : int32 (E, 2)
        Vertex pairs, ``edges[:, 0] < edges[:, 1]``, in lexicographic order.
    tri_edges : int32 (M, 3)
        Edge of each local edge (local edge ``i`` is opposite vertex ``i``).
    edge_triangles : int32 (E, 2)
        The first two triangles of each edge in half-edge order (-1: none).
    counts : int32 (E,)
        Triangles per edge (1 on the boundary, 2 inside; more is non-manifold).
    forward : int8 (E,)
        Half-edges of the edge that run from ``lo`` to ``hi`` (an interior edge
        of a consistently oriented mesh has exactly one).

    ``counts`` and ``forward`` are int8, saturated at :data:`COUNT_CAP` (they only feed
    the checks of ``Mesh._set_topology``, which recounts an offending edge exactly):
    3 bytes per edge less than int32 (150 MB at n = 4096, memory the mesh phase
    would otherwise first-touch).
    """
    m = t.shape[0]
    if _small(m):
        return _edge_topology_numpy(t, n)
    if patches is None:
        ptr = vertex_patch_ptr(t, n)
        patches = (ptr, *vertex_patches(t, ptr))
    ptr, ptris, plocal = patches
    chunks = ranges(n, n_threads(), GRAIN)
    index = {lo: c for c, (lo, _) in enumerate(chunks)}
    width = 2 * int(np.diff(ptr).max()) if n else 0  # candidates of one bucket, at most
    scratch = np.empty((len(chunks), 2, max(width, 1)), dtype=np.int64)
    distinct = np.zeros(len(chunks), dtype=np.int64)

    def count(lo, hi):
        c = index[lo]
        distinct[c] = _count_edges(lo, hi, t, ptr, ptris, plocal, scratch[c, 0], scratch[c, 1])

    run_ranges(count, chunks)
    first = np.zeros(len(chunks) + 1, dtype=np.int64)
    np.cumsum(distinct, out=first[1:])
    ne = int(first[-1])
    edges = np.empty((ne, 2), dtype=np.int32)
    tri_edges = np.empty((m, 3), dtype=np.int32)
    et = np.empty((ne, 2), dtype=np.int32)
    counts = np.empty(ne, dtype=np.int8)
    forward = np.empty(ne, dtype=np.int8)

    def number(lo, hi):
        c = index[lo]
        _number_edges(
            lo,
            hi,
            first[c],
            t,
            ptr,
            ptris,
            plocal,
            scratch[c, 0],
            scratch[c, 1],
            edges,
            tri_edges,
            et,
            counts,
            forward,
        )

    run_ranges(number, chunks)
    return edges, tri_edges, et, counts, forward


def _edge_topology_numpy(t, n):
    """:func:`edge_topology` by a stable sort of the half-edge keys ``lo * n + hi``."""
    m = t.shape[0]
    t = np.asarray(t, dtype=np.int64)
    a = t[:, [1, 2, 0]].ravel()  # half-edge 3 k + i runs from t[k, i + 1] to t[k, i + 2]
    b = t[:, [2, 0, 1]].ravel()
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    order = np.argsort(lo * max(n, 1) + hi, kind="stable")
    key_lo, key_hi = lo[order], hi[order]
    new = np.ones(order.size, dtype=bool)
    new[1:] = (key_lo[1:] != key_lo[:-1]) | (key_hi[1:] != key_hi[:-1])
    edge_of = np.cumsum(new) - 1
    start = np.flatnonzero(new)
    ne = start.size
    edges = np.empty((ne, 2), dtype=np.int32)
    edges[:, 0], edges[:, 1] = key_lo[start], key_hi[start]
    tri_edges = np.empty(3 * m, dtype=np.int32)
    tri_edges[order] = edge_of
    count = np.bincount(edge_of, minlength=ne)
    et = np.full((ne, 2), -1, dtype=np.int32)
    et[:, 0] = order[start] // 3
    two = count >= 2
    et[two, 1] = order[start[two] + 1] // 3
    forward = np.bincount(edge_of, weights=(a < b)[order], minlength=ne)
    return (
        edges,
        tri_edges.reshape(m, 3),
        et,
        np.minimum(count, COUNT_CAP).astype(np.int8),
        np.minimum(forward, COUNT_CAP).astype(np.int8),
    )


@jit
def _bucket(v, t, ptr, ptris, plocal, w, h):
    """Sort the half-edges leaving ``v`` towards a higher vertex by (that vertex, h).

    Fills ``w`` (end points) and ``h`` (half-edges ``3 k + j``) and returns their
    number.  The patch lists its triangles ascending, so the candidates come in
    ascending ``h``; the insertion sort by ``w`` is stable.
    """
    nc = 0
    for p in range(ptr[v], ptr[v + 1]):
        k = ptris[p]
        i = plocal[p]
        # the two local edges j != i of triangle k contain v (local edge j joins the two
        # local vertices other than j: i and 3 - i - j), in ascending j
        j1 = 1 if i == 0 else 0
        j2 = 1 if i == 2 else 2
        for j in (j1, j2):
            b = t[k, 3 - i - j]
            if b > v:
                key = b
                hh = 3 * k + j
                q = nc - 1
                while q >= 0 and w[q] > key:
                    w[q + 1] = w[q]
                    h[q + 1] = h[q]
                    q -= 1
                w[q + 1] = key
                h[q + 1] = hh
                nc += 1
    return nc


@jit
def _count_edges(lo, hi_end, t, ptr, ptris, plocal, w, h):
    """Count the distinct pairs ``(v, w)``, ``w > v``, of the buckets ``lo <= v < hi_end``."""
    ne = 0
    for v in range(lo, hi_end):
        nc = _bucket(v, t, ptr, ptris, plocal, w, h)
        for q in range(nc):
            if q == 0 or w[q] != w[q - 1]:
                ne += 1
    return ne


@jit
def _number_edges(
    lo, hi_end, e0, t, ptr, ptris, plocal, w, h, edges, tri_edges, et, counts, forward
):
    """Fill the arrays of :func:`edge_topology` for the buckets ``lo <= v < hi_end``.

    ``e0``: the number of the first edge of bucket ``lo`` (edges of the earlier buckets).
    Writes only the rows of its own edges and the half-edges of its own buckets.
    """
    e = e0 - 1
    for v in range(lo, hi_end):
        nc = _bucket(v, t, ptr, ptris, plocal, w, h)
        for q in range(nc):
            hh = h[q]
            k = hh // 3
            i = hh - 3 * k
            if q == 0 or w[q] != w[q - 1]:
                e += 1
                edges[e, 0] = v
                edges[e, 1] = w[q]
                et[e, 0] = -1
                et[e, 1] = -1
                counts[e] = 0
                forward[e] = 0
            c = counts[e]
            if c < 2:
                et[e, c] = k
            if c < COUNT_CAP:
                counts[e] = c + 1
            if t[k, (i + 1) % 3] < t[k, (i + 2) % 3] and forward[e] < COUNT_CAP:
                forward[e] += 1
            tri_edges[k, i] = e


def refined_edge_topology(t, parent, m_old, old_edges, old_edge_triangles, edge_vertex, n_old, n):
    """:func:`edge_topology` of a mesh refined by NVB, derived from its parent's edges.

    ``t`` (M, 3) are the children of :func:`fastmem.kernels.nvb.bisect` (children of
    a parent contiguous, in the parent's order), ``parent`` their parent triangles
    (of ``m_old``),
    ``old_edges`` / ``old_edge_triangles`` the parent mesh's topology,
    ``edge_vertex[e]`` the new vertex on old edge ``e`` (-1: not bisected),
    ``n_old`` / ``n`` the vertex counts before and after.  Returns the same five
    arrays as :func:`edge_topology` on ``(t, n)``, with the same numbering:

    * an edge between two old vertices is an old edge that was not bisected (children's
      vertices are their parent's and midpoints of its edges); its triangles are the
      children of its old triangles that contain it, in the same order (children keep
      the order of their parents), found among the 1 to 4 children: no search, parallel
      over the old edges;
    * the edges with a new end point (halves of bisected edges, edges inside a split
      parent) are the only ones sorted: a counting sort on ``lo`` and an insertion sort
      by ``hi`` over their half-edges only (about a fifth of all on an adaptive step);
    * in the lexicographic order, an old vertex's bucket lists its surviving old edges
      (``hi < n_old``, in the parent's order) before its edges to new vertices.

    The surviving old edges are filled in parallel (:mod:`.pool`), the rest serially.
    """
    edges, tri_edges, et, counts, forward, cptr, remap = _refined_new_edges(
        t, parent, m_old, old_edges, edge_vertex, n_old, n
    )
    bad = []

    def survivors(e0, e1):
        bad.append(
            _surviving_edges_range(
                e0, e1, t, old_edges, old_edge_triangles, cptr, remap,
                edges, tri_edges, et, counts, forward,
            )
        )  # fmt: skip

    run_ranges(survivors, ranges(old_edges.shape[0], n_threads(), GRAIN))
    if any(bad):
        raise ValueError("an old edge that was not bisected is in no child of its triangles")
    return edges, tri_edges, et, counts, forward


@jit
def _refined_new_edges(t, parent, m_old, old_edges, edge_vertex, n_old, n):
    """Run the serial part of :func:`refined_edge_topology`: the edges with a new end point.

    Returns its five arrays with only those edges filled, the children's pointer
    of each old triangle, and the new index of each surviving old edge (-1: bisected).
    """
    m = t.shape[0]
    e_old = old_edges.shape[0]
    cptr = np.zeros(m_old + 1, dtype=np.int64)  # children of old triangle k: cptr[k]:cptr[k+1]
    for k in range(m):
        cptr[parent[k] + 1] += 1
    for k in range(m_old):
        cptr[k + 1] += cptr[k]
    # surviving old edges per lower end point; new-type half-edges per lower end point
    ptr = np.zeros(n + 1, dtype=np.int64)
    for e in range(e_old):
        if edge_vertex[e] < 0:
            ptr[old_edges[e, 0] + 1] += 1
    hptr = np.zeros(n + 1, dtype=np.int64)
    n_h = 0
    for k in range(m):
        for i in range(3):
            a = t[k, (i + 1) % 3]
            b = t[k, (i + 2) % 3]
            if a >= n_old or b >= n_old:
                hptr[min(a, b) + 1] += 1
                n_h += 1
    for v in range(n):
        hptr[v + 1] += hptr[v]
    fill = hptr[:-1].copy()
    order = np.empty(n_h, dtype=np.int64)
    hi = np.empty(n_h, dtype=np.int64)
    for k in range(m):
        for i in range(3):
            a = t[k, (i + 1) % 3]
            b = t[k, (i + 2) % 3]
            if a >= n_old or b >= n_old:
                lo = min(a, b)
                p = fill[lo]
                order[p] = 3 * k + i
                hi[p] = max(a, b)
                fill[lo] = p + 1
    # stable insertion sort by hi inside each bucket (half-edges already in order of h)
    for v in range(n):
        for p in range(hptr[v] + 1, hptr[v + 1]):
            h = order[p]
            key = hi[p]
            q = p - 1
            while q >= hptr[v] and hi[q] > key:
                order[q + 1] = order[q]
                hi[q + 1] = hi[q]
                q -= 1
            order[q + 1] = h
            hi[q + 1] = key
    for v in range(n):
        for p in range(hptr[v], hptr[v + 1]):
            if p == hptr[v] or hi[p] != hi[p - 1]:
                ptr[v + 1] += 1
    for v in range(n):
        ptr[v + 1] += ptr[v]
    ne = ptr[n]
    edges = np.empty((ne, 2), dtype=np.int32)
    et = np.empty((ne, 2), dtype=np.int32)
    counts = np.empty(ne, dtype=np.int32)
    forward = np.empty(ne, dtype=np.int32)
    tri_edges = np.empty((m, 3), dtype=np.int32)
    remap = np.full(e_old, -1, dtype=np.int64)
    fill = ptr[:-1].copy()
    for e in range(e_old):
        if edge_vertex[e] < 0:
            lo = old_edges[e, 0]
            j = fill[lo]
            fill[lo] = j + 1
            remap[e] = j
    # edges with a new end point: the sorted half-edges, grouped by (lo, hi)
    for v in range(n):
        j = fill[v] - 1
        for p in range(hptr[v], hptr[v + 1]):
            h = order[p]
            k = h // 3
            i = h % 3
            if p == hptr[v] or hi[p] != hi[p - 1]:
                j += 1
                edges[j, 0] = v
                edges[j, 1] = hi[p]
                et[j, 0] = k
                et[j, 1] = -1
                counts[j] = 1
                forward[j] = 0
            else:
                if counts[j] < 2:
                    et[j, 1] = k
                counts[j] += 1
            if t[k, (i + 1) % 3] < t[k, (i + 2) % 3]:
                forward[j] += 1
            tri_edges[k, i] = j
    return edges, tri_edges, et, counts, forward, cptr, remap


@jit
def _surviving_edges_range(
    e0, e1, t, old_edges, old_edge_triangles, cptr, remap, edges, tri_edges, et, counts, forward
):
    """Fill the surviving old edges among e0..e1-1 from the children of their old triangles.

    Returns how many of their old triangles have no child containing them (0 on a valid input).
    """
    bad = 0
    for e in range(e0, e1):
        j = remap[e]
        if j < 0:
            continue
        lo = old_edges[e, 0]
        hi_ = old_edges[e, 1]
        edges[j, 0] = lo
        edges[j, 1] = hi_
        et[j, 0] = -1
        et[j, 1] = -1
        c = 0
        f = 0
        for s in range(2):
            ko = old_edge_triangles[e, s]
            if ko < 0:
                continue
            found = False
            for k in range(cptr[ko], cptr[ko + 1]):
                for i in range(3):
                    a = t[k, (i + 1) % 3]
                    b = t[k, (i + 2) % 3]
                    if (a == lo and b == hi_) or (a == hi_ and b == lo):
                        et[j, c] = k
                        tri_edges[k, i] = j
                        if a < b:
                            f += 1
                        found = True
            if found:
                c += 1
            else:
                bad += 1
        counts[j] = c
        forward[j] = f
    return bad


def vertex_patch_ptr(t, n):
    """CSR pointer (int64, (n + 1,)) of the vertex patches: the prefix sum of the degrees.

    The same values as ``np.cumsum(np.bincount(t.ravel(), minlength=n))`` after a 0.
    The degrees are counted by a kernel into an array first touched by two threads
    (:func:`._par.zeros`): ``np.bincount`` counts into calloc'ed memory, and its
    read-then-write first touch of each page cost 2 s of system time for the 134 MB
    of n = 4096 (memory the host had taken back, faulted in page by page).
    """
    if _small(t.shape[0]):
        ptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(np.bincount(np.ravel(t), minlength=n), out=ptr[1:])
        return ptr
    ptr = zeros(n + 1, np.int64)
    _count_degrees(t, ptr[1:])
    np.cumsum(ptr[1:], out=ptr[1:])
    return ptr


@jit
def _count_degrees(t, deg):
    for k in range(t.shape[0]):
        for i in range(3):
            deg[t[k, i]] += 1


def vertex_patches(t, ptr):
    """Patch arrays in CSR form: the half-edges ``3 k + i`` of each vertex ``t[k, i]``.

    ``ptr`` (N + 1,) is the prefix sum of the vertex degrees.  A counting sort,
    O(N + M): the same order as a stable argsort of ``t.ravel()`` (triangles of a
    patch ascending).  Returns ``patch_triangles`` (int32: ``M < 2**31``, checked by
    :data:`fastmem.mesh.mesh.INDEX_LIMIT`) and ``patch_local`` (int8: 0, 1 or 2).
    A wrapper around the Numba kernel :func:`_fill_patches` (arrays allocated here).
    """
    m = t.shape[0]
    if _small(m):
        order = np.argsort(np.ravel(t), kind="stable")
        return (order // 3).astype(np.int32), (order % 3).astype(np.int8)
    tris = zeros(3 * m, np.int32)  # first touched by two threads (_par.zeros)
    local = zeros(3 * m, np.int8)
    _fill_patches(t, ptr[:-1].copy(), tris, local)
    return tris, local


@jit
def _fill_patches(t, fill, tris, local):
    """Counting-sort the half-edges by vertex; ``fill`` (N,) starts at the bucket starts."""
    for k in range(t.shape[0]):
        for i in range(3):
            v = t[k, i]
            p = fill[v]
            tris[p] = k
            local[p] = i
            fill[v] = p + 1


def lumped_mass(t, areas, n):
    """``B_a = sum over the patch of |K| / 3``, summed in the order of ``t.ravel()``.

    The same additions in the same order as ``np.bincount(t.ravel(),
    np.repeat(areas / 3, 3))``, so the same bits.  A wrapper around the Numba
    kernel :func:`_add_thirds` (the result is allocated here).
    """
    if _small(t.shape[0]):
        return np.bincount(np.ravel(t), np.repeat(areas / 3.0, 3), minlength=n)
    b = np.zeros(n)
    _add_thirds(t, areas, b)
    return b


@numba.njit(cache=True, nogil=True)  # no fastmath: x / 3 must not become x * (1 / 3)
def _add_thirds(t, areas, b):
    for k in range(t.shape[0]):
        w = areas[k] / 3.0
        for i in range(3):
            b[t[k, i]] += w


def rectangle_triangles(nx, ny, diagonal):
    """Triangles (int64, (2 nx ny, 3)) of the structured ``nx`` x ``ny`` rectangle mesh.

    Cells row by row, lower-left corner ``a = j (nx + 1) + i``; cell ``(a, b = a + 1,
    c = a + nx + 2, d = a + nx + 1)`` is split by its "slash" diagonal a-c into
    ``(a, b, c), (a, c, d)`` or by its "backslash" diagonal b-d into ``(a, b, d),
    (b, c, d)``.  ``diagonal``: "right" (all slash), "left" (all backslash) or
    "symmetric" (slash where ``(2 j + 1 - ny) (2 i + 1 - nx) >= 0``).  Written in
    place by a kernel over the cell rows (two threads): the NumPy version allocated
    five (nx ny,) int64 temporaries and an (M, 2, 3) array that ``Mesh`` then copied.
    """
    mode = {"right": 0, "left": 1, "symmetric": 2}[diagonal]
    if _small(2 * nx * ny):
        return _rectangle_triangles_numpy(nx, ny, mode)
    tris = np.empty((2 * nx * ny, 3), dtype=np.int64)
    parallel_for(
        _rectangle_triangles_rows, ny, nx, ny, mode, tris, grain=max(1, GRAIN // max(nx, 1))
    )
    return tris


def _rectangle_triangles_numpy(nx, ny, mode):
    j, i = np.divmod(np.arange(nx * ny, dtype=np.int64), nx)
    a = j * (nx + 1) + i
    if mode == 2:
        slash = (2 * j + 1 - ny) * (2 * i + 1 - nx) >= 0
    else:
        slash = np.full(a.size, mode == 0)
    tris = np.empty((nx * ny, 2, 3), dtype=np.int64)
    tris[:, 0, 0], tris[:, 0, 1] = a, a + 1
    tris[:, 0, 2] = np.where(slash, a + (nx + 2), a + (nx + 1))
    tris[:, 1, 0] = np.where(slash, a, a + 1)
    tris[:, 1, 1], tris[:, 1, 2] = a + (nx + 2), a + (nx + 1)
    return tris.reshape(2 * nx * ny, 3)


@jit
def _rectangle_triangles_rows(lo, hi, nx, ny, mode, tris):
    for j in range(lo, hi):
        yc = (2 * j + 1 - ny) * 1.0
        for i in range(nx):
            a = j * (nx + 1) + i
            c = 2 * (j * nx + i)
            tris[c, 0] = a
            tris[c, 1] = a + 1
            tris[c + 1, 1] = a + (nx + 2)
            tris[c + 1, 2] = a + (nx + 1)
            if mode == 0:
                slash = True
            elif mode == 1:
                slash = False
            else:
                slash = yc * ((2 * i + 1 - nx) * 1.0) >= 0
            if slash:
                tris[c, 2] = a + (nx + 2)
                tris[c + 1, 0] = a
            else:
                tris[c, 2] = a + (nx + 1)
                tris[c + 1, 0] = a + 1


def triangle_checks(vertices, triangles, min_h2, tol2, used=None):
    """Twice the signed areas and squared diameters, with the counts of the cheap checks.

    One pass over the triangles (two threads), the arithmetic of
    :func:`fastmem.kernels.assembly.area2_and_diameter2` (the same bits), counting on
    the way the triangles that repeat a vertex, have ``h2 < min_h2``, have
    ``|area2| <= tol2 * h2`` (degenerate) or ``area2 < 0`` (clockwise): no (M,)
    masks and temporaries (``Mesh`` forms those only to report an error).

    Returns ``area2``, ``h2`` (float64 (M,)) and ``counts`` (int64 (4,): repeated,
    small, degenerate, clockwise).  ``used`` (uint8 (N,), zero on entry), if given, is
    set to 1 at every vertex of a triangle (the unused-vertex check; the threads may
    write the same byte, always the value 1).
    """
    if used is None:
        used = np.zeros(vertices.shape[0], dtype=np.uint8)
    m = triangles.shape[0]
    if _small(m):
        return _triangle_checks_numpy(vertices, triangles, min_h2, tol2, used)
    area2 = np.empty(m)
    h2 = np.empty(m)
    chunks = ranges(m, n_threads(), GRAIN)
    per_chunk = np.zeros((len(chunks), 4), dtype=np.int64)
    index = {lo: c for c, (lo, _) in enumerate(chunks)}
    run_ranges(
        lambda lo, hi: _triangle_checks_range(
            lo, hi, vertices, triangles, min_h2, tol2, area2, h2, per_chunk[index[lo]], used
        ),
        chunks,
    )
    return area2, h2, per_chunk.sum(axis=0)


def _triangle_checks_numpy(vertices, triangles, min_h2, tol2, used):
    i0, i1, i2 = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    used[np.ravel(triangles)] = 1
    x0, y0 = vertices[i0, 0], vertices[i0, 1]
    ax, ay = vertices[i1, 0] - x0, vertices[i1, 1] - y0
    bx, by = vertices[i2, 0] - x0, vertices[i2, 1] - y0
    area2 = ax * by - bx * ay
    cx, cy = bx - ax, by - ay
    h2 = np.maximum(np.maximum(ax * ax + ay * ay, bx * bx + by * by), cx * cx + cy * cy)
    counts = np.array(
        [
            np.count_nonzero((i0 == i1) | (i1 == i2) | (i0 == i2)),
            np.count_nonzero(h2 < min_h2),
            np.count_nonzero(np.abs(area2) <= tol2 * h2),
            np.count_nonzero(area2 < 0),
        ],
        dtype=np.int64,
    )
    return area2, h2, counts


@jit
def _triangle_checks_range(lo, hi, vertices, triangles, min_h2, tol2, area2, h2, counts, used):
    n_rep = 0
    n_small = 0
    n_degenerate = 0
    n_cw = 0
    for k in range(lo, hi):
        i0, i1, i2 = triangles[k, 0], triangles[k, 1], triangles[k, 2]
        if i0 == i1 or i1 == i2 or i0 == i2:
            n_rep += 1
        used[i0] = 1
        used[i1] = 1
        used[i2] = 1
        x0, y0 = vertices[i0, 0], vertices[i0, 1]
        ax, ay = vertices[i1, 0] - x0, vertices[i1, 1] - y0
        bx, by = vertices[i2, 0] - x0, vertices[i2, 1] - y0
        a2 = ax * by - bx * ay
        cx, cy = bx - ax, by - ay
        d2 = max(ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy)
        area2[k] = a2
        h2[k] = d2
        if d2 < min_h2:
            n_small += 1
        if abs(a2) <= tol2 * d2:
            n_degenerate += 1
        if a2 < 0:
            n_cw += 1
    counts[0] = n_rep
    counts[1] = n_small
    counts[2] = n_degenerate
    counts[3] = n_cw
