"""Threaded sparse helpers: CSR products with vectors in the kernel threads, bit for bit scipy's."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..kernels import pool as _par
from ..kernels.masked import (
    gap_counts_range,
    gap_fill_range,
    submatrix_counts_range,
    submatrix_fill_range,
)
from ..kernels.mg import residual_range
from ..kernels.smooth import csr_abs_matvec_range, csr_diagonal_range, csr_matvec_range

__all__ = [
    "THREADED_ROWS",
    "ThreadedCSR",
    "csr_diagonal",
    "masked_gap",
    "read_only",
    "submatrix",
    "threaded",
]


def as_unsigned(index: np.ndarray) -> np.ndarray:
    """Return the same (non-negative) indices as unsigned integers, a view.

    Numba indexes with a signed integer only after a test for negative values
    (Python's wrap-around); with unsigned indices the kernels' inner loops lose
    that test: a CSR product at n = 1024 took 8.0 ms with int32 indices, 5.4 ms
    (scipy's time) with their uint32 view.
    """
    return index.view(np.uint32 if index.dtype == np.int32 else np.uint64)


def plain_float64(arrays, length: int) -> bool:
    """Tell whether every array is a C-contiguous float64 ndarray of shape ``(length,)``.

    The vectors the kernel paths take as they are (others go to the NumPy paths).
    """
    return all(
        isinstance(x, np.ndarray)
        and x.dtype == np.float64
        and x.shape == (length,)
        and x.flags.c_contiguous
        for x in arrays
    )


def read_only(x: np.ndarray) -> np.ndarray:
    """Return ``x`` as a read-only view (``x`` itself when it is read-only already).

    The vector of a threaded CSR product always reaches
    :func:`fastmem.kernels.smooth.csr_matvec_range` read-only: Numba compiles one
    specialisation per writeable flag, and a Result's arrays are read-only, so
    without the view a first run compiled the kernel twice (0.2 s more).
    """
    if not x.flags.writeable:
        return x
    view = x.view()
    view.flags.writeable = False
    return view


def _kernel_arrays(a) -> bool:
    """Index arrays the kernel takes (int32 or int64, contiguous)."""
    return (
        a.indptr.dtype == a.indices.dtype
        and a.indices.dtype in (np.int32, np.int64)
        and a.indptr.flags.c_contiguous
        and a.indices.flags.c_contiguous
        and a.data.flags.c_contiguous
    )


#: Rows from which a CSR product runs in the kernel threads (:class:`ThreadedCSR`).
THREADED_ROWS = 32768


class ThreadedCSR(sp.csr_matrix):
    """A CSR matrix whose products with vectors run in the kernel threads.

    The same arrays as the matrix it views (no copy).  A product ``A @ x`` with
    a float64 vector is computed by :func:`fastmem.kernels.smooth.csr_matvec_range`
    over row chunks, summing each row in scipy's order: the same result bit for
    bit, about 1.9x faster on 2 threads at n = 1024 (5.2 -> 2.75 ms), where scipy's
    kernel keeps one core.  Used for the CG matrices and the large levels of the
    multigrid hierarchies (their residuals), where the solver spends its time.
    """

    def _matmul_vector(self, other):  # scipy >= 1.13
        return self._product(other, "_matmul_vector")

    def _mul_vector(self, other):  # scipy < 1.13
        return self._product(other, "_mul_vector")

    def _product(self, other, name):
        if (
            self.dtype != np.float64
            or getattr(other, "dtype", None) != np.float64
            or other.ndim != 1
            or not _kernel_arrays(self)
        ):
            return getattr(super(), name)(other)

        x = read_only(np.ascontiguousarray(other))
        y = np.empty(self.shape[0])
        indptr, indices, data = (
            as_unsigned(self.indptr),
            as_unsigned(self.indices),
            self.data,
        )
        _par.parallel_for(csr_matvec_range, self.shape[0], indptr, indices, data, x, y)
        return y

    def residual(self, x: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Return ``b - A x`` (float64 vectors) from the kernel threads, in one pass.

        Each row's product summed as :meth:`_product` sums it, then subtracted
        from ``b``: the same bits as ``b - A @ x``, without the product's
        temporary (:func:`fastmem.kernels.mg.residual_range`).
        """
        n = self.shape[0]
        if (
            self.dtype != np.float64
            or not plain_float64((b,), n)
            or not plain_float64((x,), self.shape[1])
            or not _kernel_arrays(self)
        ):
            return b - self @ x
        r = np.empty(n)
        indptr, indices = as_unsigned(self.indptr), as_unsigned(self.indices)
        _par.parallel_for(residual_range, n, indptr, indices, self.data, x, b, r)
        return r

    def diagonal(self, k: int = 0) -> np.ndarray:
        """Return the main diagonal from the kernel threads (:func:`csr_diagonal`, same bits)."""
        if k != 0 or self.shape[0] != self.shape[1] or not _kernel_arrays(self):
            return super().diagonal(k)
        return csr_diagonal(self)

    def abs_product_plus(self, x: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Return ``|A| |x| + |b|`` (float64 vectors) from the kernel threads, without ``|A|``.

        The same bits as ``abs(A) @ abs(x) + abs(b)`` with SciPy and NumPy
        (:func:`fastmem.kernels.smooth.csr_abs_matvec_range`); the scale of the
        attainable residual (:meth:`fastmem.linalg.amg.PCG.attainable`).
        """
        x = np.asarray(x)
        b = np.asarray(b)
        if (
            self.dtype != np.float64
            or x.dtype != np.float64
            or b.dtype != np.float64
            or not _kernel_arrays(self)
        ):
            return abs(self) @ np.abs(x) + np.abs(b)
        x = read_only(np.ascontiguousarray(x))
        b = read_only(np.ascontiguousarray(b))
        y = np.empty(self.shape[0])
        indptr, indices = as_unsigned(self.indptr), as_unsigned(self.indices)
        _par.parallel_for(csr_abs_matvec_range, self.shape[0], indptr, indices, self.data, x, b, y)
        return y


def csr_diagonal(a) -> np.ndarray:
    """Return the main diagonal of the square CSR matrix ``a``, rows in the kernel threads.

    Each entry the sum of the row's stored entries in the diagonal column, as
    scipy's ``diagonal()`` sums them (0 where there is none): the same bits.
    Smaller matrices, and arrays the kernel does not take, go to scipy.
    """
    n = a.shape[0]
    if n < THREADED_ROWS or a.shape[1] != n or a.dtype != np.float64 or not _kernel_arrays(a):
        return sp.csr_matrix.diagonal(a)
    d = np.empty(n)
    _par.parallel_for(
        csr_diagonal_range, n, as_unsigned(a.indptr), as_unsigned(a.indices), a.data, d
    )
    return d


def threaded(a):
    """Return ``a`` as a :class:`ThreadedCSR` view if it is a large float64 CSR matrix."""
    if (
        isinstance(a, ThreadedCSR)
        or not isinstance(a, sp.spmatrix)  # a csr_array's * is elementwise: left alone
        or a.format != "csr"
        or a.shape[0] < THREADED_ROWS
        or a.dtype != np.float64
    ):
        return a
    out = ThreadedCSR((a.data, a.indices, a.indptr), shape=a.shape, copy=False)
    out.has_sorted_indices = a.has_sorted_indices
    return out


def submatrix(a, rows: np.ndarray, cols: np.ndarray) -> sp.csr_matrix:
    """Return ``a[rows][:, cols]`` as a CSR matrix, in the kernel threads when ``a`` is large.

    ``rows``, ``cols``: increasing index arrays (the interior vertices of a mesh, say).
    The matrix scipy's fancy indexing gives, entry for entry: the kept entries of each
    row in their stored order, stored zeros included, the index dtype of ``a``.
    From :data:`THREADED_ROWS` selected rows on, two passes over row chunks
    (:mod:`fastmem.kernels.masked`): count, prefix sum, copy; smaller matrices, and
    arrays the kernels do not take, go to scipy.
    """
    rows = np.asarray(rows)
    cols = np.asarray(cols)
    if (
        rows.size < THREADED_ROWS
        or not isinstance(a, sp.csr_matrix)
        or a.dtype != np.float64
        or not _kernel_arrays(a)
    ):
        return a[rows][:, cols].tocsr()
    return threaded_submatrix(a, rows, cols)


def threaded_submatrix(a, rows, cols):
    """:func:`submatrix`'s kernel path, for any size (:func:`fastmem.warm_up` compiles it)."""
    col_map = np.full(a.shape[1], -1, dtype=np.int64)
    col_map[cols] = np.arange(cols.size)
    rows = read_only(np.ascontiguousarray(rows, dtype=np.int64))
    col_map = read_only(col_map)
    data, indices, new_ptr = _kept_rows(
        a, rows.size, submatrix_counts_range, (rows, col_map),
        submatrix_fill_range, (a.data, rows, col_map), a.indices.dtype,
    )  # fmt: skip
    return sp.csr_matrix((data, indices, new_ptr), shape=(rows.size, cols.size), copy=False)


def _kept_rows(a, n_rows, count, count_args, fill, fill_args, index_dtype):
    """Build the rows of a CSR matrix from ``a`` by a count pass and a fill pass.

    ``count(lo, hi, indptr, indices, *count_args, counts)`` writes the entries each
    new row keeps; after their prefix sum ``fill(lo, hi, indptr, indices,
    *fill_args, new_ptr, out_indices, out_data)`` copies them (row chunks in the
    kernel threads, :mod:`fastmem.kernels.masked`).  Returns ``(data, indices,
    indptr)``: indices of dtype ``index_dtype``, the pointer of ``a``'s dtype.
    """
    indptr, indices = as_unsigned(a.indptr), as_unsigned(a.indices)
    counts = np.empty(n_rows, dtype=indptr.dtype)
    # rows cost unequal time (an active row of a gap matrix keeps its diagonal alone):
    # smaller pieces handed out one at a time
    _par.parallel_for(count, n_rows, indptr, indices, *count_args, counts, pieces=4)
    new_ptr = np.zeros(n_rows + 1, dtype=a.indptr.dtype)
    np.cumsum(counts, out=new_ptr[1:], dtype=new_ptr.dtype)
    out_indices = np.empty(int(new_ptr[-1]), dtype=index_dtype)
    out_data = np.empty(out_indices.size, dtype=np.float64)
    _par.parallel_for(
        fill, n_rows, indptr, indices, *fill_args, as_unsigned(new_ptr), out_indices, out_data,
        pieces=4,
    )  # fmt: skip
    return out_data, out_indices, new_ptr


def masked_gap(a, active: np.ndarray):
    """Return the gap matrix of ``a`` for the active set ``active``, built in the kernel threads.

    The entries of the canonical CSR matrix ``a`` in inactive rows and
    columns, and the diagonal of the active rows; stored zeros dropped; the
    index dtype of ``a`` kept (:func:`fastmem.solver.steps.gap_matrix` has the
    definition and a NumPy version, which this matches bit for bit).  Two
    passes over row chunks (:mod:`fastmem.kernels.masked`): count, prefix sum,
    copy.  None when ``a``'s arrays are not the kernel's (the caller falls back).
    """
    if not _kernel_arrays(a) or a.dtype != np.float64:
        return None
    mask = np.ascontiguousarray(active, dtype=np.bool_)
    data, indices, new_ptr = _kept_rows(
        a, a.shape[0], gap_counts_range, (a.data, mask), gap_fill_range, (a.data, mask),
        as_unsigned(a.indices).dtype,
    )  # fmt: skip
    out = sp.csr_matrix((data, indices.view(a.indices.dtype), new_ptr), shape=a.shape, copy=False)
    out.has_sorted_indices = a.has_sorted_indices
    return out
