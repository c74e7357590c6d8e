import naive
import numba
import numpy as np
import pytest
import scipy.sparse as sp
from meshes import perturbed_square
from numpy.testing import assert_allclose

import fastmem as fm
from fastmem.fem.assembly import assemble_load, assemble_mass, assemble_stiffness
from fastmem.fem.quadrature import triangle_rule
from fastmem.mesh import refine_marked
from fastmem.mesh.pattern import csr_structure

MESHES = {
    "square-right": lambda: fm.Mesh.square(5, diagonal="right"),
    "square-symmetric": lambda: fm.Mesh.square(6),
    "lshape": lambda: fm.Mesh.lshape(4),
    "perturbed": lambda: perturbed_square(6, 0.3),
    "refined-perturbed": lambda: perturbed_square(3, 0.3).refine(),
}


def _rel(a, b):
    a = a.toarray() if hasattr(a, "toarray") else np.asarray(a)
    b = b.toarray() if hasattr(b, "toarray") else np.asarray(b)
    return np.abs(a - b).max() / np.abs(b).max()


@pytest.mark.parametrize("name", sorted(MESHES))
def test_stiffness_and_mass_match_naive(name):
    mesh = MESHES[name]()
    assert _rel(assemble_stiffness(mesh), naive.stiffness(mesh.vertices, mesh.triangles)) < 1e-12
    assert _rel(assemble_mass(mesh), naive.mass(mesh.vertices, mesh.triangles)) < 1e-12


def test_per_triangle_coefficient(rng):
    mesh = perturbed_square(5, 0.3)
    coef = rng.uniform(0.1, 10.0, mesh.n_triangles)
    ref = naive.stiffness(mesh.vertices, mesh.triangles, coef)
    assert _rel(assemble_stiffness(mesh, coef), ref) < 1e-12


def test_matches_scikit_fem_on_unstructured(unstructured_mesh):
    skfem = pytest.importorskip("skfem")
    from skfem.models.poisson import laplace, mass

    mesh = unstructured_mesh
    basis = skfem.Basis(
        skfem.MeshTri(mesh.vertices.T.copy(), mesh.triangles.T.copy()), skfem.ElementTriP1()
    )
    assert _rel(assemble_stiffness(mesh), laplace.assemble(basis)) < 1e-12
    assert _rel(assemble_mass(mesh), mass.assemble(basis)) < 1e-12


def test_pattern_is_vertex_graph():
    mesh = perturbed_square(4, 0.2)
    indptr, indices, offsets = csr_structure(mesh)
    n = mesh.n_vertices
    assert indptr[-1] == n + 2 * mesh.n_edges
    for a in range(n):  # tiny mesh: rows sorted, diagonal present, neighbours exactly the edges
        row = indices[indptr[a] : indptr[a + 1]]
        assert np.all(np.diff(row) > 0)
        nb = set(mesh.edges[mesh.edges[:, 0] == a, 1]) | set(mesh.edges[mesh.edges[:, 1] == a, 0])
        assert set(row.tolist()) == nb | {a}
    t = mesh.triangles
    pos = indptr[t[:, :, None]] + offsets  # (M, 3, 3)
    assert np.array_equal(indices[pos], np.broadcast_to(t[:, None, :], pos.shape))
    assert csr_structure(mesh) is csr_structure(mesh)  # cached


def test_pattern_matches_the_triangle_pairs_in_several_chunks():
    """The rows built from the patches in vertex chunks: scipy's pattern of all triangle pairs."""
    base = fm.Mesh.square(96)  # 9,409 vertices: more than one chunk of the kernel threads
    marked = np.zeros(base.n_triangles, dtype=bool)
    marked[::7] = True
    mesh = refine_marked(base, marked)[0]  # refined: patches of unequal sizes
    indptr, indices, _ = csr_structure(mesh)
    t = mesh.triangles
    rows = np.repeat(t, 3, axis=1).ravel()
    cols = np.tile(t, (1, 3)).ravel()
    ref = sp.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(mesh.n_vertices,) * 2).tocsr()
    ref.sum_duplicates()
    ref.sort_indices()
    assert indptr.dtype == indices.dtype == np.int32
    np.testing.assert_array_equal(indptr, ref.indptr)
    np.testing.assert_array_equal(indices, ref.indices)


