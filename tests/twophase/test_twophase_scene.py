"""Two-phase scene files: units checked, the benchmark reproduced, bad files refused."""

import pathlib

import numpy as np
import pytest

from fastmem.cli.main import main
from fastmem.errors import ParameterError
from fastmem.twophase import YEAR, benchmark, simulate
from fastmem.twophase.scene import load_scene, quantity

EXAMPLE = pathlib.Path(__file__).resolve().parents[2] / "examples" / "twophase_benchmark.toml"


def test_the_example_scene_file_is_the_benchmark():
    problem, options = load_scene(EXAMPLE)
    ref = benchmark("momas")
    assert problem.physics == ref.physics
    assert np.allclose(problem.hydrogen, ref.hydrogen, rtol=1e-14)
    assert np.array_equal(problem.boundary, ref.boundary)
    assert options["dt"] == pytest.approx(5000 * YEAR)
    assert options["t_end"] == pytest.approx(5e5 * YEAR)
    assert options["strategy"] == "adaptive"
    a = simulate(problem, t_end=4 * 5000 * YEAR, linear_solver="direct", estimate=False)
    b = simulate(ref, t_end=4 * 5000 * YEAR, linear_solver="direct", estimate=False)
    # the rate went through "kg/m2/year": equal up to the last bit, and so the states
    assert np.abs((a.final - b.final) / ref.units()).max() <= 1e-10


@pytest.mark.parametrize(
    ("value", "field", "si"),
    [
        ("3 darcy", "physics.permeability", 3 * 9.869233e-13),
        ("1 cP", "physics.mu_l", 1e-3),
        ("2 g/mol", "physics.molar_h", 2e-3),
        ("5.57e-6 kg/m2/year", "injection.rate", 5.57e-6 / YEAR),
        ("7.65e-6 mol/(Pa m3)", "physics.henry", 7.65e-6),
        ("3e-9 m^2 s^-1", "physics.diffusion", 3e-9),
        ("1 bar", "boundary.pressure", 1e5),
        (0.15, "physics.porosity", 0.15),
    ],
)
def test_units_convert_to_si(value, field, si):
    assert quantity(value, field) == pytest.approx(si, rel=1e-12)


@pytest.mark.parametrize(
    ("value", "field", "message"),
    [
        ("5e-20 m", "physics.permeability", r"dimension m, expected m\^2"),
        ("1e-3 Pa", "physics.mu_l", r"expected m\^-1 kg s\^-1"),
        ("5000 m", "time.dt", "expected s"),
        ("0.15 m", "physics.porosity", "expected dimensionless"),
        ("5.57e-6 kg/m2", "injection.rate", r"expected m\^-2 kg s\^-1"),
        ("3 furlongs", "scene.length", "unknown unit 'furlongs'"),
        ("fast", "time.dt", "does not start with a number"),
        (True, "physics.n", "must be a number"),
    ],
)
def test_inconsistent_units_are_refused_naming_the_field(value, field, message):
    with pytest.raises(ParameterError, match=message) as info:
        quantity(value, field)
    if not isinstance(value, bool):
        assert field in str(info.value)


def test_bad_scene_files(tmp_path):
    text = EXAMPLE.read_text()
    cases = {
        "typo.toml": (
            text.replace("porosity = 0.15", "porsity = 0.15"),
            "unknown key physics.porsity",
        ),
        "table.toml": (text + "\n[mesh]\nn = 3\n", r"unknown table \[mesh\]"),
        "kind.toml": (text.replace('kind = "column"', 'kind = "cube"'), "scene.kind must be"),
        "sat.toml": (
            text.replace("[initial]\nsaturation = 1.0", "[initial]\nsaturation = 0.2"),
            r"S outside \[S_lr, 1\]",
        ),
        "toml.toml": ("[scene\nkind=", "not valid TOML"),
    }
    for name, (body, message) in cases.items():
        path = tmp_path / name
        path.write_text(body)
        with pytest.raises(ParameterError, match=message):
            load_scene(path)
    with pytest.raises(ParameterError, match="no such scene file"):
        load_scene(tmp_path / "missing.toml")


def test_command_line_runs_a_scene_file(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["twophase", "run", str(EXAMPLE), "--steps", "3", "--quiet"]) == 0
    assert (tmp_path / "twophase_benchmark.h5").exists()
    bad = tmp_path / "bad.toml"
    bad.write_text(EXAMPLE.read_text().replace('"5e-20 m2"', '"5e-20 m"'))
    assert main(["twophase", "run", str(bad)]) == 2
    assert "physics.permeability" in capsys.readouterr().err
    assert not (tmp_path / "bad.h5").exists()
    assert main(["twophase", "run", "column"]) == 2
    assert "scene must be one of" in capsys.readouterr().err


def test_command_line_honours_the_scene_files_end_and_refuses_its_flags(tmp_path, capsys):
    scene = tmp_path / "short.toml"
    text = EXAMPLE.read_text().replace('end = "5e5 year"', 'end = "12000 year"')
    scene.write_text(text.replace("cells = 1000", "cells = 40"))
    out = tmp_path / "short.h5"
    assert main(["twophase", "run", str(scene), "-o", str(out), "--quiet"]) == 0
    assert main(["info", str(out), "--json"]) == 0
    assert '"t_end_years": 12000.0' in capsys.readouterr().out
    assert main(["twophase", "run", str(scene), "--cells", "80", "-o", str(out)]) == 2
    assert "--cells do not apply to a scene file" in capsys.readouterr().err
