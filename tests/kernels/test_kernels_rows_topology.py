"""Numba kernels of the mesh topology and of the history rows against plain NumPy references.

Meshes below :data:`fastmem.kernels.topology.NUMPY_BELOW` triangles take NumPy paths
instead of the kernels: every topology test runs twice, once with the kernels forced
and once with the NumPy paths forced, against the same references.
"""

import numba
import numpy as np
import pytest
from fastmem.kernels import pool
from fastmem.kernels.rows import row_measures
from fastmem.kernels.topology import edge_topology

import fastmem as fm
from fastmem.mesh.refine import refine_marked

_EV = np.array([[1, 2], [2, 0], [0, 1]])


@pytest.fixture(autouse=True, params=["kernels", "numpy"])
def topology_path(request, monkeypatch):
    """Force the kernels (NUMPY_BELOW = 0) or the NumPy paths (any size) of the topology."""
    from fastmem.kernels import topology as kt

    monkeypatch.setattr(kt, "NUMPY_BELOW", 0 if request.param == "kernels" else 2**62)
    return request.param


def _reference_topology(t, n):
    """Edges by a stable sort of the keys lo * n + hi (the former NumPy implementation)."""
    m = t.shape[0]
    half = t[:, _EV]
    a, b = half[..., 0].ravel(), half[..., 1].ravel()
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    key = lo * np.int64(n) + hi
    perm = np.argsort(key, kind="stable")
    skey = key[perm]
    first = np.r_[True, skey[1:] != skey[:-1]]
    starts = np.flatnonzero(first)
    counts = np.diff(np.append(starts, skey.size))
    tri_edges = np.empty(3 * m, dtype=np.int64)
    tri_edges[perm] = np.cumsum(first) - 1
    edges = np.stack([skey[starts] // n, skey[starts] % n], axis=1)
    et = np.full((starts.size, 2), -1, dtype=np.int64)
    et[:, 0] = perm[starts] // 3
    two = counts == 2
    et[two, 1] = perm[starts[two] + 1] // 3
    forward = np.add.reduceat((a < b)[perm].astype(np.int64), starts)
    return edges, tri_edges.reshape(m, 3), et, counts, forward


def _meshes():
    rng = np.random.default_rng(7)
    out = [fm.Mesh.square(12), fm.Mesh.lshape(8), fm.Mesh.square(3).refine().refine()]
    m = fm.Mesh.square(4)
    for _ in range(5):
        m, _ = refine_marked(m, rng.random(m.n_triangles) < 0.3)
    out.append(m)
    base = out[0]
    p = rng.permutation(base.n_vertices)
    inv = np.empty_like(p)
    inv[p] = np.arange(p.size)
    out.append(fm.Mesh(base.vertices[p], inv[base.triangles]))
    return out


@pytest.mark.parametrize("mesh", _meshes(), ids=["square", "lshape", "red", "nvb", "permuted"])
def test_edge_topology_matches_the_sort(mesh):
    got = edge_topology(np.asarray(mesh.triangles), mesh.n_vertices)
    want = _reference_topology(np.asarray(mesh.triangles), mesh.n_vertices)
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)
    assert (got[3] <= 2).all()
    assert (got[4][got[3] == 2] == 1).all()  # consistently oriented


def test_edge_topology_sees_non_manifold_and_folded_edges():
    t = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # edge (0, 1) in three triangles
    _, _, _, counts, _ = edge_topology(t, 5)
    assert counts.max() == 3
    t = np.array([[0, 1, 2], [0, 1, 3]])  # both run 0 -> 1: folded
    edges, _, _, counts, forward = edge_topology(t, 4)
    e = np.flatnonzero((edges[:, 0] == 0) & (edges[:, 1] == 1))[0]
    assert counts[e] == 2
    assert forward[e] == 2


@pytest.mark.parametrize("threads,grain", [(2, 1), (3, 5), (7, 1)])
def test_edge_topology_same_arrays_for_any_chunking(monkeypatch, threads, grain):
    """The buckets are sorted and numbered over vertex ranges: any split, same arrays."""
    from fastmem.kernels import topology as kt

    meshes = _meshes()  # built before the chunking changes
    monkeypatch.setattr(kt, "GRAIN", grain)
    monkeypatch.setattr(kt, "n_threads", lambda threads=threads: threads)
    for mesh in meshes:
        t = np.asarray(mesh.triangles)
        want = _reference_topology(t, mesh.n_vertices)
        got = kt.edge_topology(t, mesh.n_vertices)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_array_equal(g, w)
        assert [g.dtype for g in got] == [np.int32, np.int32, np.int32, np.int8, np.int8]


def test_edge_topology_counts_saturate():
    """counts and forward are int8, saturated at COUNT_CAP (only the checks read them)."""
    from fastmem.kernels.topology import COUNT_CAP

    t = np.array([[0, 1, k] for k in range(2, 2 + 200)])  # edge (0, 1) in 200 triangles
    edges, _, _, counts, forward = edge_topology(t, 202)
    e = np.flatnonzero((edges[:, 0] == 0) & (edges[:, 1] == 1))[0]
    assert counts[e] == COUNT_CAP and forward[e] == COUNT_CAP
    with pytest.raises(fm.errors.MeshError, match=r"\(0, 1\) in 200 triangles"):
        fm.Mesh(np.c_[np.arange(202.0), np.arange(202.0) ** 2], t)


def _reference_rectangle_triangles(nx, ny, diagonal):
    """The former NumPy construction of Mesh.rectangle's triangles."""
    a = ((np.arange(ny) * (nx + 1))[:, None] + np.arange(nx)).ravel()
    tris = np.empty((a.size, 2, 3), dtype=np.int64)
    tris[:, 0, 0], tris[:, 0, 1] = a, a + 1
    tris[:, 1, 1], tris[:, 1, 2] = a + (nx + 2), a + (nx + 1)
    if diagonal == "right":
        slash = np.ones(a.size, dtype=bool)
    elif diagonal == "left":
        slash = np.zeros(a.size, dtype=bool)
    else:
        xc = (2 * np.arange(nx) + 1 - nx) * 1.0
        yc = (2 * np.arange(ny) + 1 - ny) * 1.0
        slash = (yc[:, None] * xc[None, :] >= 0).ravel()
    tris[:, 0, 2] = np.where(slash, tris[:, 1, 1], tris[:, 1, 2])
    tris[:, 1, 0] = np.where(slash, a, tris[:, 0, 1])
    return tris.reshape(-1, 3)


@pytest.mark.parametrize("diagonal", ["right", "left", "symmetric"])
@pytest.mark.parametrize("nx,ny", [(1, 1), (1, 5), (4, 4), (5, 3), (7, 8), (64, 33)])
def test_rectangle_triangles_match_numpy(monkeypatch, diagonal, nx, ny):
    from fastmem.kernels import topology as kt

    want = _reference_rectangle_triangles(nx, ny, diagonal)
    got = kt.rectangle_triangles(nx, ny, diagonal)
    assert got.dtype == np.int64 and got.flags.c_contiguous
    np.testing.assert_array_equal(got, want)
    monkeypatch.setattr(kt, "GRAIN", 1)  # one row per chunk at least: several threads
    np.testing.assert_array_equal(kt.rectangle_triangles(nx, ny, diagonal), want)


def test_triangle_checks_match_numpy():
    from fastmem.kernels.assembly import area2_and_diameter2
    from fastmem.kernels.topology import triangle_checks

    rng = np.random.default_rng(11)
    v = rng.standard_normal((300, 2))
    v[1] = v[2] = v[0]  # a zero-diameter triangle (8, below)
    t = rng.integers(0, 300, (5000, 3))
    t[8] = [0, 1, 2]
    t[:7, 1] = t[:7, 0]  # repeated vertices
    v[299] = 0.5 * (v[297] + v[298])  # a collinear triangle
    t[7] = [297, 298, 299]
    tol2 = 2.0 * 1e-13
    used = np.zeros(301, dtype=np.uint8)
    area2, h2, counts = triangle_checks(v, t, 1e-100, tol2, used)
    np.testing.assert_array_equal(used, np.bincount(t.ravel(), minlength=301) > 0)
    a_ref, h_ref = area2_and_diameter2(v, t)
    assert area2.tobytes() == a_ref.tobytes() and h2.tobytes() == h_ref.tobytes()
    rep = (t[:, 0] == t[:, 1]) | (t[:, 1] == t[:, 2]) | (t[:, 0] == t[:, 2])
    want = [rep.sum(), (h_ref < 1e-100).sum(), (np.abs(a_ref) <= tol2 * h_ref).sum()]
    want.append((a_ref < 0).sum())
    assert counts.tolist() == want
    assert all(c > 0 for c in want)


def test_row_measures_match_numpy():
    rng = np.random.default_rng(3)
    n = 500
    interior = np.sort(rng.choice(n, 400, replace=False))
    u1, u2 = rng.standard_normal(n), rng.standard_normal(n)
    lam = np.where(rng.random(n) < 0.3, 0.0, rng.standard_normal(n))
    active = rng.random(interior.size) < 0.5
    for c in (1.0, 0.3):
        changed, comp_sq = row_measures(u1, u2, lam, interior, active, c)
        gap, li = u1[interior] - u2[interior], lam[interior]
        assert changed == np.count_nonzero((li > c * gap) != active)
        assert comp_sq == pytest.approx(np.sum(np.minimum(gap, li) ** 2), rel=1e-13)


def test_mesh_refuses_unused_vertices_marked_by_the_check_kernel():
    v = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [5.0, 5.0], [1.0, 1.0]])
    with pytest.raises(fm.errors.MeshError, match=r"unused vertices: 1 vertices .*vertex 3"):
        fm.Mesh(v, [[0, 1, 2], [1, 4, 2]])


