"""Unknown keywords of the public entry points (fastmem.errors.checked_keywords).

docs/api.md promises a ParameterError for an unknown keyword of ``fm.solve``,
raised before any work, naming the closest valid keyword and listing them all.
"""

from __future__ import annotations

import inspect

import pytest

import fastmem as fm
from fastmem.errors import ParameterError, closest_name


@pytest.fixture(scope="module")
def scene():
    return fm.Scene(fm.Mesh.square(4), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)


@pytest.mark.parametrize(
    ("typo", "meant"),
    [("tols", "tol"), ("Tol", "tol"), ("gama_alg", "gamma_alg"), ("maxnewton", "max_newton")],
)
def test_solve_names_the_closest_keyword(scene, typo, meant):
    with pytest.raises(ParameterError) as info:
        fm.solve(scene, **{typo: 1e-3})
    text = str(info.value)
    assert f"unknown keyword {typo!r} (did you mean {meant!r}?)" in text
    assert "valid keywords: scene, method, path, max_newton" in text
    assert isinstance(info.value, ValueError)  # as every ParameterError


def test_solve_lists_the_keywords_when_nothing_is_close(scene):
    with pytest.raises(ParameterError, match="valid keywords:") as info:
        fm.solve(scene, xyz=1, thetaa=0.3)
    text = str(info.value)
    assert "unknown keywords 'thetaa' (did you mean 'theta'?), 'xyz'; valid" in text


def test_solve_keeps_its_signature_and_works(scene):
    params = inspect.signature(fm.solve).parameters
    assert {"tol", "max_newton", "memory_limit"} <= set(params)
    assert params["tol"].kind is inspect.Parameter.KEYWORD_ONLY
    assert fm.solve(scene, method="exact", max_newton=50).converged


def test_warm_up_refuses_unknown_keywords():
    with pytest.raises(ParameterError, match=r"'adaptiv' \(did you mean 'adaptive'\?\)"):
        fm.warm_up("inexact", adaptiv=True)


@pytest.mark.parametrize(
    ("name", "choices", "expected"),
    [
        ("--N", ["--n", "--g", "--mesh"], "--n"),
        ("-n", ["--n", "--g"], "--n"),
        ("--gamma_alg", ["--gamma-alg", "--gamma-lin"], "--gamma-alg"),
        ("--tols", ["--tol", "--rtol", "--theta"], "--tol"),
        ("--foo", ["--f1", "--f2", "--mesh"], None),
        ("anything", [], None),
    ],
)
def test_closest_name(name, choices, expected):
    assert closest_name(name, choices) == expected


@pytest.mark.parametrize(
    ("call", "where", "typo", "meant"),
    [
        (lambda: fm.Scene(fm.Mesh.square(2), muu=(1.0, 1.0)), "fastmem.Scene", "muu", "mu"),
        (
            lambda: fm.Mesh([[0, 0], [1, 0], [0, 1]], [[0, 1, 2]], orient="fix"),
            "fastmem.Mesh",
            "orient",
            "orientation",
        ),
        (lambda: fm.estimate(None, 0, 0, 0, r_1=None), "fastmem.estimate", "r_1", "r1"),
        (lambda: fm.load("x.h5", paht="y"), "fastmem.load", "paht", "path"),
    ],
)
def test_other_entry_points(call, where, typo, meant):
    """The constructors and the other functions of fm refuse typos the same way."""
    with pytest.raises(ParameterError) as info:
        call()
    text = str(info.value)
    assert text.startswith(f"{where}() got the unknown keyword {typo!r} (did you mean {meant!r}?)")
    assert "self" not in text.split("valid keywords: ", 1)[1].split(", ")
