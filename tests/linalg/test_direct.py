"""fastmem.direct: nested-dissection factorisation independent of the vertex numbering."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from meshes import gmsh_square

import fastmem as fm
from fastmem.errors import DataError, InputTypeError, ParameterError
from fastmem.linalg.direct import ORDERINGS, factorize, fill_reducing_order
from fastmem.solver.linear import GeneralStep


def _permuted(mesh, seed=5):
    p = np.random.default_rng(seed).permutation(mesh.n_vertices)
    inv = np.empty_like(p)
    inv[p] = np.arange(p.size)
    return fm.Mesh(mesh.vertices[p], inv[mesh.triangles])


def _laplacian(mesh):
    ii = mesh.interior_vertices
    return fm.Scene(mesh).stiffness[ii][:, ii].tocsr(), mesh.vertices[ii]


def _reduced(mesh):
    """P^T K P of the general step with the active set |x| < 0.5 (and its coordinates)."""
    step = GeneralStep(fm.Scene(mesh, mu=(1.0, 2.0), f=(-1.0, 1.0), g=0.1))
    xy = mesh.vertices[mesh.interior_vertices]
    active = np.hypot(*xy.T) < 0.5
    p = step.prolongation(active)
    return (p.T @ step.k_ii @ p).tocsr(), np.vstack([xy, xy[~active]])


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    square = fm.Mesh.square(24)
    return {
        "structured": square,
        "refined": fm.Mesh.square(6).refine().refine(),
        "permuted": _permuted(square),
        "gmsh": gmsh_square(0.09, tmp_path_factory.mktemp("gmsh")),
    }


@pytest.mark.parametrize("kind", ["structured", "refined", "permuted", "gmsh"])
@pytest.mark.parametrize("system", [_laplacian, _reduced])
@pytest.mark.parametrize("with_coordinates", [True, False])
def test_solve_matches_spsolve(meshes, kind, system, with_coordinates):
    a, xy = system(meshes[kind])
    rhs = np.random.default_rng(3).standard_normal(a.shape[0])
    lu = factorize(a, xy if with_coordinates else None)
    x = lu.solve(rhs)
    ref = spla.spsolve(a.tocsc(), rhs)
    assert np.linalg.norm(x - ref) <= 1e-10 * np.linalg.norm(ref)
    assert lu.ordering == ORDERINGS[0 if with_coordinates else 1]
    assert isinstance(lu.fill, int)
    assert lu.fill >= a.shape[0]
    assert lu.seconds >= 0.0
    assert lu.seconds == pytest.approx(lu.order_seconds + lu.factor_seconds)


@pytest.mark.parametrize("with_coordinates", [True, False])
def test_renumbering_is_a_permutation(meshes, with_coordinates):
    a, xy = _reduced(meshes["gmsh"])
    blocks = sp.block_diag([a, sp.identity(3), a]).tocsr()  # disconnected parts, lone vertices
    coords = np.vstack([xy, np.zeros((3, 2)), xy + 5.0])
    for mat, c in ((a, xy), (blocks, coords)):
        perm, name = fill_reducing_order(mat, c if with_coordinates else None)
        assert perm.dtype == np.int64
        np.testing.assert_array_equal(np.sort(perm), np.arange(mat.shape[0]))
        assert name == ORDERINGS[0 if with_coordinates else 1]
        assert np.array_equal(factorize(mat, c if with_coordinates else None).perm, perm)


def test_degenerate_graphs_are_ordered():
    n = 200
    star = sp.lil_matrix((n, n))  # arrow matrix: one vertex joined to every other
    star.setdiag(float(n))
    star[0, 1:] = 1.0
    star[1:, 0] = 1.0
    path = sp.diags([-np.ones(n - 1), 3 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1])
    same_point = np.zeros((n, 2))  # all coordinates equal: median cuts by position only
    for mat in (star.tocsr(), path.tocsr(), sp.identity(n).tocsr()):
        for c in (None, same_point, np.arange(n, dtype=float)):
            perm, _ = fill_reducing_order(mat, c)
            np.testing.assert_array_equal(np.sort(perm), np.arange(n))
            rhs = np.arange(n, dtype=float)
            x = factorize(mat, c).solve(rhs)
            np.testing.assert_allclose(mat @ x, rhs, rtol=0, atol=1e-12 * n)
    x = factorize(np.array([[2.0]])).solve(np.array([4.0]))  # a 1x1 dense matrix
    np.testing.assert_array_equal(x, [2.0])


@pytest.mark.parametrize("with_coordinates", [True, False])
def test_fill_does_not_depend_on_the_numbering(meshes, with_coordinates):
    """Refined and structured meshes of the same size (129 x 129 in the issue, 25 x 25 here)."""
    fills = {}
    for kind in ("structured", "refined", "permuted", "gmsh"):
        for system in (_laplacian, _reduced):
            a, xy = system(meshes[kind])
            fills[kind, system.__name__] = factorize(a, xy if with_coordinates else None).fill
    for system in ("_laplacian", "_reduced"):
        base = fills["structured", system]
        for kind in ("refined", "permuted", "gmsh"):
            assert 0.5 <= fills[kind, system] / base <= 2.0, (kind, system, fills)
        if with_coordinates:  # the same graph and points under another numbering
            assert fills["permuted", system] == base


def test_matrix_is_not_modified_and_zeros_are_dropped():
    a, xy = _laplacian(fm.Mesh.square(8))  # right angles: explicit zeros in the pattern
    assert (a.data == 0).any()
    before = a.copy()
    lu = factorize(a, xy)
    assert (a != before).nnz == 0
    assert a.nnz == before.nnz
    dropped = a.copy()
    dropped.eliminate_zeros()
    assert lu.fill == factorize(dropped, xy).fill


def test_matrix_rhs_and_dense_input():
    a, xy = _laplacian(fm.Mesh.square(6))
    lu = factorize(a.toarray(), xy)
    rhs = np.random.default_rng(0).standard_normal((a.shape[0], 3))
    np.testing.assert_allclose(a @ lu.solve(rhs), rhs, atol=1e-12)
    assert "Factorization(n=25" in repr(lu)


def test_bad_input_names_the_value():
    a, xy = _laplacian(fm.Mesh.square(6))
    with pytest.raises(ParameterError, match=r"square, got shape \(25, 24\)"):
        factorize(a[:, :24])
    with pytest.raises(ParameterError, match=r"\(0, 0\)"):
        factorize(sp.csr_matrix((0, 0)))
    with pytest.raises(InputTypeError, match="2-D"):
        factorize(np.ones(4))
    with pytest.raises(InputTypeError, match="numeric"):
        factorize(np.array([["a"]]))
    bad = a.copy()
    bad.data[0] = np.nan
    with pytest.raises(DataError, match="non-finite"):
        factorize(bad)
    with pytest.raises(ParameterError, match=r"coordinates must have shape \(25, d\).*\(24, 2\)"):
        factorize(a, xy[:24])
    with pytest.raises(DataError, match="coordinates"):
        factorize(a, np.full_like(xy, np.inf))
    with pytest.raises(InputTypeError, match="coordinates"):
        factorize(a, xy.astype(complex))
    lu = factorize(a, xy)
    with pytest.raises(ParameterError, match=r"length 25 .*got shape \(24,\)"):
        lu.solve(np.ones(24))
    with pytest.raises(ParameterError, match=r"got shape \(25, 1, 1\)"):
        lu.solve(np.ones((25, 1, 1)))
    with pytest.raises(DataError, match="rhs"):
        lu.solve(np.full(25, np.nan))
    with pytest.raises(InputTypeError, match="rhs"):
        lu.solve(np.array(["x"] * 25))
