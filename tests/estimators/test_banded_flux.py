"""The flux estimators band by band (no stored fluxes) give the stored path's bits.

:func:`fastmem.estimators.flux.flux_norms` solves the patch problems band after
band into a ring of rows (one row per patch of a triangle), sums each completed
triangle's rows in its vertices' colour order and forms its norms at once.  Every
test compares with :func:`~fastmem.estimators.flux.reconstruct` followed by
:func:`~fastmem.estimators.bound.flux_terms`, which store all the fluxes first.
"""

import numba
import numpy as np
import pytest
from fastmem.kernels import flux as kf

import fastmem as fm
import fastmem.estimators.bound as bound
import fastmem.estimators.flux as flux
from fastmem.mesh import csr_structure, refine_marked
from fastmem.problems import Manufactured


def _stored(scene, triple):
    fluxes = flux.reconstruct(scene, *triple, redistribute="glued")
    return bound.flux_terms(scene, triple[0], triple[1], fluxes), fluxes.contact


def _noisy_triple(scene, seed=0):
    """A solve's triple with u1 perturbed inside (every residual term is exercised)."""
    mesh = scene.mesh
    res = fm.solve(scene, estimate=False)
    rng = np.random.default_rng(seed)
    u1 = res.u1.copy()
    inner = mesh.interior_vertices
    u1[inner] += 1e-3 * rng.standard_normal(inner.size)
    return u1, res.u2, res.lam


