"""The inexact step frees its system matrices during a flux reconstruction (issue 15).

:meth:`fastmem.adaptive.AdaptiveStep.spill` drops the CG matrices (decoupled: the
interior Laplacian and the gap matrix; general: ``K_II`` and the reduced matrix) and
the consistent mass matrix before each flux reconstruction, and ``restore`` rebuilds
them when the level goes on.  Only the memory peak may change: the results must be
bit for bit those of a solve that keeps everything.
"""

import numpy as np
import pytest

import fastmem as fm
from fastmem import adaptive, steps


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
    spilled = _solve(path, mu)
    assert any(rebuilt), "no flux check was followed by a rebuild: the test proves nothing"
    monkeypatch.setattr(adaptive.AdaptiveStep, "spill", lambda self: None)
    kept = _solve(path, mu)
    for name in ("u1", "u2", "lam", "r1", "r2"):
        np.testing.assert_array_equal(getattr(spilled, name), getattr(kept, name))
    assert spilled.eta == kept.eta
    for col in ("inner", "eta_disc", "eta_alg", "eta_lin", "fresh_disc"):
        np.testing.assert_array_equal(spilled.history[col], kept.history[col])


@pytest.mark.parametrize(("path", "mu"), [("auto", (1.0, 1.0)), ("general", (1.0, 2.0))])
def test_flux_runs_without_the_system_matrices(monkeypatch, path, mu):
    seen = []
    original = adaptive.AdaptiveStep.spill

    def spy(self):
        original(self)
        cg = self.cg
        if self.decoupled:
            held = [cg.a_ii, cg.system.a_ii, cg.pre_all.matrix, getattr(cg.cg_w, "a", None)]
        else:
            held = [cg.system.k_ii, getattr(cg, "mat", None)]
        seen.append(all(m is None for m in held) and "M" not in cg.system.scene._cache)

    monkeypatch.setattr(adaptive.AdaptiveStep, "spill", spy)
    _solve(path, mu, n=32)
    assert seen
    assert all(seen)
