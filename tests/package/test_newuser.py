"""The first hour of a new user (issue 18): what they see, what they can break, what they get."""

from __future__ import annotations

import h5py
import meshio
import numpy as np
import pytest

import fastmem as fm
from fastmem import errors
from fastmem.cli.main import main
from fastmem.io.schema import DATASETS, GROUPS

SCENE = fm.Scene(fm.Mesh.square(8), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)


@pytest.fixture(scope="module")
def result():
    return fm.solve(SCENE)


# ----------------------------------------------------------------------------- the estimate


def test_eta_components_are_the_three_components(result):
    parts = result.eta_components
    assert set(parts) == {"eta_disc", "eta_lin", "eta_alg"}
    assert result.eta <= sum(parts.values()) * (1 + 1e-12)
    diag = result.estimate.diagnostics
    assert {"C_F", "a", "c", "eta_nc", "seconds_flux", "eta_unguaranteed_slides"} <= set(diag)
    assert not ({"eta", *parts} & set(diag))
    # nothing lost: totals is still everything
    assert set(result.estimate.totals) == {"eta", *parts, *diag}


@pytest.mark.parametrize("method", ["exact", "exact-amg"])
def test_exact_methods_compute_the_bound_by_default(method):
    r = fm.solve(SCENE, method=method)
    assert r.eta is not None
    assert r.eta > 0
    assert set(r.eta_components) == {"eta_disc", "eta_lin", "eta_alg"}
    assert fm.solve(SCENE, method=method, estimate=False).eta is None


def test_inexact_bound_matches_an_independent_estimate(result):
    again = fm.estimate(SCENE, result.u1, result.u2, result.lam)
    assert again.eta == pytest.approx(result.eta, rel=1e-12)


# ----------------------------------------------------------------------------- results


def test_result_arrays_are_read_only(result):
    for name in ("u1", "u2", "lam", "r1", "r2", "active"):
        with pytest.raises(ValueError, match="read-only"):
            getattr(result, name)[0] = 5
    with pytest.raises(ValueError, match="read-only"):
        result.history["eta_lin"][0] = 0.0
    with pytest.raises(ValueError, match="read-only"):
        result.estimate.maps["eta_F1"][0] = 0.0
    copy = result.u1.copy()
    copy[0] = 5.0  # a copy is the user's to change
    assert result.u1[0] != 5.0


def test_readable_reprs(result):
    text = repr(result)
    assert text.startswith("Result(Mesh(n_vertices=81, n_triangles=128)")
    assert "array(" not in text
    assert len(text) < 300
    assert f"eta={result.eta:.4e}" in text
    assert "converged=True" in text
    est = repr(result.estimate)
    assert est.startswith("Estimate(eta=")
    assert "array(" not in est
    assert repr(SCENE).startswith("Scene(Mesh(n_vertices=81")
    assert str(result) == text


def test_top_level_namespace_is_clean():
    for name in ("os", "PackageNotFoundError", "version"):
        assert not hasattr(fm, name), name
    assert isinstance(fm.__version__, str)
    with pytest.raises(AttributeError, match="no attribute 'nonsense'"):
        fm.nonsense  # noqa: B018


# ----------------------------------------------------------------------------- mesh files


def test_missing_mesh_file_is_an_oserror(tmp_path):
    with pytest.raises(OSError, match="mesh file not found") as info:
        fm.Mesh.read(tmp_path / "nosuch.msh")
    assert isinstance(info.value, errors.MeshError)
    assert isinstance(info.value, errors.MeshFileError)


def test_garbage_mesh_file_says_what_failed(tmp_path, capsys):
    bad = tmp_path / "notamesh.msh"
    bad.write_text("this is not a mesh\n")
    with pytest.raises(errors.MeshFileError) as info:
        fm.Mesh.read(bad)
    text = str(info.value)
    assert "notamesh.msh" in text
    assert "meshio" in text
    assert not text.rstrip().endswith(": 1")
    assert capsys.readouterr().out == ""  # meshio's own print is folded into the message


# ----------------------------------------------------------------------------- command line


def _run(argv, capsys):
    rc = main(argv)
    captured = capsys.readouterr()
    return rc, captured.out, captured.err


def test_cli_values_in_messages_are_plain_numbers(capsys):
    rc, _, err = _run(["run", "--n", "4", "--no-save", "--g", "-0.1"], capsys)
    assert rc == 2
    assert "got -0.1" in err
    assert "np.float64" not in err


