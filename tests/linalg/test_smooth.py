"""Threaded multigrid cycles: hybrid Gauss-Seidel and threaded CSR products (issue 15).

:class:`fastmem.linalg.amg.HybridGaussSeidel` sweeps fixed row blocks in parallel
(Gauss-Seidel inside a block, Jacobi across blocks); :class:`fastmem.linalg.sparse.ThreadedCSR`
computes ``A @ x`` over row chunks.  Checked against pyamg's and scipy's serial
kernels, for independence of the thread count, for the symmetry of the cycle
(CG needs an SPD preconditioner), and for the convergence test that keeps
pyamg's sweep where the hybrid one could fail.
"""

import numba
import numpy as np
import pytest
import scipy.sparse as sp
from fastmem.kernels.smooth import cross_block_dominant
from pyamg.relaxation.relaxation import gauss_seidel

import fastmem as fm
from fastmem.fem.assembly import assemble_stiffness
from fastmem.linalg import amg
from fastmem.linalg.amg import (
    AMG_DEFAULTS,
    HybridGaussSeidel,
    amg_preconditioner,
)
from fastmem.linalg.sparse import ThreadedCSR, as_unsigned, threaded
from fastmem.solver.steps import gap_matrix


def _laplacian(n):
    mesh = fm.Mesh.square(n)
    ii = mesh.interior_vertices
    a = assemble_stiffness(mesh)[ii][:, ii].tocsr()
    a.sort_indices()
    x, y = mesh.vertices[ii].T
    return a, x, y


@pytest.fixture
def threads():
    """Restore the Numba thread count a test changes."""
    before = numba.get_num_threads()
    yield
    numba.set_num_threads(before)


def test_one_block_is_pyamgs_symmetric_sweep():
    a, _, _ = _laplacian(48)
    b = np.random.default_rng(0).standard_normal(a.shape[0])
    x0 = np.random.default_rng(1).standard_normal(a.shape[0])
    ours, ref = x0.copy(), x0.copy()
    HybridGaussSeidel(1)(a, ours, b)
    gauss_seidel(a, ref, b, iterations=1, sweep="symmetric")
    np.testing.assert_array_equal(ours, ref)


def test_hybrid_sweep_is_the_block_formula():
    """Forward sweep = (D + L_B)^-1 (b - (U + L - L_B) x_old), checked with a dense solve."""
    a, _, _ = _laplacian(20)
    n, nb = a.shape[0], 3
    edges = [n * k // nb for k in range(nb + 1)]
    rng = np.random.default_rng(2)
    b, x0 = rng.standard_normal(n), rng.standard_normal(n)
    dense = a.toarray()
    block = np.searchsorted(edges, np.arange(n), side="right") - 1
    same = block[:, None] == block[None, :]
    lower_b = np.tril(dense, -1) * same
    m = np.diag(np.diag(dense)) + lower_b
    forward = np.linalg.solve(m, b - (dense - m) @ x0)
    upper_b = np.triu(dense, 1) * same
    m2 = np.diag(np.diag(dense)) + upper_b
    expected = np.linalg.solve(m2, b - (dense - m2) @ forward)
    got = x0.copy()
    HybridGaussSeidel(nb)(a, got, b)
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)


def test_cycle_does_not_depend_on_the_thread_count(threads):
    a, x, y = _laplacian(200)  # 39,601 rows: the finest level is swept by blocks
    g = gap_matrix(a, x * x + 0.7 * y * y < 0.3)
    pre = amg_preconditioner(g, dict(AMG_DEFAULTS))
    assert isinstance(pre.ml.levels[0].presmoother, HybridGaussSeidel)
    r = np.random.default_rng(3).standard_normal(a.shape[0])
    numba.set_num_threads(1)
    one = pre(r)
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    many = pre(r)
    np.testing.assert_array_equal(one, many)


