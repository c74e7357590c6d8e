"""Geometric multigrid on nested hierarchies (issue 33): fastmem.linalg.gmg.

- the Galerkin kernel against scipy's products, with and without a mask, on
  structured, red-refined and auxiliary (non-nested) interpolations;
- the Galerkin operators of the P1 Laplacian are the coarser meshes' Laplacians;
- the V-cycle is a symmetric positive definite preconditioner, the same with
  any number of threads, and CG with it converges in a bounded number of
  iterations (the Laplacian and a gap system with a large active set);
- fm.solve with multigrid="geometric" gives what "algebraic" gives: the same
  solution to round-off with exact-amg, a guaranteed bound with inexact; on
  the decoupled path and on the general path (per-triangle tensions, the
  block interpolations of GeneralCG);
- a gap hierarchy moved to a new active set is the one a build gives, bit for
  bit; hierarchies freed for a flux and rebuilt change no result;
- after fm.warm_up(large=True) a solve that takes it compiles nothing.
"""

import numba
import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg  # noqa: F401  (sp.linalg)

import fastmem as fm
from fastmem.errors import ParameterError
from fastmem.fem.assembly import assemble_stiffness
from fastmem.linalg.amg import PCG
from fastmem.linalg.gmg import NestedChain, NestedMG, galerkin, restriction
from fastmem.mesh.coarsen import coarse_mesh
from fastmem.problems import Manufactured
from fastmem.solver.nested import interpolation_matrix
from fastmem.solver.steps import gap_matrix


def _laplacian(mesh):
    ii = mesh.interior_vertices
    a = assemble_stiffness(mesh)[ii][:, ii].tocsr()
    a.eliminate_zeros()
    return a


def _chain(mesh, levels=None):
    """Interior Laplacian of ``mesh`` and the interpolations of its chain, finest first."""
    meshes = [mesh]
    while (levels is None or len(meshes) <= levels) and meshes[-1].n_vertices > 300:
        c = meshes[-1].coarser()
        if c is None:
            break
        meshes.append(c)
    ps = [
        interpolation_matrix(c, f)[f.interior_vertices][:, c.interior_vertices].tocsr()
        for f, c in zip(meshes, meshes[1:], strict=False)
    ]
    return _laplacian(mesh), ps, meshes


def _reference(a, p, keep):
    k = sp.diags(keep.astype(float))
    ref = (p.T @ k @ a @ k @ p).tocsr()
    ref.eliminate_zeros()
    empty = np.diff(ref.indptr) == 0
    return (ref + sp.diags(empty.astype(float))).tocsr()


def _pairs():
    fine = fm.Mesh.square(24)
    yield "structured", fine, fm.Mesh.square(12)
    parent = fm.Mesh.square(10)
    yield "red refinement", parent.refine(), parent
    jittered = fm.Mesh.square(20)
    aux = coarse_mesh(jittered)
    yield "auxiliary", jittered, aux.mesh


@pytest.mark.parametrize("masked", [False, True])
def test_galerkin_kernel_matches_scipy(masked):
    rng = np.random.default_rng(33)
    for name, fine, coarse in _pairs():
        a = _laplacian(fine)
        p = interpolation_matrix(coarse, fine)[fine.interior_vertices][
            :, coarse.interior_vertices
        ].tocsr()
        keep = np.ones(a.shape[0], bool)
        if masked:  # scattered vertices, and a disc that cuts coarse unknowns off entirely
            v = fine.vertices[fine.interior_vertices]
            keep = (rng.random(a.shape[0]) > 0.3) & (
                (v[:, 0] - 0.4) ** 2 + (v[:, 1] - 0.5) ** 2 > 0.05
            )
        out = galerkin(a, p, keep=keep)
        ref = _reference(a, p, keep)
        assert out.has_sorted_indices
        assert np.all(np.diff(out.indptr) >= 1), name
        diff = abs(out - ref).max()
        assert diff <= 1e-13 * abs(ref).max(), (name, diff)
        if masked:  # the cut-off coarse unknowns: a unit diagonal and nothing else
            cut = np.flatnonzero(np.asarray(abs(p[keep]).sum(axis=0)).ravel() == 0)
            assert cut.size, name  # the mask must cut something off for the test to mean it
            rows = out[cut]
            assert np.array_equal(rows.indices, cut)
            assert np.all(rows.data == 1.0)


def test_galerkin_of_the_laplacian_is_the_coarse_laplacian():
    fine, coarse = fm.Mesh.square(64), fm.Mesh.square(32)
    p = interpolation_matrix(coarse, fine)[fine.interior_vertices][:, coarse.interior_vertices]
    out = galerkin(_laplacian(fine), p.tocsr())
    ac = _laplacian(coarse)
    assert abs(out - ac).max() <= 1e-14 * abs(ac).max()
    assert out.nnz == ac.nnz  # exact cancellations are not stored


