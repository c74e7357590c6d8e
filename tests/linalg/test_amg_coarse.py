"""The coarsest multigrid level: sparse LU (the default) or dense Cholesky, the
pseudo-inverse where the matrix is singular."""

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
from numpy.testing import assert_allclose

import fastmem as fm
from fastmem.linalg import gmg
from fastmem.linalg.amg import (
    AMG_DEFAULTS,
    CoarseCholesky,
    CoarseDirect,
    _DenseCholesky,
    _PseudoInverse,
    amg_preconditioner,
    coarse_factor,
)
from fastmem.solver.nested import interpolation_matrix


def laplacian_1d(n, neumann=False):
    a = sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tolil()
    if neumann:  # singular: constants in the kernel
        a[0, 0] = a[n - 1, n - 1] = 1.0
    return a.tocsr()


def test_spd_matrix_is_solved_by_its_cholesky_factor():
    a = laplacian_1d(50)
    b = np.random.default_rng(0).random(50)
    solve = CoarseCholesky()
    x = solve(a, b)
    assert_allclose(a @ x, b, rtol=0, atol=1e-12)
    assert isinstance(solve._factor, _DenseCholesky)
    factor = solve._factor
    solve(a, 2 * b)
    assert solve._factor is factor  # kept for the same matrix object
    solve(a.copy(), b)
    assert solve._factor is not factor  # a new matrix: factored again


def test_singular_matrix_falls_back_to_the_pseudo_inverse():
    a = laplacian_1d(40, neumann=True)
    b = np.random.default_rng(1).random(40)
    b -= b.mean()  # in the range of a
    solve = CoarseCholesky()
    x = solve(a, b)
    assert isinstance(solve._factor, _PseudoInverse)
    assert_allclose(a @ x, b, rtol=0, atol=1e-10)
    assert abs(x.mean()) < 1e-12  # the minimum-norm solution, as pyamg's default


def test_default_hierarchy_uses_it_and_solves(monkeypatch):
    assert AMG_DEFAULTS["coarse_solver"] == "direct"
    calls = []
    original = CoarseDirect.__call__
    monkeypatch.setattr(
        CoarseDirect, "__call__", lambda self, a, b: calls.append(1) or original(self, a, b)
    )
    scene = fm.Scene(fm.Mesh.square(48), mu=(1.0, 1.0))
    ii = scene.mesh.interior_vertices
    a = scene.stiffness[ii][:, ii].tocsr()
    pre = amg_preconditioner(a, dict(AMG_DEFAULTS))
    b = np.ones(a.shape[0])
    x = np.zeros_like(b)
    for _ in range(30):  # stationary iteration with the V-cycle: converges
        x += pre(b - a @ x)
    assert np.linalg.norm(b - a @ x) < 1e-8 * np.linalg.norm(b)
    assert len(calls) >= 30  # one coarse solve per cycle, by CoarseDirect


def _fe_laplacian(n, rng=None):
    """The interior P1 Laplacian of Mesh.lshape(n), optionally randomly renumbered."""
    mesh = fm.Mesh.lshape(n)
    ii = mesh.interior_vertices
    a = fm.Scene(mesh, mu=(1.0, 1.0)).stiffness[ii][:, ii].tocsr()
    if rng is not None:
        p = rng.permutation(a.shape[0])
        a = a[p][:, p].tocsr()
    return a


@pytest.mark.parametrize("renumber", [False, True])
def test_sparse_lu_solves_like_the_dense_cholesky_factor(renumber):
    """The coarse LU against a dense Cholesky solve of the same SPD matrix (an
    independent path), on a 2-D finite-element Laplacian, numbered as built and
    randomly (SuperLU's ordering must not depend on it)."""
    rng = np.random.default_rng(3)
    a = _fe_laplacian(24, rng if renumber else None)
    b = rng.standard_normal(a.shape[0])
    x = coarse_factor(a).solve(b)
    ref = scipy.linalg.cho_solve(scipy.linalg.cho_factor(a.toarray()), b)
    assert_allclose(x, ref, rtol=1e-11, atol=1e-13 * np.abs(ref).max())
    assert_allclose(a @ x, b, rtol=0, atol=1e-10 * np.abs(b).max())


def test_direct_solver_keeps_its_factor_and_falls_back_on_singular_matrices():
    a = laplacian_1d(50)
    b = np.random.default_rng(0).random(50)
    solve = CoarseDirect()
    assert_allclose(a @ solve(a, b), b, rtol=0, atol=1e-12)
    factor = solve._factor
    solve(a, 2 * b)
    assert solve._factor is factor  # kept for the same matrix object
    solve(a.copy(), b)
    assert solve._factor is not factor
    # singular: the pure Neumann Laplacian (constants in its kernel)
    s = laplacian_1d(40, neumann=True)
    c = np.random.default_rng(1).random(40)
    c -= c.mean()
    x = CoarseDirect()(s, c)
    assert_allclose(s @ x, c, rtol=0, atol=1e-10)
    assert abs(x.mean()) < 1e-12  # the minimum-norm solution
    # numerically singular (a pivot at round-off, not exactly zero): also the pseudo-inverse
    t = s.astype(float).tolil()
    t[0, 0] += 1e-15
    y = coarse_factor(t.tocsr()).solve(c)
    assert np.all(np.isfinite(y))
    assert abs(y.mean()) < 1e-6
    assert coarse_factor(sp.csr_matrix((0, 0))).solve(np.zeros(0)).shape == (0,)


def test_nested_multigrid_factors_its_coarsest_level_by_sparse_lu(monkeypatch):
    """NestedMG factors its coarsest operator (here the 961 interior unknowns of
    Mesh.square(32), below COARSE_DIRECT) with coarse_factor, and that factor solves
    like a dense solve of the operator; the cycle then converges as a preconditioner."""
    seen = []

    def spy(a):
        factor = coarse_factor(a)
        seen.append((a, factor))
        return factor

    monkeypatch.setattr(gmg, "coarse_factor", spy)
    fine, coarse = fm.Mesh.square(64), fm.Mesh.square(32)
    ii, ci = fine.interior_vertices, coarse.interior_vertices
    a = fm.Scene(fine, mu=(1.0, 1.0)).stiffness[ii][:, ii].tocsr()
    a.eliminate_zeros()
    p = interpolation_matrix(coarse, fine)[ii][:, ci].tocsr()
    mg = gmg.NestedMG(a, gmg.NestedChain([p]))
    b = np.random.default_rng(4).standard_normal(a.shape[0])
    x = np.zeros_like(b)
    for _ in range(30):  # a stationary two-grid iteration: about 0.2 per step
        x += mg(b - a @ x)
    assert np.linalg.norm(b - a @ x) < 1e-8 * np.linalg.norm(b)
    assert len(seen) == 1
    op, factor = seen[0]
    assert op.shape[0] == ci.size <= gmg.COARSE_DIRECT
    c = np.random.default_rng(5).standard_normal(op.shape[0])
    assert_allclose(factor.solve(c), np.linalg.solve(op.toarray(), c), rtol=1e-10, atol=1e-12)
