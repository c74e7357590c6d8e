"""Numba kernels of the mesh topology and of the history rows against plain NumPy references."""

import numpy as np
import pytest
from fastmem.kernels.rows import row_measures
from fastmem.kernels.topology import edge_topology

import fastmem as fm
from fastmem.refine import refine_marked

_EV = np.array([[1, 2], [2, 0], [0, 1]])


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
