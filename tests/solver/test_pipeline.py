"""The solve pipeline: option objects, one history schema, nested iteration for every method."""

import dataclasses
import math

import numpy as np
import pytest

import fastmem as fm
from fastmem.errors import InputTypeError, ParameterError
from fastmem.solver.history import HISTORY_COLUMNS
from fastmem.solver.options import InnerOptions, NewtonOptions, RecordOptions, SolveOptions

METHODS = ("inexact", "exact-amg", "exact")
SCENE = fm.Scene(fm.Mesh.square(64), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)


@pytest.fixture(scope="module")
def results():
    return {
        (m, p): fm.solve(SCENE, method=m, path=p) for m in METHODS for p in ("general", "decoupled")
    }


def test_options_are_frozen_and_validated_once():
    opts = SolveOptions.from_keywords(method="exact", gamma_alg=0.2, max_inner=7)
    assert opts.newton.method == "exact"
    assert opts.newton.exact
    assert opts.inner.gamma_alg == 0.2
    assert opts.inner.max_inner == 7
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.newton.method = "inexact"
    with pytest.raises(TypeError):  # the AMG options are a read-only mapping
        opts.inner.amg_options["cycle"] = "W"
    assert InnerOptions().amg_options["cycle"] == "V"


@pytest.mark.parametrize(
    ("make", "error", "match"),
    [
        (lambda: NewtonOptions(method="newton"), ParameterError, "method"),
        (lambda: NewtonOptions(path="diagonal"), ParameterError, "path"),
        (lambda: NewtonOptions(max_newton=0), ParameterError, "max_newton"),
        (lambda: NewtonOptions(max_newton=2.5), ParameterError, "max_newton"),
        (lambda: NewtonOptions(gamma_lin=math.nan), ParameterError, "gamma_lin"),
        (lambda: NewtonOptions(nested="sometimes"), ParameterError, "nested"),
        (lambda: NewtonOptions(estimate=1), InputTypeError, "estimate"),
        (lambda: InnerOptions(gamma_alg=-1.0), ParameterError, "gamma_alg"),
        (lambda: InnerOptions(amg_reuse=-0.1), ParameterError, "amg_reuse"),
        (lambda: InnerOptions(amg_options={"colour": 1}), ParameterError, "colour"),
        (lambda: RecordOptions(monitor=3), InputTypeError, "monitor"),
        (lambda: SolveOptions.from_keywords(gama_alg=0.1), ParameterError, "gama_alg"),
    ],
)
def test_bad_options_name_the_field(make, error, match):
    with pytest.raises(error, match=match):
        make()


def test_one_history_schema_for_every_method(results):
    for (method, path), r in results.items():
        h = r.history
        assert tuple(h) == HISTORY_COLUMNS, (method, path)
        n = len(h["k"])
        assert all(len(h[c]) == n for c in HISTORY_COLUMNS)
        for name in HISTORY_COLUMNS:
            if name not in ("eta", "eta_disc"):
                assert np.isfinite(h[name]).all(), (method, path, name)
        # eta exactly where a flux was reconstructed
        assert np.array_equal(np.isfinite(h["eta"]), h["fresh_disc"] == 1)
        # the last row is the returned triple
        assert h["n_changed"][-1] == 0 or not r.converged
        assert h["res_norm"][-1] == pytest.approx(np.hypot(*map(np.linalg.norm, (r.r1, r.r2))))
        levels = r.parameters["solver"]["levels"]
        assert [lv["level"] for lv in levels] == sorted(set(h["level"].tolist()))
        assert r.n_newton == levels[-1]["newton"] == h["k"][h["level"] == h["level"].max()].max()


def test_exact_methods_agree_and_use_nested_iteration(results):
    """Nested iteration for "exact" too: fewer finest steps, the same discrete solution."""
    plain = fm.solve(SCENE, method="exact", nested=False)
    ref = results[("exact", "decoupled")]
    assert len(ref.parameters["solver"]["levels"]) == 3  # 17^2, 33^2 and 65^2 vertices
    assert ref.n_newton < plain.n_newton
    scale = np.abs(plain.u1).max()
    for r in results.values():
        if r.method == "inexact":
            continue
        assert np.abs(r.u1 - plain.u1).max() <= 1e-10 * scale
        assert np.abs(r.u2 - plain.u2).max() <= 1e-10 * scale
        assert np.array_equal(r.active, plain.active)
        assert r.converged


def test_history_rows_reach_the_monitor_as_recorded():
    rows = []
    r = fm.solve(SCENE, method="exact-amg", monitor=rows.append)
    assert len(rows) == len(r.history["k"])
    for name in HISTORY_COLUMNS:
        assert np.array_equal(
            np.asarray([row[name] for row in rows], dtype=float),
            r.history[name].astype(float),
            equal_nan=True,
        )


def test_archive_keeps_the_schema(results, tmp_path):
    r = results[("exact", "general")]
    r.save(tmp_path / "r.h5")
    back = fm.load(tmp_path / "r.h5")
    assert tuple(back.history) == HISTORY_COLUMNS
    for name in HISTORY_COLUMNS:
        assert np.array_equal(back.history[name], r.history[name], equal_nan=True)