def test_stiffness_properties():
    mesh = perturbed_square(8, 0.3)
    a = assemble_stiffness(mesh)
    assert_allclose(a @ np.ones(mesh.n_vertices), 0.0, atol=1e-12)  # constants in the kernel
    assert abs(a - a.T).max() < 1e-14
    x, y = mesh.vertices.T
    # a(u, v) = integral grad u . grad v for linear u = x, v = x + 2y: |Omega| * (1)
    assert_allclose(x @ (a @ (x + 2 * y)), 4.0, rtol=1e-12)
    m = assemble_mass(mesh)
    assert_allclose(np.ones(mesh.n_vertices) @ (m @ np.ones(mesh.n_vertices)), 4.0, rtol=1e-13)
    assert_allclose(np.asarray(m.sum(axis=1)).ravel(), mesh.lumped_mass, rtol=1e-12)


def test_loads_constant_vertex_callable(rng):
    mesh = perturbed_square(6, 0.3)
    assert_allclose(assemble_load(mesh, 2.5), 2.5 * mesh.lumped_mass, rtol=1e-15)
    fv = rng.standard_normal(mesh.n_vertices)
    assert_allclose(assemble_load(mesh, fv), assemble_mass(mesh) @ fv, rtol=1e-12, atol=1e-14)

    def f(x, y):
        return np.sin(3 * x) * np.exp(y)

    bary, w = triangle_rule(5)
    ref = naive.load(mesh.vertices, mesh.triangles, f, bary, w)
    assert_allclose(assemble_load(mesh, f), ref, rtol=1e-12, atol=1e-15)


def test_callable_load_exact_for_polynomials():
    """f of degree 4: f * psi has degree 5, integrated exactly by the default rule."""
    skfem = pytest.importorskip("skfem")
    mesh = perturbed_square(5, 0.3)

    def f(x, y):
        return 1 + x**4 - 3 * x**2 * y**2 + y**3 - x * y

    basis = skfem.Basis(
        skfem.MeshTri(mesh.vertices.T.copy(), mesh.triangles.T.copy()),
        skfem.ElementTriP1(),
        intorder=10,
    )
    ref = skfem.LinearForm(lambda v, w: f(w.x[0], w.x[1]) * v).assemble(basis)
    assert_allclose(assemble_load(mesh, f), ref, rtol=1e-12, atol=1e-15)
    # ...and a P1 callable equals the per-vertex path
    x, y = mesh.vertices.T
    assert_allclose(
        assemble_load(mesh, lambda x, y: 1 + 2 * x - y),
        assemble_load(mesh, 1 + 2 * x - y),
        rtol=1e-12,
    )


def test_serial_and_parallel_agree_bitwise():
    mesh = perturbed_square(20, 0.3)
    old = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        a1 = assemble_stiffness(mesh).data.copy()
        f1 = assemble_load(mesh, lambda x, y: np.cos(x * y))
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        a2 = assemble_stiffness(mesh).data
        f2 = assemble_load(mesh, lambda x, y: np.cos(x * y))
    finally:
        numba.set_num_threads(old)
    assert np.array_equal(a1, a2)
    assert np.array_equal(f1, f2)


def test_fused_and_coo_routes_agree(rng):
    from fastmem.kernels.assembly import mass_local, stiffness_local

    from fastmem.fem.assembly import gather_to_csr

    mesh = perturbed_square(9, 0.3)
    coef = rng.uniform(0.5, 2.0, mesh.n_triangles)
    for c in (np.ones(1), coef):
        fused = assemble_stiffness(mesh, c if c.size > 1 else None)
        coo = gather_to_csr(mesh, stiffness_local(mesh.vertices, mesh.triangles, c))
        assert_allclose(fused.data, coo.data, rtol=1e-14, atol=1e-15)
        fused_m = assemble_mass(mesh, c if c.size > 1 else None)
        coo_m = gather_to_csr(mesh, mass_local(mesh.areas, c))
        assert_allclose(fused_m.data, coo_m.data, rtol=1e-14, atol=1e-17)
