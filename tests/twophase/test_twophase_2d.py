"""The 2D vertex-centred scheme, the block ILU(0) kernel and CPR."""

import numpy as np
import pytest
import scipy.sparse as sp
from fastmem.kernels.bilu import bilu0_factor, bilu0_solve
from scipy.sparse.linalg import spsolve

import fastmem as fm
from fastmem.errors import ParameterError
from fastmem.fem.assembly import assemble_stiffness
from fastmem.twophase import YEAR, Grid, Physics, Problem, mesh_grid, section, simulate
from fastmem.twophase.linear import gmres, preconditioner
from fastmem.twophase.newton import _ORDER


def _reference_bilu0(indptr, indices, blocks):
    """Block ILU(0) written out with dictionaries: the kernel's independent twin."""
    n = indptr.size - 1
    rows = [
        {int(indices[p]): blocks[p].copy() for p in range(indptr[i], indptr[i + 1])}
        for i in range(n)
    ]
    for i in range(n):
        for k in sorted(c for c in rows[i] if c < i):
            rows[i][k] = rows[i][k] @ np.linalg.inv(rows[k][k])
            for j, ukj in rows[k].items():
                if j > k and j in rows[i]:
                    rows[i][j] = rows[i][j] - rows[i][k] @ ukj
    return rows


def _reference_solve(rows, r):
    n = len(rows)
    y = r.reshape(n, -1).copy()
    for i in range(n):
        for k, lik in rows[i].items():
            if k < i:
                y[i] -= lik @ y[k]
    for i in range(n - 1, -1, -1):
        acc = y[i].copy()
        for j, uij in rows[i].items():
            if j > i:
                acc -= uij @ y[j]
        y[i] = np.linalg.solve(rows[i][i], acc)
    return y.ravel()


def _random_block_matrix(n_side, seed=0):
    """A block-sparse 2D five-point pattern with 3 x 3 blocks, diagonally dominant blocks."""
    rng = np.random.default_rng(seed)
    n = n_side * n_side
    idx = np.arange(n).reshape(n_side, n_side)
    pairs = [(idx[:, :-1].ravel(), idx[:, 1:].ravel()), (idx[:-1].ravel(), idx[1:].ravel())]
    i = np.concatenate([np.arange(n)] + [p for a, b in pairs for p in (a, b)])
    j = np.concatenate([np.arange(n)] + [p for a, b in pairs for p in (b, a)])
    blocks = rng.standard_normal((i.size, 3, 3))
    blocks[:n] += 8 * np.eye(3)
    return _assemble(i, j, blocks, n)


def _assemble(i, j, blocks, n):
    """The 3n x 3n BSR matrix with block ``blocks[e]`` at block position ``(i[e], j[e])``."""
    rows = (3 * i[:, None, None] + np.arange(3)[None, :, None]).repeat(3, 2).ravel()
    cols = (3 * j[:, None, None] + np.arange(3)[None, None, :]).repeat(3, 1).ravel()
    a = sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(3 * n, 3 * n))
    bsr = a.tobsr(blocksize=(3, 3))
    bsr.sort_indices()
    return bsr


def test_block_ilu_kernel_against_its_reference():
    bsr = _random_block_matrix(6)
    indptr, indices = bsr.indptr.astype(np.int64), bsr.indices.astype(np.int64)
    blocks = bsr.data.copy()  # the kernel factors in place
    ref = _reference_bilu0(indptr, indices, blocks)
    diag_pos, inv_diag, singular = bilu0_factor(indptr, indices, blocks)
    assert singular == -1
    r = np.random.default_rng(1).standard_normal(bsr.shape[0])
    z = bilu0_solve(indptr, indices, blocks, diag_pos, inv_diag, r)
    assert np.allclose(z, _reference_solve(ref, r), rtol=1e-11, atol=1e-12)
    # it is an incomplete factorisation: not the inverse of the 2D matrix
    assert np.linalg.norm(bsr @ z - r) > 1e-6 * np.linalg.norm(r)


def test_block_ilu_is_exact_on_a_block_tridiagonal_matrix():
    n = 40
    rng = np.random.default_rng(2)
    i = np.r_[np.arange(n), np.arange(n - 1), np.arange(1, n)]
    j = np.r_[np.arange(n), np.arange(1, n), np.arange(n - 1)]
    blocks = rng.standard_normal((i.size, 3, 3))
    blocks[:n] += 6 * np.eye(3)
    bsr = _assemble(i, j, blocks, n)
    a = bsr.tocsr()
    data = bsr.data.copy()
    ip, ix = bsr.indptr.astype(np.int64), bsr.indices.astype(np.int64)
    diag_pos, inv_diag, singular = bilu0_factor(ip, ix, data)
    r = rng.standard_normal(3 * n)
    z = bilu0_solve(ip, ix, data, diag_pos, inv_diag, r)
    assert np.allclose(z, spsolve(a.tocsc(), r), rtol=1e-10, atol=1e-12)


