import logging

import naive
import numpy as np
import pytest
from meshes import SYMMETRIES, perturbed_square
from numpy.testing import assert_allclose

import fastmem as fm
from fastmem.errors import CyclingError, ParameterError
from fastmem.fem.residual import residuals


def _scene(mesh, mu, **kw):
    kw.setdefault("f", (-1.0, 1.0))
    kw.setdefault("g", 0.1)
    return fm.Scene(mesh, mu=mu, **kw)


def _rel(a, b):
    return np.abs(a - b).max() / max(np.abs(b).max(), 1e-300)


@pytest.mark.parametrize("mu", [(1.0, 10.0), (3.0, 0.2)])
@pytest.mark.parametrize("mesh_kind", ["square", "perturbed"])
def test_general_and_decoupled_agree(mu, mesh_kind):
    mesh = fm.Mesh.square(24) if mesh_kind == "square" else perturbed_square(16, 0.2)
    scene = _scene(mesh, mu)
    a = fm.solve(scene, path="decoupled", method="exact")
    b = fm.solve(scene, path="general", method="exact")
    assert a.path == "decoupled"
    assert b.path == "general"
    assert a.converged
    assert b.converged
    assert a.n_newton == b.n_newton
    assert np.array_equal(a.active, b.active)
    assert 0 < a.active.sum() < mesh.interior_vertices.size  # a real contact problem
    for x, y in ((a.u1, b.u1), (a.u2, b.u2), (a.lam, b.lam)):
        assert _rel(x, y) < 1e-10


def test_auto_path_choice():
    mesh = fm.Mesh.square(8)
    assert fm.solve(_scene(mesh, (1.0, 2.0)), method="exact").path == "decoupled"
    mu1 = np.full(mesh.n_triangles, 1.0)
    mu1[::2] = 2.0
    assert fm.solve(_scene(mesh, (mu1, 1.0)), method="exact").path == "general"
    with pytest.raises(ParameterError, match="decoupled"):
        fm.solve(_scene(mesh, (mu1, 1.0)), path="decoupled", method="exact")


@pytest.mark.parametrize("path", ["general", "decoupled"])
@pytest.mark.parametrize("mu", [(1.0, 1.0), (0.5, 4.0)])
def test_converged_solution_is_exactly_complementary(path, mu):
    mesh = perturbed_square(20, 0.25)
    scene = _scene(mesh, mu, f=(lambda x, y: -1.0 - x, 1.0))
    r = fm.solve(scene, path=path, method="exact")
    assert r.converged
    ii = mesh.interior_vertices
    gap, lam = (r.u1 - r.u2)[ii], r.lam[ii]
    assert np.all(np.minimum(gap, lam) == 0.0)
    assert lam.min() >= 0.0
    assert gap.min() >= 0.0
    assert r.active.sum() > 0
    assert (~r.active[ii]).sum() > 0
    f1, f2 = scene.loads
    scale = np.abs(f1).max() + np.abs(f2).max()
    r1, r2 = residuals(scene, r.u1, r.u2, r.lam)
    assert np.abs(r1).max() < 1e-11 * scale
    assert np.abs(r2).max() < 1e-11 * scale
    assert_allclose(r.r1, r1, atol=1e-14 * scale)
    # boundary conditions exactly
    bnd = mesh.boundary_vertices
    assert np.all(r.u1[bnd] == 0.1)
    assert np.all(r.u2[bnd] == 0.0)
    assert np.all(r.lam[bnd] == 0.0)
    # history
    h = r.history
    assert len(h["k"]) == r.n_newton
    assert h["n_changed"][-1] == 0
    assert h["comp_norm"][-1] == 0.0
    assert r.parameters["solver"]["relative_residual"] < 1e-12


