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
- the nested interpolation ``P`` itself (:func:`fastmem.solver.nested.interpolation_matrix`
  on large meshes): the coarse vertices of each fine vertex (:func:`grid_pairs_range`
  for two meshes of one structured grid, :func:`red_pairs_range` for a red
  refinement), then a count-and-check pass and a fill pass of its CSR rows.
"""

import numpy as np

from ._jit import jit

__all__ = [
    "MAX_ROW",
    "galerkin_rows",
    "galerkin_values",
    "grid_cells_range",
    "grid_pairs_range",
    "grid_vertex_table_range",
    "pair_counts_range",
    "pair_fill_range",
    "prolong_add_range",
    "red_pairs_range",
    "residual_range",
]

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


# Nested interpolation (fastmem.solver.nested): each fine vertex is a coarse vertex
# (weight 1) or the midpoint of a coarse edge (weights 1/2, 1/2).  ``first``/``second``
# (int64, per fine vertex) name the coarse vertices, ``second = -1`` for a coarse
# vertex; ``fail[0]`` (int8) is set to 1 by any chunk that finds a vertex off the
# pattern (the only value ever written there, so concurrent writes agree).


@jit
def _grid_index(x, x0, x1, n):
    """Return the grid index of ``x`` on ``n`` cells of ``[x0, x1]`` (NumPy's rounding)."""
    return np.int64(np.rint((x - x0) * (n / (x1 - x0))))


@jit
def grid_vertex_table_range(lo, hi, xy, ncx, ncy, x0, x1, y0, y1, vertex_at, fail):
    """``vertex_at[j (ncx + 1) + i] = k`` for the coarse vertices ``lo <= k < hi`` at (i, j).

    A vertex off the grid's index range sets ``fail[0]``.  Distinct vertices of a
    valid mesh have distinct grid points, so no two indices write one entry.
    """
    for k in range(lo, hi):
        i = _grid_index(xy[k, 0], x0, x1, ncx)
        j = _grid_index(xy[k, 1], y0, y1, ncy)
        if i < 0 or j < 0 or i > ncx or j > ncy:
            fail[0] = 1
        else:
            vertex_at[j * (ncx + 1) + i] = k


@jit
def grid_cells_range(lo, hi, xy, triangles, ncx, ncy, x0, x1, y0, y1, present, slash):
    """Mark the cells of the coarse triangles ``lo <= t < hi``: present, and "slash".

    A "slash" cell's diagonal joins its corners (i, j) and (i + 1, j + 1).  Both
    triangles of a cell write only the value 1 to its entries.
    """
    for t in range(lo, hi):
        i0 = ncx + 1
        j0 = ncy + 1
        ti = np.empty(3, np.int64)
        tj = np.empty(3, np.int64)
        for c in range(3):
            v = triangles[t, c]
            ti[c] = _grid_index(xy[v, 0], x0, x1, ncx)
            tj[c] = _grid_index(xy[v, 1], y0, y1, ncy)
            i0 = min(i0, ti[c])
            j0 = min(j0, tj[c])
        low = False
        high = False
        for c in range(3):
            if ti[c] == i0 and tj[c] == j0:
                low = True
            if ti[c] == i0 + 1 and tj[c] == j0 + 1:
                high = True
        cell = j0 * ncx + i0
        present[cell] = True
        if low and high:
            slash[cell] = True


@jit
def grid_pairs_range(
    lo, hi, xy, nfx, nfy, x0, x1, y0, y1, ncx, ncy, vertex_at, present, slash, first, second, fail
):
    """Find the coarse vertices of the fine vertices ``lo <= k < hi`` (a grid twice as fine).

    Fine grid point (i, j): a coarse vertex when i and j are even; else the midpoint
    of the coarse edge through it: a side of a cell, or the diagonal of the cell it
    is the centre of (end points (i, j), (i + 1, j + 1) on a "slash" cell, (i + 1, j),
    (i, j + 1) otherwise, in coarse indices).  A missing cell or vertex sets ``fail[0]``.
    """
    for k in range(lo, hi):
        i = _grid_index(xy[k, 0], x0, x1, nfx)
        j = _grid_index(xy[k, 1], y0, y1, nfy)
        if i < 0 or j < 0 or i > nfx or j > nfy:
            fail[0] = 1
            first[k] = -1
            second[k] = -1
            continue
        hi_, hj = i // 2, j // 2
        oi, oj = i % 2, j % 2
        back = 0
        if oi == 1 and oj == 1:
            c = min(hj, ncy - 1) * ncx + min(hi_, ncx - 1)
            if not present[c]:
                fail[0] = 1
                first[k] = -1
                second[k] = -1
                continue
            if not slash[c]:
                back = 1
        a_i = hi_ + back
        b_i = hi_ if back == 1 else hi_ + oi
        b_j = hj + oj
        f = vertex_at[min(hj, ncy) * (ncx + 1) + min(a_i, ncx)]
        s = -1
        if oi == 1 or oj == 1:
            s = vertex_at[min(b_j, ncy) * (ncx + 1) + min(b_i, ncx)]
            if s < 0:
                fail[0] = 1
        if f < 0:
            fail[0] = 1
        first[k] = f
        second[k] = s


@jit
def red_pairs_range(lo, hi, n_coarse, edges, first, second):
    """Find the coarse vertices of the fine vertices ``lo <= k < hi`` of a red refinement.

    Its vertices are the coarse ones, then the midpoint of coarse edge ``e`` as
    vertex ``n_coarse + e``.
    """
    for k in range(lo, hi):
        if k < n_coarse:
            first[k] = k
            second[k] = -1
        else:
            first[k] = edges[k - n_coarse, 0]
            second[k] = edges[k - n_coarse, 1]


@jit
def pair_counts_range(lo, hi, first, second, coarse_xy, fine_xy, tol, counts, fail):
    """Count the entries of the interpolation's rows ``lo <= k < hi`` (1 or 2).

    And check that each fine vertex lies (within ``tol``) where its coarse vertices
    put it.
    """
    for k in range(lo, hi):
        f = first[k]
        s = second[k]
        if f < 0:
            fail[0] = 1
            counts[k] = 0
            continue
        if s < 0:
            x = 1.0 * (coarse_xy[f, 0] + 0.0)
            y = 1.0 * (coarse_xy[f, 1] + 0.0)
            counts[k] = 1
        else:
            x = 0.5 * (coarse_xy[f, 0] + coarse_xy[s, 0])
            y = 0.5 * (coarse_xy[f, 1] + coarse_xy[s, 1])
            counts[k] = 2
        if abs(x - fine_xy[k, 0]) > tol or abs(y - fine_xy[k, 1]) > tol:
            fail[0] = 1


@jit
def pair_fill_range(lo, hi, first, second, indptr, indices, data):
    """Fill the CSR rows ``lo <= k < hi``: weight 1, or 1/2 and 1/2 (columns ascending)."""
    for k in range(lo, hi):
        p = indptr[k]
        f = first[k]
        s = second[k]
        if s < 0:
            indices[p] = f
            data[p] = 1.0
        else:
            indices[p] = min(f, s)
            indices[p + 1] = max(f, s)
            data[p] = 0.5
            data[p + 1] = 0.5
