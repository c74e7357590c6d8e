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
of the edge list): already sorted.  With :data:`BLOCK_THREADS` kernel threads
or more, they build it in blocks of rows with no sort and no serial pass
(:func:`_sorted_pattern`): the edges are bucketed by the block of their ``q``
(counts per edge chunk and block, then each chunk writes its edge ids into its
slots, in order), and each block counts, sums and fills its own rows from its
bucket.  With fewer threads, or an edge list in another order, one thread
makes it (a counting sort by row, then an insertion sort per row).  Same
pattern either way.

:func:`csr_transpose`: the transpose of a CSR matrix in column blocks, for the
restrictions of the geometric multigrid on many cores.

Meshes of fewer than :data:`fastmem.kernels.topology.NUMPY_BELOW` triangles take
NumPy paths (one sort of the entry keys; a binary search of every local entry)
until the kernel is in the process (:func:`fastmem.kernels.topology.numpy_path`):
the same arrays, and no kernel compiled for them (about 1 s of the first run
after an install, against a few milliseconds of run time at 32,768 triangles).
"""

import numpy as np

from ._jit import jit
from .pool import n_threads, parallel_for, ranges, run_ranges
from .topology import numpy_path

__all__ = ["csr_pattern", "csr_transpose", "position_map", "precompile_blocks"]


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
#: fewest kernel threads for the pattern in row blocks and :func:`csr_transpose` in
#: column blocks.  With fewer, the serial passes take about as long (pattern at
#: n = 2048, 4.2M vertices: 0.08-0.10 s either way on one or two threads), and a
#: first run would compile kernels for nothing (about 1 s for the pattern's).
BLOCK_THREADS = 4


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
        for b in range(n_blocks):  # (loops, not slices: slices cost seconds to compile)
            own[b] = 0
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
        for b in range(n_blocks):
            counts[k, b] = own[b]
        bad[k] = 0 if ok else 1


@jit
def _edge_chunks_bucket(lo, hi, edges, n_chunks, n, bounds, slots, bucket):
    """Edge chunks ``lo <= k < hi``: write each edge id into its block's bucket.

    ``slots[k, b]``: where chunk k's first edge of block b goes; the ids of one
    block follow the edge order (chunks in order, each in order).
    """
    m = edges.shape[0]
    n_blocks = bounds.shape[0] - 1
    scale = n_blocks / n
    at = np.empty(n_blocks, dtype=np.int64)
    for k in range(lo, hi):
        for b in range(n_blocks):  # advanced here: rows of slots share cache lines
            at[b] = slots[k, b]
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
def _starts(r0, r1, pos, fill, indptr):
    """Rows ``r0 <= a < r1`` from position ``pos``: ``indptr[a]``, and ``fill[a]``.

    ``fill[a]`` holds the length of row a and becomes its first slot; the last
    row of the matrix also sets ``indptr[n]``.
    """
    for a in range(r0, r1):
        indptr[a] = pos
        length = fill[a]
        fill[a] = pos
        pos += length
    if r1 == fill.shape[0]:
        indptr[r1] = pos


@jit
def _block_rows_fill(lo, hi, edges, bounds, bstart, bucket, ustart, offsets, fill, indptr, indices):
    """Row blocks ``lo <= b < hi``: ``indptr`` of their rows, then the sorted rows.

    ``offsets[b]``: the entries of the rows before block b; ``fill[a]`` (row
    lengths, from :func:`_block_rows_count`) becomes the next free slot of row a.
    """
    direct = bucket.shape[0] == 0
    for b in range(lo, hi):
        r0 = bounds[b]
        r1 = bounds[b + 1]
        _starts(r0, r1, offsets[b], fill, indptr)
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

    With :data:`BLOCK_THREADS` kernel threads or more (else nothing to compile): a
    tiny mesh's edges in blocks of one row take the path of a large mesh.
    """
    if n_threads() >= BLOCK_THREADS:
        _sorted_pattern(int(n), edges, index_dtype, 2, grain=1)