def test_mesh_grid_weights_are_the_p1_stiffness():
    mesh = fm.Mesh.rectangle(7, 5, (0.0, 3.0, 0.0, 2.0), diagonal="symmetric")
    fixed = np.isclose(mesh.vertices[:, 0], 3.0)
    grid, free, vb = mesh_grid(mesh, fixed)
    k = assemble_stiffness(mesh).tocsr()
    lo, hi = free[grid.faces[:, 0]], free[grid.faces[:, 1]]
    assert np.allclose(grid.geometry, -np.asarray(k[lo, hi]).ravel(), rtol=1e-12)
    assert np.allclose(
        grid.boundary_geometry, -np.asarray(k[free[grid.boundary_cells], vb]).ravel()
    )
    assert np.allclose(grid.volume, mesh.lumped_mass[free])
    # every nonzero off-diagonal coupling of a free vertex is a face
    kf = k[free][:, free].tocoo()
    off = (kf.row < kf.col) & (np.abs(kf.data) > 1e-12 * np.abs(kf.data).max())
    assert off.sum() == grid.faces.shape[0]


def test_mesh_grid_refuses_a_non_delaunay_mesh():
    v = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 0.1], [0.5, -0.1]])
    t = np.array([[0, 1, 2], [0, 3, 1]])
    mesh = fm.Mesh(v, t)
    with pytest.raises(ParameterError, match="not Delaunay"):
        mesh_grid(mesh, np.zeros(4, dtype=bool))


def _column_vertex_centred(length, n, physics, rate):
    """The 1D vertex-centred column: vertices x_i = i h, the last one Dirichlet."""
    h = length / n
    vol = np.full(n, h)
    vol[0] = h / 2
    cells = np.arange(n)
    grid = Grid(
        vol,
        cells * h,
        np.stack([cells[:-1], cells[1:]], axis=1),
        np.full(n - 1, 1 / h),
        [n - 1],
        [1 / h],
    )
    q = np.zeros(n)
    q[0] = rate / YEAR
    return Problem(grid, physics, hydrogen=q)


def test_section_with_the_whole_edge_injecting_is_the_vertex_centred_column():
    """Two independent paths: the 2D mesh scheme, y-invariant, against a 1D grid by hand."""
    nx, ny, length, height = 40, 3, 20.0, 1.5
    physics = Physics()
    rate = 5.57e-5
    prob2 = section(nx, ny, length=length, height=height, stretch=(0.0, height), injection=rate)
    prob1 = _column_vertex_centred(length, nx, physics, rate)
    t_end = 8 * 5000 * YEAR
    run2 = simulate(prob2, t_end=t_end, linear_solver="direct")
    run1 = simulate(prob1, t_end=t_end, linear_solver="direct")
    assert run1.gas_cells[-1] > 0
    x2 = run2.final.reshape(ny + 1, nx, 3)
    units = prob1.units()
    assert np.abs((x2 - x2[0]) / units).max() <= 1e-9  # y-invariant
    assert np.abs((x2[0] - run1.final) / units).max() <= 1e-9
    assert np.abs(run2.balance).max() <= 1e-12 * run2.injected[-1]


def _system(prob, steps):
    dt = 5000 * YEAR
    run = simulate(prob, t_end=steps * dt, linear_solver="direct", estimate=False)
    x = run.final
    gas = prob.gas(x)
    r = prob.residual(x, x, dt, (steps + 1) * dt, gas)
    jac = prob.jacobian(x, gas, dt)
    sc = prob.row_scales(dt, gas)
    a = (sp.diags(1 / sc.ravel()) @ jac @ sp.diags(np.tile(prob.units(), prob.grid.n))).tocsr()
    perm = (3 * np.arange(prob.grid.n)[:, None] + _ORDER).ravel()
    return a[perm].tocsr(), -(r.ravel() / sc.ravel())[perm], sc.ravel()[perm]


def test_cpr_needs_far_fewer_iterations_than_block_ilu_in_2d():
    """On a 120 x 12 section after 4 steps: 142 block-ILU iterations against 8 CPR ones
    (379 against 9 on 200 x 20, 6 s: the gap grows with the section)."""
    prob = section(120, 12)
    a, b, scales = _system(prob, 4)
    assert prob.gas(simulate(prob, t_end=4 * 5000 * YEAR, linear_solver="direct").final).any()
    its = {}
    for kind in ("ilu", "cpr"):
        m = preconditioner(kind, a, prob.grid.n, scales)
        y, stats = gmres(a, b, m, rtol=1e-8, maxiter=600, restart=100)
        assert np.linalg.norm(a @ y - b) <= 1e-7 * np.linalg.norm(b)
        its[kind] = stats.iterations
    assert 3 * its["cpr"] <= its["ilu"], its


def test_gmres_checks_after_each_drop_only():
    """``drop`` spares estimator checks while the residual has not fallen enough."""
    prob = section(60, 6)
    a, b, scales = _system(prob, 3)
    m = preconditioner("ilu", a, prob.grid.n, scales)
    calls = {1.0: [], 0.1: []}
    for drop, seen in calls.items():
        gmres(
            a,
            b,
            m,
            rtol=1e-12,
            maxiter=400,
            every=1,
            drop=drop,
            check=lambda x, k, s=seen: s.append(k) and False,
        )
    assert len(calls[0.1]) < len(calls[1.0])
    assert len(calls[1.0]) >= 10