@pytest.mark.parametrize("n", [64, 256])  # plain sweeps; hybrid sweeps on the finest (65k rows)
def test_cycle_is_spd_and_thread_independent(n):
    a, ps, _ = _chain(fm.Mesh.square(n))
    rng = np.random.default_rng(1)
    x, y = rng.random(a.shape[0]), rng.random(a.shape[0])
    threads = numba.get_num_threads()
    outs = []
    try:
        for t in sorted({1, threads}):
            numba.set_num_threads(t)
            m = NestedMG(a, NestedChain(ps))
            outs.append((m(x), m(y)))
    finally:
        numba.set_num_threads(threads)
    mx, my = outs[0]
    for other in outs[1:]:  # bit for bit with any number of threads
        assert np.array_equal(other[0], mx)
        assert np.array_equal(other[1], my)
    assert abs(x @ my - y @ mx) <= 1e-12 * abs(x @ my)
    assert x @ mx > 0
    assert y @ my > 0


def test_cg_converges_in_few_iterations():
    a, ps, meshes = _chain(fm.Mesh.square(256))
    assert len(ps) >= 4
    b = np.random.default_rng(2).random(a.shape[0])
    cg = PCG(a, b, np.zeros_like(b), NestedMG(a, NestedChain(ps)))
    its = cg.solve(1e-10, 100)
    assert np.linalg.norm(b - a @ cg.x) <= 1e-10 * np.linalg.norm(b)
    assert its <= 14, its
    # the gap system of a disc of active vertices (about a third of them)
    v = meshes[0].vertices[meshes[0].interior_vertices]
    active = (v[:, 0] - 0.5) ** 2 + (v[:, 1] - 0.5) ** 2 < 0.1
    g = gap_matrix(a, active)
    mg = NestedMG(g, NestedChain(ps), base=a, active=active)
    d = g.diagonal()

    def pre(r):
        z = mg(np.where(active, 0.0, r))
        z[active] = r[active] / d[active]
        return z

    bw = np.where(active, 0.0, b)
    cg = PCG(g, bw, np.zeros_like(b), pre)
    its = cg.solve(1e-10, 100)
    assert np.linalg.norm(bw - g @ cg.x) <= 1e-10 * np.linalg.norm(bw)
    assert np.all(cg.x[active] == 0.0)
    assert its <= 16, its


def test_update_gives_the_hierarchy_a_build_gives():
    """A gap hierarchy moved to a new active set equals one built for it, bit for bit."""
    a, ps, meshes = _chain(fm.Mesh.square(128))
    chain = NestedChain(ps)
    v = meshes[0].vertices[meshes[0].interior_vertices]
    r2 = (v[:, 0] - 0.5) ** 2 + (v[:, 1] - 0.5) ** 2
    old, new = r2 < 0.09, r2 < 0.1
    moved = NestedMG(gap_matrix(a, old), chain, base=a, active=old)
    moved.build()
    seconds = moved.update(gap_matrix(a, new), new)
    assert seconds >= 0.0
    assert moved.stats["amg_updates"] == 1
    fresh = NestedMG(gap_matrix(a, new), chain, base=a, active=new)
    for x, y in zip(moved.operators(), fresh.operators(), strict=True):
        assert np.array_equal(x.indptr, y.indptr)
        assert np.array_equal(x.indices, y.indices)
        assert np.array_equal(x.data, y.data)
    r = np.random.default_rng(4).random(a.shape[0])
    r[new] = 0.0
    assert np.array_equal(moved(r), fresh(r))
    # and the truncated operators are those of scipy's products
    ref = _reference(a, ps[0], ~new)
    assert abs(fresh.operators()[1] - ref).max() <= 1e-13 * abs(ref).max()


def test_release_and_rebuild_give_the_same_cycle():
    a, ps, _ = _chain(fm.Mesh.square(64))
    m = NestedMG(a, NestedChain(ps))
    r = np.random.default_rng(3).random(a.shape[0])
    z = m(r)
    m.release()
    assert not m.built
    assert np.array_equal(m(r), z)
    m.release(final=True)  # no chain: an AMG cycle on the matrix itself (too big to factor)
    e = sp.linalg.spsolve(a.tocsc(), r)
    d = e - m(r)
    assert d @ (a @ d) < 0.25 * (e @ (a @ e))  # the energy error at least halved


def test_solve_geometric_against_algebraic():
    mesh = fm.Mesh.square(128)
    mms = Manufactured()
    ref = fm.solve(mms.scene(mesh), method="exact-amg", multigrid="algebraic")
    geo = fm.solve(mms.scene(mesh), method="exact-amg", multigrid="geometric")
    for u, v in ((ref.u1, geo.u1), (ref.u2, geo.u2), (ref.lam, geo.lam)):
        assert np.abs(u - v).max() <= 1e-9 * max(1.0, np.abs(u).max())
    assert geo.parameters["solver"]["levels"][-1]["amg_setups"] >= 1
    # inexact: a guaranteed bound either way, with the same effectivity within 3 %
    eff = {}
    for mg in ("algebraic", "geometric"):
        out = fm.solve(mms.scene(mesh), method="inexact", multigrid=mg)
        err = mms.energy_error(mesh, out.u1, out.u2)
        assert out.eta >= err, mg
        eff[mg] = out.eta / err
    assert abs(eff["geometric"] / eff["algebraic"] - 1.0) < 0.03, eff


