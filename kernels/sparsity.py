"""Sparsity pattern of P1 matrices and the COO -> CSR position map.

The pattern of every P1 matrix on a mesh is the vertex graph: row ``a`` holds
``a`` itself and its edge neighbours, columns sorted.  It is built from the
edge list in O(N + E), and the position map ``offsets[t, i, j]`` says where
the local entry ``(i, j)`` of triangle ``t`` lands inside row
``triangles[t, i]``.  Both are computed once per mesh; every later assembly is
a gather through them.

The edge list of a :class:`~fastmem.mesh.Mesh` is sorted (``p < q`` in each
edge, the pairs ``(p, q)`` in lexicographic order).  Then row ``a`` is its
lower part (the ``p`` of the edges ``(p, a)``, met in increasing order in the
edge list), ``a``, and its upper part (the ``q`` of the edges ``(a, q)``, a run
of the edge list): already sorted.  The kernel threads build it in blocks of
rows with no sort and no serial pass (:func:`_sorted_pattern`): the edges are
bucketed by the block of their ``q`` (counts per edge chunk and block, then
each chunk writes its edge ids into its slots, in order), and each block
counts, sums and fills its own rows from its bucket.  An edge list in any
other order goes the serial way (a counting sort by row, then an insertion
sort per row).
"""

import numpy as np

from ._jit import jit
from .pool import n_threads, parallel_for, ranges, run_ranges

__all__ = ["csr_pattern", "position_map", "precompile_blocks"]


@jit
def _count_rows(edges, counts):
    for e in range(edges.shape[0]):
        counts[edges[e, 0]] += 1
        counts[edges[e, 1]] += 1


def _sort_rows(indptr, indices):
    parallel_for(_sort_rows_range, indptr.shape[0] - 1, indptr, indices)


@jit
def _sort_rows_range(lo_row, hi_row, indptr, indices):
    for a in range(lo_row, hi_row):
        lo, hi = indptr[a], indptr[a + 1]
        for k in range(lo + 1, hi):  # insertion sort: rows have ~7 entries
            x = indices[k]
            m = k - 1
            while m >= lo and indices[m] > x:
                indices[m + 1] = indices[m]
                m -= 1
            indices[m + 1] = x


@jit
def _fill_rows(edges, fill, indices):
    for a in range(fill.shape[0]):
        indices[fill[a]] = a
        fill[a] += 1
    for e in range(edges.shape[0]):
        p, q = edges[e, 0], edges[e, 1]
        indices[fill[p]] = q
        fill[p] += 1
        indices[fill[q]] = p
        fill[q] += 1


#: fewest edges (and rows) per thread of the sorted edge list's pattern
PATTERN_GRAIN = 1 << 15


@jit
def _block_of(q, bounds, scale):
    """Return the block b with ``bounds[b] <= q < bounds[b + 1]`` (a product, a step or two)."""
    b = min(int(q * scale), bounds.shape[0] - 2)
    while q < bounds[b]:
        b -= 1
    while q >= bounds[b + 1]:
        b += 1
    return b


@jit
def _edge_chunks_count(lo, hi, edges, n_chunks, n, bounds, counts, ustart, bad):
    """Edge chunks ``lo <= k < hi``: bucket counts, run starts and the order check.

    Chunk k holds the edges ``E k / K <= e < E (k + 1) / K`` (``K = n_chunks``).
    ``counts[k, b]``: its edges whose ``q`` lies in row block b (rows
    ``bounds[b] <= q < bounds[b + 1]``; not counted with one block);
    ``ustart[a]``: the first edge with ``p >= a``, for the rows ``a`` whose
    first such edge is in the chunk (``ustart[n] = E`` is the caller's);
    ``bad[k]``: 1 when an edge of the chunk breaks the order (``p < q < n``,
    strictly increasing pairs, ``0 <= p``), else 0.
    """
    m = edges.shape[0]
    n_blocks = bounds.shape[0] - 1
    scale = n_blocks / n
    own = np.zeros(n_blocks, dtype=np.int64)  # counted here: rows of counts share cache lines
    for k in range(lo, hi):
        e0 = m * k // n_chunks
        e1 = m * (k + 1) // n_chunks
        own[:] = 0
        ok = True
        prev_p = -1 if e0 == 0 else edges[e0 - 1, 0]
        prev_q = -1 if e0 == 0 else edges[e0 - 1, 1]
        for e in range(e0, e1):
            p = edges[e, 0]
            q = edges[e, 1]
            if not (0 <= p and p < q and q < n and (p > prev_p or (p == prev_p and q > prev_q))):
                ok = False
                break
            for a in range(prev_p + 1, p + 1):
                ustart[a] = e
            if n_blocks > 1:
                own[_block_of(q, bounds, scale)] += 1
            prev_p = p
            prev_q = q
        if ok and e1 == m:
            for a in range(prev_p + 1, n):
                ustart[a] = m
        counts[k, :] = own
        bad[k] = 0 if ok else 1


