"""The stress matrix (issue 6): hard cases x solver variants, see cases.py and checks.py.

The fast subset runs by default (small meshes, "exact" and "inexact" on every
case, "exact-amg" on a subset, "exact" without safeguard on non-M-matrix
meshes).  ``FASTMEM_STRESS=full`` enables the full matrix (bigger meshes,
every method); without it the full tests are skipped with that reason.
A row of ``known.KNOWN`` turns its (case, variant) into a strict xfail.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

import fastmem as fm

from . import meshes
from .cases import CASES, CASES_BY_NAME, matrix
from .checks import nonfinite_fields, run
from .known import known_breakage

FULL = os.environ.get("FASTMEM_STRESS", "").strip().lower() == "full"
FULL_REASON = "full stress matrix (bigger meshes, all methods): set FASTMEM_STRESS=full"


def _params(mode):
    out = []
    for case, variant in matrix(mode):
        marks = []
        reason = known_breakage(case.name, variant, mode)
        if reason:
            marks.append(pytest.mark.xfail(strict=True, reason=reason))
        out.append(pytest.param(case.name, variant, id=f"{case.name}[{variant}]", marks=marks))
    return out


def _check(name, variant, mode):
    rec = run(CASES_BY_NAME[name], variant, mode)
    if rec.skipped:
        pytest.skip(rec.skipped)
    details = (
        f"{name} [{variant}, {mode}]: outcome {rec.outcome}, Newton {rec.n_newton}, "
        f"safeguard {rec.safeguard}, eta {rec.eta}, error {rec.error}, info {rec.info}"
    )
    assert not rec.problems, details + "\n  - " + "\n  - ".join(rec.problems)


@pytest.mark.parametrize(("name", "variant"), _params("fast"))
def test_stress_fast(name, variant):
    _check(name, variant, "fast")


@pytest.mark.skipif(not FULL, reason=FULL_REASON)
@pytest.mark.parametrize(("name", "variant"), _params("full"))
def test_stress_full(name, variant):
    _check(name, variant, "full")


# ------------------------------------------------------------------ the suite itself


def test_case_table_is_well_formed():
    assert len({c.name for c in CASES}) == len(CASES)
    groups = {c.group for c in CASES}
    assert {"mu", "g", "scale", "mesh", "contact", "data", "domain"} <= groups
    for case in CASES:
        assert case.description
        assert {"exact", "inexact"} <= set(case.variants("fast"))
        assert {"exact", "inexact", "exact-amg"} <= set(case.variants("full"))


def test_non_m_matrix_meshes_really_have_positive_offdiagonals():
    """The suite's obtuse / perturbed meshes are what their names claim (and the square is not)."""
    assert meshes.positive_offdiagonals(meshes.square(16)) == 0
    for mesh in (
        meshes.perturbed(16),
        meshes.anti_delaunay(16),
        meshes.criss_cross(32, 4),
        meshes.criss_cross(128, 4),
    ):
        assert meshes.positive_offdiagonals(mesh) > 0
        assert meshes.max_angle_degrees(mesh) > 100.0


def test_stretched_meshes_reach_aspect_ratio_1e3():
    assert meshes.max_aspect_ratio(meshes.stretched_rectangle(16)) >= 1e3
    assert meshes.max_aspect_ratio(meshes.boundary_layer(16, 1e3)) >= 0.99e3
    assert meshes.max_aspect_ratio(meshes.scaled(meshes.square(16), 1e3, 1.0)) >= 1e3


def test_checks_detect_nan_and_a_violated_bound():
    """The checks can fail: a poisoned result and an impossible bound are both reported."""
    scene = fm.Manufactured().scene(meshes.square(8))
    res = fm.solve(scene, method="exact", estimate=True)
    assert nonfinite_fields(res) == []
    res.lam = res.lam.copy()
    res.lam[5] = np.nan
    res.estimate.maps["eta_C"] = res.estimate.maps["eta_C"].copy()
    res.estimate.maps["eta_C"][0] = np.inf
    bad = nonfinite_fields(res)
    assert any(b.startswith("lam") for b in bad)
    assert any("eta_C" in b for b in bad)


def test_run_reports_a_bound_violation(monkeypatch):
    """If the library returned a too-small eta, the record carries a 'bound violated' problem."""
    real = fm.solve

    def shrunk(*args, **kwargs):
        r = real(*args, **kwargs)
        r.estimate.totals["eta"] *= 1e-3
        return r

    monkeypatch.setattr(fm, "solve", shrunk)
    rec = run(CASES_BY_NAME["mms-mu=1,1e6"], "exact", "fast")
    assert any("bound violated" in p for p in rec.problems)
    assert any("recomputed eta" in p for p in rec.problems)
