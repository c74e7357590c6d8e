"""Dtype and memory-layout acceptance at the public API (issue 6).

Policy (documented in the Mesh and Scene docstrings): numeric arrays of any real dtype
(float16/32/64, longdouble, every integer width, either byte order) and any layout
(Fortran order, strided views, negative strides, read-only, memmaps, nested lists) are
converted once to C-contiguous float64 (int64 for triangles) and give the same result as
the canonical float64/int64 input of the same values.  Bool, complex, object and string
arrays are refused with InputTypeError naming the field; floating-point triangle indices
are refused too (no silent truncation), and so are masked arrays with masked entries.
"""

from __future__ import annotations

import numpy as np
import pytest

import fastmem as fm
from fastmem.errors import DataError, InputTypeError

INT_DTYPES = [
    np.int8,
    np.int16,
    np.int32,
    np.int64,
    np.uint8,
    np.uint16,
    np.uint32,
    np.uint64,
]


def _jittered(n=4, seed=20261121):
    base = fm.Mesh.square(n, diagonal="right")
    rng = np.random.default_rng(seed)
    v = base.vertices.copy()
    v[base.interior_vertices] += rng.uniform(-0.1, 0.1, (base.interior_vertices.size, 2)) / n
    return v, base.triangles.copy()


V64, T64 = _jittered()  # 25 vertices: indices fit every integer dtype, int8 included
N, M = len(V64), len(T64)
RNG = np.random.default_rng(5)
F1 = RNG.normal(size=N) - 1.0
MU1 = RNG.uniform(0.5, 2.0, M)
G = np.full(N, 0.05)


def solve(mesh, mu=(1.0, 2.0), f=(-1.0, 1.0), g=0.05):
    return fm.solve(fm.Scene(mesh, mu=mu, f=f, g=g), method="exact", path="general")


@pytest.fixture(scope="module")
def reference():
    return solve(fm.Mesh(V64, T64))


def assert_same(result, ref, rtol=1e-12):
    scale = max(np.abs(ref.u1).max(), np.abs(ref.u2).max(), 1.0)
    for name in ("u1", "u2"):
        np.testing.assert_allclose(
            getattr(result, name), getattr(ref, name), rtol=0, atol=rtol * scale
        )
    lam_scale = max(np.abs(ref.lam).max(), 1.0)
    np.testing.assert_allclose(result.lam, ref.lam, rtol=0, atol=rtol * lam_scale)
    np.testing.assert_array_equal(result.active, ref.active)


def readonly(a):
    a = np.array(a)
    a.flags.writeable = False
    return a


def layouts(a):
    """The same values in many layouts: (id, array-like)."""
    wide = np.zeros((a.shape[0], 2 * a.shape[1]) if a.ndim == 2 else (2 * a.shape[0],), a.dtype)
    if a.ndim == 2:
        wide[:, ::2] = a
        strided = wide[:, ::2]
        rows = np.zeros((2 * a.shape[0], a.shape[1]), a.dtype)
        rows[::2] = a
        every_other = rows[::2]
    else:
        wide[::2] = a
        strided = every_other = wide[::2]
    return [
        ("C", np.ascontiguousarray(a)),
        ("fortran", np.asfortranarray(a)),
        ("strided-columns", strided),
        ("every-other-row", every_other),
        ("reversed-twice", a[::-1][::-1]),
        ("read-only", readonly(a)),
        ("big-endian", a.astype(a.dtype.newbyteorder(">"))),
        ("list", a.tolist()),
    ]


# ---------------------------------------------------------------------------- mesh arrays


@pytest.mark.parametrize(
    ("layout", "vertices"), layouts(V64), ids=lambda x: x if isinstance(x, str) else ""
)
def test_vertex_layouts_give_identical_results(reference, layout, vertices):
    mesh = fm.Mesh(vertices, T64)
    assert mesh.vertices.dtype == np.float64
    assert mesh.vertices.flags.c_contiguous
    np.testing.assert_array_equal(mesh.vertices, V64)
    assert_same(solve(mesh), reference, rtol=0)  # bit-identical


@pytest.mark.parametrize(
    ("layout", "triangles"), layouts(T64), ids=lambda x: x if isinstance(x, str) else ""
)
def test_triangle_layouts_give_identical_results(reference, layout, triangles):
    mesh = fm.Mesh(V64, triangles)
    assert mesh.triangles.dtype == np.int64
    assert mesh.triangles.flags.c_contiguous
    assert_same(solve(mesh), reference, rtol=0)