@jit
def _edge_chunks_bucket(lo, hi, edges, n_chunks, n, bounds, slots, bucket):
    """Edge chunks ``lo <= k < hi``: write each edge id into its block's bucket.

    ``slots[k, b]``: where chunk k's first edge of block b goes; the ids of one
    block follow the edge order (chunks in order, each in order).
    """
    m = edges.shape[0]
    scale = (bounds.shape[0] - 1) / n
    for k in range(lo, hi):
        at = slots[k, :].copy()  # advanced here: rows of slots share cache lines
        for e in range(m * k // n_chunks, m * (k + 1) // n_chunks):
            b = _block_of(edges[e, 1], bounds, scale)
            bucket[at[b]] = e
            at[b] += 1


@jit
def _block_rows_count(lo, hi, edges, bounds, bstart, bucket, ustart, fill, totals):
    """Row blocks ``lo <= b < hi``: each row's length (``fill[a]``) and the block's sum.

    A row's length is its lower part (its edges in the bucket of block b; an
    empty ``bucket``: one block, every edge) + 1 (the diagonal) + its upper
    part (``ustart[a + 1] - ustart[a]``).
    """
    direct = bucket.shape[0] == 0
    for b in range(lo, hi):
        r0 = bounds[b]
        r1 = bounds[b + 1]
        for a in range(r0, r1):
            fill[a] = 1 + ustart[a + 1] - ustart[a]
        for j in range(bstart[b], bstart[b + 1]):
            e = j if direct else bucket[j]
            fill[edges[e, 1]] += 1
        t = 0
        for a in range(r0, r1):
            t += fill[a]
        totals[b] = t


@jit
def _block_rows_fill(lo, hi, edges, bounds, bstart, bucket, ustart, offsets, fill, indptr, indices):
    """Row blocks ``lo <= b < hi``: ``indptr`` of their rows, then the sorted rows.

    ``offsets[b]``: the entries of the rows before block b; ``fill[a]`` (row
    lengths, from :func:`_block_rows_count`) becomes the next free slot of row a.
    """
    direct = bucket.shape[0] == 0
    n = fill.shape[0]
    for b in range(lo, hi):
        r0 = bounds[b]
        r1 = bounds[b + 1]
        pos = offsets[b]
        for a in range(r0, r1):
            indptr[a] = pos
            length = fill[a]
            fill[a] = pos
            pos += length
        if r1 == n:
            indptr[n] = pos
        for j in range(bstart[b], bstart[b + 1]):  # lower parts, p increasing in each row
            e = j if direct else bucket[j]
            q = edges[e, 1]
            indices[fill[q]] = edges[e, 0]
            fill[q] += 1
        for a in range(r0, r1):  # the diagonal, then the upper part (q increasing)
            f = fill[a]
            indices[f] = a
            f += 1
            for e in range(ustart[a], ustart[a + 1]):
                indices[f] = edges[e, 1]
                f += 1


def _sorted_pattern(n, edges, index_dtype, threads, grain=None):
    """Build the pattern of a sorted edge list in the kernel threads; None if it is not sorted."""
    grain = PATTERN_GRAIN if grain is None else grain
    m = edges.shape[0]
    n_chunks = len(ranges(m, threads, grain))
    bounds = np.array([lo for lo, _ in ranges(n, threads, grain)] + [n], dtype=np.int64)
    n_blocks = bounds.size - 1
    counts = np.empty((n_chunks, n_blocks), dtype=np.int64)
    ustart = np.empty(n + 1, dtype=index_dtype)  # edge ids: E < nnz, which index_dtype holds
    ustart[n] = m
    bad = np.empty(n_chunks, dtype=np.int64)
    each = [(k, k + 1) for k in range(n_chunks)]
    run_ranges(
        lambda lo, hi: _edge_chunks_count(lo, hi, edges, n_chunks, n, bounds, counts, ustart, bad),
        each,
    )
    if bad.any():
        return None
    if n_blocks == 1:  # one block: its bucket is the edge list itself
        bstart = np.array([0, m], dtype=np.int64)
        bucket = np.empty(0, dtype=index_dtype)
    else:  # the bucket of block b: chunk 0's edges of b, then chunk 1's, ...
        order = counts.T.ravel()  # (block, chunk) order
        slots = np.zeros(order.size, dtype=np.int64)
        np.cumsum(order[:-1], out=slots[1:])
        bstart = np.append(slots.reshape(n_blocks, n_chunks)[:, 0], m)
        slots = np.ascontiguousarray(slots.reshape(n_blocks, n_chunks).T)
        bucket = np.empty(m, dtype=index_dtype)
        run_ranges(
            lambda lo, hi: _edge_chunks_bucket(lo, hi, edges, n_chunks, n, bounds, slots, bucket),
            each,
        )
    fill = np.empty(n, dtype=index_dtype)
    totals = np.empty(n_blocks, dtype=np.int64)
    every = [(b, b + 1) for b in range(n_blocks)]
    run_ranges(
        lambda lo, hi: _block_rows_count(
            lo, hi, edges, bounds, bstart, bucket, ustart, fill, totals
        ),
        every,
    )
    offsets = np.zeros(n_blocks, dtype=np.int64)
    np.cumsum(totals[:-1], out=offsets[1:])
    indptr = np.empty(n + 1, dtype=index_dtype)
    indices = np.empty(int(totals.sum()), dtype=index_dtype)
    run_ranges(
        lambda lo, hi: _block_rows_fill(
            lo, hi, edges, bounds, bstart, bucket, ustart, offsets, fill, indptr, indices
        ),
        every,
    )
    return indptr, indices


def precompile_blocks(n, edges, index_dtype) -> None:
    """Compile (or load) the kernels of the pattern in blocks, for the types of ``edges``.

    Meshes of 2 :data:`PATTERN_GRAIN` vertices and more, with two threads or more,
    split the rows into blocks (the bucket pass runs only then): a tiny mesh's
    edges in blocks of one row take the same path.
    """
    _sorted_pattern(int(n), edges, index_dtype, 2, grain=1)


def csr_pattern(n, edges, index_dtype):
    """CSR pattern (indptr, indices) of the P1 vertex graph with sorted columns.

    Parameters
    ----------
    n : int
        Number of vertices.
    edges : ndarray of int32 or int64, shape (E, 2)
        Edge list (each unordered pair once); sorted as a mesh's, the kernel
        threads build the pattern, else a serial pass.
    index_dtype : numpy dtype
        int32 or int64, the dtype of ``indptr`` and ``indices``.

    Returns
    -------
    indptr : ndarray, shape (n + 1,)
    indices : ndarray, shape (n + 2 E,)
    """
    if edges.dtype in (np.int32, np.int64) and edges.flags.c_contiguous and edges.ndim == 2:
        out = _sorted_pattern(int(n), edges, index_dtype, n_threads())
        if out is not None:
            return out
    counts = np.ones(n, dtype=np.int64)  # the diagonal
    _count_rows(edges, counts)  # (the kernels allocate nothing: less code to compile)
    indptr = np.zeros(n + 1, dtype=index_dtype)
    np.cumsum(counts, out=indptr[1:])
    indices = np.empty(int(indptr[-1]), dtype=index_dtype)
    _fill_rows(edges, indptr[:-1].copy(), indices)
    _sort_rows(indptr, indices)
    return indptr, indices


def position_map(triangles, indptr, indices):
    """Offsets of each local entry inside its CSR row.

    Threading: parallel over triangles; each iteration writes only
    ``offsets[t]``.

    Returns
    -------
    offsets : ndarray of uint16, shape (M, 3, 3)
        ``indptr[triangles[t, i]] + offsets[t, i, j]`` is the CSR position of
        the entry (row ``triangles[t, i]``, column ``triangles[t, j]``).
    """
    m = triangles.shape[0]
    offsets = np.empty((m, 3, 3), dtype=np.uint16)
    parallel_for(_position_map_range, m, triangles, indptr, indices, offsets)
    return offsets


@jit
def _position_map_range(lo_t, hi_t, triangles, indptr, indices, offsets):
    for t in range(lo_t, hi_t):
        for i in range(3):
            row = triangles[t, i]
            lo, hi = indptr[row], indptr[row + 1]
            for j in range(3):
                col = triangles[t, j]
                # binary search in the sorted row
                a, b = lo, hi
                while a < b:
                    mid = (a + b) // 2
                    if indices[mid] < col:
                        a = mid + 1
                    else:
                        b = mid
                offsets[t, i, j] = a - lo
