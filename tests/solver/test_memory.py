"""Memory: the guard that refuses runs that cannot fit, and the 32-bit index path's limit.

Nothing here allocates anything big: the refusals happen before any array of the
mesh size exists (checked with the process's peak RSS where it matters).
"""

import resource

import numpy as np
import pytest

import fastmem as fm
import fastmem.mesh.mesh as fmesh
from fastmem.errors import FastmemError, MemoryLimitError, MeshError
from fastmem.memory import (
    MEMORY_LIMIT_ENV,
    check_memory,
    estimate_memory,
    memory_limit,
)


def _peak_rss_bytes():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def test_absurd_mesh_is_refused_before_allocating(monkeypatch):
    monkeypatch.delenv(MEMORY_LIMIT_ENV, raising=False)
    before = _peak_rss_bytes()
    with pytest.raises(MemoryLimitError) as info:
        fm.Mesh.square(15_000)  # 225M vertices, 450M triangles: ~110 GB to build
    assert _peak_rss_bytes() - before < 50e6
    msg = str(info.value)
    assert "225030001 vertices" in msg
    assert "GB" in msg
    assert "the machine's memory" in msg
    assert MEMORY_LIMIT_ENV in msg
    assert isinstance(info.value, FastmemError)
    assert isinstance(info.value, MemoryError)


def test_solve_refused_above_the_limit_names_estimate_and_limit(monkeypatch):
    scene = fm.Scene(fm.Mesh.square(8), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "1M")
    with pytest.raises(MemoryLimitError) as info:
        fm.solve(scene)
    msg = str(info.value)
    need = estimate_memory(81, 128, "inexact", True)
    assert f"{need / 1e9:.1f} GB" in msg
    assert MEMORY_LIMIT_ENV in msg
    assert "0.0 GB" in msg
    assert "method='inexact'" in msg
    assert "81 vertices" in msg
    assert "A" not in scene._cache  # refused before the assembly
    # the keyword overrides the environment variable
    fm.solve(scene, memory_limit=False)
    fm.solve(scene, memory_limit="64G")
    with pytest.raises(MemoryLimitError, match="memory_limit is 0.0 GB"):
        fm.solve(scene, memory_limit=1000)


def test_environment_variable_disables_and_parses(monkeypatch):
    for off in ("0", "off", "none"):
        monkeypatch.setenv(MEMORY_LIMIT_ENV, off)
        assert memory_limit() == (None, MEMORY_LIMIT_ENV)
        check_memory(10**9, 2 * 10**9)  # no check: returns the estimate
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "20G")
    assert memory_limit()[0] == 20 * 2**30
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "lots")
    with pytest.raises(fm.errors.ParameterError, match=MEMORY_LIMIT_ENV):
        memory_limit()
    with pytest.raises(fm.errors.ParameterError, match="memory_limit"):
        memory_limit(-5)


def test_estimate_model():
    n = 4096  # the target: 16.8M vertices, 33.5M triangles
    nv, nt = (n + 1) ** 2, 2 * n * n
    inexact = estimate_memory(nv, nt, "inexact", True)
    assert estimate_memory(nv, nt, "exact-amg", False) < estimate_memory(nv, nt, "exact-amg")
    assert estimate_memory(nv, nt, "exact") > inexact
    assert estimate_memory(nv, nt, None) < inexact
    # per-triangle work counts when a mesh has many triangles per vertex
    assert estimate_memory(nv, 4 * nt) > inexact
    with pytest.raises(fm.errors.ParameterError):
        estimate_memory(nv, nt, "fast")


def test_int32_index_limit_refuses_with_a_fake_size():
    with pytest.raises(MeshError, match="32-bit"):
        fmesh.check_index_limit(2**31, 10)
    with pytest.raises(MeshError, match="715827882 triangles"):
        fmesh.check_index_limit(1000, 715_827_883)
    fmesh.check_index_limit(2**31 - 1, 715_827_882)  # the limit itself is fine