@pytest.mark.parametrize("mu", [(1.0, 1.0), (2.0, 0.5)])
def test_matches_naive_coupled_active_set_solver(mu):
    mesh = perturbed_square(7, 0.25)
    scene = _scene(mesh, mu, f=(-3.0, 2.0), g=0.05)
    r = fm.solve(scene, path="general", method="exact")
    f1, f2 = scene.loads
    u1, u2, lam, _ = naive.contact_solve(mesh.vertices, mesh.triangles, mu[0], mu[1], f1, f2, 0.05)
    assert r.active.sum() > 0
    for x, y in ((r.u1, u1), (r.u2, u2), (r.lam, lam)):
        assert _rel(x, y) < 1e-10


def test_per_triangle_mu_matches_naive(rng):
    mesh = perturbed_square(6, 0.2)
    mu1 = rng.uniform(0.5, 2.0, mesh.n_triangles)
    scene = _scene(mesh, (mu1, 1.5), f=(-4.0, 2.0), g=0.05)
    r = fm.solve(scene, method="exact")
    a1 = naive.stiffness(mesh.vertices, mesh.triangles, mu1)
    f1, f2 = scene.loads
    ii = mesh.interior_vertices
    b = mesh.lumped_mass
    # the discrete equations hold at interior vertices
    assert_allclose((a1 @ r.u1 - b * r.lam - f1)[ii], 0.0, atol=1e-12)
    assert r.active.sum() > 0


@pytest.mark.parametrize("path", ["decoupled", "general"])
def test_default_scene_symmetric(path):
    mesh = fm.Mesh.square(32)
    r = fm.solve(fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1), path=path, method="exact")
    assert 0.0 < r.contact_fraction < 1.0
    x, y = mesh.vertices.T
    key = {(round(a, 12), round(b, 12)): k for k, (a, b) in enumerate(zip(x, y, strict=True))}
    scale = np.abs(r.u1).max()
    for sym in SYMMETRIES[1:]:
        sx, sy = sym(x, y)
        perm = np.array([key[(round(a, 12), round(b, 12))] for a, b in zip(sx, sy, strict=True)])
        for field in (r.u1, r.u2):
            assert np.abs(field[perm] - field).max() < 1e-12 * scale
        assert np.abs(r.lam[perm] - r.lam).max() < 1e-12 * np.abs(r.lam).max()
        assert np.array_equal(r.active[perm], r.active)


def test_initial_guess_at_solution_converges_in_one_step():
    scene = _scene(fm.Mesh.square(16), (1.0, 1.0))
    r = fm.solve(scene, method="exact")
    r2 = fm.solve(scene, initial=(r.u1, r.u2, r.lam), method="exact")
    assert r2.n_newton == 1
    assert r2.converged
    assert _rel(r2.u1, r.u1) < 1e-12


def test_step_limit_is_reported(caplog):
    scene = _scene(fm.Mesh.square(32), (1.0, 1.0))
    with caplog.at_level(logging.WARNING, logger="fastmem"):
        r = fm.solve(scene, max_newton=2, method="exact")
    assert not r.converged
    assert r.n_newton == 2
    assert "did not converge" in caplog.text


def test_cycling_is_detected(monkeypatch):
    """Without the safeguard, iterates alternating between two active sets raise CyclingError."""
    import fastmem.solver.newton as newton

    scene = _scene(fm.Mesh.square(6), (1.0, 1.0))
    n = scene.mesh.n_vertices
    ii = scene.mesh.interior_vertices

    class Flip:
        name = "flip"
        factorizations = 0
        calls = 0

        def solve(self, active):
            self.calls += 1
            lam = np.zeros(n)
            lam[ii[self.calls % 2]] = 1.0  # active set {v0}, {v1}, {v0}, ...
            return np.zeros(n), np.zeros(n), lam

    monkeypatch.setattr(newton, "make_step", lambda scene, path: Flip())
    with pytest.raises(CyclingError, match="cycles") as info:
        fm.solve(scene, method="exact", safeguard=False)
    assert info.value.history is not None
    assert len(info.value.history["k"]) >= 2


def test_monitor_receives_every_row():
    rows = []
    r = fm.solve(_scene(fm.Mesh.square(16), (1.0, 1.0)), monitor=rows.append, method="exact")
    assert [row["k"] for row in rows] == list(range(1, r.n_newton + 1))
