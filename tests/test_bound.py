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
    from fastmem.bound import _flux_terms_reference, flux_terms
    from fastmem.flux import reconstruct

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
