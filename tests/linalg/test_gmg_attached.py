"""Coarse operators attached to the interpolations of a nested chain (issue 33).

Nested iteration and the adaptive loop know the coarser meshes' interior
Laplacians, which for nested P1 spaces are the Galerkin products that the
geometric multigrid would otherwise form (fastmem.linalg.gmg.attach_coarse_operator).
Checked here:

- on nested pairs (structured grids, red refinement, newest-vertex bisection with
  one and two rounds) the coarse Laplacian, stored zeros included, has exactly the
  pattern of the unmasked product with its cancellations kept, and the product's
  values to round-off; so every masked product fits in it;
- a chain with the operators attached forms the same coarse operators as one
  without, unmasked and masked (a gap system's hierarchy), and its cycles give the
  same vectors; on structured grids of 2^k cells (exact entries) bit for bit;
- an operator that is not the Galerkin product (an auxiliary, non-nested coarse
  mesh; a wrong matrix) fails the probe and the product is formed instead;
- fm.solve and the adaptive loop use them (no product of the Laplacian is
  formed) and give the results they give without them.
"""

import numpy as np
import pytest
import scipy.sparse as sp

import fastmem as fm
from fastmem.fem.assembly import assemble_stiffness
from fastmem.linalg import gmg
from fastmem.linalg.gmg import NestedChain, NestedMG, attach_coarse_operator, galerkin
from fastmem.mesh.coarsen import coarse_mesh
from fastmem.mesh.refine import refine_marked
from fastmem.solver.nested import interpolation_matrix


def _interior_laplacian(mesh):
    """The assembled interior Laplacian, stored zeros kept (as the solver's steps hold it)."""
    ii = mesh.interior_vertices
    a = assemble_stiffness(mesh)[ii][:, ii].tocsr()
    a.sort_indices()
    return a


def _link(coarse, fine, p=None):
    p = interpolation_matrix(coarse, fine) if p is None else p
    return p[fine.interior_vertices][:, coarse.interior_vertices].tocsr()


def _nvb(mesh, rounds, seed):
    """A locally refined mesh: a random quarter of the triangles near a corner, marked."""
    rng = np.random.default_rng(seed)
    c = mesh.vertices[mesh.triangles].mean(axis=1)
    marked = (np.hypot(c[:, 0] - 0.1, c[:, 1] - 0.2) < 0.5) & (rng.random(mesh.n_triangles) < 0.6)
    fine, ref = refine_marked(mesh, marked, bisections=rounds)
    return fine, ref.prolongation_matrix()


def _nested_pairs():
    """(name, coarse mesh, fine mesh, full interpolation or None)."""
    yield "structured", fm.Mesh.square(16), fm.Mesh.square(32), None
    parent = fm.Mesh.lshape(8)
    yield "red refinement", parent, parent.refine(), None
    base = fm.Mesh.lshape(16)
    for rounds in (1, 2):
        fine, p = _nvb(base, rounds, seed=rounds)
        yield f"bisection x{rounds}", base, fine, p
    # two generations of bisection: the second refines a mesh that came from the first
    mid, p1 = _nvb(fm.Mesh.square(16), 2, seed=5)
    fine, p2 = _nvb(mid, 2, seed=6)
    yield "bisection of a bisected mesh", mid, fine, p2


@pytest.mark.parametrize("case", range(5))
def test_coarse_laplacian_is_the_galerkin_product_with_its_pattern(case):
    name, coarse, fine, p = list(_nested_pairs())[case]
    link = _link(coarse, fine, p)
    product = galerkin(_interior_laplacian(fine), link, drop=False)
    own = _interior_laplacian(coarse)
    # the whole pattern: every masked product fits in the coarse Laplacian's
    assert np.array_equal(product.indptr, own.indptr), name
    assert np.array_equal(product.indices, own.indices), name
    scale = np.abs(own.data).max()
    assert np.abs(product.data - own.data).max() <= 1e-13 * scale, name
    if name == "structured":  # a dyadic grid: every entry exact, the same bits
        assert np.array_equal(product.data, own.data)


def _chain_of(mesh, depth):
    """Interior Laplacian of ``mesh``, its chain's links and coarse Laplacians, finest first."""
    meshes = [mesh]
    for _ in range(depth):
        meshes.append(meshes[-1].coarser())
    links = [_link(c, f) for f, c in zip(meshes, meshes[1:], strict=False)]
    return _interior_laplacian(mesh), links, [_interior_laplacian(c) for c in meshes[1:]]


def _masked_active(a, seed=3):
    rng = np.random.default_rng(seed)
    return rng.random(a.shape[0]) < 0.35


def _hierarchies(a, links):
    """The unmasked and a gap system's hierarchy on ``links``: (operators, cycles)."""
    active = _masked_active(a)
    x = np.random.default_rng(9).random(a.shape[0])
    out = []
    for kwargs in ({}, {"base": a, "active": active}):
        chain = NestedChain(links)
        mat = a if not kwargs else _gap(a, active)
        mg = NestedMG(mat, chain, **kwargs)
        out.append((mg.operators(), mg(x), chain.attached_used))
    return out


def _gap(a, active):
    keep = sp.diags((~active).astype(float))
    out = (keep @ a @ keep + sp.diags(a.diagonal() * active)).tocsr()
    out.sort_indices()
    return out


