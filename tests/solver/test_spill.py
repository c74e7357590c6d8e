"""The inexact step frees its system matrices during a flux reconstruction (issue 15).

:meth:`fastmem.solver.inexact.AdaptiveStep.spill` drops the CG matrices (decoupled: the
interior Laplacian, its diagonal and the gap matrix; general: ``K_II``, ``A1_II``, the
reduced matrix and the prolongation), the CGs' right-hand sides, the AMG hierarchies,
the consistent mass matrix and the scene's stiffness matrices before each flux
reconstruction, and ``restore`` rebuilds them when the level goes on.  Only the
memory peak may change: the results must be bit for bit those of a solve that keeps
everything.  With ``SPILL = "auto"`` spilling happens under memory pressure
(:func:`fastmem.solver.inexact.memory_pressure`) and on decoupled meshes of at least
``SPILL_MIN_TRIANGLES`` triangles; the tests force it on or off.
"""

import numpy as np
import pytest

import fastmem as fm
from fastmem.solver import inexact as adaptive
from fastmem.solver import steps


def _scene(n, mu):
    return fm.Scene(fm.Mesh.square(n), mu=mu, f=(-1.0, 1.0), g=0.1)


def _solve(path, mu, n=64):
    return fm.solve(_scene(n, mu), path=path)


@pytest.mark.parametrize(("path", "mu"), [("auto", (1.0, 1.0)), ("general", (1.0, 2.0))])
def test_spill_changes_no_result(monkeypatch, path, mu):
    rebuilt = []
    for cls, freed in ((steps.DecoupledCG, "a_ii"), (steps.GeneralCG, None)):
        original = cls.restore

        def counting(self, _orig=original, _freed=freed):
            gone = getattr(self, _freed) is None if _freed else self.system.k_ii is None
            rebuilt.append(gone)
            return _orig(self)

        monkeypatch.setattr(cls, "restore", counting)
    monkeypatch.setattr(adaptive, "SPILL", True)
    spilled = _solve(path, mu)
    assert any(rebuilt), "no flux check was followed by a rebuild: the test proves nothing"
    levels = spilled.parameters["solver"]["levels"]
    assert all(lv["spill"] for lv in levels)
    # a hierarchy was freed and built again by a restore on some level
    assert sum(lv.get("spill_setups", 0) for lv in levels) > 0
    monkeypatch.setattr(adaptive, "SPILL", False)
    kept = _solve(path, mu)
    assert not any(lv["spill"] for lv in kept.parameters["solver"]["levels"])
    for name in ("u1", "u2", "lam", "r1", "r2"):
        np.testing.assert_array_equal(getattr(spilled, name), getattr(kept, name))
    assert spilled.eta == kept.eta
    for col in ("inner", "inner_total", "eta_disc", "eta_alg", "eta_lin", "fresh_disc"):
        np.testing.assert_array_equal(spilled.history[col], kept.history[col])
    for name, values in kept.estimate.maps.items():
        np.testing.assert_array_equal(spilled.estimate.maps[name], values)
    for a, b in zip(levels, kept.parameters["solver"]["levels"], strict=True):
        assert a["amg_setups"] == b["amg_setups"]  # rebuilds are booked apart


@pytest.mark.parametrize(("path", "mu"), [("auto", (1.0, 1.0)), ("general", (1.0, 2.0))])
def test_flux_runs_without_the_system_matrices(monkeypatch, path, mu):
    seen = []
    original = adaptive.AdaptiveStep.spill

    def spy(self):
        original(self)
        cg = self.cg
        if self.decoupled:
            held = [cg.a_ii, cg.system.a_ii, cg.pre_all.matrix, cg.diag]
            # the hierarchy: pyamg's (LazyAMG, TwoGridLaplacian) or the nested one (NestedMG)
            held += [getattr(cg.pre_all, k, None) for k in ("pre", "levels", "_ops")]
            if cg.cg_w is not None:
                held += [cg.cg_w.a, cg.cg_w.b]
            if cg.pre_w is not cg.pre_all:
                held.append(cg.pre_w)
        else:
            held = [cg.system.k_ii, cg.system.a1_ii, cg.mat, cg.pre, cg.p, cg.cg.a, cg.cg.m]
        cache = cg.system.scene._cache
        seen.append(all(m is None for m in held) and not {"M", "A", "A1", "A2"} & set(cache))

    monkeypatch.setattr(adaptive, "SPILL", True)
    monkeypatch.setattr(adaptive.AdaptiveStep, "spill", spy)
    _solve(path, mu, n=32)
    assert seen
    assert all(seen)