@pytest.mark.parametrize("mesh", _meshes(), ids=["square", "lshape", "red", "nvb", "permuted"])
def test_vertex_patch_ptr_matches_bincount(mesh):
    from fastmem.kernels.topology import vertex_patch_ptr

    t = np.asarray(mesh.triangles)
    got = vertex_patch_ptr(t, mesh.n_vertices)
    want = np.r_[0, np.cumsum(np.bincount(t.ravel(), minlength=mesh.n_vertices))]
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("mesh", _meshes(), ids=["square", "lshape", "red", "nvb", "permuted"])
def test_vertex_patches_and_lumped_mass_match_numpy(mesh):
    from fastmem.kernels import topology as kt

    t = np.asarray(mesh.triangles)
    ptr = kt.vertex_patch_ptr(t, mesh.n_vertices)
    tris, local = kt.vertex_patches(t, ptr)
    order = np.argsort(t.ravel(), kind="stable")
    assert tris.dtype == np.int32
    assert local.dtype == np.int8
    np.testing.assert_array_equal(tris, order // 3)
    np.testing.assert_array_equal(local, order % 3)
    areas = mesh.areas
    b = kt.lumped_mass(t, areas, mesh.n_vertices)
    want = np.bincount(t.ravel(), np.repeat(areas / 3, 3), minlength=mesh.n_vertices)
    assert b.tobytes() == want.tobytes()  # the same additions in the same order


def test_small_meshes_take_the_numpy_paths(monkeypatch, topology_path):
    """Below NUMPY_BELOW triangles no topology kernel runs (none compiles on a first run)."""
    from fastmem.kernels import topology as kt

    monkeypatch.setattr(kt, "NUMPY_BELOW", 65536)
    ran = []
    for name in (
        "_count_edges",
        "_number_edges",
        "_count_degrees",
        "_fill_patches",
        "_add_thirds",
        "_rectangle_triangles_rows",
        "_triangle_checks_range",
    ):
        monkeypatch.setattr(kt, name, lambda *a, name=name, **k: ran.append(name))
    mesh = fm.Mesh.square(128)  # 32,768 triangles: the default fastmem run
    assert mesh.n_triangles < kt.NUMPY_BELOW
    _ = mesh.edges, mesh.lumped_mass, mesh.patch_ptr
    assert ran == []


def test_kernel_paths_force_the_kernels_and_restore_the_threshold(monkeypatch, topology_path):
    """warm_up(large=True) compiles the kernels on a tiny mesh inside kernel_paths()."""
    from fastmem.kernels import topology as kt

    calls = []
    count_edges = kt._count_edges
    monkeypatch.setattr(kt, "_count_edges", lambda *a: calls.append(1) or count_edges(*a))
    small = fm.Mesh.square(4)
    t = np.asarray(small.triangles)
    before = kt.NUMPY_BELOW
    with kt.kernel_paths():
        assert kt.NUMPY_BELOW == 0
        got = kt.edge_topology(t, small.n_vertices)
    assert calls  # the kernels ran on a 32-triangle mesh
    assert kt.NUMPY_BELOW == before
    for g, w in zip(got, _reference_topology(t, small.n_vertices), strict=True):
        np.testing.assert_array_equal(g, w)
    calls.clear()
    kt.edge_topology(t, small.n_vertices)
    assert bool(calls) == (topology_path == "kernels")  # the threshold is back


@pytest.mark.parametrize("pieces", [1, 4])
@pytest.mark.parametrize("threads", [1, 2])
def test_parallel_for_covers_every_index_once(threads, pieces):
    """Static chunks or dynamic pieces: each index is handed to the kernel exactly once."""
    seen = np.zeros(100_003, dtype=np.int64)

    def kernel(lo, hi, out):  # (plain Python: the pool only needs a callable)
        out[lo:hi] += 1

    old = numba.get_num_threads()
    try:
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
        pool.parallel_for(kernel, seen.size, seen, grain=1000, pieces=pieces)
    finally:
        numba.set_num_threads(old)
    assert np.all(seen == 1)