def test_spill_changes_no_result(monkeypatch):
    """The geometric hierarchies freed during a flux and rebuilt after it: same numbers."""
    from fastmem.solver import inexact

    def solve():  # a flux at every check: spills and restores between the Newton steps
        scene = fm.Scene(fm.Mesh.square(128), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
        return fm.solve(scene, full_history=True, multigrid="geometric")

    monkeypatch.setattr(inexact, "SPILL", True)
    spilled = solve()
    levels = spilled.parameters["solver"]["levels"]
    assert sum(lv.get("spill_setups", 0) for lv in levels) > 0  # something was rebuilt
    monkeypatch.setattr(inexact, "SPILL", False)
    kept = solve()
    for name in ("u1", "u2", "lam"):
        np.testing.assert_array_equal(getattr(spilled, name), getattr(kept, name))


def test_general_path_geometric_against_algebraic():
    """The general path's CG with the chain's block interpolations (GeneralCG._geometric)."""
    mesh = fm.Mesh.square(64)
    x = mesh.vertices[mesh.triangles, 0].mean(axis=1)
    mu1 = np.where(x < 0.0, 1.0, 3.0)  # per-triangle tension: the general path

    def scene():
        return fm.Scene(mesh, mu=(mu1, 1.0), f=(-1.0, 1.0), g=0.1)

    ref = fm.solve(scene(), method="exact-amg", multigrid="algebraic")
    geo = fm.solve(scene(), method="exact-amg", multigrid="geometric")
    assert geo.parameters["solver"]["path"] == "general"
    used = [lv["multigrid"] for lv in geo.parameters["solver"]["levels"]]
    assert used[0] is None
    assert set(used[1:]) == {"geometric"}
    for u, v in ((ref.u1, geo.u1), (ref.u2, geo.u2), (ref.lam, geo.lam)):
        assert np.abs(u - v).max() <= 1e-9 * max(1.0, np.abs(u).max())
    assert np.array_equal(ref.active, geo.active)
    # inexact on the manufactured solution, forced onto the general path: the bound holds
    mms = Manufactured()
    eff = {}
    for mg in ("algebraic", "geometric"):
        out = fm.solve(mms.scene(mesh), method="inexact", path="general", multigrid=mg)
        err = mms.energy_error(mesh, out.u1, out.u2)
        assert out.eta >= err, mg
        eff[mg] = out.eta / err
    assert abs(eff["geometric"] / eff["algebraic"] - 1.0) < 0.03, eff


def test_general_path_spill_changes_no_result(monkeypatch):
    from fastmem.solver import inexact

    def solve():
        mesh = fm.Mesh.square(64)
        x = mesh.vertices[mesh.triangles, 0].mean(axis=1)
        scene = fm.Scene(mesh, mu=(np.where(x < 0.0, 1.0, 3.0), 1.0), f=(-1.0, 1.0), g=0.1)
        return fm.solve(scene, full_history=True, multigrid="geometric")

    monkeypatch.setattr(inexact, "SPILL", True)
    spilled = solve()
    assert sum(lv.get("spill_setups", 0) for lv in spilled.parameters["solver"]["levels"]) > 0
    monkeypatch.setattr(inexact, "SPILL", False)
    kept = solve()
    for name in ("u1", "u2", "lam"):
        np.testing.assert_array_equal(getattr(spilled, name), getattr(kept, name))


def test_bad_multigrid_option_is_named():
    with pytest.raises(ParameterError, match="multigrid"):
        fm.solve(fm.Scene(fm.Mesh.square(8)), multigrid="aggregation")


def test_warm_up_compiles_the_nested_multigrid():
    """After fm.warm_up(large=True) a nested solve with the geometric multigrid compiles
    nothing; multigrid="auto" takes it on the large level only."""
    from fresh import compiled_after

    work = (
        "r = fm.solve(fm.Scene(fm.Mesh.square(256), mu=(1, 1), f=(-1, 1), g=0.1))\n"
        "used = [lv['multigrid'] for lv in r.parameters['solver']['levels']]\n"
        "assert used[-1] == 'geometric' and used[-2] == 'two-grid', used"
    )
    assert compiled_after("fm.warm_up('inexact', large=True)", work) == []


def test_chains_share_the_transposes_of_their_links():
    """Nested iteration builds a chain per level from the links below: each P^T formed once."""
    rng = np.random.default_rng(3)
    p0 = sp.random(40, 15, density=0.2, random_state=rng, format="csr")
    p1 = sp.random(15, 6, density=0.3, random_state=rng, format="csr")
    low = NestedChain([p1])
    high = NestedChain([p0, p1])
    assert high.r(1) is low.r(0)
    assert restriction(p0) is high.r(0)
    np.testing.assert_array_equal(high.r(0).toarray(), p0.toarray().T)
    np.testing.assert_array_equal(low.r(0).toarray(), p1.toarray().T)
