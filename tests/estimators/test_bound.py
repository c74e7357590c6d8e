"""The guaranteed bound eta >= |||u - u_h||| on the manufactured family (MATH.md sections 5, 7).

Checked for the exact discrete solution and for perturbed triples (feasible
and infeasible, lambda of both signs), truncated Newton-min iterates and the
interpolant of the exact solution with lambda_h = 0.  Not one case may
violate the bound.
"""

import numpy as np
import pytest

import fastmem as fm
from fastmem.errors import DataError

SIZES = (8, 16, 32, 64)
CASES = {
    "mu=(1,1)": dict(mu=(1.0, 1.0)),
    "mu=(1,10)": dict(mu=(1.0, 10.0)),
    "mu=(10,1)": dict(mu=(10.0, 1.0)),
    "mu=(1e-2,1e2)": dict(mu=(1e-2, 1e2)),
    "mu=(1,1) kappa=0": dict(mu=(1.0, 1.0), kappa=0.0),
    "mu=(1,10) kappa=0": dict(mu=(1.0, 10.0), kappa=0.0),
    "mu=(10,1) kappa=0": dict(mu=(10.0, 1.0), kappa=0.0),
    "mu=(1e-2,1e2) kappa=0": dict(mu=(1e-2, 1e2), kappa=0.0),
    "mu=(1,1) discontinuous": dict(mu=(1.0, 1.0), discontinuous=True),
    "mu=(1,10) discontinuous": dict(mu=(1.0, 10.0), discontinuous=True),
}


def _triples(ms, mesh, scene, exact, rng):
    """Perturbed and partial triples, each with the boundary values of X_gh x X_0h."""
    ii = mesh.interior_vertices
    scale_u = np.abs(exact.u1).max()
    scale_l = max(np.abs(exact.lam).max(), 1.0)
    out = {}
    for amp in (1e-3, 1e-1):
        u1, u2, lam = exact.u1.copy(), exact.u2.copy(), exact.lam.copy()
        u1[ii] += amp * scale_u * rng.standard_normal(ii.size)
        u2[ii] += amp * scale_u * rng.standard_normal(ii.size)
        lam[ii] += amp * scale_l * rng.standard_normal(ii.size)  # both signs
        out[f"noise {amp:g}"] = (u1, u2, lam)
    # feasible: gap >= 0 and lam >= 0, but not complementary
    u1, u2, lam = exact.u1.copy(), exact.u2.copy(), exact.lam.copy()
    u2[ii] -= 0.05 * scale_u * rng.random(ii.size)
    lam[ii] = np.maximum(lam[ii] + 0.1 * scale_l * rng.standard_normal(ii.size), 0.0)
    out["feasible"] = (u1, u2, lam)
    # infeasible: membranes interpenetrate, lambda negative somewhere
    u1, u2, lam = exact.u1.copy(), exact.u2.copy(), exact.lam.copy()
    u2[ii] += 0.05 * scale_u * rng.random(ii.size)
    lam[ii] = -np.abs(lam[ii]) - 0.01 * scale_l
    out["infeasible"] = (u1, u2, lam)
    for k in (1, 2):
        r = fm.solve(scene, max_newton=k, method="exact")
        out[f"newton {k}"] = (r.u1, r.u2, r.lam)
    u1, u2, _ = ms.interpolate(mesh)
    out["interpolant, lam=0"] = (u1, u2, np.zeros(mesh.n_vertices))
    return out


@pytest.mark.parametrize("case", list(CASES))
def test_bound_is_guaranteed(case, rng, caplog):
    ms = fm.Manufactured(**CASES[case])
    for n in SIZES:
        mesh = fm.Mesh.square(n)
        scene = ms.scene(mesh)
        exact = fm.solve(scene, estimate=True, method="exact")
        err = ms.energy_error(mesh, exact.u1, exact.u2)
        assert exact.eta >= err, (n, exact.eta, err)
        if n == SIZES[-1]:
            continue  # perturbed triples on the coarser meshes keep the test fast
        for name, (u1, u2, lam) in _triples(ms, mesh, scene, exact, rng).items():
            est = fm.estimate(scene, u1, u2, lam)
            e = ms.energy_error(mesh, u1, u2)
            assert est.eta >= e, (n, name, est.eta, e)


def test_effectivity_on_the_smooth_default_case():
    ms = fm.Manufactured()
    mesh = fm.Mesh.square(64)
    r = fm.solve(ms.scene(mesh), estimate=True, method="exact")
    eff = r.eta / ms.energy_error(mesh, r.u1, r.u2)
    assert 1.0 <= eff <= 1.5