def test_hybrid_cycle_is_a_symmetric_positive_definite_preconditioner():
    a, x, y = _laplacian(200)
    g = gap_matrix(a, x * x + 0.7 * y * y < 0.3)
    pre = amg_preconditioner(g, dict(AMG_DEFAULTS))
    assert isinstance(pre.ml.levels[0].presmoother, HybridGaussSeidel)
    rng = np.random.default_rng(4)
    for _ in range(3):
        u, v = rng.standard_normal((2, a.shape[0]))
        uv, vu = u @ pre(v), v @ pre(u)
        assert abs(uv - vu) <= 1e-12 * max(abs(uv), np.linalg.norm(u) * np.linalg.norm(pre(u)))
        assert u @ pre(u) > 0.0


def test_hybrid_smoother_keeps_cg_iterations():
    a, x, y = _laplacian(200)
    g = gap_matrix(a, x * x + 0.7 * y * y < 0.3)
    b = np.random.default_rng(5).standard_normal(a.shape[0])
    counts = {}
    for rows in (amg.HYBRID_BLOCK_ROWS, 10**12):
        old = amg.HYBRID_BLOCK_ROWS
        amg.HYBRID_BLOCK_ROWS = rows
        try:
            pre = amg_preconditioner(g, dict(AMG_DEFAULTS))
        finally:
            amg.HYBRID_BLOCK_ROWS = old
        counts[rows] = amg.PCG(g, b, np.zeros_like(b), pre).solve(1e-8, 300)
    hybrid, plain = counts[amg.HYBRID_BLOCK_ROWS], counts[10**12]
    assert hybrid <= plain + 1


def test_not_dominant_across_blocks_keeps_pyamgs_sweep():
    """Strong couplings between two blocks: the hybrid sweep is not installed there."""
    a, _, _ = _laplacian(200)
    n = a.shape[0]
    i, j, k = 10, n - 10, n - 20  # row i in the first block, j and k in the last
    # + E on (i, j, k), E = [[2, 3, 3], [3, 20, 0], [3, 0, 20]] positive definite: still SPD,
    # but row i has diagonal 4 + 2 = 6 against 3 + 3 = 6 outside its block
    e = sp.coo_matrix(
        ([2.0, 3.0, 3.0, 3.0, 20.0, 3.0, 20.0], ([i, i, i, j, j, k, k], [i, j, k, i, j, i, k])),
        shape=a.shape,
    )
    bad = (a + e).tocsr()
    assert np.all(np.linalg.eigvalsh(np.array([[2, 3, 3], [3, 20, 0], [3, 0, 20]])) > 0)
    assert not amg._hybrid_converges(bad, amg.hybrid_blocks(n))
    assert amg._hybrid_converges(a, amg.hybrid_blocks(n))
    pre = amg_preconditioner(bad, dict(AMG_DEFAULTS))
    assert not isinstance(pre.ml.levels[0].presmoother, HybridGaussSeidel)
    good = amg_preconditioner(a, dict(AMG_DEFAULTS))
    assert isinstance(good.ml.levels[0].presmoother, HybridGaussSeidel)


def _random_csr(rng, n=50_000, nnz=400_000):
    """A random n x n CSR matrix (duplicates summed), large enough for the threaded kernels."""
    rows, cols = rng.integers(0, n, (2, nnz))
    return sp.csr_matrix((rng.standard_normal(nnz), (rows, cols)), shape=(n, n))


def test_attainable_scale_equals_the_scipy_expression():
    """|A| |x| + |b| in the kernel threads, without |A|: the bits of abs(A) @ abs(x) + abs(b)."""
    from fastmem.linalg.amg import PCG

    rng = np.random.default_rng(7)
    m = _random_csr(rng)
    n = m.shape[0]
    t = threaded(m)
    x, b = rng.standard_normal(n), rng.standard_normal(n)
    want = abs(m) @ np.abs(x) + np.abs(b)
    np.testing.assert_array_equal(t.abs_product_plus(x, b), want)
    # and through the CG's attainable residual (fused for a ThreadedCSR, scipy's otherwise)
    spd = (m @ m.T + sp.identity(n) * 10.0).tocsr()
    fused = PCG(threaded(spd), b, x, lambda r: r)
    plain = PCG(spd, b, x, lambda r: r)
    assert isinstance(fused.a, ThreadedCSR)
    assert not isinstance(plain.a, ThreadedCSR)
    assert fused.attainable() == plain.attainable() > 0.0


