"""Newest-vertex bisection (NVB) with conforming closure: the three O(M) passes.

Every triangle carries a refinement edge, given as the local index ``ref[k]``
(local edge ``i`` is opposite local vertex ``i``; see :mod:`fastmem.mesh.mesh`).
Writing ``r = ref[k]``, the triangle is read as ``(v0, v1, v2) = (t[k, r],
t[k, r+1], t[k, r+2])`` (indices mod 3), still counter-clockwise: ``v0`` is
its newest vertex and ``(v1, v2)`` its refinement edge.  Bisection at the
midpoint ``m`` of the refinement edge gives the children ``(m, v0, v1)`` and
``(m, v2, v0)``, each again with its newest vertex first, so their refinement
edges are the old edges ``(v0, v1)`` and ``(v2, v0)`` (the edges opposite the
new vertex) and every output triangle has its refinement edge at local edge 0.
"""

import numpy as np

from . import pool as _par
from ._jit import jit

__all__ = ["bisect", "closure", "longest_edge"]


def longest_edge(vertices, triangles, triangle_edges):
    """Local index of the longest edge of each triangle (ties: the lowest global edge).

    Squared lengths are compared exactly; among equally long edges the one
    with the lowest global edge index wins, so the choice does not depend on
    the order of the vertices inside a triangle.  Parallel over triangles
    (:mod:`.pool`), each writes its own entry.

    Returns
    -------
    int8 (M,)
    """
    ref = np.empty(triangles.shape[0], dtype=np.int8)
    _par.parallel_for(_longest_edge_range, ref.shape[0], vertices, triangles, triangle_edges, ref)
    return ref


@jit
def _longest_edge_range(k0, k1, vertices, triangles, triangle_edges, ref):
    """Rows k0..k1-1 of :func:`longest_edge` (written into ``ref``)."""
    for k in range(k0, k1):
        best = -1.0
        best_i = 0
        best_e = -1
        for i in range(3):
            a = triangles[k, (i + 1) % 3]
            b = triangles[k, (i + 2) % 3]
            dx = vertices[b, 0] - vertices[a, 0]
            dy = vertices[b, 1] - vertices[a, 1]
            length2 = dx * dx + dy * dy
            e = triangle_edges[k, i]
            if length2 > best or (length2 == best and e < best_e):
                best = length2
                best_i = i
                best_e = e
        ref[k] = best_i


@jit
def closure(triangle_edges, edge_triangles, ref, marked):
    """Edges to bisect: refinement edges of marked triangles, closed under the NVB rule.

    Rule: a triangle with any bisected edge has its refinement edge bisected.
    A work queue of newly marked edges visits every edge at most once, so the
    fixed point costs O(M + E) however far the closure propagates.  Serial.

    Parameters
    ----------
    triangle_edges : int64 (M, 3)
    edge_triangles : int64 (E, 2), -1 for a missing neighbour
    ref : int8 (M,)
        Local refinement edge of each triangle.
    marked : bool (M,)

    Returns
    -------
    bool (E,)
    """
    n_edges = edge_triangles.shape[0]
    bisected = np.zeros(n_edges, dtype=np.bool_)
    queue = np.empty(n_edges, dtype=np.int64)
    tail = 0
    for k in range(marked.size):
        if marked[k]:
            e = triangle_edges[k, ref[k]]
            if not bisected[e]:
                bisected[e] = True
                queue[tail] = e
                tail += 1
    head = 0
    while head < tail:
        e = queue[head]
        head += 1
        for s in range(2):
            k = edge_triangles[e, s]
            if k < 0:
                continue
            r = triangle_edges[k, ref[k]]
            if not bisected[r]:
                bisected[r] = True
                queue[tail] = r
                tail += 1
    return bisected


@jit
def _put(children, parent, p, a, b, c, k):
    children[p, 0] = a
    children[p, 1] = b
    children[p, 2] = c
    parent[p] = k


def bisect(triangles, triangle_edges, ref, edge_vertex):
    """Split every triangle by the NVB pattern of its bisected edges.

    ``edge_vertex[e]`` is the new vertex at the midpoint of edge ``e``, or -1
    when ``e`` is not bisected; the closure (:func:`closure`) guarantees that a
    triangle with a bisected edge has its refinement edge bisected.  Patterns
    (``m`` on the refinement edge, ``m1`` on ``(v2, v0)``, ``m2`` on ``(v0, v1)``):

    * nothing bisected: ``(v0, v1, v2)`` (1 child, rotated to ``ref = 0``);
    * ``m`` only: ``(m, v0, v1), (m, v2, v0)`` (2 children);
    * with ``m2``: ``(m, v0, v1)`` becomes ``(m2, m, v0), (m2, v1, m)``;
    * with ``m1``: ``(m, v2, v0)`` becomes ``(m1, m, v2), (m1, v0, m)``
      (3 children with one of them, 4 with both).

    Children of triangle ``k`` are contiguous, in the order of ``k``.  Two
    parallel passes over triangles (:mod:`.pool`: count, then fill the slots
    of a prefix sum; each triangle writes only its own rows).

    Returns
    -------
    children : int64 (M_new, 3)
        Counter-clockwise, newest vertex first (refinement edge = local edge 0).
    parent : int64 (M_new,)
        The input triangle of each child.
    """
    m = triangles.shape[0]
    ptr = np.zeros(m + 1, dtype=np.int64)
    _par.parallel_for(_count_children_range, m, triangle_edges, ref, edge_vertex, ptr)
    np.cumsum(ptr, out=ptr)
    children = np.empty((ptr[m], 3), dtype=np.int64)
    parent = np.empty(ptr[m], dtype=np.int64)
    _par.parallel_for(
        _children_range, m, triangles, triangle_edges, ref, edge_vertex, ptr, children, parent
    )
    return children, parent


@jit
def _count_children_range(k0, k1, triangle_edges, ref, edge_vertex, ptr):
    """``ptr[k + 1]`` = the number of children of triangle k, for k0 <= k < k1."""
    for k in range(k0, k1):
        r = ref[k]
        if edge_vertex[triangle_edges[k, r]] < 0:
            ptr[k + 1] = 1
        else:
            ptr[k + 1] = 2
            if edge_vertex[triangle_edges[k, (r + 1) % 3]] >= 0:
                ptr[k + 1] += 1
            if edge_vertex[triangle_edges[k, (r + 2) % 3]] >= 0:
                ptr[k + 1] += 1


@jit
def _children_range(k0, k1, triangles, triangle_edges, ref, edge_vertex, ptr, children, parent):
    """Write the children of the triangles k0..k1-1 into their slots ``ptr[k]:ptr[k + 1]``."""
    for k in range(k0, k1):
        r = ref[k]
        v0 = triangles[k, r]
        v1 = triangles[k, (r + 1) % 3]
        v2 = triangles[k, (r + 2) % 3]
        mid = edge_vertex[triangle_edges[k, r]]
        p = ptr[k]
        if mid < 0:
            _put(children, parent, p, v0, v1, v2, k)
            continue
        m1 = edge_vertex[triangle_edges[k, (r + 1) % 3]]
        m2 = edge_vertex[triangle_edges[k, (r + 2) % 3]]
        if m2 < 0:
            _put(children, parent, p, mid, v0, v1, k)
            p += 1
        else:
            _put(children, parent, p, m2, mid, v0, k)
            _put(children, parent, p + 1, m2, v1, mid, k)
            p += 2
        if m1 < 0:
            _put(children, parent, p, mid, v2, v0, k)
        else:
            _put(children, parent, p, m1, mid, v2, k)
            _put(children, parent, p + 1, m1, v0, mid, k)