def test_no_spill_without_memory_pressure(monkeypatch):
    """``SPILL = "auto"``: a small mesh keeps everything (no rebuild costs time)."""
    calls = []
    monkeypatch.setattr(steps.DecoupledCG, "spill", lambda self: calls.append(1))
    result = _solve("auto", (1.0, 1.0), n=32)
    assert adaptive.SPILL == "auto"
    assert not calls
    assert not any(lv["spill"] for lv in result.parameters["solver"]["levels"])


def test_auto_spills_on_large_decoupled_meshes_only(monkeypatch):
    """``SPILL = "auto"``: decoupled levels from ``SPILL_MIN_TRIANGLES`` on, general ones not."""
    monkeypatch.delenv(fm.memory.MEMORY_LIMIT_ENV, raising=False)
    monkeypatch.setattr(adaptive, "meminfo_bytes", lambda key: None)  # no memory pressure
    monkeypatch.setattr(adaptive, "SPILL_MIN_TRIANGLES", 2 * 32 * 32)  # the n = 32 level on
    assert adaptive.SPILL == "auto"
    for path, mu, want in (("auto", (1.0, 1.0), True), ("general", (1.0, 2.0), False)):
        levels = _solve(path, mu, n=32).parameters["solver"]["levels"]
        big = [lv["spill"] for lv in levels if lv["n_vertices"] >= 33 * 33]
        small = [lv["spill"] for lv in levels if lv["n_vertices"] < 33 * 33]
        assert big == [want], (path, levels)
        assert small
        assert not any(small)


def test_memory_pressure_compares_the_guard_estimate_with_the_memory_at_hand(monkeypatch):
    mesh = fm.Mesh.square(8)
    need = fm.memory.estimate_memory(mesh.n_vertices, mesh.n_triangles, "inexact", True)
    monkeypatch.delenv(fm.memory.MEMORY_LIMIT_ENV, raising=False)
    monkeypatch.setattr(adaptive, "meminfo_bytes", lambda key: None)  # the guard's limit only
    monkeypatch.setenv(fm.memory.MEMORY_LIMIT_ENV, str(4 * need))
    assert not adaptive.memory_pressure(mesh)  # 1/4 of the limit < SPILL_FRACTION = 1/2
    assert adaptive.memory_pressure(mesh, fraction=0.2)
    monkeypatch.setenv(fm.memory.MEMORY_LIMIT_ENV, str(need))
    assert adaptive.memory_pressure(mesh)
    # the system's available memory counts too (here: less than the guard's limit)
    monkeypatch.setenv(fm.memory.MEMORY_LIMIT_ENV, str(100 * need))
    monkeypatch.setattr(adaptive, "rss_bytes", lambda: 0)
    monkeypatch.setattr(adaptive, "meminfo_bytes", lambda key: need)
    assert adaptive.memory_pressure(mesh)
    monkeypatch.setenv(fm.memory.MEMORY_LIMIT_ENV, "off")  # no guard limit: available only
    assert adaptive.memory_pressure(mesh)
    monkeypatch.setattr(adaptive, "meminfo_bytes", lambda key: None)
    assert not adaptive.memory_pressure(mesh)  # nothing known: no pressure


def test_solve_memory_limit_reaches_the_spill_decision(monkeypatch):
    """``fm.solve(..., memory_limit=...)`` steers spilling like FASTMEM_MEMORY_LIMIT.

    A limit between the guard's estimate and twice it is accepted by the guard and
    makes the inexact step spill (estimate above SPILL_FRACTION = 1/2 of the limit);
    the same solve with a generous limit keeps everything, and both give the same
    triple (spilling changes no result).
    """
    scene = fm.Scene(fm.Mesh.square(32), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    mesh = scene.mesh
    need = fm.memory.estimate_memory(mesh.n_vertices, mesh.n_triangles, "inexact", True)
    monkeypatch.delenv(fm.memory.MEMORY_LIMIT_ENV, raising=False)
    monkeypatch.setattr(adaptive, "meminfo_bytes", lambda key: None)  # the limit alone
    tight = fm.solve(scene, memory_limit=int(1.5 * need))
    loose = fm.solve(scene, memory_limit=int(100 * need))
    assert tight.parameters["solver"]["levels"][-1]["spill"]
    assert not any(lv["spill"] for lv in loose.parameters["solver"]["levels"])
    np.testing.assert_array_equal(tight.u1, loose.u1)
    np.testing.assert_array_equal(tight.lam, loose.lam)
    assert adaptive.memory_pressure(mesh, limit=int(1.5 * need))
    assert not adaptive.memory_pressure(mesh, limit=False)  # no limit, nothing known
    with pytest.raises(fm.errors.ParameterError, match="memory_limit"):
        fm.solve(scene, memory_limit="lots")