def test_threaded_products_equal_scipys():
    rng = np.random.default_rng(6)
    m = _random_csr(rng)
    n = m.shape[0]
    t = threaded(m)
    assert isinstance(t, ThreadedCSR)
    x = rng.standard_normal(n)
    np.testing.assert_array_equal(t @ x, m @ x)
    frozen = x.copy()
    frozen.setflags(write=False)
    np.testing.assert_array_equal(t @ frozen, m @ x)
    # writable and read-only vectors reach the kernel with one type: one specialisation
    from fastmem.kernels.smooth import csr_matvec_range

    assert len(csr_matvec_range.signatures) == 1, csr_matvec_range.signatures
    assert x.flags.writeable  # the caller's vector is left writable
    np.testing.assert_array_equal(t @ x.reshape(-1, 1), m @ x.reshape(-1, 1))  # 2-D: scipy's
    np.testing.assert_array_equal(t.dot(x), m.dot(x))
    ints = np.arange(n)
    np.testing.assert_array_equal(t @ ints, m @ ints)  # not float64: scipy's path
    assert not isinstance(threaded(m[:100]), ThreadedCSR)  # small: left to scipy


@pytest.mark.parametrize("cycle", ["V", "W", "F"])
def test_direct_cycle_equals_pyamgs_preconditioner(cycle):
    """The cycle called directly (no solve loop) gives pyamg's preconditioner bit for bit."""
    a, x, y = _laplacian(64)
    pre = amg_preconditioner(gap_matrix(a, x * x + y * y < 0.3), {"cycle": cycle})
    assert pre._cycle is not None
    r = np.random.default_rng(8).standard_normal(a.shape[0])
    np.testing.assert_array_equal(pre(r), pre._op.matvec(r))


def test_concurrent_cycles_give_the_serial_result():
    """Two threads applying one hierarchy at once (the sweep's buffer is not shared)."""
    import concurrent.futures

    a, x, y = _laplacian(200)
    pre = amg_preconditioner(gap_matrix(a, x * x + 0.7 * y * y < 0.3), dict(AMG_DEFAULTS))
    assert isinstance(pre.ml.levels[0].presmoother, HybridGaussSeidel)
    rs = np.random.default_rng(9).standard_normal((6, a.shape[0]))
    serial = [pre(r) for r in rs]
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        for _ in range(3):
            got = list(pool.map(pre, rs))
            for z, ref in zip(got, serial, strict=True):
                np.testing.assert_array_equal(z, ref)


def test_smoothers_with_setup_data_are_not_updated():
    """Schwarz keeps a copy of the setup's matrix: no Galerkin update, a valid solve."""
    opts = {"presmoother": ("schwarz", {"sweep": "symmetric"})}
    opts["postsmoother"] = opts["presmoother"]
    a, x, y = _laplacian(32)
    pre = amg_preconditioner(gap_matrix(a, x * x < 0.3), dict(opts))
    assert not pre.can_update
    with pytest.raises(ValueError, match="setup"):
        pre.update(a, np.arange(1), sp.csr_matrix((1, 1)))
    scene = fm.Manufactured().scene(fm.Mesh.square(64))
    res = fm.solve(
        scene, method="exact-amg", path="decoupled", amg_options=opts, multigrid="algebraic"
    )
    assert sum(lv.get("amg_updates", 0) for lv in res.parameters["solver"]["levels"]) == 0
    ref = fm.solve(fm.Manufactured().scene(fm.Mesh.square(64)), method="exact")
    assert np.abs(res.u1 - ref.u1).max() <= 1e-9 * np.abs(ref.u1).max()
    assert np.array_equal(res.active, ref.active)


