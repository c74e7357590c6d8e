"""Sparse kernels of the multigrid cycles: a hybrid Gauss-Seidel sweep over row blocks.

Gauss-Seidel is the multigrid smoother of fastmem's CG preconditioners, and its
sweeps are most of a V-cycle's time (on the finest level of an n = 1024 square
a symmetric sweep costs about 3.5 matrix-vector products: each row waits for
the one before).  A lexicographic sweep cannot be split between threads, so
the sweep here is *hybrid*: the rows are cut into a fixed number of contiguous
blocks; within a block it is Gauss-Seidel, across blocks Jacobi (a block reads
the values other blocks had before the sweep, from a copy).  The blocks depend
on the matrix size only, never on the thread count, so the result is the same
with any number of threads.  The forward and the backward hybrid sweeps are
each other's adjoints (``(D + L_B)^T = D + U_B`` for symmetric ``A``, with
``L_B`` the strictly lower part inside the blocks), so a symmetric sweep and
the V-cycle built from it stay symmetric preconditioners, as CG requires.
"""

import numpy as np

from ._jit import jit, jit_divide
from .pool import parallel_for

__all__ = [
    "active_diagonal_range",
    "cg_direction_range",
    "cg_update_range",
    "cross_block_dominant",
    "cross_block_dominant_range",
    "copy_range",
    "copy_vector",
    "csr_diagonal_range",
    "csr_matvec_range",
    "gs_hybrid_range",
    "masked_rhs_range",
    "residual_pair_range",
]


@jit
def gs_hybrid_range(lo, hi, forward, indptr, indices, data, x, x_old, b):
    """One Gauss-Seidel sweep over the rows ``lo .. hi-1``, in place in ``x``.

    Columns inside ``[lo, hi)`` read the current ``x``, the others ``x_old``
    (the values before the sweep).  ``forward`` selects the row order.  A row
    without a stored (or with a zero) diagonal is left as it is.  Row by row
    the arithmetic of pyamg's Gauss-Seidel (off-diagonal sum, then
    ``(b_i - sum) / a_ii``): with one block it is pyamg's sweep bit for bit.
    """
    n = hi - lo
    for r in range(n):
        i = lo + r if forward else hi - 1 - r
        rsum = 0.0
        d = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            if j == i:
                d = data[k]
            elif lo <= j < hi:
                rsum += data[k] * x[j]
            else:
                rsum += data[k] * x_old[j]
        if d != 0.0:
            x[i] = (b[i] - rsum) / d


@jit
def csr_matvec_range(lo, hi, indptr, indices, data, x, y):
    """``y[i] = sum_k data[k] x[indices[k]]`` for the rows ``lo .. hi-1`` of a CSR matrix.

    Summed in the order of the stored entries, as scipy's ``csr_matvec``: the
    same result bit for bit, whichever rows a thread takes.
    """
    for i in range(lo, hi):
        s = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            s += data[k] * x[indices[k]]
        y[i] = s


@jit
def copy_range(lo, hi, src, dst):
    """``dst[i] = src[i]`` for ``i`` in ``lo .. hi-1`` (the hybrid sweep's copy of x)."""
    for i in range(lo, hi):
        dst[i] = src[i]


def copy_vector(src, dst, threaded_from) -> None:
    """``dst[:] = src``, in the threads for contiguous float64 vectors of ``threaded_from`` or more.

    Callers pass ``fastmem.linalg.sparse.THREADED_ROWS``: below it one thread copies.
    """
    plain = all(v.dtype == np.float64 and v.ndim == 1 and v.flags.c_contiguous for v in (src, dst))
    if src.shape[0] < threaded_from or not plain or not dst.flags.writeable:
        dst[...] = src
    else:
        parallel_for(copy_range, src.shape[0], src, dst)


@jit
def csr_diagonal_range(lo, hi, indptr, indices, data, d):
    """``d[i]`` = the sum of row i's stored entries in column i, rows ``lo .. hi-1``.

    In the order of the stored entries from 0.0, as scipy's ``csr_diagonal``
    sums them: the same bits (0.0 where the row stores no diagonal entry).
    """
    for i in range(lo, hi):
        s = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            if indices[k] == i:
                s += data[k]
        d[i] = s


@jit
def csr_abs_matvec_range(lo, hi, indptr, indices, data, x, b, y):
    """``y[i] = sum_k |data[k]| |x[indices[k]]| + |b[i]|`` for the rows ``lo .. hi-1``.

    ``|A| |x| + |b|`` without forming ``|A|``: each row summed in the order of
    the stored entries, as scipy's ``csr_matvec`` sums ``abs(A) @ abs(x)``,
    then ``|b_i|`` added, so the same bits as that expression.
    """
    for i in range(lo, hi):
        s = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            s += abs(data[k]) * abs(x[indices[k]])
        y[i] = s + abs(b[i])