@pytest.fixture
def no_work(monkeypatch):
    """Make building a mesh or solving fail loudly: the checks must come first."""

    def boom(*args, **kwargs):
        raise AssertionError("work started before the input was checked")

    monkeypatch.setattr(fm.Mesh, "square", boom)
    monkeypatch.setattr("fastmem.pipeline.solve", boom)


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--method", "foo"], ["--method", "'foo'", "inexact"]),
        (["-o", "{tmp}/no/such/dir/x.h5"], ["does not exist"]),
        (["-o", "{tmp}/x.txt"], ["'.txt'", ".h5", ".vtu", ".xdmf"]),
        (["-o", "{tmp}/x.h5", "-o", "{tmp}/x.h5"], ["same file twice"]),
        (["--no-save", "-o", "{tmp}/x.h5"], ["--no-save"]),
        (["--no-save"], ["not enough memory", "--memory-limit", "GB"]),
        (["--no-save", "--memory-limit", "lots"], ["memory_limit", "'lots'"]),
    ],
    ids=["method", "missing-dir", "suffix", "twice", "no-save-and-output", "memory", "limit"],
)
def test_cli_refuses_before_any_work(no_work, tmp_path, capsys, argv, words):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    rc, out, err = _run(["run", "--n", "100000", *argv], capsys)
    assert rc == 2, (out, err)
    assert err.startswith("fastmem: error: ")
    assert len(err.strip().splitlines()) == 1
    for word in words:
        assert word in err


def test_cli_output_formats_and_replacement(tmp_path, capsys):
    h5, vtu, xdmf = tmp_path / "r.h5", tmp_path / "r.vtu", tmp_path / "r.xdmf"
    h5.write_bytes(b"old")
    argv = ["run", "--n", "8", "-q", "-o", str(h5), "-o", str(vtu), "-o", str(xdmf)]
    rc, out, _ = _run(argv, capsys)
    assert rc == 0
    assert f"{h5} exists and will be replaced" in out
    assert "replaced the existing file" in out
    assert f"with {xdmf}.h5" in out
    assert "kernels" in out  # compilation (or cache loading) reported apart from the solve
    back = fm.load(h5)
    m = meshio.read(vtu)
    np.testing.assert_array_equal(np.asarray(m.point_data["u1"]).ravel(), back.u1)
    assert (tmp_path / "r.xdmf.h5").exists()
    # -o x.vtu alone writes no archive
    rc, out, _ = _run(["run", "--n", "8", "-q", "-o", str(tmp_path / "only.vtu")], capsys)
    assert rc == 0
    assert sorted(p.name for p in tmp_path.glob("only*")) == ["only.vtu"]


def test_cli_summary_explains_the_components(tmp_path, capsys):
    rc, out, _ = _run(["run", "--n", "8", "-q", "--no-save"], capsys)
    assert rc == 0
    assert "eta <= eta_disc + eta_lin + eta_alg" in out
    assert "may be smaller than eta_disc" in out
    assert "nan" not in out.lower()


def test_cli_monitor_prints_blanks_not_nan(capsys):
    rc, out, _ = _run(["run", "--n", "16", "--no-save", "--method", "exact-amg"], capsys)
    assert rc == 0
    assert "nan" not in out.lower()


def test_cli_export_names_its_companion(result, tmp_path, capsys):
    archive = tmp_path / "run.h5"
    result.save(archive)
    rc, out, _ = _run(["export", str(archive), str(tmp_path / "run.xdmf")], capsys)
    assert rc == 0
    assert f"{tmp_path / 'run.xdmf.h5'}" in out
    rc, _, err = _run(["export", str(archive), str(tmp_path / "run.png")], capsys)
    assert rc == 2
    assert ".vtu" in err


# ----------------------------------------------------------------------------- archives


def test_archive_datasets_describe_themselves(tmp_path):
    r = fm.solve(fm.Scene(fm.Mesh.lshape(4), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1), tol=0.1)
    path = tmp_path / "a.h5"
    r.save(path)
    seen = []
    with h5py.File(path, "r") as f:

        def visit(name, obj):
            seen.append(name)
            if isinstance(obj, h5py.Dataset):
                assert obj.attrs["description"], name
                if name in DATASETS and DATASETS[name][1]:
                    assert obj.attrs["units"] == DATASETS[name][1]
            elif name not in ("estimators", "timings"):
                assert obj.attrs["description"] == GROUPS[name]

        f.visititems(visit)
        assert "per vertex" in f["solution/u1"].attrs["description"]
        assert "per triangle" in f["estimators/eta_F1"].attrs["description"]
        assert f["history/seconds"].attrs["units"] == "s"
    assert {"adaptivity/eta", "solution/r1", "mesh/vertices"} <= set(seen)
    back = fm.load(path)  # descriptions do not leak into the loaded data
    assert set(back.estimate.totals) == set(r.estimate.totals)


# ----------------------------------------------------------------------------- warm-up


def test_warm_up_counts_kernels():
    """In a fresh process warm_up compiles or loads every kernel; a second call has none left."""
    from fresh import run_python

    script = (
        "import fastmem as fm\n"
        "a = fm.warm_up('inexact'); b = fm.warm_up('inexact')\n"
        "print(a.compiled + a.loaded, b.compiled + b.loaded, a.seconds > 0)\n"
    )
    first, second, timed = run_python(script).split()
    # the default pipeline's kernels: 6 loaded from a warm cache (their callees come with
    # them; small meshes build their topology, pattern and matrices with NumPy)
    assert int(first) >= 5
    assert int(second) == 0
    assert timed == "True"


def test_warm_up_names_a_bad_method():
    from fastmem.cli.warmup import warm_up

    with pytest.raises(errors.ParameterError, match="method must be one of .* got 'magic'"):
        warm_up("magic")