def test_int32_index_limit_on_a_real_mesh(monkeypatch):
    mesh = fm.Mesh.square(4)
    monkeypatch.setattr(fmesh, "INDEX_LIMIT", 3 * mesh.n_triangles - 1)
    with pytest.raises(MeshError, match="32-bit topology indices"):
        _ = mesh.edges
    monkeypatch.setattr(fmesh, "INDEX_LIMIT", 3 * mesh.n_triangles)
    assert mesh.edges.dtype == np.int32
    # and the generator refuses before allocating (memory guard disabled to reach it)
    monkeypatch.setattr(fmesh, "INDEX_LIMIT", 100)
    monkeypatch.setenv(MEMORY_LIMIT_ENV, "0")
    with pytest.raises(MeshError, match="32-bit"):
        fm.Mesh.square(8)


def test_shared_pattern_of_weighted_stiffness():
    mesh = fm.Mesh.square(6)
    a = fm.Scene(mesh, mu=(1.0, 2.5)).stiffness
    scene = fm.Scene(mesh, mu=(1.0, 2.5))
    a1, a2 = scene.weighted_stiffness(1), scene.weighted_stiffness(2)
    assert a1 is scene.stiffness  # mu1 = 1: A itself
    assert np.shares_memory(a2.indices, scene.stiffness.indices)  # no copy of the pattern
    assert np.shares_memory(a2.indptr, scene.stiffness.indptr)
    np.testing.assert_array_equal((a * 2.5).toarray(), a2.toarray())  # bit for bit


