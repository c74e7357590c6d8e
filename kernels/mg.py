"""Kernels of the geometric multigrid on nested hierarchies (fastmem.linalg.gmg).

Every kernel works on a range of rows ``lo .. hi-1`` and writes only those
rows, so chunks run in parallel threads (:mod:`.pool`) and the result does
not depend on the number of threads.

- :func:`galerkin_rows`: rows of the coarse operator ``P^T K A K P`` (``K`` the
  diagonal 0/1 matrix ``keep``), computed coarse row by coarse row from the
  transpose ``R = P^T``; a count pass and a fill pass of the same loop;
- :func:`galerkin_values`: the same rows' values on a pattern known to hold
  them (the unmasked product's), for a list of rows: a new active set changes
  only the rows near the vertices that changed.
- :func:`residual_range`: ``r = b - A x``.
- :func:`prolong_add_range`: ``x += K P x_c``.
"""

import numpy as np

from ._jit import jit

__all__ = ["MAX_ROW", "galerkin_rows", "galerkin_values", "prolong_add_range", "residual_range"]

#: Most distinct columns one coarse row may have (a P1 coarse vertex has its
#: neighbours and itself: 7 on structured meshes, rarely above 20 elsewhere).
MAX_ROW = 256


@jit
def _row_product(row, rp, ri, rd, ap, ai, ad, pp, pi, pd, keep, cols, vals):
    """Row ``row`` of ``C = R K A K P`` into ``cols``/``vals`` (unsorted); its length.

    The terms are summed in the order of ``R``'s, ``A``'s and ``P``'s stored
    entries, whichever thread computes the row.  ``-1`` when the row has more
    than :data:`MAX_ROW` distinct columns.
    """
    nc = 0
    for k in range(rp[row], rp[row + 1]):
        i = ri[k]
        if not keep[i]:
            continue
        r = rd[k]
        for m in range(ap[i], ap[i + 1]):
            j = ai[m]
            if not keep[j]:
                continue
            v = r * ad[m]
            for q in range(pp[j], pp[j + 1]):
                col = pi[q]
                pos = -1
                for s in range(nc):
                    if cols[s] == col:
                        pos = s
                        break
                if pos < 0:
                    if nc == MAX_ROW:
                        return -1
                    cols[nc] = col
                    vals[nc] = 0.0
                    pos = nc
                    nc += 1
                vals[pos] += v * pd[q]
    return nc


@jit
def galerkin_rows(
    lo, hi, rp, ri, rd, ap, ai, ad, pp, pi, pd, keep, fill, drop, counts, out_idx, out_data
):
    """Rows ``lo .. hi-1`` of ``C = R K A K P`` with ``R = P^T`` (all CSR arrays).

    ``fill`` False: ``counts[I]`` = entries of row ``I`` (its distinct columns, with
    ``drop`` only those with a nonzero sum, and the diagonal; a
    row with none gets one, a unit diagonal, so that an unknown cut off by the mask
    stays decoupled and the operator invertible); ``-1`` when a row has more than
    :data:`MAX_ROW` columns.  ``fill`` True: writes the row from ``counts[I]``
    (there: the row pointer) on, columns increasing.  Within a row the terms are
    summed in the order of ``R``'s, ``A``'s and ``P``'s stored entries, whichever
    thread computes it.
    """
    cols = np.empty(MAX_ROW, dtype=np.int64)
    vals = np.empty(MAX_ROW, dtype=np.float64)
    for row in range(lo, hi):
        nc = _row_product(row, rp, ri, rd, ap, ai, ad, pp, pi, pd, keep, cols, vals)
        if nc < 0:
            if not fill:
                counts[row] = -1
            continue
        # with ``drop``, exact cancellations (the couplings across the hypotenuses of
        # a structured mesh's coarse Laplacian) are not stored; the diagonal always is
        kept = 0
        for s in range(nc):
            if not drop or vals[s] != 0.0 or cols[s] == row:
                cols[kept] = cols[s]
                vals[kept] = vals[s]
                kept += 1
        nc = kept
        if nc == 0:
            if fill:
                out_idx[counts[row]] = row
                out_data[counts[row]] = 1.0
            else:
                counts[row] = 1
            continue
        if not fill:
            counts[row] = nc
            continue
        # insertion sort of the row by column (a handful of entries)
        for s in range(1, nc):
            c = cols[s]
            v = vals[s]
            t = s - 1
            while t >= 0 and cols[t] > c:
                cols[t + 1] = cols[t]
                vals[t + 1] = vals[t]
                t -= 1
            cols[t + 1] = c
            vals[t + 1] = v
        base = counts[row]
        for s in range(nc):
            out_idx[base + s] = cols[s]
            out_data[base + s] = vals[s]


@jit
def residual_range(lo, hi, indptr, indices, data, x, b, r):
    """``r[i] = b[i] - sum_k data[k] x[indices[k]]`` for the rows ``lo .. hi-1``."""
    for i in range(lo, hi):
        s = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            s += data[k] * x[indices[k]]
        r[i] = b[i] - s


@jit
def prolong_add_range(lo, hi, indptr, indices, data, keep, xc, x):
    """``x[i] += sum_k data[k] xc[indices[k]]`` for the kept rows ``lo .. hi-1``."""
    for i in range(lo, hi):
        if not keep[i]:
            continue
        s = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            s += data[k] * xc[indices[k]]
        x[i] += s


@jit
def galerkin_values(lo, hi, rows, rp, ri, rd, ap, ai, ad, pp, pi, pd, keep, cptr, cidx, cdata):
    """Values of the rows ``rows[lo .. hi-1]`` of ``C = R K A K P`` on a known pattern.

    ``cptr``/``cidx`` hold a pattern that contains every entry of ``C`` (that of
    the unmasked product, cancellations kept); ``cdata`` receives the values
    of the listed rows, the same sums in the same order as
    :func:`galerkin_rows`.  A row that the mask cuts off entirely gets a unit
    diagonal (the pattern always has the diagonal) and zeros elsewhere.  The
    pattern's rows must have at most :data:`MAX_ROW` entries (the caller checks).
    """
    cols = np.empty(MAX_ROW, dtype=np.int64)
    vals = np.empty(MAX_ROW, dtype=np.float64)
    for t in range(lo, hi):
        row = rows[t]
        first = cptr[row]
        last = cptr[row + 1]
        for s in range(first, last):
            cdata[s] = 0.0
        nc = _row_product(row, rp, ri, rd, ap, ai, ad, pp, pi, pd, keep, cols, vals)
        for u in range(nc):
            for s in range(first, last):
                if cidx[s] == cols[u]:
                    cdata[s] = vals[u]
                    break
        if nc == 0:
            for s in range(first, last):
                if cidx[s] == row:
                    cdata[s] = 1.0
