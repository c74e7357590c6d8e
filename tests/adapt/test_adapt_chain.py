"""The adaptive loop's multigrid chain and its rounds of bisection (fastmem.adapt.loop).

Every mesh of the loop is a refinement of the one before, so its multigrid
hierarchy is the previous one plus a level (``extend_chain``); and with
``bisections=2`` each marked triangle is bisected twice per step, so the loop
makes fewer, larger meshes.
"""

import numpy as np
import pytest

import fastmem as fm
import fastmem.adapt.loop as afem
from fastmem.fem.assembly import assemble_stiffness
from fastmem.linalg.amg import PCG
from fastmem.linalg.gmg import NestedChain, NestedMG
from fastmem.mesh.refine import refine_marked


def _default(mesh):
    return fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, -1.0), g=0.1)


def _refined_chain(steps=5, bisections=1):
    """An L-shape refined ``steps`` times towards the re-entrant corner, and its chain.

    Returns the final mesh, the chain and the (mesh, refinement) of every step.
    """
    mesh, chain, steps_made = fm.Mesh.lshape(16), [], []
    for _ in range(steps):
        centroids = mesh.vertices[mesh.triangles].mean(axis=1)
        near = np.hypot(centroids[:, 0], centroids[:, 1])
        marked = near <= np.quantile(near, 0.3)
        fine, refinement = refine_marked(mesh, marked, validate=False, bisections=bisections)
        afem.extend_chain(chain, mesh, fine, refinement)
        steps_made.append((mesh, refinement))
        mesh = fine
    return mesh, chain, steps_made


@pytest.mark.parametrize("bisections", [1, 2])
def test_chain_links_interpolate_interior_values(bisections):
    mesh, chain, steps = _refined_chain(4, bisections)
    assert chain[0].shape[0] == mesh.interior_vertices.size
    for fine, coarse in zip(chain, chain[1:], strict=False):
        assert fine.shape[1] == coarse.shape[0]
    # coarser links are dropped once a level has fewer than CHAIN_MIN_UNKNOWNS rows
    assert chain[-1].shape[0] >= afem.CHAIN_MIN_UNKNOWNS or len(chain) == 1
    assert len(chain) < len(steps) or chain[-1].shape[1] < afem.CHAIN_MIN_UNKNOWNS
    # each kept link is the refinement's prolongation of functions vanishing on the boundary
    rng = np.random.default_rng(11)
    for k, link in enumerate(chain):
        coarse_mesh, refinement = steps[len(steps) - 1 - k]
        v = np.zeros(coarse_mesh.n_vertices)
        ic = coarse_mesh.interior_vertices
        v[ic] = rng.random(ic.size)
        fine_values = refinement.prolong(v)
        fine_mesh = mesh if k == 0 else steps[len(steps) - k][0]
        assert np.allclose(
            link @ v[ic], fine_values[fine_mesh.interior_vertices], rtol=0, atol=1e-15
        )


def test_geometric_multigrid_on_the_adaptive_chain_converges_fast():
    mesh, chain, _ = _refined_chain(8)
    assert len(chain) >= 2
    ii = mesh.interior_vertices
    a = assemble_stiffness(mesh)[ii][:, ii].tocsr()
    b = np.random.default_rng(3).random(a.shape[0])
    cg = PCG(a, b, np.zeros_like(b), NestedMG(a, NestedChain(chain)))
    its = cg.solve(1e-10, 200)
    assert np.linalg.norm(b - a @ cg.x) <= 1e-10 * np.linalg.norm(b)
    # 7 iterations; 25-34 with the 1/2 weights of one link's new vertices set to 1/4
    assert its <= 12, its


