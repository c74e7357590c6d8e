r"""Sparse direct factorisation whose cost does not depend on the vertex numbering.

::

    from fastmem.linalg.direct import factorize
    lu = factorize(a_ii, coordinates=mesh.vertices[mesh.interior_vertices])
    x = lu.solve(b)            # a_ii @ x == b
    lu.fill, lu.seconds, lu.ordering

:func:`factorize` renumbers the unknowns once by **nested dissection**
(:func:`fastmem.kernels.ordering.nested_dissection`, a Numba kernel), then
factors the renumbered matrix with SuperLU (scipy) in that order
(``permc_spec="NATURAL"``, diagonal pivots); the renumbering is applied to
the right-hand side and undone on the solution inside ``solve``.
Explicitly stored zeros are dropped before ordering (structured meshes with
right angles have them: the 45-degree couplings of the P1 Laplacian are 0).

Nested dissection cuts every part of more than :data:`LEAF` unknowns in two
halves and eliminates the vertex separator between them last:

* with ``coordinates`` (one row per unknown: for the reduced system of the
  general step, the vertex of every ``u1`` unknown followed by the vertex of
  every ``u2`` unknown), at the median along the axis of largest extent;
* without, at the median level of a breadth-first search from a
  pseudo-peripheral vertex (George's automatic nested dissection, graph
  only).  Slower to compute and up to 1.2x more fill on unstructured meshes
  (fill 47M vs 41M, 6.2 s vs 4.3 s at 400k unknowns below), but it needs
  nothing but the matrix.

Both depend on the mesh, not on how its vertices are numbered (only ties
between equal coordinates are broken by the numbering).  Before the
dissection the graph is renumbered for memory locality (a Morton curve of
the coordinates, or reverse Cuthill-McKee without them), which halves the
ordering time on badly numbered meshes.

Why (``bench/direct_ordering.py``; 2-core machine, scipy 1.17 SuperLU,
seconds = ordering + factorisation, medians of 3, fill = nnz(L) + nnz(U)).
SuperLU's own minimum-degree ordering (``MMD_AT_PLUS_A``, used until now)
is fast only on a locally numbered mesh: on the interior Laplacian of the
same 129 x 129 grid (16,129 unknowns) it takes 0.04 s on ``Mesh.square(128)``
but 2.2 s on ``Mesh.square(16)`` refined three times, 16 s on a randomly
permuted numbering and 13 s on a gmsh mesh of the square; on the reduced
system of the general step with a realistic active set (24k unknowns)
0.13 / 8.0 / 57 / 15 s.  COLAMD and MMD_ATA do not depend on the numbering
but fill 1.7-2x more.  A renumbering by reverse Cuthill-McKee or along a
space-filling curve before MMD removes the dependence on the numbering, but
minimum degree itself scales badly on unstructured meshes:

=====================  ================  ===============  =================
reduced system, 400k   structured        refined          gmsh
=====================  ================  ===============  =================
RCM + MMD              4.2 s, 30M        4.2 s, 29M       15.6 s, 50M
Hilbert + MMD          5.8 s, 32M        4.9 s, 32M       19.9 s, 55M
nested dissection      3.2 s, 38M        ~                4.3 s, 41M
=====================  ================  ===============  =================

(the table of ``bench/direct_ordering.py`` has every size and ordering).
Nested dissection fills more than minimum degree on the 5-point graph of a
structured grid but its factors are denser blocks (faster per entry), it
fills less on unstructured meshes, and its time and fill stay within 1.4x
between structured, refined, permuted and gmsh meshes at every size
measured (16k-400k unknowns).  A pure-NumPy version of the same dissection
took 1-3 s at 400k unknowns; the Numba kernel takes 0.2-0.7 s.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla

from ..errors import DataError, InputTypeError, ParameterError
from ..kernels.ordering import nested_dissection

__all__ = ["LEAF", "Factorization", "factorize", "fill_reducing_order"]

#: Parts of at most this many unknowns are not dissected further (fill and
#: time vary by < 5 % between 8 and 32).
LEAF = 16

#: Names of the orderings (the ``ordering`` attribute of a factorisation).
ORDERINGS = ("nested-dissection-coordinates", "nested-dissection-graph")


def _as_matrix(matrix):
    """Return a validated square CSR copy of ``matrix`` with explicit zeros dropped."""
    if not sp.issparse(matrix):
        arr = np.asarray(matrix) if not isinstance(matrix, np.ndarray) else matrix
        if arr.dtype == object or arr.ndim != 2:
            raise InputTypeError(
                f"matrix must be a 2-D sparse matrix or array, got {type(matrix).__name__}"
                + (f" of shape {arr.shape}" if arr.dtype != object else "")
            )
        matrix = arr
    shape = tuple(matrix.shape)
    if len(shape) != 2 or shape[0] != shape[1]:
        raise ParameterError(f"matrix must be square, got shape {shape}")
    if shape[0] == 0:
        raise ParameterError("matrix must have at least one row, got shape (0, 0)")
    dtype = np.dtype(matrix.dtype)
    if dtype.kind not in "biufc":
        raise InputTypeError(f"matrix must have a numeric dtype, got {dtype}")
    a = sp.csr_matrix(matrix, dtype=np.complex128 if dtype.kind == "c" else np.float64, copy=True)
    a.sum_duplicates()
    if not np.isfinite(a.data).all():
        raise DataError("matrix has non-finite entries (NaN or inf)")
    a.eliminate_zeros()
    return a


def _as_coordinates(coordinates, n):
    if coordinates is None:
        return None
    c = np.asarray(coordinates)
    if c.dtype.kind not in "biuf":
        raise InputTypeError(f"coordinates must be real numbers, got dtype {c.dtype}")
    if c.ndim == 1:
        c = c[:, None]
    if c.ndim != 2 or c.shape[0] != n or c.shape[1] < 1:
        raise ParameterError(
            f"coordinates must have shape ({n}, d), one row per unknown, got shape "
            f"{np.shape(coordinates)}"
        )
    c = np.ascontiguousarray(c, dtype=np.float64)
    if not np.isfinite(c).all():
        raise DataError("coordinates have non-finite entries (NaN or inf)")
    return c


def _graph(a):
    """Pattern of ``|A| + |A|^T`` (the kernel ignores the diagonal)."""
    g = sp.csr_matrix((np.ones(a.data.size), a.indices, a.indptr), shape=a.shape)
    return (g + g.T).tocsr()


def _morton(c, component):
    """Order of the rows of ``c`` along a Morton (Z-order) curve, one component after another."""
    n, d = c.shape
    bits = max(1, min(16, 62 // d))  # 65536 cells per axis: locality, not exactness
    lo = c.min(axis=0)
    span = (c.max(axis=0) - lo).max()
    scale = (2**bits - 1) / span if span > 0 else 0.0
    q = ((c - lo) * scale).astype(np.int64)
    code = np.zeros(n, dtype=np.int64)
    for b in range(bits - 1, -1, -1):
        for k in range(d):
            code = (code << 1) | ((q[:, k] >> b) & 1)
    return np.lexsort((code, component))


def fill_reducing_order(matrix, coordinates=None):
    """Nested-dissection renumbering of a structurally symmetric sparse matrix.

    Parameters
    ----------
    matrix : sparse matrix or 2-D array (n, n)
        Only the pattern of ``|A| + |A|^T`` is used (explicit zeros dropped).
    coordinates : array (n, d), optional
        A point per unknown; geometric separators when given, breadth-first
        level separators otherwise (see the module docstring).

    Returns
    -------
    perm : int64 array (n,)
        ``perm[i]`` is the unknown eliminated in position ``i``: factor
        ``A[perm][:, perm]``.
    name : str
        ``"nested-dissection-coordinates"`` or ``"nested-dissection-graph"``.
    """
    a = _as_matrix(matrix)
    return _order(a, _as_coordinates(coordinates, a.shape[0]))


def _order(a, coords):

    g = _graph(a)
    if coords is not None:
        # connected components apart (the reduced system with an empty active set has two
        # copies of every point), each along a space-filling curve
        local = _morton(coords, csgraph.connected_components(g, directed=False)[1])
        name = ORDERINGS[0]
    else:
        local = csgraph.reverse_cuthill_mckee(g, symmetric_mode=True)
        name = ORDERINGS[1]
    local = local.astype(np.int64)
    g = g[local][:, local]
    indptr = g.indptr.astype(np.int64)
    indices = g.indices.astype(np.int64)
    if coords is not None:
        c = np.ascontiguousarray(coords[local])
        lists = np.ascontiguousarray(np.argsort(c, axis=0, kind="stable").T, dtype=np.int64)
    else:
        c = np.zeros((0, 0))
        lists = np.arange(a.shape[0], dtype=np.int64)[None, :]
    return local[nested_dissection(indptr, indices, lists, c, LEAF)], name


def _permuted_csc(a, perm):
    """``A[perm][:, perm]`` in CSC (column gather, then row renumbering)."""
    b = a.tocsc()[:, perm]
    inv = np.empty_like(perm)
    inv[perm] = np.arange(perm.size)
    b.indices = inv[b.indices].astype(b.indices.dtype)
    b.has_sorted_indices = False
    b.sort_indices()
    return b


class Factorization:
    """Sparse LU factors of ``P A P^T`` for a nested-dissection permutation ``P``.

    Attributes
    ----------
    n : int
        Number of unknowns.
    perm : int64 array (n,)
        The renumbering (``perm[i]`` is eliminated in position ``i``).
    ordering : str
        Name of the ordering (:data:`ORDERINGS`).
    fill : int
        Stored entries of the factors, ``nnz(L) + nnz(U)``.
    seconds : float
        Wall time of ordering plus factorisation (``order_seconds +
        factor_seconds``), validation excluded.
    """

    def __init__(self, lu, perm, ordering, order_seconds, factor_seconds):
        self._lu = lu
        self.perm = perm
        self.n = int(perm.size)
        self.ordering = ordering
        self.fill = int(lu.L.nnz + lu.U.nnz)
        self.order_seconds = float(order_seconds)
        self.factor_seconds = float(factor_seconds)
        self.seconds = self.order_seconds + self.factor_seconds

    def solve(self, rhs):
        """Solve ``A x = rhs`` for a vector ``rhs`` of length n (or an (n, k) array).

        Raises
        ------
        ParameterError
            ``rhs`` has the wrong length or more than two dimensions.
        DataError
            ``rhs`` has NaN or inf entries.
        """
        b = np.asarray(rhs)
        if b.dtype.kind not in "biufc":
            raise InputTypeError(f"rhs must be numeric, got dtype {b.dtype}")
        if b.ndim not in (1, 2) or b.shape[0] != self.n:
            raise ParameterError(
                f"rhs must have length {self.n} (the matrix size), got shape {b.shape}"
            )
        if not np.isfinite(b).all():
            raise DataError("rhs has non-finite entries (NaN or inf)")
        dtype = np.result_type(b.dtype, self._lu.L.dtype, np.float64)
        y = self._lu.solve(np.ascontiguousarray(b[self.perm], dtype=dtype))
        x = np.empty_like(y)
        x[self.perm] = y
        return x

    def __repr__(self):
        return (
            f"Factorization(n={self.n}, ordering={self.ordering!r}, fill={self.fill}, "
            f"seconds={self.seconds:.3g})"
        )


def factorize(matrix, coordinates=None):
    """Factor a sparse symmetric positive definite matrix, ordered by nested dissection.

    Parameters
    ----------
    matrix : sparse matrix or 2-D array (n, n)
        Symmetric positive definite (the interior Laplacian, the reduced
        system of the general step): SuperLU pivots on the diagonal, in the
        nested-dissection order (a zero diagonal pivot falls back to partial
        pivoting).  Not modified.
    coordinates : array (n, d), optional
        A point per unknown (for P1 unknowns: their vertex).  Without it the
        ordering uses the graph only (breadth-first separators: same
        independence of the numbering, about 1.2x slower and more fill on
        unstructured meshes).

    Returns
    -------
    Factorization
        ``solve(rhs)``, ``fill``, ``seconds``, ``ordering``.

    Raises
    ------
    ParameterError
        ``matrix`` is not square or empty, or ``coordinates`` has not one row
        per unknown.
    InputTypeError, DataError
        Non-numeric or non-finite entries.
    RuntimeError
        From SuperLU, when the matrix is exactly singular.
    """
    a = _as_matrix(matrix)
    coords = _as_coordinates(coordinates, a.shape[0])
    t0 = time.perf_counter()
    perm, name = _order(a, coords)
    t1 = time.perf_counter()
    lu = spla.splu(_permuted_csc(a, perm), permc_spec="NATURAL", diag_pivot_thresh=0.0)
    t2 = time.perf_counter()
    return Factorization(lu, perm, name, t1 - t0, t2 - t1)
