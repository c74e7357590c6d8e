"""Nested-dissection fill-reducing ordering of a symmetric sparsity graph.

One iterative pass over a stack of parts (no recursion).  A part of more than
``leaf`` vertices is split in two halves and a vertex separator between them:

* with coordinates, at the median along the axis of largest extent (each
  part keeps its vertices sorted along every axis, by stable partitioning,
  so the median is read off, never searched);
* without, at the median level of a breadth-first search from a
  pseudo-peripheral vertex of the part (George's automatic nested dissection).

The separator is the smaller of the two one-sided boundaries of the cut (the
vertices of one half that have a neighbour in the other), so it is a vertex
separator of the graph whatever the geometry.  A part that is not connected
is first split into its connected components (no separator), ordered one
after another.  The final order lists each
part's first half, then its second half, then its separator (post-order), so
the separators of the coarsest cuts are eliminated last.  Parts of at most
``leaf`` vertices keep the order they have.  Every level costs O(N + E); with
coordinates the depth is O(log N) (median cuts).
"""

import numpy as np

from ._jit import jit

__all__ = ["nested_dissection"]


@jit
def _bfs(indptr, indices, label, pid, root, dist, queue):
    """Breadth-first levels from ``root`` inside part ``pid``; returns the count reached.

    ``dist`` must be -1 on the part's vertices; reached vertices get their level
    and are listed in ``queue[:count]`` in order of level.
    """
    dist[root] = 0
    queue[0] = root
    head, tail = 0, 1
    while head < tail:
        v = queue[head]
        head += 1
        for q in range(indptr[v], indptr[v + 1]):
            u = indices[q]
            if label[u] >> 2 == pid and dist[u] < 0:
                dist[u] = dist[v] + 1
                queue[tail] = u
                tail += 1
    return tail


@jit
def _partition(lists, start, size, n0, label, cs, work, pos, js, place):
    """Stable partition of every list's segment: first half, second half; drop the separator.

    Separator vertices (cut flag set on side ``cs``) get positions ``js, js + 1, ...``
    in the order of list 0 when ``place``.
    """
    for k in range(lists.shape[0]):
        i0, i1 = 0, n0
        for t in range(size):
            v = lists[k, start + t]
            lab = label[v]
            sv = lab & 1
            if lab & 2 and sv == cs:
                if k == 0 and place:
                    pos[v] = js
                    js += 1
                continue
            if sv == 0:
                work[i0] = v
                i0 += 1
            else:
                work[i1] = v
                i1 += 1
        for t in range(i1):
            lists[k, start + t] = work[t]


