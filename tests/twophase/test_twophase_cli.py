"""Two-phase archives, their summary, exports, plots and the ``fastmem twophase`` command."""

import json
import xml.etree.ElementTree as ET

import h5py
import meshio
import numpy as np
import pytest

from fastmem.cli.main import main
from fastmem.errors import ArchiveError, ParameterError
from fastmem.twophase import YEAR, benchmark, section, simulate
from fastmem.twophase.archive import export_run, info_run, is_archive, load_run, save_run


@pytest.fixture(scope="module")
def column_run():
    prob = benchmark("momas", n_cells=60)
    return simulate(prob, t_end=8 * 5000 * YEAR, keep="all")


def test_archive_round_trip(tmp_path, column_run):
    path = save_run(column_run, tmp_path / "run.h5")
    assert is_archive(path)
    d = load_run(path)
    assert np.array_equal(d["steps"]["newton"], column_run.newton)
    assert np.allclose(d["steps"]["eta"], column_run.eta)
    assert d["profiles"]["state"].shape == (8, 60, 3)
    assert np.array_equal(d["profiles"]["state"][-1], column_run.final)
    assert d["problem"]["physics"]["mu_l"] == 1e-3
    s = info_run(path)
    assert s["steps"] == 8
    assert s["gas_appears_years"] == pytest.approx(15000.0)
    assert s["newton"] == sum(column_run.newton)
    # nothing is left behind but the archive (atomic write)
    assert [p.name for p in tmp_path.iterdir()] == ["run.h5"]


def test_keep_every_k_steps_and_the_last():
    prob = benchmark("momas", n_cells=30)
    run = simulate(prob, t_end=7 * 5000 * YEAR, keep=3, estimate=False, linear_solver="direct")
    assert [round(t / YEAR) for t in run.kept_times] == [15000, 30000, 35000]
    with pytest.raises(ParameterError, match="keep must be"):
        simulate(prob, t_end=5000 * YEAR, keep="some")


def test_pvd_series_and_vtu(tmp_path, column_run):
    path = save_run(column_run, tmp_path / "run.h5")
    pvd = export_run(path, tmp_path / "series.pvd")
    files = [e.attrib["file"] for e in ET.parse(pvd).getroot().iter("DataSet")]
    assert len(files) == 8
    m = meshio.read(tmp_path / files[-1])
    assert np.allclose(m.point_data["P"], column_run.final[:, 1])
    assert np.allclose(m.point_data["S_gas"], 1 - column_run.final[:, 0])
    with pytest.raises(ParameterError, match=r"\.vtu .* or \.pvd"):
        export_run(path, tmp_path / "x.xdmf")


def test_section_export_fills_the_dirichlet_vertices(tmp_path):
    prob = section(20, 4, length=20.0, height=2.0, stretch=(0.5, 1.5))
    run = simulate(prob, t_end=2 * 5000 * YEAR, keep="all", linear_solver="direct")
    path = save_run(run, tmp_path / "s.h5")
    out = export_run(path, tmp_path / "s.vtu")
    m = meshio.read(out)
    right = np.isclose(m.points[:, 0], 20.0)
    assert np.allclose(m.point_data["P"][right], 1e6)
    assert np.allclose(m.point_data["P"][prob.cell_vertex], run.final[:, 1])


def test_archive_errors(tmp_path, column_run):
    with pytest.raises(ParameterError, match=r"\.h5 or \.hdf5"):
        save_run(column_run, tmp_path / "run.txt")
    with pytest.raises(ArchiveError, match="no such archive"):
        load_run(tmp_path / "missing.h5")
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.attrs["format"] = "something"
    with pytest.raises(ArchiveError, match="not a fastmem two-phase archive"):
        load_run(other)


def test_command_line_run_info_plot_export(tmp_path, capsys):
    out = tmp_path / "bm.h5"
    argv = ["twophase", "run", "benchmark", "--cells", "50", "--steps", "4", "-o", str(out)]
    assert main(argv) == 0
    text = capsys.readouterr().out
    lines = [ln for ln in text.splitlines() if ln.strip().split(" ")[0].isdigit()]
    assert len(lines) == 4  # one progress line per step
    assert "wrote" in text
    assert "gas first in step 4" in text  # 4 m cells: a step later than with 0.2 m
    assert main(["info", str(out)]) == 0
    assert "two-phase archive" in capsys.readouterr().out
    assert main(["info", str(out), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["steps"] == 4
    assert main(["export", str(out), str(tmp_path / "bm.pvd")]) == 0
    assert (tmp_path / "bm_0003.vtu").exists()
    pytest.importorskip("matplotlib")
    assert main(["twophase", "plot", str(out), "-o", str(tmp_path / "bm.png")]) == 0
    assert (tmp_path / "bm.png").stat().st_size > 10_000


def test_command_line_refuses_bad_options(tmp_path, capsys):
    assert (
        main(["twophase", "run", "benchmark", "--dt-years", "-5", "-o", str(tmp_path / "a.h5")])
        == 2
    )
    assert "--dt-years must be positive" in capsys.readouterr().err
    assert main(["twophase", "run", "benchmark", "-o", str(tmp_path / "a.txt")]) == 2
    assert ".h5 or .hdf5" in capsys.readouterr().err
    assert main(["twophase", "run", "column"]) == 2
    assert "scene must be one of" in capsys.readouterr().err