@pytest.mark.parametrize("dtype", INT_DTYPES)
def test_triangle_index_dtypes(reference, dtype):
    t = T64.astype(dtype)
    mesh = fm.Mesh(V64, t)
    assert mesh.triangles.dtype == np.int64
    np.testing.assert_array_equal(mesh.triangles, T64)
    assert_same(solve(mesh), reference, rtol=0)
    # also non-native byte order and non-contiguous
    wide = np.zeros((M, 6), dtype=np.dtype(dtype).newbyteorder(">"))
    wide[:, ::2] = t
    assert_same(solve(fm.Mesh(V64, wide[:, ::2])), reference, rtol=0)


@pytest.mark.parametrize("dtype", [np.float32, np.float16, np.longdouble])
def test_float_vertex_dtypes(reference, dtype):
    """Rounded input: identical to float64 input of the rounded values, close to the original."""
    v = V64.astype(dtype)
    mesh = fm.Mesh(v, T64)
    assert mesh.vertices.dtype == np.float64
    exact = solve(fm.Mesh(v.astype(np.float64), T64))
    assert_same(solve(mesh), exact, rtol=0)
    eps = float(np.finfo(dtype).eps) if dtype != np.longdouble else 1e-16
    assert_same(solve(mesh), reference, rtol=max(200 * eps, 1e-12))


@pytest.mark.parametrize("dtype", INT_DTYPES)
def test_integer_vertex_coordinates(dtype):
    """Integer coordinates (a 4 x 4 grid of unit cells): same as their float64 values."""
    base = fm.Mesh.rectangle(4, 4, bounds=(0, 4, 0, 4), diagonal="right")
    v = np.rint(base.vertices).astype(dtype)
    mesh = fm.Mesh(v, base.triangles)
    np.testing.assert_array_equal(mesh.vertices, base.vertices)
    f = (-1 / 16, 1 / 16)
    assert_same(solve(mesh, f=f), solve(base, f=f), rtol=0)


def test_masked_vertices_refused():
    v = np.ma.masked_array(V64, mask=np.zeros_like(V64, dtype=bool))
    fm.Mesh(v, T64)  # nothing masked: fine
    v.mask[3, 0] = True
    with pytest.raises(DataError, match="vertices"):
        fm.Mesh(v, T64)
    t = np.ma.masked_array(T64, mask=np.zeros_like(T64, dtype=bool))
    t.mask[0, 0] = True
    with pytest.raises(DataError, match="triangles"):
        fm.Mesh(V64, t)


def test_memmap_inputs(tmp_path, reference):
    vm = np.lib.format.open_memmap(tmp_path / "v.npy", mode="w+", dtype=np.float64, shape=V64.shape)
    vm[:] = V64
    tm = np.lib.format.open_memmap(tmp_path / "t.npy", mode="w+", dtype=np.int32, shape=T64.shape)
    tm[:] = T64
    mesh = fm.Mesh(
        np.load(tmp_path / "v.npy", mmap_mode="r"), np.load(tmp_path / "t.npy", mmap_mode="r")
    )
    assert_same(solve(mesh), reference, rtol=0)


@pytest.mark.parametrize(
    ("vertices", "triangles", "field"),
    [
        pytest.param(V64 > 0, T64, "vertices", id="bool-vertices"),
        pytest.param(V64 + 0j, T64, "vertices", id="complex-vertices"),
        pytest.param(V64.astype(object), T64, "vertices", id="object-vertices"),
        pytest.param(V64.astype(str), T64, "vertices", id="str-vertices"),
        pytest.param(V64.astype("S8"), T64, "vertices", id="bytes-vertices"),
        pytest.param(V64.astype("datetime64[s]"), T64, "vertices", id="datetime-vertices"),
        pytest.param(V64, T64 > 0, "triangles", id="bool-triangles"),
        pytest.param(V64, T64.astype(np.float64), "triangles", id="float-triangles"),
        pytest.param(V64, T64.astype(np.float32), "triangles", id="float32-triangles"),
        pytest.param(V64, T64 + 0j, "triangles", id="complex-triangles"),
        pytest.param(V64, T64.astype(object), "triangles", id="object-triangles"),
        pytest.param(V64, T64.astype(str), "triangles", id="str-triangles"),
        pytest.param(V64, T64.astype("timedelta64[s]"), "triangles", id="timedelta-triangles"),
    ],
)
def test_refused_mesh_dtypes(vertices, triangles, field):
    with pytest.raises(InputTypeError, match=field):
        fm.Mesh(vertices, triangles)


