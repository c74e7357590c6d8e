"""Tests of the HDF5 result archive and the meshio export (fastmem.io.archive)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

h5py = pytest.importorskip("h5py")
meshio = pytest.importorskip("meshio")

from fastmem.errors import ArchiveError, ParameterError  # noqa: E402
from fastmem.io import archive  # noqa: E402
from fastmem.io import writer as archive_write  # noqa: E402
from fastmem.io.result import Estimate, Result  # noqa: E402
from fastmem.mesh.mesh import Mesh  # noqa: E402

SOLUTION_FIELDS = ("u1", "u2", "lam", "r1", "r2", "active")


@pytest.fixture
def seed():
    return 20261121


@pytest.fixture(scope="module")
def mesh():
    return Mesh.square(6)


def make_result(mesh, seed, *, with_estimate=True, n_rows=7):
    rng = np.random.default_rng(seed)
    n, m = mesh.vertices.shape[0], mesh.triangles.shape[0]
    eta = rng.random(n_rows)
    eta[1] = np.nan  # non-finite values and signed zeros must survive bit-exactly
    eta[2] = -0.0
    history = {
        "k": np.arange(n_rows, dtype=np.int64),
        "inner": rng.integers(0, 50, n_rows).astype(np.int32),
        "n_active": rng.integers(0, n, n_rows).astype(np.uint32),
        "eta_disc": rng.random(n_rows).astype(np.float32),
        "eta": eta,
        "changed": rng.random(n_rows) < 0.5,
    }
    estimate = None
    if with_estimate:
        estimate = Estimate(
            totals={"eta": 0.25, "eta_disc": 0.2, "eta_lin": 0.04, "eta_alg": 0.01},
            maps={"eta_F1": rng.random(m), "eta_F2": rng.random(m), "eta_C": rng.random(m)},
        )
    return Result(
        mesh=mesh,
        u1=rng.standard_normal(n),
        u2=rng.standard_normal(n),
        lam=np.abs(rng.standard_normal(n)),
        r1=rng.standard_normal(n) * 1e-12,
        r2=rng.standard_normal(n) * 1e-12,
        active=rng.random(n) < 0.3,
        history=history,
        timings={"assembly": 0.125, "solve": 1.0 / 3.0, "estimate": 2.5e-3},
        parameters={
            "mu": (1.0, 2.0),
            "f": [-1.0, 1.0],
            "g": np.float64(0.1),
            "n": np.int64(6),
            "flags": np.array([True, False]),
            "data": np.arange(3.0),
            "name": "unit square",
            "nested": {"tol": np.float32(0.5), "none": None},
        },
        converged=True,
        n_newton=n_rows,
        method="inexact",
        path="decoupled",
        estimate=estimate,
    )


@pytest.fixture
def result(mesh, seed):
    return make_result(mesh, seed)


@pytest.fixture
def archive_file(tmp_path, result):
    path = tmp_path / "run.h5"
    archive.save(result, path)
    return path


def assert_bit_exact(a, b):
    a, b = np.asarray(a), np.asarray(b)
    assert a.dtype == b.dtype
    assert a.shape == b.shape
    assert a.tobytes() == b.tobytes()


def assert_same_result(r, s):
    assert_bit_exact(r.mesh.vertices, s.mesh.vertices)
    assert_bit_exact(r.mesh.triangles, s.mesh.triangles)
    for name in SOLUTION_FIELDS:
        assert_bit_exact(getattr(r, name), getattr(s, name))
    assert list(s.history) == list(r.history)
    for name in r.history:
        assert_bit_exact(r.history[name], s.history[name])
    assert s.timings == r.timings
    assert list(s.timings) == list(r.timings)
    assert s.converged is r.converged
    assert s.n_newton == r.n_newton
    assert s.method == r.method
    assert s.path == r.path
    if r.estimate is None:
        assert s.estimate is None
    else:
        assert s.estimate.totals == r.estimate.totals
        assert list(s.estimate.maps) == list(r.estimate.maps)
        for name, value in r.estimate.maps.items():
            assert_bit_exact(value, s.estimate.maps[name])


def test_public_api():
    for name in archive.__all__:
        assert hasattr(archive, name)
    assert archive.FORMAT == "fastmem-result"
    assert archive.FORMAT_VERSION == 1


# ---------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("with_estimate", [True, False])
def test_round_trip_bit_exact(tmp_path, mesh, seed, with_estimate):
    r = make_result(mesh, seed, with_estimate=with_estimate)
    path = tmp_path / "run.h5"
    r.save(path)  # through Result.save
    s = archive.load(path)
    assert isinstance(s, Result)
    assert isinstance(s.mesh, Mesh)
    assert_same_result(r, s)
    assert s.eta == r.eta
    assert s.contact_fraction == r.contact_fraction


def test_parameters_become_json(tmp_path, result):
    archive.save(result, str(tmp_path / "run.h5"))  # a str path works too
    params = archive.load(str(tmp_path / "run.h5")).parameters
    assert params == {
        "mu": [1.0, 2.0],
        "f": [-1.0, 1.0],
        "g": 0.1,
        "n": 6,
        "flags": [True, False],
        "data": [0.0, 1.0, 2.0],
        "name": "unit square",
        "nested": {"tol": 0.5, "none": None},
    }
    assert type(params["n"]) is int


def test_root_attributes(archive_file):
    with h5py.File(archive_file, "r") as f:
        attrs = dict(f.attrs)
        assert attrs["format"] == "fastmem-result"
        assert attrs["format_version"] == 1
        assert isinstance(attrs["fastmem_version"], str)
        assert attrs["created"].endswith("+00:00")
        assert set(f) == {"mesh", "solution", "estimators", "history", "timings"}
        assert set(f["solution"]) == {"u1", "u2", "lambda", "r1", "r2", "active"}
        assert list(f["history"].attrs["columns"]) == list(f["history"])


def test_large_arrays_are_compressed_and_exact(tmp_path, seed):
    big_mesh = Mesh.square(190)  # 36481 vertices: (N, 2) vertices exceed 2**16 elements
    r = make_result(big_mesh, seed, n_rows=2**16 + 5)
    path = tmp_path / "big.h5"
    archive.save(r, path)
    with h5py.File(path, "r") as f:
        for name in ("history/eta", "mesh/vertices", "mesh/triangles", "estimators/eta_C"):
            big = f[name]
            assert big.compression == "gzip"
            assert big.shuffle
            assert big.chunks[1:] == big.shape[1:]  # chunks hold whole rows
        small = f["solution/u1"]
        assert small.compression is None
        assert small.chunks is None
    assert_same_result(r, archive.load(path))


def test_empty_history_and_timings(tmp_path, mesh, seed):
    r = make_result(mesh, seed, with_estimate=False)
    r.history, r.timings = {}, {}
    path = tmp_path / "empty.h5"
    archive.save(r, path)
    s = archive.load(path)
    assert s.history == {}
    assert s.timings == {}
    assert archive.info(path)["n_history_rows"] == 0


def test_save_overwrites_existing_archive(tmp_path, mesh, seed):
    path = tmp_path / "run.h5"
    archive.save(make_result(mesh, seed), path)
    r2 = make_result(mesh, seed + 1, with_estimate=False)
    archive.save(r2, path)
    assert_same_result(r2, archive.load(path))
    assert os.listdir(tmp_path) == ["run.h5"]


def test_saved_file_gets_umask_permissions(tmp_path, result):
    path = tmp_path / "run.h5"
    archive.save(result, path)
    probe = tmp_path / "probe"
    probe.touch()
    assert path.stat().st_mode & 0o777 == probe.stat().st_mode & 0o777


# ---------------------------------------------------------------------------- atomic writes


def _boom(*args, **kwargs):
    raise RuntimeError("simulated crash while writing the history")


def test_interrupted_write_leaves_nothing(tmp_path, result, monkeypatch):
    monkeypatch.setattr(archive_write, "_write_history", _boom)
    with pytest.raises(RuntimeError, match="simulated crash"):
        archive.save(result, tmp_path / "run.h5")
    assert os.listdir(tmp_path) == []


def test_interrupted_write_keeps_old_archive(tmp_path, mesh, seed, monkeypatch):
    path = tmp_path / "run.h5"
    archive.save(make_result(mesh, seed), path)
    before = path.read_bytes()
    monkeypatch.setattr(archive_write, "_write_history", _boom)
    with pytest.raises(RuntimeError, match="simulated crash"):
        archive.save(make_result(mesh, seed + 1), path)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["run.h5"]


def test_unstorable_history_name_is_archive_error(tmp_path, result):
    result.history["eta/disc"] = np.zeros(7)
    with pytest.raises(ArchiveError, match="eta/disc"):
        archive.save(result, tmp_path / "run.h5")
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("dtype", [object, str])
def test_unstorable_dtype_is_archive_error(tmp_path, result, dtype):
    result.history["label"] = np.array(["a"] * 7, dtype=dtype)
    with pytest.raises(ArchiveError, match="history/label"):
        archive.save(result, tmp_path / "run.h5")
    assert os.listdir(tmp_path) == []


def test_missing_parent_directory(tmp_path, result):
    missing = tmp_path / "no" / "such"
    with pytest.raises(ArchiveError, match="does not exist") as excinfo:
        archive.save(result, missing / "run.h5")
    assert str(missing) in str(excinfo.value)
    assert isinstance(excinfo.value, OSError)


# ---------------------------------------------------------------------------- load refuses


def test_load_missing_file(tmp_path):
    path = tmp_path / "absent.h5"
    with pytest.raises(ArchiveError, match="does not exist") as excinfo:
        archive.load(path)
    assert str(path) in str(excinfo.value)


def test_load_text_file(tmp_path):
    path = tmp_path / "notes.h5"
    path.write_text("u1 = 1.0\n")
    with pytest.raises(ArchiveError, match="not an HDF5 file"):
        archive.load(path)


def test_load_foreign_hdf5(tmp_path):
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "someone-else"
        f["solution/u1"] = np.zeros(3)
    with pytest.raises(ArchiveError, match="foreign"):
        archive.load(path)
    with pytest.raises(ArchiveError, match="foreign"):
        archive.info(path)


def test_load_future_version(archive_file):
    with h5py.File(archive_file, "r+") as f:
        f.attrs["format_version"] = np.int64(archive.FORMAT_VERSION + 1)
    with pytest.raises(ArchiveError, match="newer fastmem") as excinfo:
        archive.load(archive_file)
    message = str(excinfo.value)
    assert f"format_version {archive.FORMAT_VERSION + 1}" in message
    assert f"<= {archive.FORMAT_VERSION}" in message


def test_load_missing_dataset(archive_file):
    with h5py.File(archive_file, "r+") as f:
        del f["solution/u1"]
    with pytest.raises(ArchiveError, match="missing /solution/u1"):
        archive.load(archive_file)


def test_load_missing_history_column(archive_file):
    with h5py.File(archive_file, "r+") as f:
        del f["history/eta"]
    with pytest.raises(ArchiveError, match="missing /history/eta"):
        archive.load(archive_file)


def test_load_wrong_solution_length(archive_file):
    with h5py.File(archive_file, "r+") as f:
        del f["solution/u2"]
        f["solution/u2"] = np.zeros(3)
    with pytest.raises(ArchiveError, match="u2"):
        archive.load(archive_file)


def test_load_truncated(archive_file):
    data = archive_file.read_bytes()
    archive_file.write_bytes(data[: len(data) // 2])
    with pytest.raises(ArchiveError, match="truncated") as excinfo:
        archive.load(archive_file)
    assert str(archive_file) in str(excinfo.value)


def test_load_directory(tmp_path):
    with pytest.raises(ArchiveError, match="not a regular file"):
        archive.load(tmp_path)


# ---------------------------------------------------------------------------- info


def test_info(archive_file, result, mesh):
    summary = archive.info(archive_file)
    assert summary["format_version"] == archive.FORMAT_VERSION
    assert summary["n_vertices"] == mesh.vertices.shape[0] == 49
    assert summary["n_triangles"] == mesh.triangles.shape[0] == 72
    assert summary["n_history_rows"] == 7
    assert summary["history_columns"] == list(result.history)
    assert summary["has_estimate"] is True
    assert summary["estimator_totals"] == result.estimate.totals
    assert summary["estimator_maps"] == list(result.estimate.maps)
    assert summary["timings"] == result.timings
    assert summary["method"] == "inexact"
    assert summary["path"] == "decoupled"
    assert summary["converged"] is True
    assert summary["n_newton"] == 7
    assert summary["parameters"]["name"] == "unit square"
    assert summary["file"] == str(archive_file)


def test_info_without_estimate(tmp_path, mesh, seed):
    path = tmp_path / "run.h5"
    archive.save(make_result(mesh, seed, with_estimate=False), path)
    summary = archive.info(path)
    assert summary["has_estimate"] is False
    assert summary["estimator_totals"] == {}


# ---------------------------------------------------------------------------- export


def test_export_vtu(tmp_path, result):
    path = tmp_path / "run.vtu"
    result.export(path)  # through Result.export
    assert os.listdir(tmp_path) == ["run.vtu"]
    back = meshio.read(path)
    np.testing.assert_array_equal(back.points[:, :2], result.mesh.vertices)
    np.testing.assert_array_equal(back.points[:, 2], 0.0)
    np.testing.assert_array_equal(back.cells_dict["triangle"], result.mesh.triangles)
    expected = {
        "u1": result.u1,
        "u2": result.u2,
        "lambda": result.lam,
        "gap": result.u1 - result.u2,
        "active": result.active.astype(np.float64),
        "r1": result.r1,
        "r2": result.r2,
    }
    assert set(back.point_data) == set(expected)
    for name, value in expected.items():
        np.testing.assert_array_equal(back.point_data[name], value)
    for name, value in result.estimate.maps.items():
        np.testing.assert_array_equal(back.cell_data[name][0], value)


def test_export_xdmf(tmp_path, result):
    archive.save(result, tmp_path / "run.h5")
    before = (tmp_path / "run.h5").read_bytes()
    path = tmp_path / "run.xdmf"
    archive.export(result, path)
    # the companion heavy-data file never clobbers the archive of the same stem
    assert sorted(os.listdir(tmp_path)) == ["run.h5", "run.xdmf", "run.xdmf.h5"]
    assert (tmp_path / "run.h5").read_bytes() == before
    back = meshio.read(path)
    np.testing.assert_array_equal(back.points[:, :2], result.mesh.vertices)
    np.testing.assert_array_equal(back.cells_dict["triangle"], result.mesh.triangles)
    np.testing.assert_array_equal(back.point_data["gap"], result.u1 - result.u2)
    np.testing.assert_array_equal(back.point_data["lambda"], result.lam)
    np.testing.assert_array_equal(back.cell_data["eta_C"][0], result.estimate.maps["eta_C"])
    archive.export(result, path)  # overwriting works and leaves no temporaries
    assert sorted(os.listdir(tmp_path)) == ["run.h5", "run.xdmf", "run.xdmf.h5"]


def test_export_failure_leaves_nothing(tmp_path, result, monkeypatch):
    def broken_write(*args, **kwargs):
        raise RuntimeError("simulated meshio failure")

    monkeypatch.setattr(meshio, "write", broken_write)
    for name in ("run.vtu", "run.xdmf"):
        with pytest.raises(RuntimeError, match="simulated"):
            archive.export(result, tmp_path / name)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("name", ["run.vtk", "run.txt", "run"])
def test_export_bad_suffix(tmp_path, result, name):
    with pytest.raises(ParameterError, match=Path(name).suffix or "no suffix"):
        archive.export(result, tmp_path / name)
    assert os.listdir(tmp_path) == []


def test_export_missing_parent_directory(tmp_path, result):
    with pytest.raises(ArchiveError, match="does not exist"):
        archive.export(result, tmp_path / "no" / "run.vtu")