@pytest.mark.parametrize("n", [8, 33, 200])
@pytest.mark.parametrize("frac", [0.0, 0.3, 1.0])
@pytest.mark.parametrize("path", ["dispatch", "numpy", "kernel"])
def test_gap_matrix_is_scipys_expression_bit_for_bit(n, frac, path):
    """Both builds of the gap matrix (NumPy masks; row chunks in the kernel threads,
    used from THREADED_ROWS rows on: n = 200 has 39,601) give scipy's arrays."""
    import scipy.sparse as sp

    from fastmem.linalg.sparse import THREADED_ROWS, masked_gap
    from fastmem.solver import steps
    from fastmem.solver.linear import DecoupledStep

    gap_matrix = {
        "dispatch": steps.gap_matrix,
        "numpy": steps._gap_matrix_numpy,
        "kernel": masked_gap,
    }[path]
    assert (200 - 1) ** 2 >= THREADED_ROWS > (33 - 1) ** 2

    scene = fm.Scene(fm.Mesh.square(n), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    a = DecoupledStep(scene).a_ii
    assert (a.data == 0).any()  # stored zeros (right angles): must be dropped as scipy does
    active = np.random.default_rng(n).random(a.shape[0]) < frac
    keep = sp.diags((~active).astype(np.float64))
    ref = (keep @ a @ keep + sp.diags(a.diagonal() * active)).tocsr()
    got = gap_matrix(a, active)
    for name in ("indices", "indptr"):
        x, y = getattr(ref, name), getattr(got, name)
        assert x.dtype == y.dtype
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(ref.data.view(np.uint64), got.data.view(np.uint64))
    assert got.has_sorted_indices == ref.has_sorted_indices


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize(
    "case", ["interior-block", "refined-interpolation", "unsorted-pattern", "int64", "small"]
)
def test_submatrix_is_scipys_fancy_indexing(monkeypatch, case, threads):
    """The threaded submatrix gives a[rows][:, cols] entry for entry: each row's kept
    entries in stored order (stored zeros included), the index dtypes of ``a``."""
    import scipy.sparse as sp

    from fastmem.linalg import sparse
    from fastmem.solver.nested import interpolation_matrix

    mesh = fm.Mesh.square(12)
    ii = mesh.interior_vertices
    rows = cols = ii
    a = fm.Scene(mesh, mu=(1.0, 1.0)).stiffness.copy()
    if case == "refined-interpolation":  # rows of the fine mesh, columns of the coarse one
        fine = mesh.refine()
        a = interpolation_matrix(mesh, fine)
        rows = fine.interior_vertices
    elif case == "unsorted-pattern":  # reversed entries within each row
        a = a.copy()
        for i in range(a.shape[0]):
            lo, hi = a.indptr[i], a.indptr[i + 1]
            a.indices[lo:hi] = a.indices[lo:hi][::-1].copy()
            a.data[lo:hi] = a.data[lo:hi][::-1].copy()
        a.has_sorted_indices = False
    elif case == "int64":
        a = sp.csr_matrix(
            (a.data, a.indices.astype(np.int64), a.indptr.astype(np.int64)), shape=a.shape
        )
    if case != "small":
        monkeypatch.setattr(sparse, "THREADED_ROWS", 1)
    assert (a.data == 0).any() or case == "refined-interpolation"  # stored zeros are kept
    ref = a[rows][:, cols].tocsr()
    got = _with_threads(threads, lambda: sparse.submatrix(a, rows, cols))
    assert got.shape == ref.shape
    for name in ("indices", "indptr"):
        x, y = getattr(ref, name), getattr(got, name)
        assert x.dtype == y.dtype, name
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(ref.data.view(np.uint64), got.data.view(np.uint64))


def test_lazy_hierarchy_and_released_state():
    """The Laplacian's hierarchy of the decoupled path is built only when applied."""
    from fastmem.linalg.amg import PCG, LazyAMG
    from fastmem.solver.linear import DecoupledStep

    scene = fm.Scene(fm.Mesh.square(32), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)

    st = DecoupledStep(scene)
    stats = {"amg_setups": 0, "amg_setup_seconds": 0.0}
    lazy = LazyAMG(st.a_ii, fm.linalg.amg.AMG_DEFAULTS, stats)
    cg = PCG(st.a_ii, st.rhs_s, np.zeros(st.rhs_s.size), lazy)
    assert not lazy.built
    assert stats["amg_setups"] == 0
    assert cg.p is None  # no direction before the first step
    pre = fm.linalg.amg.amg_preconditioner(st.a_ii)
    eager = PCG(st.a_ii, st.rhs_s, np.zeros(st.rhs_s.size), pre)
    for _ in range(3):
        assert cg.step()
        assert eager.step()
    assert lazy.built
    assert stats["amg_setups"] == 1
    np.testing.assert_array_equal(cg.x, eager.x)  # deferred z: bit for bit the same iterates
    cg.release()
    assert cg.p is None
    assert not cg.step()
    assert np.isfinite(cg.true_residual_norm())
    lazy.release()
    assert not lazy.built


def test_decoupled_finest_level_builds_no_unused_hierarchy():
    r = fm.solve(fm.Scene(fm.Mesh.square(128), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1))
    last = r.parameters["solver"]["levels"][-1]
    if last["s_iterations"] == 0:  # the CG of s never advanced: only the gap's hierarchy
        assert last["amg_setups"] <= last["newton"]


def _csr_levels_as_bsr(ml):
    """Undo the CSR conversion of the coarse operators (the block kernel's arithmetic)."""
    for lv in ml.levels[1:]:
        lv.A = lv.A.tobsr(blocksize=(1, 1))


def test_trimmed_hierarchy_cycles_bit_for_bit(monkeypatch):
    """R as the transpose view of P and no B: the same preconditioner output, bit for bit.

    The coarse operators as CSR change only the rounding of Gauss-Seidel's diagonal
    division: with them turned back into 1 x 1 BSR the cycles are bit-identical to the
    untrimmed hierarchy, and as CSR they agree to round-off.
    """
    import fastmem.linalg.amg as amg
    from fastmem.solver.linear import DecoupledStep
    from fastmem.solver.steps import gap_matrix

    st = DecoupledStep(fm.Scene(fm.Mesh.square(96), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1))
    rng = np.random.default_rng(3)
    active = rng.random(st.a_ii.shape[0]) < 0.4
    for mat in (st.a_ii, gap_matrix(st.a_ii, active)):
        trimmed = amg.amg_preconditioner(mat)
        with monkeypatch.context() as m:
            m.setattr(amg, "_trim", lambda ml: None)
            full = amg.amg_preconditioner(mat)
        assert all(not hasattr(lv, "B") for lv in trimmed.ml.levels)
        assert any(lv.R.format == "csc" for lv in trimmed.ml.levels[:-1])
        assert all(lv.A.format == "csr" for lv in trimmed.ml.levels)
        assert any(lv.A.format == "bsr" for lv in full.ml.levels[1:])
        rs = [rng.standard_normal(mat.shape[0]) for _ in range(2)]
        for r in rs:
            z, ref = trimmed(r), full(r)
            assert np.max(np.abs(z - ref)) <= 1e-13 * np.max(np.abs(ref))
        _csr_levels_as_bsr(trimmed.ml)
        for r in rs:
            np.testing.assert_array_equal(trimmed(r).view(np.uint64), full(r).view(np.uint64))


def test_bsr_canonical_check():
    """The O(nnz) test behind the setup's fast sum_duplicates: sorted, no duplicates."""
    import scipy.sparse as sp

    from fastmem.linalg.amg import _bsr_is_canonical

    def bsr(indptr, indices):
        data = np.arange(1.0, len(indices) + 1).reshape(-1, 1, 1)
        return sp.bsr_matrix((data, np.array(indices), np.array(indptr)), shape=(3, 3))

    assert _bsr_is_canonical(bsr([0, 2, 3, 5], [0, 2, 1, 0, 2]))
    assert _bsr_is_canonical(bsr([0, 0, 1, 1], [2]))  # empty rows
    assert not _bsr_is_canonical(bsr([0, 2, 3, 5], [2, 0, 1, 0, 2]))  # unsorted row
    assert not _bsr_is_canonical(bsr([0, 2, 3, 5], [0, 0, 1, 0, 2]))  # duplicate
    # a row ending in a large column followed by a row starting small is fine
    assert _bsr_is_canonical(bsr([0, 1, 2, 3], [2, 0, 1]))


def test_fast_dedup_setup_builds_the_same_hierarchy(monkeypatch):
    """The setup with the loop-free sum_duplicates gives pyamg's hierarchy exactly.

    Same operators, prolongators and restrictions on every level, bit for bit, as
    with scipy's own method; the replacement is installed during the setup only.
    """
    import contextlib

    import scipy.sparse._bsr as bsr_module

    import fastmem.linalg.amg as amg
    from fastmem.solver.linear import DecoupledStep
    from fastmem.solver.steps import gap_matrix

    original = bsr_module._bsr_base.sum_duplicates
    checked, is_canonical = amg._checked_sum_duplicates, amg._bsr_is_canonical
    calls, flagged = [], []

    def counting(self):
        calls.append(self.shape)
        return checked(self)

    def counting_check(m):
        ok = is_canonical(m)
        flagged.append(ok)
        return ok

    st = DecoupledStep(fm.Scene(fm.Mesh.square(96), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1))
    active = np.random.default_rng(4).random(st.a_ii.shape[0]) < 0.3
    for mat in (st.a_ii, gap_matrix(st.a_ii, active)):
        with monkeypatch.context() as m:
            m.setattr(amg, "_trim", lambda ml: None)
            m.setattr(amg, "_checked_sum_duplicates", counting)
            m.setattr(amg, "_bsr_is_canonical", counting_check)
            fast = amg.amg_preconditioner(mat)
            assert bsr_module._bsr_base.sum_duplicates is original  # removed after the setup
            m.setattr(amg, "_fast_bsr_dedup", contextlib.nullcontext)
            plain = amg.amg_preconditioner(mat)
        assert calls, "the setup never reached sum_duplicates: the test checks nothing"
        assert any(flagged), "no Galerkin product was found canonical: the loop still runs"
        for a, b in zip(fast.ml.levels, plain.ml.levels, strict=True):
            for name in ("A", "P", "R"):
                x, y = getattr(a, name, None), getattr(b, name, None)
                if x is None and y is None:
                    continue
                x, y = x.tocsr(), y.tocsr()
                np.testing.assert_array_equal(x.indptr, y.indptr)
                np.testing.assert_array_equal(x.indices, y.indices)
                np.testing.assert_array_equal(x.data.view(np.uint64), y.data.view(np.uint64))


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("mu", [(1.0, 1.0), (1.0, 2.5), (3.0, 0.5), "per-triangle"])
def test_fused_residuals_are_the_numpy_expressions_bit_for_bit(monkeypatch, mu, threads):
    """One pass over the shared pattern gives F1 - A1 u1 + B lam and F2 - A2 u2 - B lam
    with NumPy's bits, zero on the boundary (per-triangle tensions share the mesh's
    pattern too)."""

    from fastmem.fem import residual

    mesh = fm.Mesh.square(20)
    if mu == "per-triangle":
        mu = (np.linspace(1.0, 2.0, mesh.n_triangles), 1.5)
    scene = fm.Scene(mesh, mu=mu, f=(-1.0, 1.0), g=0.1)
    rng = np.random.default_rng(5)
    n = scene.mesh.n_vertices
    u1, u2, lam = rng.standard_normal(n), rng.standard_normal(n), rng.standard_normal(n)
    want = residual.residuals(scene, u1, u2, lam)  # below THREADED_ROWS: the NumPy path
    monkeypatch.setattr(residual, "THREADED_ROWS", 1)
    args = (
        scene.weighted_stiffness(1), scene.weighted_stiffness(2), u1, u2, lam, *scene.loads,
        scene.mesh.lumped_mass, scene.mesh.boundary_vertex_mask,
    )  # fmt: skip
    assert residual._fused(*args) is not None  # the fused path is taken
    got = _with_threads(threads, lambda: residual.residuals(scene, u1, u2, lam))
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g.view(np.uint64), w.view(np.uint64))
    assert not got[0][scene.mesh.boundary_vertices].any()


