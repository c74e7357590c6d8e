"""The safeguard of Newton-min (fastmem.solver.safeguard): monotone, correct, wired into solve()."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from meshes import perturbed_square

import fastmem as fm
import fastmem.solver.newton as newton
import fastmem.solver.safeguard as sg
from fastmem.solver.linear import DecoupledStep, GeneralStep


def _scene(mesh, mu=(1.0, 1.0), **kw):
    kw.setdefault("f", (-1.0, 1.0))
    kw.setdefault("g", 0.1)
    return fm.Scene(mesh, mu=mu, **kw)


def _energy(scene, u1, u2):
    a1, a2 = scene.weighted_stiffness(1), scene.weighted_stiffness(2)
    f1, f2 = scene.loads
    return 0.5 * u1 @ (a1 @ u1) + 0.5 * u2 @ (a2 @ u2) - f1 @ u1 - f2 @ u2


def _pgs_gap(scene, sweeps=20000, tol=1e-14):
    """Independent reference: projected Gauss-Seidel on the obstacle problem of the gap.

    Constant mu: w = u1 - u2 minimises 1/2 w^T A w - r^T w over w >= 0 (docs/method.md §3.3),
    with A the interior Laplacian and r = F1/mu1 - F2/mu2 - A_IB g_B.
    """
    step = DecoupledStep(scene)
    a = step.a_ii.toarray()
    r = step.rhs_w
    w = np.zeros(r.size)
    diag = np.diag(a)
    for _ in range(sweeps):
        w_old = w.copy()
        for i in range(r.size):  # tiny test mesh: a plain loop is the point (independence)
            w[i] = max(0.0, w[i] + (r[i] - a[i] @ w) / diag[i])
        if np.abs(w - w_old).max() <= tol * max(np.abs(w).max(), 1e-300):
            break
    return w


def test_merit_stalled_counts_steps_without_a_new_best(monkeypatch):
    monkeypatch.setattr(sg, "STALL_STEPS", 2)
    tracker = [np.inf, 0]
    assert not sg.merit_stalled(tracker, 1.0)
    assert not sg.merit_stalled(tracker, 0.5)
    assert not sg.merit_stalled(tracker, 0.7)  # 1 step without a new best
    assert sg.merit_stalled(tracker, 0.6)  # 2 steps
    assert not sg.merit_stalled(tracker, 0.1)  # a new best resets the count


@pytest.mark.parametrize("amount", [0.0, 0.45])
def test_safeguard_matches_independent_projected_gauss_seidel(amount):
    """From a hostile start the safeguard reaches the KKT point that PGS finds independently."""
    mesh = perturbed_square(8, amount)
    scene = _scene(mesh, f=(-4.0, 4.0), g=0.05)
    if amount:  # the perturbed mesh must really be a non-M-matrix case
        a = scene.stiffness.tocoo()
        assert (a.data[a.row != a.col] > 1e-12).any()
    ii = mesh.interior_vertices
    step = GeneralStep(scene)
    rng = np.random.default_rng(3)
    u1 = rng.normal(size=mesh.n_vertices)
    u2 = rng.normal(size=mesh.n_vertices)
    out = sg.monotone_active_set(scene, step.solve, u1, u2, max_steps=200)
    assert out.converged
    assert np.all(np.diff(out.energies) <= 1e-12 * np.abs(out.energies).max())
    w_ref = _pgs_gap(scene)
    gap = (out.u1 - out.u2)[ii]
    assert np.abs(gap - w_ref).max() <= 1e-9 * np.abs(w_ref).max()
    # KKT: feasible, non-negative multiplier, complementarity, equations at round-off
    lam = out.lam[ii]
    assert gap.min() >= -1e-12
    assert lam.min() >= -1e-10 * lam.max()
    assert np.abs(np.minimum(gap, lam)).max() <= 1e-10 * max(lam.max(), gap.max())
    r1, r2 = fm.fem.residual.residuals(scene, out.u1, out.u2, out.lam)
    f1, f2 = scene.loads
    assert np.sqrt(r1 @ r1 + r2 @ r2) <= 1e-10 * np.sqrt(f1 @ f1 + f2 @ f2)
    # and the energy of the KKT point is below the energy of the projected start
    assert _energy(scene, out.u1, out.u2) <= out.energies[0]


def test_release_rule_falls_back_to_one_vertex_when_stuck():
    """A working set of every interior vertex (full contact start) is released in few steps."""
    scene = _scene(fm.Mesh.square(16))
    ii = scene.mesh.interior_vertices
    step = GeneralStep(scene)
    u = scene.boundary_values.copy()
    out = sg.monotone_active_set(scene, step.solve, u, u, max_steps=100)
    assert out.converged
    ref = fm.solve(scene, method="exact")
    assert np.abs(out.u1 - ref.u1).max() <= 1e-12 * np.abs(ref.u1).max()
    assert np.array_equal(out.active & (out.lam[ii] > 0), ref.active[ii] & (ref.lam[ii] > 0))
    assert out.steps <= 2 * ref.n_newton + 2


def test_cycling_newton_min_is_rescued(monkeypatch, caplog):
    """Newton-min that cycles hands over to the safeguard, which returns the exact solution."""
    scene = _scene(fm.Mesh.square(8))
    n = scene.mesh.n_vertices
    ii = scene.mesh.interior_vertices
    real = GeneralStep(scene)

    class CyclingStep:
        """The real linear step, except that its first three answers alternate two sets."""

        name = "general"
        factorizations = 0
        calls = 0

        def solve(self, active):
            self.calls += 1
            if self.calls > 3:
                return real.solve(active)
            lam = np.zeros(n)
            lam[ii[self.calls % 2]] = 1.0  # Newton-min reads the sets {v1}, {v0}, {v1}
            return np.zeros(n), np.zeros(n), lam

    monkeypatch.setattr(newton, "make_step", lambda scene, path: CyclingStep())
    with caplog.at_level(logging.WARNING, logger="fastmem"):
        r = fm.solve(scene, method="exact")
    monkeypatch.undo()
    ref = fm.solve(scene, method="exact")
    assert "cycles" in caplog.text
    assert "safeguard" in caplog.text
    guard = r.parameters["solver"]["safeguard"]
    assert guard["uses"] == 1
    assert guard["triggers"] == ["level 0: cycle at step 3"]
    assert guard["reached_kkt"] == [True]
    assert r.converged
    assert np.abs(r.u1 - ref.u1).max() <= 1e-12 * np.abs(ref.u1).max()
    assert np.abs(r.lam - ref.lam).max() <= 1e-10 * np.abs(ref.lam).max()
    assert r.history["safeguard"].sum() == guard["steps"] > 0
    assert r.n_newton == len(r.history["k"])


@pytest.mark.parametrize(
    ("method", "path"),
    [
        ("exact", "general"),
        ("exact", "decoupled"),
        ("exact-amg", "general"),
        ("exact-amg", "decoupled"),
        ("inexact", "general"),
        ("inexact", "decoupled"),
    ],
)
def test_stall_trigger_on_every_method_and_path(monkeypatch, method, path):
    """Forced to take over at step 2, the safeguard reaches the same solution, then stops."""
    scene = _scene(fm.Mesh.square(24), mu=(1.0, 3.0))
    ref = fm.solve(scene, method="exact")
    monkeypatch.setattr(sg, "STALL_STEPS", 0)
    r = fm.solve(scene, method=method, path=path, nested=False)
    guard = r.parameters["solver"]["safeguard"]
    assert guard["uses"] == 1
    assert guard["reached_kkt"] == [True]
    assert "stall" in guard["triggers"][0]
    assert r.converged
    tol = 1e-12 if method == "exact" else 1e-9
    assert np.abs(r.u1 - ref.u1).max() <= tol * np.abs(ref.u1).max()
    assert np.abs(r.u2 - ref.u2).max() <= tol * np.abs(ref.u1).max()
    # the safeguard is not a slow crawl: about as many face solves as Newton-min steps
    assert guard["steps"] <= ref.n_newton + 2
    assert r.history["safeguard"].sum() == guard["steps"]
    assert np.all(np.isfinite([r.u1, r.u2, r.lam]))


def test_safeguard_false_keeps_the_plain_iteration(monkeypatch):
    scene = _scene(fm.Mesh.square(16))
    monkeypatch.setattr(sg, "STALL_STEPS", 0)
    r = fm.solve(scene, method="exact", safeguard=False)
    assert r.parameters["solver"]["safeguard"]["uses"] == 0
    assert r.history["safeguard"].sum() == 0


def test_safeguard_flag_is_validated():
    with pytest.raises(fm.errors.InputTypeError, match="safeguard"):
        fm.solve(_scene(fm.Mesh.square(4)), safeguard="yes")


def test_safeguard_in_archive_round_trip(tmp_path, monkeypatch):
    monkeypatch.setattr(sg, "STALL_STEPS", 0)
    r = fm.solve(_scene(fm.Mesh.square(12)), method="exact")
    r.save(tmp_path / "r.h5")
    back = fm.load(tmp_path / "r.h5")
    assert np.array_equal(back.history["safeguard"], r.history["safeguard"])
    assert back.parameters["solver"]["safeguard"]["uses"] == 1