@jit
def nested_dissection(indptr, indices, lists, coords, leaf):
    """Nested-dissection permutation of the graph ``(indptr, indices)``.

    Parameters
    ----------
    indptr, indices : int arrays
        Symmetric adjacency (CSR); self loops are ignored.
    lists : int64 array (d, n)
        ``lists[k]`` is a permutation of the vertices sorted along coordinate
        ``k`` (with coordinates), or one row holding any permutation (without:
        it fixes the start vertices of the searches and the order inside leaves).
        Overwritten.
    coords : float64 array (n, d) or (0, 0)
        Vertex coordinates; an empty array selects the breadth-first separators.
    leaf : int
        Parts of at most this many vertices are not split.

    Returns
    -------
    perm : int64 array (n,)
        ``perm[i]`` is the vertex eliminated in position ``i``.
    """
    n = indptr.size - 1
    d = lists.shape[0]
    geometric = coords.shape[0] == n and n > 0
    pos = np.empty(n, dtype=np.int64)
    # label = 4 * part + 2 * (on the cut) + side: one load per neighbour test
    label = np.zeros(n, dtype=np.int64)
    dist = np.full(n, -1, dtype=np.int64)
    comp = np.empty(n, dtype=np.int64)
    queue = np.empty(n, dtype=np.int64)
    work = np.empty(n, dtype=np.int64)
    # stack of parts: segment [start, start + size) of every list, final positions from base
    st_start = np.empty(n + 2, dtype=np.int64)
    st_size = np.empty(n + 2, dtype=np.int64)
    st_base = np.empty(n + 2, dtype=np.int64)
    st_start[0], st_size[0], st_base[0] = 0, n, 0
    top = 1
    pid = 0
    while top > 0:
        top -= 1
        start, size, base = st_start[top], st_size[top], st_base[top]
        if size <= leaf:
            for k in range(size):
                pos[lists[0, start + k]] = base + k
            continue
        pid += 1
        tag = 4 * pid
        for k in range(size):
            v = lists[0, start + k]
            label[v] = tag
            dist[v] = -1
        root = lists[0, start]
        reached = _bfs(indptr, indices, label, pid, root, dist, queue)
        if reached < size:
            # disconnected part: its components become parts, one after another, no
            # separator (interleaved components would share no supernode)
            for k in range(size):
                v = lists[0, start + k]
                comp[v] = 0 if dist[v] >= 0 else -1
            ncomp = 1
            for k in range(size):
                v = lists[0, start + k]
                if comp[v] < 0:
                    count = _bfs(indptr, indices, label, pid, v, dist, queue)
                    for t in range(count):
                        comp[queue[t]] = ncomp
                    ncomp += 1
            offset = np.zeros(ncomp + 1, dtype=np.int64)
            for k in range(size):
                offset[comp[lists[0, start + k]] + 1] += 1
            for c in range(ncomp):
                offset[c + 1] += offset[c]
            for k in range(d):
                fill = offset[:-1].copy()
                for t in range(size):
                    v = lists[k, start + t]
                    work[fill[comp[v]]] = v
                    fill[comp[v]] += 1
                for t in range(size):
                    lists[k, start + t] = work[t]
            for c in range(ncomp):
                st_start[top] = start + offset[c]
                st_size[top] = offset[c + 1] - offset[c]
                st_base[top] = base + offset[c]
                top += 1
            continue
        if geometric:
            ax = 0
            best = -1.0
            for k in range(d):
                ext = coords[lists[k, start + size - 1], k] - coords[lists[k, start], k]
                if ext > best:
                    best = ext
                    ax = k
            half = size // 2
            for k in range(size):
                label[lists[ax, start + k]] = tag if k < half else tag + 1
        else:
            # pseudo-peripheral root: search again from a vertex of least degree in the
            # last level while the eccentricity grows (at most 3 more searches)
            ecc = -1
            for sweep in range(4):
                if sweep > 0:
                    for t in range(reached):
                        dist[queue[t]] = -1
                    reached = _bfs(indptr, indices, label, pid, root, dist, queue)
                last = queue[reached - 1]
                if dist[last] <= ecc:
                    break
                ecc = dist[last]
                best_deg = n + 1
                for t in range(reached - 1, -1, -1):
                    v = queue[t]
                    if dist[v] != ecc:
                        break
                    deg = indptr[v + 1] - indptr[v]
                    if deg < best_deg:
                        best_deg = deg
                        root = v
            # median level (kept below the last level so that the second half is not empty)
            med = dist[queue[size // 2]]
            if med == dist[queue[size - 1]] and med > 0:
                med -= 1
            half = 0
            for k in range(size):
                v = lists[0, start + k]
                if dist[v] > med:
                    label[v] = tag + 1
                else:
                    half += 1
        # the two one-sided boundaries of the cut; keep the smaller one
        c0 = 0
        c1 = 0
        for k in range(size):
            v = lists[0, start + k]
            lab = label[v]
            other = (lab & 1) ^ 1
            for q in range(indptr[v], indptr[v + 1]):
                lu = label[indices[q]]
                if lu >> 2 == pid and lu & 1 == other:
                    label[v] = lab | 2
                    if other:
                        c0 += 1
                    else:
                        c1 += 1
                    break
        # breadth-first: the median level's vertices next to the following level
        cs = 0 if (c0 <= c1 or not geometric) else 1
        n0 = half - (c0 if cs == 0 else 0)
        n1 = size - half - (c1 if cs == 1 else 0)
        if n0 == size or n1 == size:
            # no progress possible (e.g. a star): keep the part as it is
            for k in range(size):
                pos[lists[0, start + k]] = base + k
            continue
        # separator last, in the order of list 0
        _partition(lists, start, size, n0, label, cs, work, pos, base + n0 + n1, True)
        if n0 > 0:
            st_start[top], st_size[top], st_base[top] = start, n0, base
            top += 1
        if n1 > 0:
            st_start[top], st_size[top], st_base[top] = start + n0, n1, base + n0
            top += 1
    perm = np.empty(n, dtype=np.int64)
    for i in range(n):
        perm[pos[i]] = i
    return perm
