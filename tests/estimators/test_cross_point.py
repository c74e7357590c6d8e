"""Divergence-free correction at non-quasi-monotone vertices (issue 16, fastmem.estimators.flux).

At a checkerboard cross point the patch fluxes leave an O(1) mismatch in the
first ring of triangles that does not decrease with h; the correction adds
curl(phi), phi in P2 on a few rings around such vertices and zero where the
region meets the rest of the mesh.  It must keep the flux H(div)-conforming
with the same divergence, leave everything outside the region alone, never
raise eta_F, and lower the checkerboard effectivity (limits from measured
values, never to be loosened).
"""

import numpy as np
import pytest
from meshes import perturbed_square
from test_bound import _checkerboard, _reference_error
from test_flux import _normal_jump

import fastmem as fm
import fastmem.estimators.flux as flux
from fastmem.estimators.bound import flux_terms


def _scene(mesh, mu1, f=(-1.0, 1.0)):
    return fm.Scene(mesh, mu=(mu1, 1.0), f=f, g=0.1)


def test_marks_exactly_the_checkerboard_cross_points():
    mesh = fm.Mesh.square(8)
    for c in (1e3, 1e-3, 1e6):
        marked = flux.cross_point_vertices(mesh, _checkerboard(mesh, c))
        xy = mesh.vertices[marked]
        expect = {(x, y) for x in (-0.5, 0.0, 0.5) for y in (-0.5, 0.0, 0.5)}
        assert {tuple(np.round(p, 12)) for p in xy} == expect
    # quasi-monotone or mild: nothing
    assert not flux.cross_point_vertices(mesh, _checkerboard(mesh, 5.0)).any()
    assert not flux.cross_point_vertices(mesh, 3.0).any()
    lsh = fm.Mesh.lshape(8)
    cen = lsh.vertices[lsh.triangles].mean(axis=1)
    assert not flux.cross_point_vertices(lsh, np.where(cen[:, 0] < 0, 1.0, 1e3)).any()


def _random_mu(mesh, seed=3):
    return np.where(np.random.default_rng(seed).random(mesh.n_triangles) < 0.5, 1.0, 1e3)


CASES = {
    "checker-structured": lambda: (fm.Mesh.square(12), _checkerboard, (-1.0, 1.0)),
    "checker-jittered": lambda: (perturbed_square(12, 0.3), _checkerboard, (-4.0, 2.0)),
    "random-jittered": lambda: (perturbed_square(10, 0.3), lambda m, c: _random_mu(m), (-4.0, 2.0)),
}


@pytest.mark.parametrize("name", list(CASES))
def test_correction_is_divergence_free_conforming_and_local(name, rng):
    mesh, mu_fn, f = CASES[name]()
    scene = _scene(mesh, mu_fn(mesh, 1e3), f)
    r = fm.solve(scene, method="exact")
    u1, u2, lam = r.u1, r.u2, r.lam.copy()
    lam[mesh.interior_vertices] += 0.2 * rng.standard_normal(mesh.interior_vertices.size)
    base = flux.reconstruct(scene, u1, u2, lam)
    rings = flux.cross_point_correction(scene, u1, u2, base, glob=False)
    corr = flux.cross_point_correction(scene, u1, u2, base)
    assert corr is not base
    marked = flux.cross_point_vertices(mesh, scene.mu1)
    assert marked.any()
    vm = marked.copy()
    for _ in range(flux.CROSS_POINT_RINGS):
        vm[mesh.triangles[vm[mesh.triangles].any(axis=1)].ravel()] = True
    region = vm[mesh.triangles].any(axis=1)
    # the rings alone: outside the region (and membrane 2, constant tension) nothing changes
    assert np.array_equal(rings.coef[0, ~region], base.coef[0, ~region])
    assert np.abs(rings.coef[0] - base.coef[0]).max() > 1e-6 * np.abs(base.coef[0]).max()
    # with the global stream function: membrane 2 untouched, membrane 1 changed outside too
    assert np.array_equal(corr.coef[1], base.coef[1])
    if (~region).any():
        assert np.abs(corr.coef[0, ~region] - base.coef[0, ~region]).max() > 0.0
    # same divergence everywhere (curl phi is divergence-free)
    tri = rng.integers(0, mesh.n_triangles, size=500)
    bary = rng.dirichlet(np.ones(3), size=500)
    pts = np.einsum("pk,pkc->pc", bary, mesh.vertices[mesh.triangles[tri]])
    d0 = base.divergence(0, tri, pts[:, 0], pts[:, 1])
    d1 = corr.divergence(0, tri, pts[:, 0], pts[:, 1])
    assert np.abs(d1 - d0).max() <= 1e-11 * np.abs(d0).max()
    # normal components continuous across every interior edge, the correction alone too
    jump, scale = _normal_jump(lambda t, x, y: corr.evaluate(0, t, x, y), mesh)
    assert jump <= 1e-11 * scale

    def diff(t, x, y):
        return corr.evaluate(0, t, x, y) - base.evaluate(0, t, x, y)

    jump_d, _ = _normal_jump(diff, mesh)
    assert jump_d <= 1e-11 * scale
    # eta_F cannot increase (phi = 0 is admissible), and it does decrease; the
    # global alternations lower it below the rings alone
    f_base = flux_terms(scene, u1, u2, base)[0]
    f_rings = flux_terms(scene, u1, u2, rings)[0]
    f_corr = flux_terms(scene, u1, u2, corr)[0]
    assert (f_corr**2).sum() <= (f_rings**2).sum() * (1 + 1e-12)
    assert (f_rings**2).sum() <= (f_base**2).sum() * (1 + 1e-12)
    assert (f_rings**2).sum() < 0.99 * (f_base**2).sum()


