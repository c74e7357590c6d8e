"""The P1 pattern built in row blocks (kernels.sparsity) against the serial path and scipy."""

import numpy as np
import pytest
import scipy.sparse as sp
from fastmem.kernels import sparsity as ks

import fastmem as fm
from fastmem.mesh.refine import refine_marked


def _serial(n, edges, dtype):
    """The serial path: counting sort by row, then an insertion sort per row."""
    counts = np.ones(n, dtype=np.int64)
    ks._count_rows(edges, counts)
    indptr = np.zeros(n + 1, dtype=dtype)
    np.cumsum(counts, out=indptr[1:])
    indices = np.empty(int(indptr[-1]), dtype=dtype)
    ks._fill_rows(edges, indptr[:-1].copy(), indices)
    ks._sort_rows(indptr, indices)
    return indptr, indices


def _triangle_pairs(mesh):
    """scipy's pattern of all vertex pairs of each triangle (the vertex graph)."""
    t = mesh.triangles
    rows = np.repeat(t, 3, axis=1).ravel()
    cols = np.tile(t, (1, 3)).ravel()
    n = mesh.n_vertices
    ref = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n)).tocsr()
    ref.sort_indices()
    return ref.indptr, ref.indices


def _refined():
    base = fm.Mesh.square(40)
    marked = np.zeros(base.n_triangles, dtype=bool)
    marked[::5] = True
    return refine_marked(base, marked)[0]  # patches of unequal sizes, edges from the parent's


@pytest.mark.parametrize("make", [lambda: fm.Mesh.square(1), lambda: fm.Mesh.lshape(24), _refined])
@pytest.mark.parametrize("dtype", [np.int32, np.int64])
def test_blocks_give_the_serial_pattern(make, dtype):
    """Any number of blocks and chunks: the rows of the serial path and of scipy, bit for bit."""
    mesh = make()
    n, edges = mesh.n_vertices, mesh.edges
    want = _serial(n, edges, dtype)
    ref_ptr, ref_idx = _triangle_pairs(mesh)
    np.testing.assert_array_equal(want[0], ref_ptr)
    np.testing.assert_array_equal(want[1], ref_idx)
    for threads in (1, 2, 3, 16):
        for grain in (1, 5, ks.PATTERN_GRAIN):
            got = ks._sorted_pattern(n, edges, dtype, threads, grain=grain)
            assert got is not None
            assert got[0].dtype == got[1].dtype == dtype
            np.testing.assert_array_equal(got[0], want[0], err_msg=f"{threads} {grain}")
            np.testing.assert_array_equal(got[1], want[1], err_msg=f"{threads} {grain}")


def test_an_edge_list_out_of_order_goes_the_serial_way():
    """Swapped edges or reversed pairs: no block pattern, and csr_pattern still right."""
    mesh = fm.Mesh.lshape(16)
    n = mesh.n_vertices
    want = _serial(n, mesh.edges, np.int32)
    swapped = mesh.edges.copy()
    swapped[[3, 40]] = swapped[[40, 3]]
    reversed_pairs = np.ascontiguousarray(mesh.edges[:, ::-1])
    duplicated = np.ascontiguousarray(np.vstack([mesh.edges[:1], mesh.edges]))
    for edges in (swapped, reversed_pairs):
        assert ks._sorted_pattern(n, edges, np.int32, 3, grain=1) is None
        got = ks.csr_pattern(n, edges, np.int32)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
    assert ks._sorted_pattern(n, duplicated, np.int32, 3, grain=1) is None


@pytest.mark.parametrize("n", [1, 2, 7, 100, 4097, 65536, 1_000_003])
@pytest.mark.parametrize("blocks", [1, 2, 3, 7, 16])
def test_block_of_finds_the_block_of_ranges(n, blocks):
    """_block_of agrees with the chunks of pool.ranges for every index tested."""
    chunks = ks.ranges(n, blocks, 1)
    bounds = np.array([lo for lo, _ in chunks] + [n], dtype=np.int64)
    scale = (bounds.size - 1) / n
    q = np.unique(np.r_[0, n - 1, bounds[:-1], np.maximum(bounds[1:] - 1, 0), np.arange(0, n, 97)])
    q = q[(q >= 0) & (q < n)]
    got = np.array([ks._block_of(int(x), bounds, scale) for x in q])
    want = np.searchsorted(bounds, q, side="right") - 1
    np.testing.assert_array_equal(got, want)
