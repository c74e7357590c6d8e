"""The coarsest AMG level: dense Cholesky, the pseudo-inverse where it is not SPD."""

import numpy as np
import scipy.sparse as sp
from numpy.testing import assert_allclose

import fastmem as fm
from fastmem.linalg.amg import AMG_DEFAULTS, CoarseCholesky, amg_preconditioner


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
    assert solve._factor is not None
    assert solve._pinv is None
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
    assert solve._factor is None
    assert solve._pinv is not None
    assert_allclose(a @ x, b, rtol=0, atol=1e-10)
    assert abs(x.mean()) < 1e-12  # the minimum-norm solution, as pyamg's default


def test_default_hierarchy_uses_it_and_solves(monkeypatch):
    assert AMG_DEFAULTS["coarse_solver"] == "cholesky"
    calls = []
    original = CoarseCholesky.__call__
    monkeypatch.setattr(
        CoarseCholesky, "__call__", lambda self, a, b: calls.append(1) or original(self, a, b)
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
    assert len(calls) >= 30  # one coarse solve per cycle, by CoarseCholesky