def csr_pattern(n, edges, index_dtype, n_triangles=None):
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
    n_triangles : int, optional
        Triangles of the mesh: a small mesh takes the NumPy path
        (:func:`_csr_pattern_numpy`) while the pattern kernels it would take (the
        serial ones, or the row blocks' from :data:`BLOCK_THREADS` threads on) are
        not in the process.  Without it the kernels build the pattern.

    Returns
    -------
    indptr : ndarray, shape (n + 1,)
    indices : ndarray, shape (n + 2 E,)
    """
    threads = n_threads()
    if n_triangles is not None:  # (the kernel the other path would take, loaded or not)
        kernel = _count_rows if threads < BLOCK_THREADS else _block_rows_fill
        if numpy_path(n_triangles, kernel):
            return _csr_pattern_numpy(int(n), edges, index_dtype)
    if (
        threads >= BLOCK_THREADS
        and edges.dtype in (np.int32, np.int64)
        and edges.flags.c_contiguous
        and edges.ndim == 2
    ):
        out = _sorted_pattern(int(n), edges, index_dtype, threads)
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
    if numpy_path(m, _position_map_range):
        return _position_map_numpy(triangles, indptr, indices)
    offsets = np.empty((m, 3, 3), dtype=np.uint16)
    parallel_for(_position_map_range, m, triangles, indptr, indices, offsets)
    return offsets


def _csr_pattern_numpy(n, edges, index_dtype):
    """:func:`csr_pattern` by one sort of the keys ``row * n + column`` of every entry."""
    diagonal = np.arange(n, dtype=np.int64)
    p = edges[:, 0].astype(np.int64)
    q = edges[:, 1].astype(np.int64)
    keys = np.concatenate((diagonal * (n + 1), p * n + q, q * n + p))
    keys.sort()
    rows, columns = np.divmod(keys, max(n, 1))
    indptr = np.zeros(n + 1, dtype=index_dtype)
    np.cumsum(np.bincount(rows, minlength=n), out=indptr[1:])
    return indptr, columns.astype(index_dtype)


def _position_map_numpy(triangles, indptr, indices):
    """:func:`position_map` by a binary search of every local entry's key among the rows'."""
    n = indptr.shape[0] - 1
    starts = indptr[:-1].astype(np.int64)
    counts = np.diff(indptr).astype(np.int64)
    keys = np.repeat(np.arange(n, dtype=np.int64) * n, counts) + indices
    t = triangles.astype(np.int64)
    rows = t[:, :, None]
    wanted = rows * n + t[:, None, :]  # (M, 3, 3): row t[i], column t[j]
    return (np.searchsorted(keys, wanted) - starts[rows]).astype(np.uint16)


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


#: row chunks per thread of :func:`csr_transpose` (finer chunks: tighter column spans)
TRANSPOSE_CHUNKS = 4


@jit
def _chunk_column_span(lo, hi, indptr, indices, n_chunks, n_cols, cmin, cmax):
    """Row chunks ``lo <= k < hi``: the smallest and largest column of their entries.

    Chunk k holds the rows ``m k / K <= i < m (k + 1) / K`` (``K = n_chunks``);
    an empty chunk gets ``cmin = n_cols``, ``cmax = -1``.
    """
    m = indptr.shape[0] - 1
    for k in range(lo, hi):
        c0 = n_cols
        c1 = -1
        for j in range(indptr[m * k // n_chunks], indptr[m * (k + 1) // n_chunks]):
            c = indices[j]
            c0 = min(c0, c)
            c1 = max(c1, c)
        cmin[k] = c0
        cmax[k] = c1


@jit
def _transpose_count(lo, hi, indptr, indices, n_chunks, cmin, cmax, bounds, fill, totals):
    """Column blocks ``lo <= b < hi``: the entries of each of their columns, and the block's sum.

    Only the row chunks whose column span meets the block are read (for the
    interpolation between nested meshes, a few per block).
    """
    m = indptr.shape[0] - 1
    for b in range(lo, hi):
        c0 = bounds[b]
        c1 = bounds[b + 1]
        for c in range(c0, c1):
            fill[c] = 0
        for k in range(n_chunks):
            if cmax[k] < c0 or cmin[k] >= c1:
                continue
            for j in range(indptr[m * k // n_chunks], indptr[m * (k + 1) // n_chunks]):
                c = indices[j]
                if c0 <= c and c < c1:
                    fill[c] += 1
        t = 0
        for c in range(c0, c1):
            t += fill[c]
        totals[b] = t


@jit
def _transpose_fill(
    lo, hi, indptr, indices, data, n_chunks, cmin, cmax, bounds, offsets, fill, t_indptr,
    t_indices, t_data,
):  # fmt: skip
    """Column blocks ``lo <= b < hi``: their rows of the transpose, in increasing row order.

    ``offsets[b]``: the entries of the columns before block b; ``fill[c]`` (the
    counts of :func:`_transpose_count`) becomes the next free slot of column c.
    """
    m = indptr.shape[0] - 1
    for b in range(lo, hi):
        c0 = bounds[b]
        c1 = bounds[b + 1]
        _starts(c0, c1, offsets[b], fill, t_indptr)
        for k in range(n_chunks):
            if cmax[k] < c0 or cmin[k] >= c1:
                continue
            for i in range(m * k // n_chunks, m * (k + 1) // n_chunks):
                for j in range(indptr[i], indptr[i + 1]):
                    c = indices[j]
                    if c0 <= c and c < c1:
                        f = fill[c]
                        t_indices[f] = i
                        t_data[f] = data[j]
                        fill[c] = f + 1


def _unsigned_type(dtype):
    return np.uint32 if np.dtype(dtype) == np.int32 else np.uint64


def _unsigned(index):
    """Return the same non-negative indices as unsigned integers (a view; unsigned stays)."""
    if index.dtype.kind == "u":
        return index
    return index.view(_unsigned_type(index.dtype))


def csr_transpose(indptr, indices, data, n_cols, index_dtype, threads=None, grain=None):
    """Return the CSR arrays ``(indptr, indices, data)`` of the transpose of a CSR matrix.

    The matrix is ``m x n_cols``, any column order within a row; its transpose
    is ``n_cols x m`` with sorted rows, the entries of scipy's ``csr_tocsc``
    (the same values in the same order), index arrays of ``index_dtype``.  In
    the kernel threads, by blocks of columns: each block reads the row chunks
    whose columns reach it (:data:`TRANSPOSE_CHUNKS` per thread), counts,
    sums and fills its rows in increasing row order.  No buffer beyond the
    output and one cursor per column.  For a matrix whose rows' columns follow
    the rows (the interpolation between nested meshes) each block reads about
    its share of the entries; for one without that locality every block reads
    them all (correct, not faster).  ``threads``: default
    :func:`fastmem.kernels.pool.n_threads`; ``grain``: fewest columns per block
    and rows per chunk (default :data:`PATTERN_GRAIN`).  Callers use it from
    :data:`BLOCK_THREADS` threads on (scipy's serial transpose is as fast below).
    """
    threads = n_threads() if threads is None else max(1, int(threads))
    grain = PATTERN_GRAIN if grain is None else grain
    # unsigned views: Numba then indexes without the test for negative indices
    indptr, indices = _unsigned(indptr), _unsigned(indices)
    m = indptr.shape[0] - 1
    n = int(n_cols)
    nnz = int(indptr[m])
    blocks = ranges(n, threads, grain)
    n_blocks = len(blocks)
    n_chunks = 1 if n_blocks == 1 else len(ranges(m, TRANSPOSE_CHUNKS * threads, grain))
    bounds = np.array([lo for lo, _ in blocks] + [n], dtype=np.int64)
    cmin = np.empty(n_chunks, dtype=np.int64)
    cmax = np.empty(n_chunks, dtype=np.int64)
    if n_blocks == 1:  # one block reads everything: no spans needed
        cmin[:] = 0
        cmax[:] = n
    else:
        run_ranges(
            lambda lo, hi: _chunk_column_span(lo, hi, indptr, indices, n_chunks, n, cmin, cmax),
            ranges(n_chunks, threads, 1),
        )
    fill = np.empty(n, dtype=index_dtype).view(_unsigned_type(index_dtype))
    totals = np.empty(n_blocks, dtype=np.int64)
    every = [(b, b + 1) for b in range(n_blocks)]
    run_ranges(
        lambda lo, hi: _transpose_count(
            lo, hi, indptr, indices, n_chunks, cmin, cmax, bounds, fill, totals
        ),
        every,
    )
    offsets = np.zeros(n_blocks, dtype=np.int64)
    np.cumsum(totals[:-1], out=offsets[1:])
    t_indptr = np.empty(n + 1, dtype=index_dtype)
    t_indices = np.empty(nnz, dtype=index_dtype)
    t_data = np.empty(nnz, dtype=data.dtype)
    run_ranges(
        lambda lo, hi: _transpose_fill(
            lo,
            hi,
            indptr,
            indices,
            data,
            n_chunks,
            cmin,
            cmax,
            bounds,
            offsets,
            fill,
            t_indptr,
            t_indices,
            t_data,
        ),  # fmt: skip
        every,
    )
    return t_indptr, t_indices, t_data