def test_loop_uses_the_chain_and_meets_the_tolerance():
    tol = 1.5e-2
    geo = fm.solve(_default(fm.Mesh.lshape(8)), tol=tol, multigrid="geometric")
    alg = fm.solve(_default(fm.Mesh.lshape(8)), tol=tol, multigrid="algebraic")
    for r in (geo, alg):
        assert r.converged
        assert r.eta <= tol
    used = [info["multigrid"] for info in geo.parameters["solver"]["levels"]]
    assert used[0] is None  # the first mesh (no coarser version): pyamg
    assert set(used[1:]) == {"geometric"}, used
    assert {info["multigrid"] for info in alg.parameters["solver"]["levels"]} <= {None, "two-grid"}
    # the same problem: the final bounds agree to the tolerance's scale
    assert abs(geo.eta - alg.eta) <= 0.2 * tol


def test_two_bisections_make_fewer_meshes():
    tol = 1.2e-2
    meshes = {}
    for rounds in (1, 2):
        r = fm.solve(_default(fm.Mesh.lshape(8)), tol=tol, bisections=rounds)
        assert r.parameters["adaptivity"]["bisections"] == rounds
        assert r.converged
        assert r.eta <= tol
        meshes[rounds] = r.adaptivity["n_vertices"].size
    assert meshes[2] < meshes[1], meshes


def test_min_growth_above_two_with_two_bisections():
    tol = 1.2e-2
    r = fm.solve(_default(fm.Mesh.lshape(8)), tol=tol, bisections=2, min_growth=2.5)
    assert r.converged
    assert r.eta <= tol
    n = r.adaptivity["n_vertices"]
    landed = {land["level"] for land in r.parameters["adaptivity"]["landings"]}
    ratios = [n[k + 1] / n[k] for k in range(n.size - 1) if k not in landed]
    assert ratios
    assert min(ratios) >= 2.5 * 0.94, ratios
    with pytest.raises(fm.errors.ParameterError, match="min_growth"):
        fm.solve(_default(fm.Mesh.lshape(8)), tol=tol, min_growth=2.5, bisections=1)


@pytest.mark.parametrize("value", [0, 4, 1.5])
def test_bad_bisections_are_named_before_solving(value):
    with pytest.raises(fm.errors.ParameterError, match="bisections"):
        fm.solve(_default(fm.Mesh.lshape(8)), tol=1e-2, bisections=value)


def test_two_bisections_in_the_obstacle_loop():
    from fastmem.problems.obstacles import ball

    r = fm.solve(ball(8), tol=6e-2, bisections=2)
    assert r.converged
    assert r.parameters["adaptivity"]["bisections"] == 2
    assert r.adaptivity["n_vertices"].size >= 2


@pytest.mark.parametrize("fraction", [0.1, 0.4])
def test_two_round_counts_land_near_the_aim(fraction):
    """The top set searched for with two rounds adds the vertices asked for (within 3 %)."""
    mesh, _, _ = _refined_chain(3)
    eta2 = np.random.default_rng(5).lognormal(size=mesh.n_triangles)
    count = afem._Counter(mesh, 2)
    dorfler = afem.dorfler_mark(eta2, 0.5)
    k0, n0 = int(dorfler.sum()), count.exact(dorfler)
    want = fraction * mesh.n_vertices
    marked = afem._mark_vertices(mesh, eta2, want, k0, n0, count)
    marked = afem._recount(mesh, eta2, want, marked, count, [(k0, n0)])
    assert eta2[marked].min() >= eta2[~marked].max()  # a top set
    fine, rounds = refine_marked(mesh, marked, bisections=2)
    assert abs(rounds.n_new_vertices - want) <= afem._ROUNDS_TOL * want, (
        rounds.n_new_vertices,
        want,
    )
    assert count.refine(marked)[0].n_vertices == fine.n_vertices


def test_later_rounds_stop_at_a_diameter():
    mesh = fm.Mesh.square(8)
    marked = np.ones(mesh.n_triangles, dtype=bool)
    limit = 1.01 * mesh.diameters.max() / 2**0.5  # the first round makes children of this size
    fine, rounds = refine_marked(mesh, marked, bisections=2, min_diameter=limit)
    once, _ = refine_marked(mesh, marked)
    assert fine.n_triangles == once.n_triangles  # no second round below the diameter
    free, _ = refine_marked(mesh, marked, bisections=2)
    assert free.n_triangles == 4 * mesh.n_triangles