def test_mesh_never_aliases_or_modifies_input():
    v, t = V64.copy(), T64.copy()
    t[0] = t[0, [0, 2, 1]]  # one clockwise triangle: re-oriented in the mesh's copy
    with pytest.warns(fm.errors.MeshWarning):
        mesh = fm.Mesh(v, t)
    assert v.flags.writeable
    assert t.flags.writeable
    np.testing.assert_array_equal(t[0], T64[0, [0, 2, 1]])  # caller's array untouched
    v[:] = 0.0
    assert mesh.areas.min() > 0


# ---------------------------------------------------------------------------- scene data


@pytest.fixture(scope="module")
def mesh():
    return fm.Mesh(V64, T64)


@pytest.fixture(scope="module")
def data_reference(mesh):
    return solve(mesh, mu=(MU1, 2.0), f=(F1, 1.0), g=G)


def _cast(a, dtype):
    return a.astype(dtype)


@pytest.mark.parametrize("which", ["mu1", "f1", "g"])
@pytest.mark.parametrize(
    ("layout", "transform"),
    [
        ("fortran", np.asfortranarray),
        ("read-only", readonly),
        ("strided", lambda a: np.repeat(a, 2)[::2]),
        ("reversed-twice", lambda a: a[::-1][::-1]),
        ("big-endian", lambda a: a.astype(">f8")),
        ("list", lambda a: a.tolist()),
        ("tuple", lambda a: tuple(a.tolist())),
    ],
)
def test_data_layouts_identical(mesh, data_reference, which, layout, transform):
    values = {"mu1": MU1, "f1": F1, "g": G}
    values[which] = transform(values[which])
    result = solve(mesh, mu=(values["mu1"], 2.0), f=(values["f1"], 1.0), g=values["g"])
    assert_same(result, data_reference, rtol=0)


@pytest.mark.parametrize("dtype", [np.float32, np.float16, np.longdouble])
@pytest.mark.parametrize("which", ["mu1", "f1", "g"])
def test_float_data_dtypes(mesh, data_reference, which, dtype):
    values = {"mu1": MU1, "f1": F1, "g": G}
    values[which] = values[which].astype(dtype)
    result = solve(mesh, mu=(values["mu1"], 2.0), f=(values["f1"], 1.0), g=values["g"])
    rounded = {k: np.asarray(v, dtype=np.float64) for k, v in values.items()}
    exact = solve(mesh, mu=(rounded["mu1"], 2.0), f=(rounded["f1"], 1.0), g=rounded["g"])
    assert_same(result, exact, rtol=0)  # converted once, exactly
    eps = float(np.finfo(dtype).eps) if dtype != np.longdouble else 1e-16
    assert_same(result, data_reference, rtol=max(100 * eps, 1e-12))


@pytest.mark.parametrize("dtype", INT_DTYPES)
def test_integer_data_arrays(mesh, dtype):
    ints_f = (np.arange(N) % 5 - 3).clip(0 if np.dtype(dtype).kind == "u" else -3)
    ints_mu = np.arange(M) % 3 + 1
    ints_g = np.ones(N)
    ref = solve(mesh, mu=(ints_mu.astype(float), 2.0), f=(ints_f.astype(float), -1.0), g=ints_g)
    got = solve(
        mesh,
        mu=(ints_mu.astype(dtype), 2.0),
        f=(ints_f.astype(dtype), -1.0),
        g=ints_g.astype(dtype),
    )
    assert_same(got, ref, rtol=0)


@pytest.mark.parametrize(
    "scalar",
    [
        np.float32(1.5),
        np.float16(1.5),
        np.longdouble(1.5),
        np.int8(1),
        np.uint64(3),
        np.array(1.5),
        2,
        1.5,
    ],
    ids=lambda s: type(s).__name__,
)
def test_scalar_types(mesh, scalar):
    value = float(scalar)
    got = solve(mesh, mu=(scalar, 1.0), f=(-value, scalar), g=scalar)
    ref = solve(mesh, mu=(value, 1.0), f=(-value, value), g=value)
    assert_same(got, ref, rtol=0)


