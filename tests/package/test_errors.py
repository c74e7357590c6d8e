"""Bad input at the public API level: the fastmem.errors hierarchy."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

import fastmem as fm
from fastmem import errors

SEED = 20261121


@pytest.fixture(scope="module")
def mesh():
    return fm.Mesh.square(4)


def per_triangle(mesh, lo=1.0, hi=2.0):
    return np.linspace(lo, hi, mesh.n_triangles)


def nan_at_one_vertex(mesh):
    f = np.zeros(mesh.n_vertices)
    f[mesh.interior_vertices[0]] = np.nan
    return f


# Each case: (id, call(mesh, tmp_path), exception class, natural built-in, field in message)
CASES = [
    # non-positive, NaN and inf tensions
    ("mu1-zero", lambda m, p: fm.Scene(m, mu=(0.0, 1.0)), errors.ParameterError, ValueError, "mu1"),
    (
        "mu1-negative",
        lambda m, p: fm.Scene(m, mu=(-1.0, 1.0)),
        errors.ParameterError,
        ValueError,
        "mu1",
    ),
    ("mu2-zero", lambda m, p: fm.Scene(m, mu=(1.0, 0)), errors.ParameterError, ValueError, "mu2"),
    (
        "mu2-negative",
        lambda m, p: fm.Scene(m, mu=(1.0, -2.5)),
        errors.ParameterError,
        ValueError,
        "mu2",
    ),
    (
        "mu1-nan",
        lambda m, p: fm.Scene(m, mu=(np.nan, 1.0)),
        errors.ParameterError,
        ValueError,
        "mu1",
    ),
    (
        "mu2-inf",
        lambda m, p: fm.Scene(m, mu=(1.0, np.inf)),
        errors.ParameterError,
        ValueError,
        "mu2",
    ),
    (
        "mu1-array-negative",
        lambda m, p: fm.Scene(m, mu=(per_triangle(m, -1.0, 1.0), 1.0)),
        errors.ParameterError,
        ValueError,
        "mu1",
    ),
    (
        "mu2-array-nan",
        lambda m, p: fm.Scene(m, mu=(1.0, np.where(per_triangle(m) > 1.5, np.nan, 1.0))),
        errors.ParameterError,
        ValueError,
        "mu2",
    ),
    # boundary value
    ("g-negative", lambda m, p: fm.Scene(m, g=-0.1), errors.ParameterError, ValueError, "g"),
    ("g-nan", lambda m, p: fm.Scene(m, g=np.nan), errors.DataError, ValueError, "g"),
    ("g-inf", lambda m, p: fm.Scene(m, g=np.inf), errors.DataError, ValueError, "g"),
    (
        "g-array-wrong-length",
        lambda m, p: fm.Scene(m, g=np.zeros(m.n_vertices + 1)),
        errors.DataError,
        ValueError,
        "g",
    ),
    (
        "g-callable-negative",
        lambda m, p: fm.Scene(m, g=lambda x, y: x),
        errors.ParameterError,
        ValueError,
        "g",
    ),
    (
        "g-callable-nan",
        lambda m, p: fm.Scene(m, g=lambda x, y: x * np.nan),
        errors.DataError,
        ValueError,
        "g",
    ),
    # loads
    (
        "f1-array-nan",
        lambda m, p: fm.Scene(m, f=(nan_at_one_vertex(m), 0.0)),
        errors.DataError,
        ValueError,
        "f1",
    ),
    (
        "f2-array-inf",
        lambda m, p: fm.Scene(m, f=(0.0, np.full(m.n_vertices, -np.inf))),
        errors.DataError,
        ValueError,
        "f2",
    ),
    (
        "f2-array-wrong-length",
        lambda m, p: fm.Scene(m, f=(0.0, np.ones(m.n_vertices - 1))),
        errors.DataError,
        ValueError,
        "f2",
    ),
    (
        "f1-array-2d",
        lambda m, p: fm.Scene(m, f=(np.ones((m.n_vertices, 1)), 0.0)),
        errors.DataError,
        ValueError,
        "f1",
    ),
    (
        "f1-scalar-nan",
        lambda m, p: fm.Scene(m, f=(np.nan, 0.0)),
        errors.DataError,
        ValueError,
        "f1",
    ),
    (
        "f2-callable-wrong-shape",
        lambda m, p: fm.Scene(m, f=(0.0, lambda x, y: np.ones(3))).loads,
        errors.DataError,
        ValueError,
        "f2",
    ),
    (
        "f1-callable-nan-solve",
        lambda m, p: fm.solve(fm.Scene(m, f=(lambda x, y: np.full_like(x, np.nan), 1.0))),
        errors.DataError,
        ValueError,
        "f1",
    ),
    (
        "f2-callable-raises",
        lambda m, p: fm.Scene(m, f=(0.0, lambda x: x)).loads,
        errors.DataError,
        ValueError,
        "f2",
    ),
    ("f2-string", lambda m, p: fm.Scene(m, f=(0.0, "1.0")), errors.InputTypeError, TypeError, "f2"),
    # pairs and types
    ("mu-not-a-pair", lambda m, p: fm.Scene(m, mu=1.0), errors.InputTypeError, TypeError, "mu"),
    (
        "mu-triple",
        lambda m, p: fm.Scene(m, mu=(1.0, 1.0, 1.0)),
        errors.InputTypeError,
        TypeError,
        "mu",
    ),
    ("f-not-a-pair", lambda m, p: fm.Scene(m, f=-1.0), errors.InputTypeError, TypeError, "f"),
    ("mu1-none", lambda m, p: fm.Scene(m, mu=(None, 1.0)), errors.InputTypeError, TypeError, "mu1"),
    (
        "mesh-not-a-mesh",
        lambda m, p: fm.Scene((m.vertices, m.triangles)),
        errors.InputTypeError,
        TypeError,
        "mesh",
    ),
    ("scene-not-a-scene", lambda m, p: fm.solve(m), errors.InputTypeError, TypeError, "scene"),
    # per-triangle mu
    (
        "mu2-array-wrong-length",
        lambda m, p: fm.Scene(m, mu=(1.0, np.ones(m.n_triangles + 2))),
        errors.DataError,
        ValueError,
        "mu2",
    ),
    (
        "mu1-array-per-vertex",
        lambda m, p: fm.Scene(m, mu=(np.ones(m.n_vertices), 1.0)),
        errors.DataError,
        ValueError,
        "mu1",
    ),
    # solver options
    (
        "method-unknown",
        lambda m, p: fm.solve(fm.Scene(m), method="newton"),
        errors.ParameterError,
        ValueError,
        "method",
    ),
    (
        "path-unknown",
        lambda m, p: fm.solve(fm.Scene(m), path="fast"),
        errors.ParameterError,
        ValueError,
        "path",
    ),
    (
        "path-decoupled-per-triangle-mu",
        lambda m, p: fm.solve(fm.Scene(m, mu=(per_triangle(m), 1.0)), path="decoupled"),
        errors.ParameterError,
        ValueError,
        "decoupled",
    ),
    (
        "max-newton-zero",
        lambda m, p: fm.solve(fm.Scene(m), max_newton=0),
        errors.ParameterError,
        ValueError,
        "max_newton",
    ),
    (
        "initial-wrong-shape",
        lambda m, p: fm.solve(fm.Scene(m), initial=(np.zeros(3), np.zeros(3), np.zeros(3))),
        errors.DataError,
        ValueError,
        "u1",
    ),
    # meshes
    (
        "mesh-inverted-raise",
        lambda m, p: fm.Mesh(m.vertices, m.triangles[:, ::-1], orientation="raise"),
        errors.MeshError,
        ValueError,
        "triangles",
    ),
    (
        "mesh-float-triangles",
        lambda m, p: fm.Mesh(m.vertices, m.triangles.astype(float)),
        errors.InputTypeError,
        TypeError,
        "triangles",
    ),
    (
        "mesh-vertices-shape",
        lambda m, p: fm.Mesh(m.vertices.T, m.triangles),
        errors.MeshError,
        ValueError,
        "vertices",
    ),
    (
        "mesh-file-missing",
        lambda m, p: fm.Mesh.read(p / "nothing.msh"),
        errors.MeshError,
        ValueError,
        "nothing.msh",
    ),
    # archives
    (
        "archive-missing",
        lambda m, p: fm.load(p / "missing.h5"),
        errors.ArchiveError,
        OSError,
        "missing.h5",
    ),
    (
        "archive-not-hdf5",
        lambda m, p: fm.load(_write(p / "junk.h5", b"not an archive")),
        errors.ArchiveError,
        OSError,
        "junk.h5",
    ),
    (
        "archive-foreign-hdf5",
        lambda m, p: fm.load(_foreign_hdf5(p / "foreign.h5")),
        errors.ArchiveError,
        OSError,
        "foreign.h5",
    ),
    ("archive-directory", lambda m, p: fm.load(p), errors.ArchiveError, OSError, "regular file"),
    # threads
    (
        "threads-numba-zero",
        lambda m, p: fm.set_threads(numba=0),
        errors.ParameterError,
        ValueError,
        "numba",
    ),
    (
        "threads-numba-too-many",
        lambda m, p: fm.set_threads(numba=10**6),
        errors.ParameterError,
        ValueError,
        "numba",
    ),
    (
        "threads-blas-negative",
        lambda m, p: fm.set_threads(blas=-1),
        errors.ParameterError,
        ValueError,
        "blas",
    ),
    (
        "threads-blas-float",
        lambda m, p: fm.set_threads(blas=1.5),
        errors.InputTypeError,
        TypeError,
        "blas",
    ),
]


def _write(path, data):
    path.write_bytes(data)
    return path


def _foreign_hdf5(path):
    h5py = pytest.importorskip("h5py")
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "something-else"
        f["x"] = np.arange(3)
    return path


@pytest.mark.parametrize(
    ("call", "exc", "builtin", "field"),
    [pytest.param(*case[1:], id=case[0]) for case in CASES],
)
def test_bad_input(mesh, tmp_path, call, exc, builtin, field):
    threads_before = fm.get_threads()
    with pytest.raises(exc) as info:
        call(mesh, tmp_path)
    err = info.value
    assert isinstance(err, fm.FastmemError)
    assert isinstance(err, builtin)
    # the natural built-in catches it too
    assert issubclass(type(err), builtin)
    msg = str(err)
    assert re.search(rf"(?<![\w]){field}(?![\w])", msg), msg
    assert "Traceback" not in msg
    # a refused setting leaves the thread configuration alone
    assert fm.get_threads() == threads_before


def test_cases_cover_each_category():
    kinds = {case[2] for case in CASES}
    assert {
        errors.ParameterError,
        errors.DataError,
        errors.InputTypeError,
        errors.MeshError,
        errors.ArchiveError,
    } <= kinds
    assert len(CASES) >= 12


@pytest.mark.parametrize(
    ("cls", "builtin"),
    [
        (errors.InputTypeError, TypeError),
        (errors.MeshError, ValueError),
        (errors.ParameterError, ValueError),
        (errors.DataError, ValueError),
        (errors.ArchiveError, OSError),
        (errors.ConvergenceError, RuntimeError),
        (errors.CyclingError, RuntimeError),
    ],
)
def test_hierarchy(cls, builtin):
    assert issubclass(cls, errors.FastmemError)
    assert issubclass(cls, builtin)
    with pytest.raises(builtin, match="boom"):
        raise cls("boom")
    assert issubclass(errors.MeshWarning, errors.FastmemWarning)
    assert issubclass(errors.FastmemWarning, UserWarning)
    assert not issubclass(errors.FastmemWarning, errors.FastmemError)


def test_cycling_error_is_convergence_error_with_history():
    err = errors.CyclingError("cycles", history={"k": np.arange(3)})
    assert isinstance(err, errors.ConvergenceError)
    assert err.history["k"].tolist() == [0, 1, 2]


def test_callable_f_checked_lazily(mesh):
    # a bad callable load is accepted by Scene and refused when the loads are assembled
    scene = fm.Scene(mesh, f=(0.0, lambda x, y: np.full_like(x, np.inf)))
    with pytest.raises(errors.DataError, match=r"f2\(x, y\).*NaN or inf"):
        _ = scene.loads


def test_valid_scene_passes(mesh):
    # the same constructors with good values do not raise: the refusals above are targeted
    rng = np.random.default_rng(SEED)
    scene = fm.Scene(
        mesh,
        mu=(per_triangle(mesh), 2.0),
        f=(rng.standard_normal(mesh.n_vertices), lambda x, y: x * y),
        g=0.0,
    )
    assert not scene.constant_mu
    f1, f2 = scene.loads
    assert np.isfinite(f1).all()
    assert np.isfinite(f2).all()
    result = fm.solve(scene, path="general")
    assert result.converged


@pytest.mark.parametrize(
    ("make", "field"),
    [
        pytest.param(lambda m: fm.Scene(m, f=(lambda x, y: None, 0.0)).loads, "f1", id="f1-none"),
        pytest.param(
            lambda m: fm.Scene(m, f=(0.0, lambda x, y: np.full(x.shape, "a"))).loads,
            "f2",
            id="f2-strings",
        ),
        pytest.param(
            lambda m: fm.Scene(m, f=(lambda x, y: x + 1j, 0.0)).loads,
            "f1",
            id="f1-complex",
            marks=pytest.mark.filterwarnings("ignore:Casting complex values"),
        ),
        pytest.param(lambda m: fm.Scene(m, g=lambda x, y: None), "g", id="g-none"),
    ],
)
def test_callable_returning_non_real_values(mesh, make, field):
    with pytest.raises(errors.DataError, match=rf"\b{field}\b"):
        make(mesh)


def test_all_names_exist():
    assert len(fm.__all__) == len(set(fm.__all__))
    for name in fm.__all__:
        assert hasattr(fm, name), name
    for name in errors.__all__:
        assert isinstance(getattr(errors, name), type)
    for name in ("Scene", "Mesh", "solve", "load", "set_threads", "FastmemError"):
        assert name in fm.__all__
    assert fm.FastmemError is errors.FastmemError


def test_kernels_location():
    import fastmem.kernels

    package_dir = Path(fm.__file__).resolve().parent
    kernels_file = Path(fastmem.kernels.__file__).resolve()
    repo = Path(__file__).resolve().parents[2]
    if package_dir == repo / "fastmem":
        # editable install (or source tree): kernels come from the repository's kernels/ folder
        assert kernels_file.parent == repo / "kernels"
        assert (repo / "kernels" / "__init__.py").is_file()
    else:
        # regular install: kernels are a subpackage inside the installed fastmem
        assert kernels_file.parent == package_dir / "kernels"
    assert kernels_file.name == "__init__.py"
    assert hasattr(fastmem.kernels, "FASTMATH")


def test_set_threads_refusal_changes_nothing():
    before = fm.get_threads()
    with pytest.raises(errors.ParameterError):
        fm.set_threads(numba=1, blas=-1)
    assert fm.get_threads() == before
    with pytest.raises(errors.InputTypeError, match="blas"):
        fm.set_threads(blas="2")


def test_bad_path_is_refused_before_assembly():
    scene = fm.Scene(fm.Mesh.square(4), f=(lambda x, y: None, 1.0))
    with pytest.raises(errors.ParameterError, match="path"):
        fm.solve(scene, path="nope")