def test_skipped_for_constant_and_quasi_monotone_tensions():
    mesh = fm.Mesh.lshape(8)
    cen = mesh.vertices[mesh.triangles].mean(axis=1)
    for mu1 in (2.0, np.where(cen[:, 0] < 0, 1.0, 1e3)):
        scene = _scene(mesh, mu1)
        r = fm.solve(scene, method="exact")
        base = flux.reconstruct(scene, r.u1, r.u2, r.lam)
        assert flux.cross_point_correction(scene, r.u1, r.u2, base) is base


def test_checkerboard_flux_term_drops_at_n32():
    """eta_F of the checkerboard c = 1e3, n = 32: 0.0623 -> 0.0547 (measured)."""
    mesh = fm.Mesh.square(32)
    scene = _scene(mesh, _checkerboard(mesh, 1e3))
    r = fm.solve(scene, method="exact")
    base = flux.reconstruct(scene, r.u1, r.u2, r.lam)
    corr = flux.cross_point_correction(scene, r.u1, r.u2, base)
    fb = np.sqrt(sum((e**2).sum() for e in flux_terms(scene, r.u1, r.u2, base)))
    fc = np.sqrt(sum((e**2).sum() for e in flux_terms(scene, r.u1, r.u2, corr)))
    assert fc <= 0.885 * fb, (fb, fc)


#: eta / |||u_ref - u_h||| on the checkerboard mu1 in {1, 1e3}, mu2 = 1, g = 0.1,
#: f = (-1, 1), u_ref 3 refinements finer, measured with the cross-point
#: correction (issue 16); limits = measured + 1 %, never to be loosened.
#: Without the correction: 1.31 (n = 16), 1.69 / 1.81 (n = 32, exact / inexact).
CROSS_POINT_EFFECTIVITY = {
    (16, "exact"): 1.2385,
    (16, "inexact"): 1.2385,
    (32, "exact"): 1.4843,
    (32, "inexact"): 1.5670,
}


@pytest.mark.parametrize("n", [16, 32])
def test_checkerboard_effectivity_with_correction(n):
    mesh = fm.Mesh.square(n)
    mu1 = _checkerboard(mesh, 1e3)

    def build(m, k=1):
        return _scene(m, np.repeat(mu1, k))

    err = _reference_error(mesh, 3, build)
    for method in ("exact", "inexact"):
        r = fm.solve(build(mesh), method=method, estimate=True)
        eff = r.eta / err(r.u1, r.u2)
        assert 1.0 <= eff <= 1.01 * CROSS_POINT_EFFECTIVITY[(n, method)], (method, eff)


def _marked_by_angle_sort(mesh, mu, contrast=flux.CROSS_POINT_CONTRAST):
    """Plain reference: sort each patch by angle, count the runs of high triangles."""
    out = np.zeros(mesh.n_vertices, dtype=bool)
    cen = mesh.vertices[mesh.triangles].mean(axis=1)
    for a in mesh.interior_vertices:
        tris = mesh.patch_triangles[mesh.patch_ptr[a] : mesh.patch_ptr[a + 1]]
        d = cen[tris] - mesh.vertices[a]
        m = mu[tris[np.argsort(np.arctan2(d[:, 1], d[:, 0]))]]
        if m.max() < contrast * m.min():
            continue
        high = m >= np.sqrt(m.max() * m.min())
        runs = sum(1 for k in range(m.size) if high[k] and not high[k - 1])
        out[a] = runs >= 2
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_marking_by_edge_transitions_matches_angle_sort(seed):
    rng = np.random.default_rng(seed)
    for mesh in (fm.Mesh.square(10), perturbed_square(11, 0.3, seed=seed), fm.Mesh.lshape(6)):
        for mu in (
            _checkerboard(mesh, 1e3),
            np.where(rng.random(mesh.n_triangles) < 0.5, 1.0, 1e3),
            10.0 ** rng.uniform(-3, 3, mesh.n_triangles),
        ):
            want = _marked_by_angle_sort(mesh, mu)
            assert np.array_equal(flux.cross_point_vertices(mesh, mu), want)
        assert 0 < want.sum() < mesh.n_vertices  # the random fields mark some, not all


def test_setup_cached_per_scene():
    mesh = fm.Mesh.square(12)
    scene = _scene(mesh, _checkerboard(mesh, 1e3))
    r = fm.solve(scene, method="exact", estimate=False)
    base = flux.reconstruct(scene, r.u1, r.u2, r.lam)
    first = flux.cross_point_correction(scene, r.u1, r.u2, base)
    setup = scene._cache[("cross_point", 0, flux.CROSS_POINT_RINGS)]
    assert setup is not None
    assert scene._cache[("cross_point", 1, flux.CROSS_POINT_RINGS)] is None
    again = flux.cross_point_correction(scene, r.u1, r.u2, base)
    assert scene._cache[("cross_point", 0, flux.CROSS_POINT_RINGS)] is setup
    assert np.array_equal(first.coef, again.coef)
    # a fresh scene (no cache) gives the same correction
    fresh = flux.cross_point_correction(_scene(mesh, scene.mu1), r.u1, r.u2, base)
    assert np.array_equal(first.coef, fresh.coef)
