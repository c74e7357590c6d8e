"""Auxiliary coarse meshes: nested iteration for meshes that did not come from refinement."""

import numpy as np
import pytest
from fastmem.kernels.coarsen import independent_set
from meshes import circle_mesh, perturbed_square
from numpy.testing import assert_allclose

import fastmem as fm
from fastmem.mesh.coarsen import coarse_mesh, locate
from fastmem.mesh.pattern import csr_structure
from fastmem.solver.nested import coarse_scenes, interpolation_matrix


def _plain(mesh):
    """The same mesh without its coarse recipe or parent."""
    return fm.Mesh(mesh.vertices, mesh.triangles)


def test_independent_set_is_maximal_and_independent(rng):
    mesh = perturbed_square(12, 0.2)
    indptr, indices, _ = csr_structure(mesh)
    order = rng.permutation(mesh.n_vertices).astype(np.int64)
    taken = independent_set(indptr, indices, order)
    for v in range(mesh.n_vertices):
        nbrs = indices[indptr[v] : indptr[v + 1]]
        nbrs = nbrs[nbrs != v]
        if taken[v]:
            assert not taken[nbrs].any()  # independent
        else:
            assert taken[nbrs].any()  # maximal


@pytest.mark.parametrize(
    "make",
    [
        lambda: perturbed_square(32, 0.2),
        lambda: _plain(fm.Mesh.lshape(24)),
        lambda: circle_mesh(4),
    ],
    ids=["perturbed-square", "lshape", "disk"],
)
def test_coarse_mesh_covers_the_domain_with_fine_vertices(make):
    fine = make()
    cmap = coarse_mesh(fine)
    assert cmap is not None
    coarse = cmap.mesh
    assert 0.15 < coarse.n_vertices / fine.n_vertices < 0.4
    assert_allclose(coarse.vertices, fine.vertices[cmap.vertex], rtol=0, atol=0)
    # every coarse triangle lies in the fine domain (its centroid is in triangle cmap.triangle)
    cent = coarse.vertices[coarse.triangles].mean(axis=1)
    tri, bary = locate(fine, cent)
    assert np.array_equal(tri, cmap.triangle)
    assert bary.min() >= -1e-12
    # polygonal domains are reproduced exactly; a disk by an inscribed polygon
    area_f, area_c = fine.areas.sum(), coarse.areas.sum()
    assert area_c <= area_f * (1 + 1e-12)
    assert area_c > 0.98 * area_f
    # shape regularity comparable to the fine mesh (Delaunay of well-spaced points)
    quality = lambda m: np.min(2 * m.areas / m.diameters**2)  # noqa: E731
    assert quality(coarse) > 0.3 * quality(fine)


def _cut(mesh, drop):
    """Mesh without the triangles whose centroid satisfies ``drop(x, y)``."""
    cen = mesh.vertices[mesh.triangles].mean(axis=1)
    return fm.Mesh._compact(mesh.vertices, mesh.triangles[~drop(cen[:, 0], cen[:, 1])])


@pytest.mark.parametrize(
    "drop",
    [
        lambda x, y: (np.abs(x) < 0.25) & (np.abs(y) < 0.25),  # square hole
        lambda x, y: np.abs(x) < 0.2,  # two strips, 0.4 apart
        lambda x, y: (np.abs(x) < 0.1) & (y > -0.5),  # a slit two cells wide
    ],
    ids=["hole", "two-parts", "slit"],
)
def test_coarse_mesh_stays_inside_holes_gaps_and_slits(drop):
    fine = _cut(fm.Mesh.square(24), drop)
    coarse = coarse_mesh(fine).mesh
    assert_allclose(coarse.areas.sum(), fine.areas.sum(), rtol=1e-12)
    probes = coarse.vertices[coarse.triangles].mean(axis=1)
    assert not drop(probes[:, 0], probes[:, 1]).any()


def test_interpolation_refuses_points_outside_a_non_auxiliary_coarse_mesh():
    coarse = fm.Mesh.square(4)
    fine = fm.Mesh(1.01 * fm.Mesh.square(8).vertices, fm.Mesh.square(8).triangles)
    with pytest.raises(fm.errors.MeshError, match="outside the coarse mesh"):
        interpolation_matrix(coarse, fine)