def test_residuals_of_two_patterns_keep_two_products(monkeypatch):
    """Matrices whose patterns are separate arrays: no fused pass, the products as before."""
    from fastmem.fem import residual

    mesh = fm.Mesh.square(8)
    scene = fm.Scene(mesh, mu=(np.linspace(1.0, 2.0, mesh.n_triangles), 1.0), f=(-1.0, 1.0))
    monkeypatch.setattr(residual, "THREADED_ROWS", 1)
    z = np.zeros(mesh.n_vertices)
    a1, a2 = scene.weighted_stiffness(1), scene.weighted_stiffness(2).copy()
    assert residual._fused(a1, a2, z, z, z, *scene.loads, mesh.lumped_mass, z > 0) is None


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("s_kind", ["all-vertices", "interior"])
@pytest.mark.parametrize("mu", [(1.0, 1.0), (2.0, 0.5)])
def test_threaded_decoupled_triple_is_numpys_bit_for_bit(monkeypatch, s_kind, mu, threads):
    """The decoupled step's triple from one pass of the kernel threads: the NumPy path's
    arrays bit for bit (an s of all vertices or of the interior ones)."""

    from fastmem.solver import linear

    scene = fm.Scene(fm.Mesh.square(20), mu=mu, f=(-1.0, 1.0), g=0.1)
    step = linear.DecoupledStep(scene)
    rng = np.random.default_rng(6)
    ni = step.interior.size
    active = rng.random(ni) < 0.4
    s = rng.standard_normal(step.n if s_kind == "all-vertices" else ni)
    w_i = rng.standard_normal(ni)
    want = step.triple(active, s, w_i)  # below THREADED_ROWS: NumPy
    monkeypatch.setattr(linear, "THREADED_ROWS", 1)
    assert step._triple_threaded(active, s, w_i) is not None
    got = _with_threads(threads, lambda: step.triple(active, s, w_i))
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g.view(np.uint64), w.view(np.uint64))
    assert (got[2][step.interior][active] != 0).all()  # the active rows were computed


def _with_threads(threads, fn):
    """Call ``fn()`` with ``threads`` Numba threads (the count restored after)."""
    import numba

    old = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        return fn()
    finally:
        numba.set_num_threads(old)
