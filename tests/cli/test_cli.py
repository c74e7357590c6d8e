"""Tests of the command line (fastmem.cli.main): run, info, export, error reporting."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys

import numba
import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

import fastmem as fm
from fastmem.cli.main import main

pytest.importorskip("h5py")
meshio = pytest.importorskip("meshio")


@pytest.fixture(scope="module")
def archive(tmp_path_factory):
    """A result archive of the default scene on square(6), written by ``fastmem run``."""
    path = tmp_path_factory.mktemp("cli") / "run.h5"
    assert main(["run", "--n", "6", "-q", "-o", str(path)]) == 0
    return path


def check_archive(path, n_cells):
    result = fm.load(path)
    n_vertices = (n_cells + 1) ** 2
    assert result.mesh.n_vertices == n_vertices
    assert result.mesh.n_triangles == 2 * n_cells**2
    for field in (result.u1, result.u2, result.lam, result.r1, result.r2, result.active):
        assert field.shape == (n_vertices,)
    assert result.converged is True
    assert result.method == "inexact"
    assert result.path == "decoupled"
    bnd = result.mesh.boundary_vertices
    assert_allclose(result.u1[bnd], 0.1, rtol=0, atol=1e-14)
    assert_allclose(result.u2[bnd], 0.0, rtol=0, atol=1e-14)
    assert (result.u1 - result.u2 >= -1e-12).all()
    assert (result.lam >= -1e-12).all()
    assert result.parameters["mu1"] == 1.0
    assert result.parameters["f1"]["value"] == -1.0
    return result


def test_run_subprocess(tmp_path):
    out = tmp_path / "r.h5"
    proc = subprocess.run(
        [sys.executable, "-m", "fastmem", "run", "--n", "8", "-o", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "eta_disc" in proc.stdout
    assert "inner" in proc.stdout
    assert "contact fraction" in proc.stdout
    assert "81 vertices, 128 triangles" in proc.stdout
    assert "converged" in proc.stdout
    assert out.is_file()
    result = check_archive(out, 8)
    # the printed contact fraction is the archived one
    printed = [ln for ln in proc.stdout.splitlines() if "contact fraction" in ln][0]
    assert float(printed.split()[2]) == pytest.approx(result.contact_fraction, abs=5e-5)
    # one monitor row per estimator evaluation: the archived history, row by row
    lines = proc.stdout.splitlines()
    header = next(ln for ln in lines if ln.split()[:2] == ["lev", "k"])
    rows = [ln for ln in lines if ln.split() and ln.split()[0].isdigit()]
    cells = [ln.split()[:6] for ln in rows]
    assert [int(r[1]) for r in cells] == result.history["k"].tolist()
    assert [int(r[3]) for r in cells] == result.history["inner_total"].tolist()
    assert int(cells[-1][1]) == result.n_newton
    # eta printed exactly on the rows with a fresh bound, blank (not "nan") elsewhere
    start, end = header.index("eta_alg") + len("eta_alg"), header.rindex("eta") + 3
    fresh = [bool(ln[start:end].strip()) for ln in rows]
    assert fresh == result.history["fresh_disc"].astype(bool).tolist()
    assert "nan" not in proc.stdout
    assert "Newton steps on the finest mesh" in proc.stdout


def test_run_in_process(tmp_path, capsys):
    out = tmp_path / "r.h5"
    rc = main(["run", "--n", "6", "--mu1", "2", "--g", "0.05", "-o", str(out)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert "eta_disc" in captured.out
    assert "inner" in captured.out
    assert "contact fraction" in captured.out
    assert "49 vertices" in captured.out
    assert "mu = (2, 1)" in captured.out
    result = fm.load(out)
    assert result.u1.shape == (49,)
    assert result.converged
    assert result.parameters["mu1"] == 2.0
    assert_allclose(result.u1[result.mesh.boundary_vertices], 0.05, rtol=0, atol=1e-14)
    # the same scene through the API gives the same solution
    scene = fm.Scene(fm.Mesh.square(6), mu=(2.0, 1.0), f=(-1.0, 1.0), g=0.05)
    direct = fm.solve(scene)
    assert_allclose(result.u1, direct.u1, rtol=0, atol=1e-12)
    assert_allclose(result.u2, direct.u2, rtol=0, atol=1e-12)
    assert_array_equal(result.active, direct.active)


def test_run_quiet_and_no_save(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc = main(["run", "--n", "4", "-q", "--no-save"])
    captured = capsys.readouterr()
    assert rc == 0
    assert "inner  total" not in captured.out  # no monitor table
    assert "contact fraction" in captured.out
    assert "archive" not in captured.out
    assert list(tmp_path.iterdir()) == []


def test_info(archive, capsys):
    assert main(["info", str(archive)]) == 0
    out = capsys.readouterr().out
    assert "49 vertices, 72 triangles" in out
    assert "converged         True" in out
    assert "inexact / decoupled" in out


def test_info_json(archive, capsys):
    assert main(["info", "--json", str(archive)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["n_vertices"] == 49
    assert summary["n_triangles"] == 72
    assert summary["converged"] is True
    assert summary["method"] == "inexact"
    assert summary["n_history_rows"] >= summary["n_newton"] >= 1
    assert summary["parameters"]["g"]["value"] == 0.1


@pytest.mark.parametrize("suffix", [".vtu", ".xdmf"])
def test_export(archive, tmp_path, capsys, suffix):
    out = tmp_path / f"fields{suffix}"
    assert main(["export", str(archive), str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    assert out.is_file()
    result = fm.load(archive)
    back = meshio.read(out)
    assert back.points.shape[0] == result.mesh.n_vertices
    assert_allclose(np.asarray(back.point_data["u1"]).ravel(), result.u1, rtol=0, atol=0)
    assert_allclose(
        np.asarray(back.point_data["gap"]).ravel(), result.u1 - result.u2, rtol=0, atol=1e-15
    )


@pytest.mark.parametrize(
    ("argv", "field"),
    [
        pytest.param(["run", "--n", "4", "--no-save", "--mu1", "-1"], "mu1", id="mu1-negative"),
        pytest.param(["run", "--n", "4", "--no-save", "--mu2", "0"], "mu2", id="mu2-zero"),
        pytest.param(["run", "--n", "4", "--no-save", "--g", "-0.5"], "g", id="g-negative"),
        pytest.param(["run", "--n", "4", "--no-save", "--f1", "nan"], "f1", id="f1-nan"),
        pytest.param(["run", "--n", "4", "--no-save", "--method", "magic"], "method", id="method"),
        pytest.param(
            ["run", "--n", "4", "--no-save", "--refine", "-1"], "--refine", id="refine-negative"
        ),
        pytest.param(
            ["run", "--n", "4", "--no-save", "--max-newton", "0"], "max_newton", id="max-newton"
        ),
        pytest.param(["run", "--mesh", "{tmp}/missing.msh"], "missing.msh", id="mesh-missing"),
        pytest.param(["info", "{tmp}/not-there.h5"], "not-there.h5", id="info-missing"),
        pytest.param(
            ["export", "{tmp}/not-there.h5", "{tmp}/o.vtu"], "not-there.h5", id="export-missing"
        ),
    ],
)
def test_bad_input_exit_status_2(tmp_path, capsys, argv, field):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    rc = main(argv)
    captured = capsys.readouterr()
    assert rc == 2
    assert captured.err.startswith("fastmem: error: ")
    assert field in captured.err
    assert "Traceback" not in captured.err
    assert len(captured.err.strip().splitlines()) == 1
    assert "contact fraction" not in captured.out


def test_export_bad_suffix(archive, tmp_path, capsys):
    rc = main(["export", str(archive), str(tmp_path / "out.txt")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "fastmem: error:" in err
    assert ".txt" in err
    assert not (tmp_path / "out.txt").exists()


def test_bad_input_subprocess(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "fastmem", "run", "--mu1", "-1", "--n", "4", "--no-save"],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert proc.returncode == 2
    assert "error" in proc.stderr
    assert "mu1" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_argparse_errors_exit_2(capsys):
    with pytest.raises(SystemExit) as info:
        main(["run", "--path", "sideways"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "error" in err
    assert "--path" in err
    with pytest.raises(SystemExit) as info:
        main([])
    assert info.value.code == 2


def test_run_with_mesh_file(tmp_path, capsys):
    mesh = fm.Mesh.lshape(4)
    path = tmp_path / "l.msh"
    mesh.write(path)
    out = tmp_path / "l.h5"
    rc = main(["run", "--mesh", str(path), "-q", "-o", str(out)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert f"{mesh.n_vertices} vertices, {mesh.n_triangles} triangles" in captured.out
    assert str(path) in captured.out
    result = fm.load(out)
    assert result.converged
    assert_array_equal(result.mesh.vertices, mesh.vertices)
    assert_array_equal(result.mesh.triangles, mesh.triangles)
    assert_allclose(result.u1[mesh.boundary_vertices], 0.1, rtol=0, atol=1e-14)


def test_refine_doubles_resolution(tmp_path, capsys):
    out = tmp_path / "fine.h5"
    rc = main(["run", "--n", "4", "--refine", "1", "-q", "-o", str(out)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert "81 vertices, 128 triangles" in captured.out
    result = check_archive(out, 8)
    coarse = fm.Mesh.square(4)
    assert_allclose(result.mesh.h, coarse.h / 2, rtol=1e-14)
    # the vertices are those of the 8 x 8 grid
    grid = fm.Mesh.square(8).vertices
    got = result.mesh.vertices[np.lexsort(result.mesh.vertices.T[::-1])]
    want = grid[np.lexsort(grid.T[::-1])]
    assert_allclose(got, want, rtol=0, atol=1e-15)


def test_refine_mesh_file(tmp_path, capsys):
    mesh = fm.Mesh.lshape(2)
    path = tmp_path / "l.vtu"
    mesh.write(path)
    rc = main(["run", "--mesh", str(path), "--refine", "2", "-q", "--no-save"])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert f"{16 * mesh.n_triangles} triangles" in captured.out


def test_run_corrupt_mesh_file(tmp_path, capsys):
    path = tmp_path / "corrupt.msh"
    path.write_text("this is not a gmsh file\n")
    try:
        rc = main(["run", "--mesh", str(path), "--no-save"])
    except SystemExit as exc:
        pytest.fail(f"main raised SystemExit({exc.code})")
    err = capsys.readouterr().err
    assert rc == 2
    assert "fastmem: error:" in err
    assert "corrupt.msh" in err


def test_run_prints_the_bound_and_no_estimate_skips_it(tmp_path, capsys):
    from fastmem.cli.main import main

    assert main(["run", "--n", "8", "-q", "-o", str(tmp_path / "a.h5")]) == 0
    out = capsys.readouterr().out
    assert "error bound eta" in out
    assert "eta_disc" in out
    assert "eta_alg" in out
    assert fm.load(tmp_path / "a.h5").eta > 0
    assert main(["run", "--n", "8", "-q", "--no-estimate", "-o", str(tmp_path / "b.h5")]) == 0
    out = capsys.readouterr().out
    assert "error bound" not in out
    assert "method = exact-amg" in out
    assert fm.load(tmp_path / "b.h5").estimate is None
    # the inexact method cannot run without its estimator
    argv = ["run", "--n", "8", "--no-save", "--no-estimate", "--method", "inexact"]
    assert main(argv) == 2
    assert "--no-estimate cannot be combined" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "command", "hint"),
    [
        pytest.param(["run", "--N", "64"], "run", "did you mean --n instead of --N?", id="run-N"),
        pytest.param(
            ["run", "--n", "4", "--gamma_alg", "0.2"],
            "run",
            "did you mean --gamma-alg instead of --gamma_alg?",
            id="run-underscore",
        ),
        pytest.param(
            ["run", "--tols=1e-3"], "run", "did you mean --tol instead of --tols?", id="eq"
        ),
        pytest.param(["info", "a.h5", "--jsn"], "info", "did you mean --json", id="info"),
        pytest.param(["plot", "a.h5", "--dpii", "3"], "plot", "did you mean --dpi ", id="plot"),
        pytest.param(
            ["export", "a.h5", "b.vtu", "--force"],
            "export",
            "fastmem export --help lists the options",
            id="nothing-close",
        ),
    ],
)
def test_unknown_option_is_refused_by_its_subcommand(capsys, argv, command, hint):
    """The subcommand's usage and error, with the closest of its options (not the top level's)."""
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(f"usage: fastmem {command} "), err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"fastmem {command}: error: unrecognized arguments: "), last
    assert hint in last


def test_first_use_is_counted_and_said(capsys, monkeypatch):
    """Kernels compiled while the mesh is built count as compiled; the note only then.

    A kernel without a cache (compiled in every process) stands in for a mesh
    kernel on its first use: the run after it has been compiled reports nothing
    compiled and no note.
    """
    cli = importlib.import_module("fastmem.cli.main")
    warmup = importlib.import_module("fastmem.cli.warmup")
    argv = ["run", "--n", "4", "--no-save"]
    assert main(argv) == 0  # everything this run needs is now in this process
    capsys.readouterr()

    @numba.njit
    def probe(x):
        return x + 1.0

    kernels, build = warmup._dispatchers, cli._build_mesh

    def building(args):
        probe(1.0)
        return build(args)

    monkeypatch.setattr(warmup, "_dispatchers", lambda: [*kernels(), probe])
    monkeypatch.setattr(cli, "_build_mesh", building)
    monkeypatch.setattr(cli, "kernels_cached", lambda: True)
    assert main(argv) == 0
    out = capsys.readouterr().out
    label = "  Numba kernels (loading from cache, compiling any not there) ... "
    line = next(ln for ln in out.splitlines() if ln.startswith(label))
    assert line.endswith(" s (1 compiled, 0 loaded from cache)"), line
    assert cli.FIRST_USE_NOTE in out
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "(0 compiled, 0 loaded from cache)" in out
    assert "note:" not in out
    monkeypatch.setattr(cli, "kernels_cached", lambda: False)
    assert main(argv) == 0
    assert "  compiling Numba kernels (first use) ... " in capsys.readouterr().out
