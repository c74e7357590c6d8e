r"""Block ILU(0) of a block-sparse matrix with square blocks, and its solve.

The matrix is in block CSR form: ``indptr`` (n+1,), ``indices`` (nnzb,) sorted
within every block row, ``blocks`` (nnzb, b, b).  The factorisation keeps the
pattern (no fill): for every block row ``i`` in order and every ``k < i`` in it,

.. math::

    A_{ik} \leftarrow A_{ik} A_{kk}^{-1}, \qquad
    A_{ij} \leftarrow A_{ij} - A_{ik} A_{kj} \quad (j > k,\ A_{ij}, A_{kj} \text{ in the pattern}),

then the diagonal block is inverted.  The solve is the block forward
substitution with the unit lower factor and the backward one with the upper
factor.  Serial by nature (each row needs the rows before it); the work is
``O(nnzb b^3)``.

Reservoir simulators precondition their Newton systems this way (3 x 3
blocks here: a cell's three equations against its three unknowns).
"""

import numpy as np

from ._jit import jit

__all__ = ["bilu0_factor", "bilu0_solve"]


@jit
def _gemm_sub(c, a, b):
    """``c -= a @ b`` for square blocks, no temporaries."""
    m = c.shape[0]
    for r in range(m):
        for q in range(m):
            acc = 0.0
            for k in range(m):
                acc += a[r, k] * b[k, q]
            c[r, q] -= acc


@jit
def _gemv_sub(y, a, x):
    """``y -= a @ x`` for a square block, no temporaries."""
    m = y.shape[0]
    for r in range(m):
        acc = 0.0
        for k in range(m):
            acc += a[r, k] * x[k]
        y[r] -= acc


@jit
def bilu0_factor(indptr, indices, blocks):
    """Factor in place; return ``(diag_pos (n,), inv_diag (n, b, b))``.

    Every block row must hold its diagonal block (the caller's pattern has
    it).  A singular diagonal block raises numba's LinAlgError.
    """
    n = indptr.size - 1
    b = blocks.shape[1]
    diag_pos = np.full(n, -1, dtype=np.int64)
    for i in range(n):
        for p in range(indptr[i], indptr[i + 1]):
            if indices[p] == i:
                diag_pos[i] = p
    inv_diag = np.empty((n, b, b))
    marker = np.full(n, -1, dtype=np.int64)
    tmp = np.empty((b, b))
    for i in range(n):
        for p in range(indptr[i], indptr[i + 1]):
            marker[indices[p]] = p
        for p in range(indptr[i], indptr[i + 1]):
            k = indices[p]
            if k >= i:
                break
            tmp[:, :] = 0.0
            _gemm_sub(tmp, blocks[p], inv_diag[k])  # tmp = -A_ik A_kk^-1
            for r in range(b):
                for q in range(b):
                    blocks[p, r, q] = -tmp[r, q]
            for q in range(diag_pos[k] + 1, indptr[k + 1]):
                m = marker[indices[q]]
                if m >= 0:
                    _gemm_sub(blocks[m], blocks[p], blocks[q])
        inv_diag[i] = np.linalg.inv(blocks[diag_pos[i]])
        for p in range(indptr[i], indptr[i + 1]):
            marker[indices[p]] = -1
    return diag_pos, inv_diag


@jit
def bilu0_solve(indptr, indices, blocks, diag_pos, inv_diag, r):
    """Return ``(LU)^{-1} r`` for ``r`` (n * b,) with the factors of :func:`bilu0_factor`."""
    n = indptr.size - 1
    b = blocks.shape[1]
    y = r.reshape(n, b).copy()
    acc = np.empty(b)
    for i in range(n):
        for p in range(indptr[i], diag_pos[i]):
            _gemv_sub(y[i], blocks[p], y[indices[p]])
    for i in range(n - 1, -1, -1):
        acc[:] = y[i]
        for p in range(diag_pos[i] + 1, indptr[i + 1]):
            _gemv_sub(acc, blocks[p], y[indices[p]])
        for q in range(b):
            s = 0.0
            for k in range(b):
                s += inv_diag[i, q, k] * acc[k]
            y[i, q] = s
    return y.reshape(n * b)
