"""Active-set masked CSR matrices, row chunks in the kernel threads.

The gap system of a Newton-min step keeps the entries of a CSR matrix ``A`` in
inactive rows and columns and only the diagonal in active rows (the gap is
fixed to zero there).  Two passes over the rows: count the entries each row
keeps, then, after a prefix sum, copy them in place.  Each chunk of rows reads
and writes only its own rows, so the result does not depend on the threads.
"""

from ._jit import jit

__all__ = ["gap_counts_range", "gap_fill_range"]


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