def test_attached_chain_gives_the_hierarchy_of_the_products():
    a, links, coarse = _chain_of(fm.Mesh.square(64), 3)
    plain = _hierarchies(a, [q.copy() for q in links])
    for q, c in zip(links, coarse, strict=True):
        attach_coarse_operator(q, c)
    given = _hierarchies(a, links)
    for (ops0, z0, used0), (ops1, z1, used1) in zip(plain, given, strict=True):
        assert used0 == 0
        assert used1 == len(links)
        for m0, m1 in zip(ops0, ops1, strict=True):
            assert np.array_equal(m0.indptr, m1.indptr)
            assert np.array_equal(m0.indices, m1.indices)
            assert np.array_equal(m0.data, m1.data)  # a dyadic grid: bit for bit
        assert np.array_equal(z0, z1)


def test_bisected_chain_agrees_to_roundoff():
    m0 = fm.Mesh.lshape(16)
    m1, p1 = _nvb(m0, 2, seed=11)
    m2, p2 = _nvb(m1, 2, seed=12)
    a = _interior_laplacian(m2)
    links = [_link(m1, m2, p2), _link(m0, m1, p1)]
    plain = _hierarchies(a, [q.copy() for q in links])
    attach_coarse_operator(links[0], _interior_laplacian(m1))
    attach_coarse_operator(links[1], _interior_laplacian(m0))
    given = _hierarchies(a, links)
    for (ops0, z0, _), (ops1, z1, used) in zip(plain, given, strict=True):
        assert used == 2
        for c0, c1 in zip(ops0[1:], ops1[1:], strict=True):
            assert abs(c0 - c1).max() <= 1e-13 * abs(c0).max()
        assert np.abs(z0 - z1).max() <= 1e-10 * np.abs(z0).max()


def test_an_operator_that_is_not_the_product_is_not_used():
    square = fm.Mesh.square(20)
    v = square.vertices.copy()  # interior vertices moved: no coarse mesh is nested in it
    inner = square.interior_vertices
    v[inner] += np.random.default_rng(4).uniform(-0.01, 0.01, (inner.size, 2))
    fine = fm.Mesh(v, square.triangles)
    aux = coarse_mesh(fine).mesh  # its Laplacian is not P^T A P
    link = _link(aux, fine)
    a = _interior_laplacian(fine)
    attach_coarse_operator(link, _interior_laplacian(aux))
    chain = NestedChain([link])
    ops = chain.full_operators(a)
    assert chain.attached_used == 0
    ref = galerkin(a, link, drop=False)
    assert np.array_equal(ops[0].data, ref.data)
    # a nested pair with a wrong matrix of the right pattern (scaled by 2): not used either
    a, links, coarse = _chain_of(fm.Mesh.square(32), 1)
    attach_coarse_operator(links[0], 2.0 * coarse[0])
    chain = NestedChain(links)
    chain.full_operators(a)
    assert chain.attached_used == 0
    with pytest.raises(ValueError, match="operator"):
        attach_coarse_operator(links[0], coarse[0][:-1, :-1])


def _count_products(monkeypatch):
    calls = []
    real = gmg.galerkin

    def counting(a, p, r=None, keep=None, drop=True):
        calls.append(drop)
        return real(a, p, r, keep=keep, drop=drop)

    monkeypatch.setattr(gmg, "galerkin", counting)
    return calls


def test_solve_uses_the_attached_laplacians(monkeypatch):
    """Nested iteration on a grid of 2^k cells: no product formed, the same bits as before."""
    mesh = fm.Mesh.square(256)  # 65k interior vertices: the finest level takes the GMG

    def solve():
        scene = fm.Scene(mesh, mu=(1.0, 2.0), f=(-1.0, 1.0), g=0.1)
        return fm.solve(scene, multigrid="geometric")

    calls = _count_products(monkeypatch)
    with_ops = solve()
    assert with_ops.parameters["solver"]["levels"][-1]["multigrid"] == "geometric"
    assert False not in calls  # no unmasked product: every level's operator was given
    monkeypatch.setattr(gmg, "ATTACHED_COARSE", False)
    calls.clear()
    without = solve()
    assert False in calls
    for name in ("u1", "u2", "lam"):
        np.testing.assert_array_equal(getattr(with_ops, name), getattr(without, name))
    assert with_ops.eta == without.eta


def test_adaptive_loop_uses_the_attached_laplacians(monkeypatch):
    def solve():
        scene = fm.Scene(fm.Mesh.lshape(8), mu=(1.0, 1.0), f=(-1.0, -1.0), g=0.1)
        return fm.solve(scene, tol=2e-2, multigrid="geometric")

    calls = _count_products(monkeypatch)
    with_ops = solve()
    assert len(with_ops.adaptivity["n_vertices"]) >= 5
    assert False not in calls
    monkeypatch.setattr(gmg, "ATTACHED_COARSE", False)
    calls.clear()
    without = solve()
    assert False in calls
    assert with_ops.mesh.n_vertices == without.mesh.n_vertices
    np.testing.assert_allclose(with_ops.u1, without.u1, rtol=0, atol=1e-9)
    assert with_ops.eta == pytest.approx(without.eta, rel=1e-9)


def test_a_solve_without_geometric_multigrid_attaches_nothing(monkeypatch):
    """A default run's mesh (no level reaches the geometric multigrid) assembles no operator."""
    from fastmem.solver import levels

    calls = []
    monkeypatch.setattr(levels, "attach_coarse_operator", lambda p, a: calls.append(p.shape))
    scene = fm.Scene(fm.Mesh.square(128), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    out = fm.solve(scene)
    assert len(out.parameters["solver"]["levels"]) >= 3  # nested iteration ran
    assert calls == []
    fm.solve(scene, multigrid="geometric")  # the same mesh with the geometric multigrid
    assert len(calls) >= 2