def test_coarse_mesh_failure_falls_back_to_none(monkeypatch):
    import fastmem.mesh.coarsen as coarsen

    def broken(*args, **kwargs):
        raise MemoryError("no room for Qhull")

    monkeypatch.setattr(coarsen, "_coarse_mesh", broken)
    fine = perturbed_square(40, 0.2)
    assert coarse_mesh(fine) is None
    r = fm.solve(fm.Scene(fine, f=(-1.0, 1.0), g=0.1))  # unconstrained start instead
    assert r.converged
    assert len(r.parameters["solver"]["levels"]) == 1


def test_nodal_g_moves_by_its_boundary_values():
    fine = perturbed_square(40, 0.2)
    g = np.full(fine.n_vertices, -5.0)  # interior entries are ignored by the Scene
    g[fine.boundary_vertices] = 0.1
    chain = coarse_scenes(fm.Scene(fine, f=(-1.0, 1.0), g=g), auxiliary=True)
    top = chain[-1]
    assert_allclose(top.boundary_values[top.mesh.boundary_vertices], 0.1)


def test_coarse_mesh_keeps_corners():
    fine = _plain(fm.Mesh.lshape(16))
    coarse = coarse_mesh(fine).mesh
    corners = np.array([[-1, -1], [0, -1], [0, 0], [1, 0], [1, 1], [-1, 1]], dtype=float)
    for c in corners:
        assert np.min(np.linalg.norm(coarse.vertices - c, axis=1)) == 0.0
    assert_allclose(coarse.areas.sum(), 3.0, rtol=1e-13)


def test_interpolation_from_an_inscribed_coarse_mesh():
    """Fine vertices outside the coarse disk still get convex weights; linears are exact inside."""
    fine = circle_mesh(4)
    coarse = coarse_mesh(fine).mesh
    mat = interpolation_matrix(coarse, fine)
    assert_allclose(mat.sum(axis=1).A.ravel(), 1.0, rtol=1e-13)
    assert mat.min() >= -1e-14
    lin = lambda p: 1.0 + 2.0 * p[:, 0] - 3.0 * p[:, 1]  # noqa: E731
    vals = mat @ lin(coarse.vertices)
    tri, bary = locate(coarse, fine.vertices)
    back = np.einsum("pk,pkd->pd", bary, coarse.vertices[coarse.triangles[tri]])
    inside = np.linalg.norm(back - fine.vertices, axis=1) < 1e-12
    assert inside.mean() > 0.9
    assert_allclose(vals[inside], lin(fine.vertices)[inside], rtol=1e-12, atol=1e-12)


def test_data_move_to_the_auxiliary_chain(rng):
    fine = perturbed_square(40, 0.2)
    mu2 = rng.uniform(1.0, 3.0, fine.n_triangles)
    f1 = -1.0 - 0.1 * fine.vertices[:, 0]
    scene = fm.Scene(fine, mu=(1.0, mu2), f=(f1, 1.0), g=0.1)
    chain = coarse_scenes(scene, auxiliary=True)
    assert len(chain) >= 1
    assert coarse_scenes(scene) == []  # without auxiliary meshes: no chain
    top = chain[-1]
    # nodal data restrict by vertex, per-triangle data by the triangle under the centroid
    cent = top.mesh.vertices[top.mesh.triangles].mean(axis=1)
    tri, _ = locate(fine, cent)
    assert_allclose(top.mu2, mu2[tri])
    idx = np.array([np.flatnonzero((fine.vertices == p).all(axis=1))[0] for p in top.mesh.vertices])
    assert_allclose(top.f1, f1[idx])


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["default", "manufactured"])
def test_auxiliary_nested_iteration_saves_newton_steps(kind):
    fine = perturbed_square(96, 0.2)
    if kind == "default":
        scene = fm.Scene(fine, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    else:
        ms = fm.Manufactured()
        scene = ms.scene(fine)
    cold = fm.solve(scene, nested=False)
    warm = fm.solve(scene)  # nested="auto": auxiliary coarse meshes
    levels = warm.parameters["solver"]["levels"]
    assert len(levels) >= 3
    assert cold.converged
    assert warm.converged
    assert warm.n_newton <= 6
    assert warm.n_newton < cold.n_newton / 2
    assert warm.eta <= 1.05 * cold.eta
    if kind == "manufactured":
        e_warm = ms.energy_error(fine, warm.u1, warm.u2)
        e_cold = ms.energy_error(fine, cold.u1, cold.u2)
        assert abs(e_warm - e_cold) <= 0.05 * e_cold
        assert warm.eta >= e_warm
