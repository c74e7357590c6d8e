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
def _invert(a, out, w):
    """``out = a^{-1}`` by Gauss-Jordan with partial pivoting (no LAPACK: fast to compile).

    ``w`` is scratch of ``a``'s shape.  Returns False for a singular block (a
    zero pivot).
    """
    m = a.shape[0]
    for r in range(m):
        for q in range(m):
            w[r, q] = a[r, q]
            out[r, q] = 1.0 if r == q else 0.0
    for c in range(m):
        p = c
        for r in range(c + 1, m):
            if abs(w[r, c]) > abs(w[p, c]):
                p = r
        if w[p, c] == 0.0:
            return False
        if p != c:
            for q in range(m):
                w[c, q], w[p, q] = w[p, q], w[c, q]
                out[c, q], out[p, q] = out[p, q], out[c, q]
        piv = 1.0 / w[c, c]
        for q in range(m):
            w[c, q] *= piv
            out[c, q] *= piv
        for r in range(m):
            if r != c and w[r, c] != 0.0:
                f = w[r, c]
                for q in range(m):
                    w[r, q] -= f * w[c, q]
                    out[r, q] -= f * out[c, q]
    return True


@jit
def bilu0_factor(indptr, indices, blocks):
    """Factor in place; return ``(diag_pos (n,), inv_diag (n, b, b), singular)``.

    Every block row must hold its diagonal block (the caller's pattern has
    it).  ``singular`` is the first block row whose pivot block is singular
    (the factorisation stops there), or -1.
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
    work = np.empty((b, b))
    for i in range(n):
        for p in range(indptr[i], indptr[i + 1]):
            marker[indices[p]] = p
        for p in range(indptr[i], indptr[i + 1]):
            k = indices[p]
            if k >= i:
                break
            for r in range(b):
                for q in range(b):
                    tmp[r, q] = 0.0
            _gemm_sub(tmp, blocks[p], inv_diag[k])  # tmp = -A_ik A_kk^-1
            for r in range(b):
                for q in range(b):
                    blocks[p, r, q] = -tmp[r, q]
            for q in range(diag_pos[k] + 1, indptr[k + 1]):
                m = marker[indices[q]]
                if m >= 0:
                    _gemm_sub(blocks[m], blocks[p], blocks[q])
        if diag_pos[i] < 0 or not _invert(blocks[diag_pos[i]], inv_diag[i], work):
            return diag_pos, inv_diag, i
        for p in range(indptr[i], indptr[i + 1]):
            marker[indices[p]] = -1
    return diag_pos, inv_diag, -1


@jit
def bilu0_solve(indptr, indices, blocks, diag_pos, inv_diag, r):
    """Return ``(LU)^{-1} r`` for ``r`` (n * b,) with the factors of :func:`bilu0_factor`."""
    n = indptr.size - 1
    b = blocks.shape[1]
    y = r.copy()
    acc = np.empty(b)
    for i in range(n):
        for p in range(indptr[i], diag_pos[i]):
            j = indices[p]
            for q in range(b):
                s = 0.0
                for k in range(b):
                    s += blocks[p, q, k] * y[j * b + k]
                y[i * b + q] -= s
    for i in range(n - 1, -1, -1):
        for q in range(b):
            acc[q] = y[i * b + q]
        for p in range(diag_pos[i] + 1, indptr[i + 1]):
            j = indices[p]
            for q in range(b):
                s = 0.0
                for k in range(b):
                    s += blocks[p, q, k] * y[j * b + k]
                acc[q] -= s
        for q in range(b):
            s = 0.0
            for k in range(b):
                s += inv_diag[i, q, k] * acc[k]
            y[i * b + q] = s
    return y
