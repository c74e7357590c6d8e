"""The passes of many threads, against their serial versions: the P1 pattern in row blocks,
the transpose in column blocks (kernels.sparsity), the patch hashes grouped in chunks
(kernels.flux)."""

import numpy as np
import pytest
import scipy.sparse as sp
from fastmem.kernels import flux as kf
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


def test_csr_pattern_takes_the_blocks_from_block_threads(monkeypatch):
    """csr_pattern: the row blocks from BLOCK_THREADS threads on, the serial path below; same."""
    mesh = _refined()
    n, edges = mesh.n_vertices, mesh.edges
    want = _serial(n, edges, np.int32)
    calls = []
    real = ks._sorted_pattern
    monkeypatch.setattr(ks, "_sorted_pattern", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setattr(ks, "PATTERN_GRAIN", 64)
    for limit in (1, 10**6):
        monkeypatch.setattr(ks, "BLOCK_THREADS", limit)
        got = ks.csr_pattern(n, edges, np.int32)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
    assert len(calls) == 1  # only with BLOCK_THREADS = 1


def _unsorted_rows(a):
    """``a`` with the entries of each row in reversed order."""
    b = a.copy()
    for i in range(b.shape[0]):
        s, e = b.indptr[i], b.indptr[i + 1]
        b.indices[s:e] = b.indices[s:e][::-1]
        b.data[s:e] = b.data[s:e][::-1]
    b.has_sorted_indices = False
    return b


def _matrices():
    from fastmem.solver.nested import interpolation_matrix

    p = interpolation_matrix(fm.Mesh.lshape(16), fm.Mesh.lshape(32)).tocsr()
    yield p  # columns follow the rows: each column block reads a few row chunks
    yield sp.random(300, 200, 0.03, format="csr", random_state=2)  # no locality
    yield _unsorted_rows(sp.random(120, 90, 0.1, format="csr", random_state=3))
    yield sp.csr_matrix((6, 9))  # no entries
    yield sp.random(1, 70, 0.5, format="csr", random_state=4)
    yield sp.random(70, 1, 0.5, format="csr", random_state=5)


@pytest.mark.parametrize("dtype", [np.int32, np.int64])
def test_transpose_is_scipys_entry_for_entry(dtype):
    """csr_transpose in any number of column blocks and row chunks: scipy's csr_tocsc."""
    for a in _matrices():
        ref = a.T.tocsr()  # scipy's transpose: sorted rows
        for threads in (1, 2, 3, 16):
            for grain in (1, 4, None):
                ip, ix, d = ks.csr_transpose(
                    a.indptr, a.indices, a.data, a.shape[1], dtype, threads, grain
                )
                assert ip.dtype == ix.dtype == dtype
                np.testing.assert_array_equal(ip, ref.indptr)
                np.testing.assert_array_equal(ix, ref.indices)
                np.testing.assert_array_equal(d, ref.data)


def test_restriction_in_the_kernel_threads_is_scipys(monkeypatch):
    """gmg.restriction with the kernel path forced: the matrix scipy's transpose gives."""
    from fastmem.linalg import gmg
    from fastmem.solver.nested import interpolation_matrix

    p = interpolation_matrix(fm.Mesh.square(24), fm.Mesh.square(48)).tocsr()
    want = gmg.restriction(p.copy())  # scipy (small matrix, or few threads)
    monkeypatch.setattr(gmg, "THREADED_ROWS", 0)
    monkeypatch.setattr(ks, "BLOCK_THREADS", 1)
    monkeypatch.setattr(ks, "PATTERN_GRAIN", 50)
    calls = []
    real = ks.csr_transpose
    monkeypatch.setattr(ks, "csr_transpose", lambda *a, **k: calls.append(1) or real(*a, **k))
    got = gmg.restriction(p.copy())
    assert calls  # the kernel path
    assert got.has_sorted_indices
    assert got.indices.dtype == want.indices.dtype == np.int32
    np.testing.assert_array_equal(got.indptr, want.indptr)
    np.testing.assert_array_equal(got.indices, want.indices)
    np.testing.assert_array_equal(got.data, want.data)


def _hash_cases():
    rng = np.random.default_rng(7)
    mix = np.uint64(0x9E3779B97F4A7C15)
    yield rng.integers(0, 40, 50_000).astype(np.uint64) * mix  # a structured mesh: few
    yield rng.integers(0, 2**63, 30_000, dtype=np.uint64)  # all distinct: tables grow
    yield rng.integers(0, 3000, 40_000).astype(np.uint64) * mix
    yield np.zeros(5000, dtype=np.uint64)  # one hash (0, the empty slot's value)
    yield np.array([3, 1, 3, 3, 2, 1], dtype=np.uint64)


def test_grouped_hashes_in_chunks_are_the_serial_ones():
    """_group_hashes_threaded: the serial kernel's first vertices and count, any chunking."""
    for hashes in _hash_cases():
        want = np.empty(hashes.size, dtype=np.int64)
        distinct = kf._group_hashes(hashes, want)
        assert distinct == np.unique(hashes).size
        first = {}
        for a, h in enumerate(hashes.tolist()):  # the definition (tables grown, collisions)
            first.setdefault(h, a)
        np.testing.assert_array_equal(want, [first[h] for h in hashes.tolist()])
        for threads in (kf.BLOCK_THREADS, 7, 64):
            for grain in (1, 1000, None):
                got = np.empty(hashes.size, dtype=np.int64)
                assert kf._group_hashes_threaded(hashes, got, threads, grain) == distinct
                np.testing.assert_array_equal(got, want)


def test_patch_classes_with_many_threads_are_the_same(monkeypatch):
    """patch_classes with the chunked grouping: the classes of the serial grouping."""
    mesh = fm.Mesh.square(96)
    from fastmem.estimators.flux import patch_arrays

    geo = patch_arrays(mesh)
    max_nt = int(np.diff(mesh.patch_ptr).max())
    monkeypatch.setattr(kf, "CLASS_SAMPLE", 64)
    want = kf.patch_classes(geo, max_nt, 1)
    calls = []
    real = kf._chunk_firsts
    monkeypatch.setattr(kf, "_chunk_firsts", lambda *a: calls.append(1) or real(*a))
    got = kf.patch_classes(geo, max_nt, 16)
    assert calls  # the chunked grouping ran
    assert want is not None
    cls, reps, cint, cflt, coff = got
    np.testing.assert_array_equal(cls, want[0])
    np.testing.assert_array_equal(reps, want[1])
    np.testing.assert_array_equal(cint, want[2])
    assert cflt.shape == want[3].shape  # the storage, filled on first use
    np.testing.assert_array_equal(coff, want[4])
    assert (cls >= 0).mean() > 0.9  # classes cover the square