def cross_block_dominant(indptr, indices, data, n_blocks):
    """Whether every row's diagonal exceeds the sum of its entries outside its block.

    The blocks are those of the hybrid sweep (row ``i`` of ``n`` in block
    ``k`` when ``n k / n_blocks <= i < n (k + 1) / n_blocks``).  With ``C`` the
    entries coupling different blocks and ``D`` the diagonal, the hybrid
    Gauss-Seidel smoother ``M = D + L_B`` of an SPD matrix converges in the
    energy norm iff ``M + M^T - A = D - C`` is positive definite, which this
    row-wise dominance implies (Gershgorin).  The blocks are checked in the
    kernel threads (:func:`cross_block_dominant_range`), each up to its first
    failing row.
    """
    ok = np.empty(max(int(n_blocks), 0), dtype=np.bool_)
    parallel_for(cross_block_dominant_range, ok.size, indptr, indices, data, ok, grain=1)
    return bool(ok.all())


@jit
def cross_block_dominant_range(lo_b, hi_b, indptr, indices, data, ok):
    """Write to ``ok[b]`` whether block ``b`` of ``ok.size`` passes, ``b`` in ``lo_b .. hi_b-1``.

    See :func:`cross_block_dominant`.
    """
    n = indptr.shape[0] - 1
    n_blocks = ok.shape[0]
    for b in range(lo_b, hi_b):
        lo = n * b // n_blocks
        hi = n * (b + 1) // n_blocks
        ok[b] = True
        for i in range(lo, hi):
            d = 0.0
            c = 0.0
            for k in range(indptr[i], indptr[i + 1]):
                j = indices[k]
                if j == i:
                    d = data[k]
                elif j < lo or j >= hi:
                    c += abs(data[k])
            if c > 0.0 and not d > c:
                ok[b] = False
                break


@jit
def residual_pair_range(
    lo, hi, indptr, indices, data1, data2, u1, u2, lam, f1, f2, b, boundary, r1, r2
):
    """Compute the residuals of a triple, rows ``lo .. hi-1``, two matrices of one pattern.

    ``r1 = f1 - A1 u1 + b lam`` and ``r2 = f2 - A2 u2 - b lam``, zero where
    ``boundary``; each product summed in the order of the stored entries and the
    terms added left to right, as NumPy evaluates
    :func:`fastmem.fem.residual.residuals`' expressions: the same bits, in one
    pass over the pattern instead of two products and eight vector passes.
    """
    for i in range(lo, hi):
        if boundary[i]:
            r1[i] = 0.0
            r2[i] = 0.0
            continue
        s1 = 0.0
        s2 = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            s1 += data1[k] * u1[j]
            s2 += data2[k] * u2[j]
        bl = b[i] * lam[i]
        r1[i] = (f1[i] - s1) + bl
        r2[i] = (f2[i] - s2) - bl


# The vector updates of a CG iteration (fastmem.linalg.amg.PCG) and of the gap
# system's preconditioner (fastmem.solver.steps.DecoupledCG): NumPy's operations in
# NumPy's order (each product rounded, then the sum; no fused multiply-add, see
# ._jit), so the same bits, in one pass of the kernel threads and without the
# temporaries NumPy allocates (a vector each, 34 MB at n = 2048: fresh memory).


@jit
def cg_update_range(lo, hi, alpha, p, ap, x, r):
    """``x += alpha p`` and ``r -= alpha ap`` for the rows ``lo .. hi-1``."""
    for i in range(lo, hi):
        x[i] += alpha * p[i]
        r[i] -= alpha * ap[i]


@jit
def cg_direction_range(lo, hi, beta, z, p):
    """``p = beta p + z`` (NumPy's ``p *= beta; p += z``) for the rows ``lo .. hi-1``."""
    for i in range(lo, hi):
        p[i] = p[i] * beta + z[i]


@jit
def masked_rhs_range(lo, hi, active, r, out):
    """``out = where(active, 0, r)`` for the rows ``lo .. hi-1``."""
    for i in range(lo, hi):
        out[i] = 0.0 if active[i] else r[i]


@jit_divide
def active_diagonal_range(lo, hi, active, r, diag, z):
    """``z[i] = r[i] / diag[i]`` where ``active[i]``, rows ``lo .. hi-1`` (a true division)."""
    for i in range(lo, hi):
        if active[i]:
            z[i] = r[i] / diag[i]
