"""Sparsity pattern of P1 matrices and the COO -> CSR position map.

The pattern of every P1 matrix on a mesh is the vertex graph: row ``a`` holds
``a`` itself and its edge neighbours, columns sorted.  It is built from the
edge list in O(N + E) (counting sort by row, then a short insertion sort per
row), and the position map ``offsets[t, i, j]`` says where the local entry
``(i, j)`` of triangle ``t`` lands inside row ``triangles[t, i]``.  Both are
computed once per mesh; every later assembly is a gather through them.
"""

import numpy as np

from ._jit import jit
from .pool import parallel_for

__all__ = ["csr_pattern", "position_map"]


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


def csr_pattern(n, edges, index_dtype):
    """CSR pattern (indptr, indices) of the P1 vertex graph with sorted columns.

    Parameters
    ----------
    n : int
        Number of vertices.
    edges : ndarray of int64, shape (E, 2)
        Edge list (each unordered pair once).
    index_dtype : numpy dtype
        int32 or int64, the dtype of ``indptr`` and ``indices``.

    Returns
    -------
    indptr : ndarray, shape (n + 1,)
    indices : ndarray, shape (n + 2 E,)
    """
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