def _plan_by_numpy(mesh, band):
    """The plan's completion bounds and ring, from the definitions (plain NumPy)."""
    order, color_ptr = flux._coloring(mesh)
    m = mesh.n_triangles
    n_bands = max(1, -(-m // band))
    first = np.minimum.reduceat(mesh.patch_triangles, mesh.patch_ptr[:-1]).astype(np.int64)
    last = np.maximum.reduceat(mesh.patch_triangles, mesh.patch_ptr[:-1]).astype(np.int64)
    vband = np.minimum(first // band, n_bands - 1)
    done = vband[mesh.triangles].max(axis=1)  # the band that completes each triangle
    lows = np.array([0] + [int(np.flatnonzero(done > b).min(initial=m)) for b in range(n_bands)])
    top = np.array([last[vband == b].max(initial=-1) for b in range(n_bands)])
    reach = np.maximum.accumulate(top)
    ring = int(max(1, (reach + 1 - lows[:-1]).max()))
    return order, color_ptr, vband, done, lows, ring


@pytest.mark.parametrize("band", [64, 333])
def test_plan_against_its_definition(band):
    mesh = fm.Mesh.square(24)
    seq, seg, lows, ring, color = flux.band_plan(mesh, band=band)
    order, color_ptr, vband, done, lows_np, ring_np = _plan_by_numpy(mesh, band)
    n_colors = color_ptr.size - 1
    assert np.array_equal(np.sort(seq), np.arange(mesh.n_vertices))
    for c in range(n_colors):
        assert np.all(color[order[color_ptr[c] : color_ptr[c + 1]]] == c)
    for k in range(seg.size - 1):  # segment k: band k // C, colour k % C
        part = seq[seg[k] : seg[k + 1]]
        assert np.all(vband[part] == k // n_colors)
        assert np.all(color[part] == k % n_colors)
    assert np.array_equal(lows, lows_np)
    assert ring == ring_np
    # every triangle is finished by a band that has run all of its patches
    which = np.searchsorted(lows, np.arange(mesh.n_triangles), side="right") - 1
    assert np.all(done <= which)
    assert np.all(np.diff(lows) >= 0)
    assert lows[0] == 0
    assert lows[-1] == mesh.n_triangles
    # the ring by simulation, not by its formula: during band b the triangles written
    # by the patches of bands <= b and not finished before b have distinct slots
    written = np.zeros(mesh.n_triangles, dtype=bool)
    for b in range(lows.size - 1):
        for a in np.flatnonzero(vband == b):
            written[mesh.patch_triangles[mesh.patch_ptr[a] : mesh.patch_ptr[a + 1]]] = True
        live = np.flatnonzero(written & (np.arange(mesh.n_triangles) >= lows[b]))
        slots = live % ring
        assert np.unique(slots).size == slots.size, b


@pytest.mark.parametrize("classes", [False, True])
@pytest.mark.parametrize("mu", [(1.0, 1.0), (1.0, 3.0)])
def test_norms_bit_for_bit(monkeypatch, classes, mu):
    """Structured square, with and without patch classes, equal and unequal tensions."""
    monkeypatch.setattr(flux, "PATCH_CLASS_MIN_VERTICES", 0 if classes else 10**9)
    mesh = fm.Mesh.square(32)
    scene = fm.Scene(mesh, mu=mu, f=(-1.0, 1.0), g=0.1)
    triple = _noisy_triple(scene)
    (ref1, ref2), contact = _stored(scene, triple)
    if mu[0] != mu[1]:
        assert contact is not None  # the glued contact load is in the patch problems
    for band in (64, 500):
        got1, got2, got_contact = flux.flux_norms(scene, *triple, plan=flux.band_plan(mesh, band))
        assert np.array_equal(got1, ref1)
        assert np.array_equal(got2, ref2)
        assert (got_contact is None) == (contact is None)
        assert not mesh._cache["flux_window"].any()  # the ring is all zero again
    assert ref1.max() > 0.0
    assert ref2.max() > 0.0


def test_callable_loads_and_thread_counts():
    scene = Manufactured().scene(fm.Mesh.square(32))
    triple = _noisy_triple(scene, seed=1)
    (ref1, ref2), _ = _stored(scene, triple)
    plan = flux.band_plan(scene.mesh, band=100)
    threads = numba.get_num_threads()
    try:
        for t in sorted({1, threads}):
            numba.set_num_threads(t)
            got1, got2, _ = flux.flux_norms(scene, *triple, plan=plan)
            assert np.array_equal(got1, ref1)
            assert np.array_equal(got2, ref2)
    finally:
        numba.set_num_threads(threads)


def test_parallel_pieces_give_the_same_bits(monkeypatch):
    """Grains of 1: every colour segment and every band's final pass in many pieces."""
    monkeypatch.setattr(kf, "PATCH_GRAIN", 1)
    monkeypatch.setattr(kf, "TRIANGLE_GRAIN", 1)
    scene = fm.Scene(fm.Mesh.lshape(16), mu=(1.0, 2.0), f=(-1.0, 1.0), g=0.1)
    triple = _noisy_triple(scene, seed=5)
    (ref1, ref2), _ = _stored(scene, triple)
    threads = numba.get_num_threads()
    try:
        for t in sorted({1, 2, threads}):
            numba.set_num_threads(min(t, numba.config.NUMBA_NUM_THREADS))
            got1, got2, _ = flux.flux_norms(scene, *triple, plan=flux.band_plan(scene.mesh, 37))
            assert np.array_equal(got1, ref1)
            assert np.array_equal(got2, ref2)
    finally:
        numba.set_num_threads(threads)


def test_refined_mesh_has_no_plan_but_a_forced_one_agrees(monkeypatch):
    """Refined meshes number new triangles last: the ring would be most of the mesh."""
    coarse = fm.Scene(fm.Mesh.lshape(8), mu=(1, 1), f=(-1, -1), g=0.1)
    mesh = fm.solve(coarse, tol=3e-2).mesh
    scene = fm.Scene(mesh, mu=(1, 1), f=(-1, -1), g=0.1)
    monkeypatch.setattr(kf, "BAND_TRIANGLES", 64)
    monkeypatch.setattr(kf, "BAND_TRIANGLES_PER_THREAD", 1)
    monkeypatch.setattr(flux, "BAND_MIN_VERTICES", 0)
    assert mesh.n_triangles >= flux.BAND_MIN * 64
    assert flux.band_plan(mesh) is None
    assert flux.flux_norms(scene, *_noisy_triple(scene)) is None
    square = fm.Mesh.square(24)
    assert flux.band_plan(square) is not None  # numbered in rows: a ring of a few bands
    # the sampled patch spans that skip the plan: at most the largest span, exact when
    # every vertex is sampled; above a sixth of the mesh on the refined one
    for m in (mesh, square):
        full = np.maximum.reduceat(m.patch_triangles, m.patch_ptr[:-1])
        full = (full - np.minimum.reduceat(m.patch_triangles, m.patch_ptr[:-1])).max()
        assert flux._sampled_span(m, samples=50) <= full == flux._sampled_span(m, 10**9)
    assert flux._sampled_span(mesh) > mesh.n_triangles // 6
    assert flux._sampled_span(square) <= 3 * 24  # two rows of triangles
    triple = _noisy_triple(scene, seed=2)
    (ref1, ref2), _ = _stored(scene, triple)
    got1, got2, _ = flux.flux_norms(scene, *triple, plan=flux.band_plan(mesh, band=64))
    assert np.array_equal(got1, ref1)
    assert np.array_equal(got2, ref2)


def test_per_triangle_tensions_are_stored():
    mesh = fm.Mesh.square(16)
    mu1 = np.where(mesh.triangles[:, 0] % 2 == 0, 1.0, 2.0)
    scene = fm.Scene(mesh, mu=(mu1, 1.0), f=(-1.0, 1.0), g=0.1)
    zero = np.zeros(mesh.n_vertices)
    assert flux.flux_norms(scene, zero, zero, zero, plan=flux.band_plan(mesh, band=64)) is None


def test_estimate_with_bands_equals_estimate_without(monkeypatch):
    """The whole bound (totals and maps) through the banded path and the stored one."""
    mesh = fm.Mesh.square(32)
    scene = fm.Scene(mesh, mu=(1.0, 2.0), f=(-1.0, 1.0), g=0.1)
    triple = _noisy_triple(scene, seed=3)
    calls = []
    real = flux.flux_norms

    def banded(*args, **kwargs):
        calls.append(1)
        return real(*args, plan=flux.band_plan(mesh, band=128), **kwargs)

    monkeypatch.setattr(bound, "flux_norms", banded)
    with_bands = fm.estimate(scene, *triple)
    monkeypatch.setattr(bound, "flux_norms", lambda *a, **k: None)
    stored = fm.estimate(scene, *triple)
    assert calls
    for key in ("eta", "eta_disc", "eta_lin", "eta_alg", "a", "c"):
        assert with_bands.totals[key] == stored.totals[key], key
    for key, value in stored.maps.items():
        assert np.array_equal(with_bands.maps[key], value), key


@pytest.mark.parametrize("which", ["ball", "twosided"])
def test_obstacle_flux_terms_bit_for_bit(monkeypatch, which):
    """The obstacle family's eta_F (one membrane, the second a zero problem)."""
    import fastmem.estimators.obstacle as obstacle
    from fastmem.problems import obstacles

    problem = getattr(obstacles, which)(32)
    mesh = problem.mesh
    result = fm.solve(problem)
    rng = np.random.default_rng(4)
    u = result.u.copy()
    inner = mesh.interior_vertices
    u[inner] += 1e-3 * rng.standard_normal(inner.size)
    lam = np.where(mesh.boundary_vertex_mask, 0.0, rng.standard_normal(mesh.n_vertices))
    rho = np.where(mesh.boundary_vertex_mask, 0.0, rng.standard_normal(mesh.n_vertices))
    monkeypatch.setattr(obstacle, "band_plan", lambda m: None)
    stored = obstacle.flux_terms(problem, u, lam, rho)
    monkeypatch.setattr(obstacle, "band_plan", lambda m: flux.band_plan(m, band=64))
    banded = obstacle.flux_terms(problem, u, lam, rho)
    assert np.array_equal(banded, stored)
    assert stored.max() > 0.0
    assert not mesh._cache["flux_window"].any()


@pytest.mark.parametrize("refined", [False, True])
def test_colour_order_is_the_stable_sort_of_the_colours(refined):
    """color_vertices' counting sort: NumPy's stable argsort of the colours; a proper colouring."""

    mesh = fm.Mesh.lshape(32)
    if refined:
        marked = np.zeros(mesh.n_triangles, dtype=bool)
        marked[::3] = True
        mesh = refine_marked(mesh, marked)[0]
    indptr, indices, _ = csr_structure(mesh)
    colors, n_colors, order, ptr = kf.color_vertices(mesh.n_vertices, indptr, indices)
    np.testing.assert_array_equal(order, np.argsort(colors, kind="stable"))
    np.testing.assert_array_equal(np.diff(ptr), np.bincount(colors, minlength=n_colors))
    assert ptr[0] == 0
    assert ptr[-1] == mesh.n_vertices
    assert colors.max() == n_colors - 1
    t = mesh.triangles  # no two vertices of a triangle share a colour
    c = colors[t]
    assert np.all((c[:, 0] != c[:, 1]) & (c[:, 1] != c[:, 2]) & (c[:, 0] != c[:, 2]))