def test_fraction_scalars(mesh):
    from fractions import Fraction

    got = solve(mesh, mu=(Fraction(3, 2), 1), f=(Fraction(-1, 3), 0), g=Fraction(1, 20))
    ref = solve(mesh, mu=(1.5, 1.0), f=(-1 / 3, 0.0), g=0.05)
    assert_same(got, ref, rtol=0)


def test_scene_never_aliases_or_freezes_input(mesh):
    f1, mu1, g = F1.copy(), MU1.copy(), G.copy()
    scene = fm.Scene(mesh, mu=(mu1, 2.0), f=(f1, 1.0), g=g)
    for name, arr in (("f1", f1), ("mu1", mu1), ("g", g)):
        assert arr.flags.writeable, f"Scene made the caller's {name} read-only"
    before = fm.solve(scene, method="exact")
    f1[:] = 1e3
    mu1[:] = -1.0
    g[:] = -1.0  # would be refused; must not leak into the scene afterwards
    after = fm.solve(scene, method="exact")
    assert_same(after, before, rtol=0)
    assert not scene.f1.flags.writeable
    assert not scene.boundary_values.flags.writeable


def test_callable_g_is_evaluated_once(mesh):
    calls = []

    def g(x, y):
        calls.append(1)
        return np.full(np.shape(x), 0.05) if len(calls) == 1 else np.full(np.shape(x), -1.0)

    scene = fm.Scene(mesh, g=g)
    result = fm.solve(scene, method="exact")
    assert len(calls) == 1
    np.testing.assert_array_equal(result.u1[mesh.boundary_vertices], 0.05)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"mu": (np.ones(M, dtype=bool), 1.0)}, "mu1"),
        ({"mu": (1.0, np.ones(M) + 0j)}, "mu2"),
        ({"mu": (np.bool_(True), 1.0)}, "mu1"),
        ({"mu": (True, 1.0)}, "mu1"),
        ({"mu": (np.complex64(1), 1.0)}, "mu1"),
        ({"mu": (np.ones(M).astype(object), 1.0)}, "mu1"),
        ({"f": (np.ones(N, dtype=bool), 0.0)}, "f1"),
        ({"f": (0.0, np.ones(N).astype(str))}, "f2"),
        ({"f": (np.ones(N) * 1j, 0.0)}, "f1"),
        ({"f": (np.array(True), 0.0)}, "f1"),
        ({"f": (np.ones(N).astype("datetime64[s]"), 0.0)}, "f1"),
        ({"g": np.ones(N, dtype=bool)}, "g"),
        ({"g": np.ones(N).astype(object)}, "g"),
        ({"g": np.bool_(False)}, "g"),
        ({"g": 0.1 + 0j}, "g"),
    ],
    ids=lambda x: x if isinstance(x, str) else "",
)
def test_refused_data_dtypes(mesh, kwargs, field):
    with pytest.raises(InputTypeError, match=rf"\b{field}\b"):
        fm.Scene(mesh, **kwargs)


def test_masked_data_refused(mesh):
    f = np.ma.masked_array(F1, mask=np.arange(N) == 3)
    with pytest.raises(DataError, match="f1"):
        fm.Scene(mesh, f=(f, 0.0))
    mu = np.ma.masked_array(MU1, mask=np.arange(M) == 0)
    with pytest.raises(DataError, match="mu2"):
        fm.Scene(mesh, mu=(1.0, mu))


# ---------------------------------------------------------------------------- triples


@pytest.mark.parametrize("dtype", [np.float32, np.int64, ">f8"])
def test_estimate_and_initial_accept_numeric_triples(mesh, dtype):
    scene = fm.Scene(mesh, mu=(1.0, 2.0), f=(-1.0, 1.0), g=1.0)
    ref = fm.solve(scene, method="exact", estimate=True)
    triple = [np.rint(a).astype(dtype) for a in (ref.u1, ref.u2, ref.lam)]
    est = fm.estimate(scene, *triple)
    est64 = fm.estimate(scene, *[a.astype(np.float64) for a in triple])
    assert est.eta == est64.eta
    again = fm.solve(scene, method="exact", initial=[np.asfortranarray(a) for a in triple])
    assert_same(again, ref)


@pytest.mark.parametrize("bad", [bool, complex, object, str])
def test_estimate_refuses_non_real_triples(mesh, bad):
    scene = fm.Scene(mesh)
    triple = [np.zeros(N), np.zeros(N), np.zeros(N).astype(bad)]
    with pytest.raises(InputTypeError, match="lam"):
        fm.estimate(scene, *triple)