def test_vector_kernels_are_numpys_operations():
    """The CG's fused updates and the gap system's masking give NumPy's bits."""
    from fastmem.kernels import smooth

    rng = np.random.default_rng(11)
    n = 1000
    p, ap, x, r, z, diag = (rng.standard_normal(n) for _ in range(6))
    diag = np.abs(diag) + 0.1
    alpha, beta = 0.3711, -1.7
    x_k, r_k, p_k = x.copy(), r.copy(), p.copy()
    smooth.cg_update_range(0, n, alpha, p, ap, x_k, r_k)
    np.testing.assert_array_equal(x_k, x + alpha * p)
    np.testing.assert_array_equal(r_k, r - alpha * ap)
    smooth.cg_direction_range(0, n, beta, z, p_k)
    np.testing.assert_array_equal(p_k, p * beta + z)
    active = rng.random(n) < 0.4
    out = np.full(n, np.nan)
    smooth.masked_rhs_range(0, n, active, r, out)
    np.testing.assert_array_equal(out, np.where(active, 0.0, r))
    z_k, z_ref = z.copy(), z.copy()
    smooth.active_diagonal_range(0, n, active, r, diag, z_k)
    z_ref[active] = r[active] / diag[active]
    np.testing.assert_array_equal(z_k, z_ref)


def test_cg_with_fused_updates_is_the_numpy_cg(monkeypatch):
    """From THREADED_ROWS unknowns on, PCG updates its vectors in the kernel threads:
    every iterate has the bits of the NumPy updates."""
    a, _, _ = _laplacian(200)  # 39,601 unknowns
    assert a.shape[0] >= amg.THREADED_ROWS
    a = threaded(a)
    b = np.random.default_rng(12).standard_normal(a.shape[0])
    inv = 1.0 / a.diagonal()

    calls = []
    real = amg.cg_update_range

    def counting(*args):
        calls.append(1)
        return real(*args)

    monkeypatch.setattr(amg, "cg_update_range", counting)

    def run():
        cg = amg.PCG(a, b, np.zeros_like(b), lambda r: inv * r)
        xs = []
        for _ in range(6):
            assert cg.step()
            xs.append(cg.x.copy())
        return xs, cg.r.copy(), cg.p.copy()

    fused = run()
    assert calls  # the kernel path was taken
    calls.clear()
    monkeypatch.setattr(amg, "THREADED_ROWS", 1 << 60)
    plain = run()
    assert not calls  # and here the NumPy path
    for got, want in zip(
        fused[0] + [fused[1], fused[2]], plain[0] + [plain[1], plain[2]], strict=True
    ):
        np.testing.assert_array_equal(got, want)


def _dominant_numpy(a, n_blocks):
    """Reference of cross_block_dominant: each row's diagonal against its cross-block sum."""
    n = a.shape[0]
    edges = np.array([n * k // n_blocks for k in range(n_blocks + 1)])
    block = np.searchsorted(edges, np.arange(n), side="right") - 1
    coo = a.tocoo()
    cross = block[coo.row] != block[coo.col]
    c = np.bincount(coo.row[cross], weights=np.abs(coo.data[cross]), minlength=n)
    d = a.diagonal()
    return bool(np.all((c == 0.0) | (d > c)))


@pytest.mark.parametrize("n_blocks", [2, 5, 16])
def test_cross_block_dominance_matches_numpy(rng, n_blocks):
    n = 2000
    a = sp.diags([-np.ones(n - 1), 2.0 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tocsr()
    arrays = (as_unsigned(a.indptr), as_unsigned(a.indices), a.data)
    assert cross_block_dominant(*arrays, n_blocks) is _dominant_numpy(a, n_blocks) is True
    # one row in the last block coupled across blocks more strongly than its diagonal
    b = a.tolil()
    row = n - 3
    b[row, 0] = -2.5
    b = b.tocsr()
    arrays = (as_unsigned(b.indptr), as_unsigned(b.indices), b.data)
    assert cross_block_dominant(*arrays, n_blocks) is _dominant_numpy(b, n_blocks) is False
    # random weights: the two agree
    c = sp.random(n, n, density=3 / n, random_state=np.random.default_rng(1), format="csr")
    c = (c + c.T + sp.diags(rng.uniform(0.0, 3.0, n))).tocsr()
    c.sort_indices()
    arrays = (as_unsigned(c.indptr), as_unsigned(c.indices), c.data)
    assert cross_block_dominant(*arrays, n_blocks) is _dominant_numpy(c, n_blocks)
