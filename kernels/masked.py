"""Active-set masked CSR matrices, row chunks in the kernel threads.

The gap system of a Newton-min step keeps the entries of a CSR matrix ``A`` in
inactive rows and columns and only the diagonal in active rows (the gap is
fixed to zero there).  Two passes over the rows: count the entries each row
keeps, then, after a prefix sum, copy them in place.  Each chunk of rows reads
and writes only its own rows, so the result does not depend on the threads.
The submatrix kernels take rows and columns of a CSR matrix the same way (the
interior block of a stiffness matrix, the interior rows and columns of an
interpolation).
"""

from ._jit import jit

__all__ = [
    "gap_counts_range",
    "gap_fill_range",
    "submatrix_counts_range",
    "submatrix_fill_range",
]


@jit
def gap_counts_range(lo, hi, indptr, indices, data, active, counts):
    """``counts[i]``: entries row ``i`` of the gap matrix keeps, for ``lo <= i < hi``.

    An inactive row keeps its nonzero entries in inactive columns; an active
    row keeps its diagonal if it is nonzero.
    """
    for i in range(lo, hi):
        c = 0
        if active[i]:
            for k in range(indptr[i], indptr[i + 1]):
                if indices[k] == i and data[k] != 0.0:
                    c += 1
        else:
            for k in range(indptr[i], indptr[i + 1]):
                if data[k] != 0.0 and not active[indices[k]]:
                    c += 1
        counts[i] = c


@jit
def gap_fill_range(lo, hi, indptr, indices, data, active, new_ptr, out_indices, out_data):
    """Copy the kept entries of rows ``lo <= i < hi`` to ``new_ptr[i]`` onwards, in order."""
    for i in range(lo, hi):
        p = new_ptr[i]
        if active[i]:
            for k in range(indptr[i], indptr[i + 1]):
                if indices[k] == i and data[k] != 0.0:
                    out_indices[p] = indices[k]
                    out_data[p] = data[k]
                    p += 1
        else:
            for k in range(indptr[i], indptr[i + 1]):
                if data[k] != 0.0 and not active[indices[k]]:
                    out_indices[p] = indices[k]
                    out_data[p] = data[k]
                    p += 1


@jit
def submatrix_counts_range(lo, hi, indptr, indices, rows, col_map, counts):
    """``counts[r]``: entries of row ``rows[r]`` in kept columns, for ``lo <= r < hi``.

    ``col_map[j]``: the new index of column ``j``, or -1 for a dropped column.
    Stored zeros count as entries (as in scipy's fancy indexing).
    """
    for r in range(lo, hi):
        i = rows[r]
        c = 0
        for k in range(indptr[i], indptr[i + 1]):
            if col_map[indices[k]] >= 0:
                c += 1
        counts[r] = c


@jit
def submatrix_fill_range(
    lo, hi, indptr, indices, data, rows, col_map, new_ptr, out_indices, out_data
):
    """Copy the kept entries of rows ``rows[r]``, ``lo <= r < hi``, renumbered, in order."""
    for r in range(lo, hi):
        i = rows[r]
        p = new_ptr[r]
        for k in range(indptr[i], indptr[i + 1]):
            j = col_map[indices[k]]
            if j >= 0:
                out_indices[p] = j
                out_data[p] = data[k]
                p += 1
