"""Sparsity pattern of P1 matrices and the COO -> CSR position map.

The pattern of every P1 matrix on a mesh is the vertex graph: row ``a`` holds
``a`` itself and its edge neighbours, columns sorted.  It is built from the
vertex patches in O(N + M), row by row in the kernel threads, and the
position map ``offsets[t, i, j]`` says where the local entry ``(i, j)`` of
triangle ``t`` lands inside row ``triangles[t, i]``.  Both are
computed once per mesh; every later assembly is a gather through them.
"""

import numpy as np

from ._jit import jit
from .pool import GRAIN, n_threads, parallel_for, ranges, run_ranges

__all__ = ["csr_pattern", "position_map"]


def csr_pattern(n, triangles, patch_ptr, patch_triangles, patch_local, index_dtype):
    """CSR pattern (indptr, indices) of the P1 vertex graph with sorted columns.

    Row ``a`` holds ``a`` and every vertex of a triangle of its patch, once each:
    the vertex itself and its edge neighbours.  Two passes over vertex chunks in
    the kernel threads (count, then fill after the prefix sum), each row gathered
    from the vertex patch, sorted and deduplicated in a scratch row of its chunk.

    Parameters
    ----------
    n : int
        Number of vertices.
    triangles : ndarray, shape (M, 3)
    patch_ptr, patch_triangles, patch_local : ndarray
        The vertex patches (:attr:`fastmem.Mesh.patch_ptr` and the others).
    index_dtype : numpy dtype
        int32 or int64, the dtype of ``indptr`` and ``indices``.

    Returns
    -------
    indptr : ndarray, shape (n + 1,)
    indices : ndarray, shape (n + 2 E,)
    """
    chunks = ranges(n, n_threads(), GRAIN)
    width = 2 * int(np.diff(patch_ptr).max()) + 1 if n else 1
    scratch = np.empty((len(chunks), width), dtype=np.int64)
    which = {lo: c for c, (lo, _) in enumerate(chunks)}
    counts = np.empty(n, dtype=np.int64)

    def count(lo, hi):
        _pattern_rows(
            lo, hi, triangles, patch_ptr, patch_triangles, patch_local, scratch[which[lo]],
            counts, counts, counts[:0],
        )  # fmt: skip

    run_ranges(count, chunks)
    indptr = np.zeros(n + 1, dtype=index_dtype)
    np.cumsum(counts, out=indptr[1:])
    indices = np.empty(int(indptr[-1]), dtype=index_dtype)
    starts = indptr[:-1].astype(np.int64)

    def fill(lo, hi):
        _pattern_rows(
            lo, hi, triangles, patch_ptr, patch_triangles, patch_local, scratch[which[lo]],
            counts, starts, indices,
        )  # fmt: skip

    run_ranges(fill, chunks)
    return indptr, indices


@jit
def _pattern_rows(lo, hi, t, ptr, ptris, plocal, row, counts, starts, out):
    """Rows ``lo .. hi-1`` of the vertex graph: their lengths (``out`` empty) or entries.

    ``row``: scratch of at least 2 (largest patch) + 1 entries.  With an empty
    ``out`` the number of distinct columns of each row goes to ``counts``;
    otherwise the sorted columns of row ``a`` go to ``out[starts[a]:]``.
    """
    fill = out.shape[0] > 0
    for a in range(lo, hi):
        m = 0
        row[m] = a
        m += 1
        for p in range(ptr[a], ptr[a + 1]):
            k = ptris[p]
            i = plocal[p]
            for d in (1, 2):
                v = t[k, (i + d) % 3]
                # insertion into the sorted prefix, skipping a column already there
                q = m - 1
                while q >= 0 and row[q] > v:
                    q -= 1
                if q >= 0 and row[q] == v:
                    continue
                for s in range(m, q + 1, -1):
                    row[s] = row[s - 1]
                row[q + 1] = v
                m += 1
        if fill:
            base = starts[a]
            for s in range(m):
                out[base + s] = row[s]
        else:
            counts[a] = m


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