def test_components_at_the_exact_discrete_solution():
    scene = fm.Scene(fm.Mesh.square(32), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    r = fm.solve(scene, estimate=True, method="exact")
    tot = r.estimate.totals
    assert tot["eta_lin"] == 0.0  # feasible: lam >= 0 and gap >= 0 at every vertex
    assert tot["eta_alg"] < 1e-10 * tot["eta_disc"]  # exact solve: R at round-off
    assert tot["eta"] <= tot["eta_disc"] + tot["eta_lin"] + tot["eta_alg"]
    assert set(r.estimate.maps) >= {"eta_F1", "eta_F2", "eta_nc", "eta_C"}
    for m in r.estimate.maps.values():
        assert m.shape == (scene.mesh.n_triangles,)
        assert np.all(m >= 0)


def test_components_react_to_their_causes():
    """eta_alg grows with the residual, eta_lin with infeasibility."""
    scene = fm.Scene(fm.Mesh.square(16), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    r = fm.solve(scene, method="exact")
    ii = scene.mesh.interior_vertices
    u1 = r.u1.copy()
    u1[ii[len(ii) // 2]] += 1e-3
    e_alg = fm.estimate(scene, u1, r.u2, r.lam).totals
    assert e_alg["eta_alg"] > 1e3 * fm.estimate(scene, r.u1, r.u2, r.lam).totals["eta_alg"]
    lam = r.lam.copy()
    lam[ii] -= 0.1
    assert fm.estimate(scene, r.u1, r.u2, lam).totals["eta_lin"] > 0


def test_estimate_validates_its_triple():
    scene = fm.Scene(fm.Mesh.square(4), f=(-1.0, 1.0), g=0.1)
    n = scene.mesh.n_vertices
    z = np.zeros(n)
    with pytest.raises(DataError, match="u1"):
        fm.estimate(scene, z, z, z)  # u1 must be g on the boundary
    u1 = scene.boundary_values.copy()
    with pytest.raises(DataError, match="lam"):
        fm.estimate(scene, u1, z, np.full(n, np.nan))
    with pytest.raises(DataError, match="u2"):
        fm.estimate(scene, u1, z[:-1], z)


def test_archive_keeps_the_estimate(tmp_path):
    r = fm.solve(fm.Scene(fm.Mesh.square(8), f=(-1.0, 1.0), g=0.1), estimate=True, method="exact")
    r.save(tmp_path / "r.h5")
    back = fm.load(tmp_path / "r.h5")
    assert back.eta == r.eta
    for k, v in r.estimate.maps.items():
        assert np.array_equal(back.estimate.maps[k], v)


def test_flux_term_kernel_matches_numpy_reference(rng):
    from fastmem.estimators.bound import _flux_terms_reference, flux_terms
    from fastmem.estimators.flux import reconstruct

    mesh = fm.Mesh.lshape(8)
    mu1 = rng.uniform(0.5, 2.0, mesh.n_triangles)
    scene = fm.Scene(mesh, mu=(mu1, 3.0), f=(lambda x, y: np.sin(x) - 1.0, 1.0), g=0.1)
    r = fm.solve(scene, method="exact")
    u1 = r.u1 + 0.01 * rng.standard_normal(mesh.n_vertices)
    fl = reconstruct(scene, u1, r.u2, r.lam)
    for a, b in zip(
        flux_terms(scene, u1, r.u2, fl), _flux_terms_reference(scene, u1, r.u2, fl), strict=True
    ):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)


# ------------------------------------------------ heterogeneous and extreme tensions


def _checkerboard(mesh, c, blocks=4):
    """Per-triangle values 1 and c on a blocks x blocks checkerboard of (-1, 1)^2."""
    cen = mesh.vertices[mesh.triangles].mean(axis=1)
    i = np.floor((cen[:, 0] + 1.0) / 2.0 * blocks)
    j = np.floor((cen[:, 1] + 1.0) / 2.0 * blocks)
    return np.where((i + j) % 2 == 0, 1.0, c)


def _reference_error(mesh, levels, build):
    """``err(u1, u2) = |||u_ref - u_h|||`` with u_ref ``levels`` refinements finer than mesh.

    ``build(mesh, k)`` makes the scene on a mesh whose triangles are the
    children of those of the coarse one, k per coarse triangle in order (the
    children inherit the tension).  The coarse P1 functions are prolonged
    exactly (vertex N + e of ``refine()`` is the midpoint of edge e); the
    energy norm uses the per-triangle tensions.
    """
    from fastmem.fem.assembly import assemble_stiffness

    chain = [mesh]
    for _ in range(levels):
        chain.append(chain[-1].refine())
    fine = chain[-1]
    ref_scene = build(fine, 4**levels)
    ref = fm.solve(ref_scene, method="exact")
    stiff = [assemble_stiffness(fine, mu) for mu in (ref_scene.mu1, ref_scene.mu2)]

    def err(u1, u2):
        for m in chain[:-1]:
            e = m.edges
            u1 = np.concatenate([u1, 0.5 * (u1[e[:, 0]] + u1[e[:, 1]])])
            u2 = np.concatenate([u2, 0.5 * (u2[e[:, 0]] + u2[e[:, 1]])])
        d1, d2 = ref.u1 - u1, ref.u2 - u2
        return float(np.sqrt(d1 @ (stiff[0] @ d1) + d2 @ (stiff[1] @ d2)))

    return err


@pytest.mark.parametrize("c", [1e6, 1e-6])
@pytest.mark.parametrize("mesh_name", ["structured", "jittered"])
def test_bound_holds_for_jumps_of_1e6(c, mesh_name, rng):
    """eta >= |||u_ref - u_h||| for a checkerboard mu1 in {1, c}, u_ref 3 refinements finer.

    Exact and inexact solves and a perturbed triple (R != 0, lam of both signs,
    interpenetration).  u_ref is itself an approximation: this checks eta
    against the part of the error the reference resolves.
    """
    from meshes import perturbed_square

    mesh = fm.Mesh.square(8) if mesh_name == "structured" else perturbed_square(8, 0.3)

    mu1 = _checkerboard(mesh, c)

    def build(m, k=1):
        return fm.Scene(m, mu=(np.repeat(mu1, k), 1.0), f=(-4.0, 2.0), g=0.1)

    err = _reference_error(mesh, 3, build)
    scene = build(mesh)
    for method in ("exact", "inexact"):
        r = fm.solve(scene, method=method, estimate=True)
        assert r.eta >= err(r.u1, r.u2), method
    ii = mesh.interior_vertices
    u1, u2, lam = r.u1.copy(), r.u2.copy(), r.lam.copy()
    u2[ii] += 0.02 * rng.standard_normal(ii.size)
    lam[ii] += 0.5 * rng.standard_normal(ii.size)
    assert fm.estimate(scene, u1, u2, lam).eta >= err(u1, u2)


@pytest.mark.parametrize("mu", [(1e-6, 1e6), (1e6, 1e-6), (1.0, 1e-6)])
def test_bound_holds_for_extreme_constant_tensions(mu):
    """Manufactured family (exact solution known): eta >= error, exact and perturbed triples."""
    ms = fm.Manufactured(mu=mu)
    rng = np.random.default_rng(37)
    for n in (8, 16):
        mesh = fm.Mesh.square(n)
        scene = ms.scene(mesh)
        r = fm.solve(scene, estimate=True, method="exact")
        assert r.eta >= ms.energy_error(mesh, r.u1, r.u2)
        ii = mesh.interior_vertices
        u1, u2, lam = r.u1.copy(), r.u2.copy(), r.lam.copy()
        scale = np.abs(u1).max()
        u1[ii] += 1e-3 * scale * rng.standard_normal(ii.size)
        lam[ii] += 0.1 * rng.standard_normal(ii.size)
        est = fm.estimate(scene, u1, u2, lam)
        assert est.eta >= ms.energy_error(mesh, u1, u2)


#: Checkerboard effectivities at n = 16 against a reference 3 refinements finer,
#: measured when the mu-weighted reconstruction and the redistributed contact
#: load landed (issue 16; before: 1.32, 2.84, 16.3 and 9.7): the upper limits are
#: the measured values plus 1 %, never to be loosened.  The low-mu cases are far
#: from the target 1.5: the floppy membrane's unresolved boundary layer, see
#: docs/heterogeneous.md.
CHECKERBOARD_EFFECTIVITY = {
    (1e3, (-1.0, 1.0)): 1.3169,
    (1e3, (-4.0, 2.0)): 2.8314,
    (1e-3, (-4.0, 2.0)): 15.5932,
    (1e-3, (-1.0, 1.0)): 9.5222,
}


@pytest.mark.parametrize(("c", "f"), list(CHECKERBOARD_EFFECTIVITY))
def test_checkerboard_effectivity(c, f):
    mesh = fm.Mesh.square(16)
    mu1 = _checkerboard(mesh, c)

    def build(m, k=1):
        return fm.Scene(m, mu=(np.repeat(mu1, k), 1.0), f=f, g=0.1)

    err = _reference_error(mesh, 3, build)
    r = fm.solve(build(mesh), method="exact", estimate=True)
    eff = r.eta / err(r.u1, r.u2)
    assert 1.0 <= eff <= 1.01 * CHECKERBOARD_EFFECTIVITY[(c, f)]
