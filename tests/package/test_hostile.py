"""Hostile input at the public API, property-based (issue 6).

Every call either returns a valid object or raises a :class:`fastmem.errors.FastmemError`
with a non-empty message: never a Numba typing error, a raw numpy/scipy exception, a
hang or a silent wrong answer.  Strategies draw small meshes (valid, degenerate,
malformed) and data (valid and hostile) and feed them to ``fm.Mesh``, ``fm.Scene``,
``fm.solve``, ``fm.estimate``, ``Result.save`` and ``fm.load``.

A valid Result has finite nodal arrays, and when mesh and data were accepted and the
method is exact, the discrete contact conditions hold to round-off.  Examples are
derandomized (reproducible in CI).  Every call runs under a hang guard (``attempt``):
SIGALRM fails the test after HANG_SECONDS, and a faulthandler watchdog dumps the
tracebacks and exits should a compiled kernel never return.  The archive tests also
corrupt files byte by byte and interrupt (or SIGKILL) writes that overwrite an archive.
"""

from __future__ import annotations

import contextlib
import faulthandler
import os
import signal
import sys
import tempfile
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, note, settings
from hypothesis import strategies as st
from hypothesis.control import currently_in_test_context

import fastmem as fm
from fastmem.errors import FastmemError, InputTypeError, MeshError, MeshWarning
from fastmem.io import archive
from fastmem.io import writer as archive_write

# Newton-min steps allowed per solve: the guard against endless iterations.
MAX_NEWTON = 60
# Hang guard: a single call running longer than this fails the test.
HANG_SECONDS = 30

FAST = settings(
    max_examples=120,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
FEW = settings(FAST, max_examples=30)


# ---------------------------------------------------------------------------- outcome guard


class Hang(AssertionError):
    """An example ran longer than HANG_SECONDS."""


def _alarm(signum, frame):
    raise Hang(f"call still running after {HANG_SECONDS} s (hang?)")


def attempt(fn, *args, **kwargs):
    """Call ``fn``; return ``(value, None)`` or ``(None, error)`` for a FastmemError.

    Any other exception propagates and fails the test.  Mesh repairs (MeshWarning) are
    allowed.  Hang guards: SIGALRM raises :class:`Hang` after HANG_SECONDS (delivered
    once control returns to Python); a faulthandler watchdog dumps every traceback and
    exits the process after twice that, should a compiled kernel never return.
    """
    use_alarm = hasattr(signal, "SIGALRM")
    if use_alarm:
        previous = signal.signal(signal.SIGALRM, _alarm)
        signal.setitimer(signal.ITIMER_REAL, HANG_SECONDS)
    faulthandler.dump_traceback_later(2 * HANG_SECONDS, exit=True, file=sys.__stderr__)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", MeshWarning)
            return fn(*args, **kwargs), None
    except FastmemError as exc:
        error = exc
    finally:
        faulthandler.cancel_dump_traceback_later()
        if use_alarm:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, previous)
    message = str(error)
    assert message.strip(), f"{type(error).__name__} raised with an empty message"
    assert "Traceback" not in message
    if currently_in_test_context():
        note(f"refused: {type(error).__name__}: {message}")
    return None, error


@contextlib.contextmanager
def short_probe(seconds=5.0):
    """Shorten the time the isolated HDF5 probe of a damaged archive may take."""
    before = archive.PROBE_TIMEOUT
    archive.PROBE_TIMEOUT = seconds
    try:
        yield
    finally:
        archive.PROBE_TIMEOUT = before


def names_field(exc, *words):
    """True when the message of ``exc`` mentions one of ``words``."""
    msg = str(exc).lower()
    return any(w.lower() in msg for w in words)


def check_result(result, scene, exact=True):
    """Check a Result: finite arrays and, for exact solves, the discrete contact conditions."""
    mesh = scene.mesh
    n = mesh.n_vertices
    for name in ("u1", "u2", "lam", "r1", "r2"):
        arr = getattr(result, name)
        assert arr.shape == (n,), name
        assert np.isfinite(arr).all(), f"{name} is not finite"
    assert result.active.shape == (n,)
    bnd = mesh.boundary_vertices
    np.testing.assert_allclose(result.u1[bnd], scene.boundary_values[bnd], rtol=1e-12, atol=0)
    assert (result.u2[bnd] == 0).all()
    assert (result.lam[bnd] == 0).all()
    if result.estimate is not None:
        totals = result.estimate.totals
        assert np.isfinite(totals["eta"])
        assert totals["eta"] >= 0
        for value in result.estimate.maps.values():
            assert np.isfinite(value).all()
    if not exact or not result.converged:
        return
    interior = mesh.interior_vertices
    gap = (result.u1 - result.u2)[interior]
    lam = result.lam[interior]
    act = result.active[interior]
    u_scale = max(np.abs(result.u1).max(), np.abs(result.u2).max(), 1e-300)
    lam_scale = max(np.abs(lam).max(initial=0.0), 1e-300)
    tol = 1e-8
    assert (np.abs(gap[act]) <= tol * u_scale).all(), "gap != 0 on the contact set"
    assert (lam[act] >= -tol * lam_scale).all(), "lambda < 0 on the contact set"
    assert (lam[~act] == 0).all(), "lambda != 0 off the contact set"
    assert (gap[~act] >= -tol * u_scale).all(), "gap < 0 off the contact set"
    f1, f2 = scene.loads
    b = mesh.lumped_mass
    scale = (
        np.linalg.norm(f1)
        + np.linalg.norm(f2)
        + np.linalg.norm(b * result.lam)
        + np.linalg.norm(abs(scene.weighted_stiffness(1)) @ np.abs(result.u1))
        + np.linalg.norm(abs(scene.weighted_stiffness(2)) @ np.abs(result.u2))
        + 1e-300
    )
    res = np.sqrt(result.r1 @ result.r1 + result.r2 @ result.r2)
    assert res <= 1e-8 * scale, f"residual {res:.3e} vs scale {scale:.3e}"


# ---------------------------------------------------------------------------- mesh strategies


def grid(nx, ny, diagonals, jitter, rng, scale=1.0, shift=(0.0, 0.0)):
    """Grid of nx x ny cells, per-cell diagonal, interior vertices jittered by a cell fraction."""
    x = np.linspace(0.0, 1.0, nx + 1)
    y = np.linspace(0.0, 1.0, ny + 1)
    X, Y = np.meshgrid(x, y)
    v = np.stack([X.ravel(), Y.ravel()], axis=1)
    inner = (X.ravel() > 0) & (X.ravel() < 1) & (Y.ravel() > 0) & (Y.ravel() < 1)
    v[inner] += rng.uniform(-jitter, jitter, size=(int(inner.sum()), 2)) / [nx, ny]
    i, j = np.meshgrid(np.arange(nx), np.arange(ny))
    a = (j * (nx + 1) + i).ravel()
    b, c, d = a + 1, a + nx + 2, a + nx + 1
    diag = np.asarray(diagonals, dtype=bool)
    t1 = np.where(diag[:, None], np.stack([a, b, c], 1), np.stack([a, b, d], 1))
    t2 = np.where(diag[:, None], np.stack([a, c, d], 1), np.stack([b, c, d], 1))
    t = np.stack([t1, t2], axis=1).reshape(-1, 3)
    return v * scale + np.asarray(shift), t


def compact(v, t):
    used = np.zeros(len(v), dtype=bool)
    used[t.ravel()] = True
    new = np.cumsum(used) - 1
    return v[used], new[t]


@st.composite
def valid_meshes(draw, max_cells=9):
    """Valid meshes: jittered grids with random diagonals, optional holes, random scale."""
    nx = draw(st.integers(1, max_cells))
    ny = draw(st.integers(1, max_cells))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    diagonals = rng.random(nx * ny) < draw(st.sampled_from([0.0, 0.5, 1.0]))
    jitter = draw(st.sampled_from([0.0, 0.1, 0.2]))  # <= 0.2 cell keeps every triangle positive
    scale = draw(st.sampled_from([1.0, 1e-3, 1e3]))
    shift = draw(st.sampled_from([(0.0, 0.0), (-0.5, -0.5), (1e3, -2e3)]))
    v, t = grid(nx, ny, diagonals, jitter, rng, scale, np.asarray(shift) * scale)
    if draw(st.booleans()):  # shuffle vertex numbering and triangle order
        perm = rng.permutation(len(v))
        inv = np.empty_like(perm)
        inv[perm] = np.arange(len(v))
        v, t = v[perm], inv[t][rng.permutation(len(t))]
    if draw(st.booleans()):  # some clockwise triangles: re-oriented with a warning
        flip = rng.random(len(t)) < 0.3
        t[flip] = t[flip][:, ::-1]
    return v, t


@st.composite
def holed_meshes(draw):
    """Grids with random cells removed: valid, or non-manifold vertices (then refused)."""
    v, t = draw(valid_meshes(max_cells=8))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    cells = len(t) // 2
    keep = np.repeat(rng.random(cells) < draw(st.sampled_from([0.5, 0.8])), 2)
    if not keep.any():
        keep[:2] = True
    return compact(v, t[keep])


DEGENERATIONS = (
    "collinear",
    "duplicate-vertex",
    "unused-vertex",
    "repeated-index",
    "duplicate-triangle",
    "non-manifold-edge",
    "tangled",
    "swap-vertices",
    "collapse-edge",
)

# Exactly degenerate in floating point: always refused.
EXACT_DEGENERATIONS = (
    "duplicate-vertex",
    "unused-vertex",
    "repeated-index",
    "duplicate-triangle",
    "non-manifold-edge",
    "collapse-edge",
)


@st.composite
def degenerate_meshes(draw, kind):
    """A valid mesh spoiled in the way ``kind``; returns (vertices, triangles, kind)."""
    v, t = draw(valid_meshes(max_cells=6))
    v, t = v.copy(), t.copy()
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    k = int(rng.integers(len(t)))
    if kind == "collinear":
        v[t[k, 0]] = 0.5 * (v[t[k, 1]] + v[t[k, 2]])
    elif kind == "duplicate-vertex":
        v = np.vstack([v, v[t[k, 0]]])
        t[k, 0] = len(v) - 1
    elif kind == "unused-vertex":
        v = np.vstack([v, v.max(axis=0) + 1.0])
    elif kind == "repeated-index":
        t[k, 2] = t[k, 0]
    elif kind == "duplicate-triangle":
        t = np.vstack([t, t[k][[1, 2, 0]]])
    elif kind == "non-manifold-edge":
        # two more triangles on the edge (t[k, 0], t[k, 1]): three or four share it
        apexes = v.max(axis=0) + rng.uniform(1.0, 2.0, (2, 2))
        v = np.vstack([v, apexes])
        t = np.vstack([t, [t[k, 0], t[k, 1], len(v) - 2], [t[k, 1], t[k, 0], len(v) - 1]])
    elif kind == "tangled":
        # push one vertex far across its neighbours: triangles invert and overlap
        a = t[k, 0]
        v[a] = v[a] + (v[t[k, 1]] - v[a]) * rng.uniform(1.5, 3.0)
    elif kind == "swap-vertices":
        i, j = rng.choice(len(v), size=2, replace=False)
        v[[i, j]] = v[[j, i]]
    else:  # collapse an edge onto one point: duplicate coordinates
        v[t[k, 1]] = v[t[k, 0]]
    return v, t, kind


@st.composite
def sliver_meshes(draw):
    """A valid mesh plus one nearly flat triangle glued outside a boundary edge."""
    v, t = draw(valid_meshes(max_cells=6))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MeshWarning)
        mesh = fm.Mesh(v, t)
    v, t = mesh.vertices.copy(), mesh.triangles.copy()
    e = mesh.boundary_edges[draw(st.integers(0, len(mesh.boundary_edges) - 1))]
    a, b = mesh.edges[e]
    k = mesh.edge_triangles[e, 0]
    c = next(x for x in t[k] if x not in (a, b))
    d = v[b] - v[a]
    normal = np.array([-d[1], d[0]])
    if normal @ (v[c] - v[a]) > 0:
        normal = -normal  # outward
    flatness = draw(st.sampled_from([1e-12, 1e-9, 1e-6, 1e-3]))
    where = draw(st.sampled_from([0.5, 0.01, 1.2]))  # apex above the edge, near a or beyond b
    apex = v[a] + where * d + flatness * normal
    v = np.vstack([v, apex])
    t = np.vstack([t, [a, b, len(v) - 1]])
    return v, t


def _object_mix(v):
    out = v.astype(object)
    out.flat[0] = "x"
    return out


MALFORMED_VERTICES = {
    "transposed": lambda v: v.T,
    "ravel": lambda v: v.ravel(),
    "3d": lambda v: v[None],
    "one-column": lambda v: v[:, :1],
    "four-columns": lambda v: np.hstack([v, v]),
    "nonplanar-z": lambda v: np.hstack([v, np.ones((len(v), 1))]),
    "strings": lambda v: v.astype(str),
    "object": _object_mix,
    "complex": lambda v: v + 0j,
    "bool": lambda v: v > 0.5,
    "nan": lambda v: np.where(np.arange(v.size).reshape(v.shape) == v.size // 2, np.nan, v),
    "inf": lambda v: np.where(np.arange(v.size).reshape(v.shape) == 1, -np.inf, v),
    "huge": lambda v: v * 1e200,
    "tiny": lambda v: v * 1e-200,
    "none": lambda v: None,
    "scalar": lambda v: 3.0,
    "string": lambda v: "vertices",
    "ragged": lambda v: [list(p) for p in v[:-1]] + [[0.0]],
    "empty": lambda v: np.zeros((0, 2)),
    "dict": lambda v: {"x": v[:, 0], "y": v[:, 1]},
}

MALFORMED_TRIANGLES = {
    "float": lambda t, n: t.astype(float),
    "float-fractional": lambda t, n: t + 0.5,
    "negative": lambda t, n: np.where(t == t.max(), -1, t),
    "equal-n": lambda t, n: np.where(t == 0, n, t),
    "2**40": lambda t, n: np.where(t == 0, 2**40, t),
    "int64-max": lambda t, n: np.where(t == 0, np.iinfo(np.int64).max, t),
    "int64-min": lambda t, n: np.where(t == 0, np.iinfo(np.int64).min, t),
    "uint64-max": lambda t, n: np.where(t == 0, np.iinfo(np.uint64).max, t.astype(np.uint64)),
    "transposed": lambda t, n: t.T,
    "ravel": lambda t, n: t.ravel(),
    "3d": lambda t, n: t[None],
    "four-columns": lambda t, n: np.hstack([t, t[:, :1]]),
    "two-columns": lambda t, n: t[:, :2],
    "empty": lambda t, n: np.zeros((0, 3), dtype=np.int64),
    "empty-list": lambda t, n: [],
    "strings": lambda t, n: t.astype(str),
    "object": lambda t, n: t.astype(object),
    "complex": lambda t, n: t + 0j,
    "bool": lambda t, n: t > 0,
    "none": lambda t, n: None,
    "string": lambda t, n: "triangles",
    "nested-ragged": lambda t, n: [list(r) for r in t[:-1]] + [[0, 1]],
}


# ---------------------------------------------------------------------------- data strategies

finite_positive = st.floats(1e-3, 1e3)
bad_number = st.sampled_from([0.0, -1.0, -1e-300, np.nan, np.inf, -np.inf])


def _raise(x, y):
    raise RuntimeError("user callable failed")


CALLABLES = {
    "smooth": (lambda x, y: np.sin(3 * x) * y - 0.5, True),
    "scalar": (lambda x, y: -0.5, True),
    "int": (lambda x, y: np.ones(np.shape(x), dtype=np.int16), True),
    "raises": (_raise, False),
    "one-arg": (lambda x: x, False),
    "wrong-shape": (lambda x, y: np.ones(3), False),
    "transposed": (lambda x, y: np.asarray(x).T, False),
    "none": (lambda x, y: None, False),
    "strings": (lambda x, y: np.full(np.shape(x), "a"), False),
    "complex": (lambda x, y: x + 1j, False),
    "nan": (lambda x, y: x * np.nan, False),
    "list": (lambda x, y: [1.0, 2.0], False),
}


@st.composite
def mu_values(draw, m):
    """(value, good) for one tension."""
    kind = draw(
        st.sampled_from(["const", "const", "per-triangle", "bad", "bad-array", "wrong", "type"])
    )
    if kind == "const":
        return draw(finite_positive), True
    if kind == "per-triangle":
        arr = draw(st.sampled_from([np.float64, np.float32]))
        vals = np.random.default_rng(draw(st.integers(0, 99))).uniform(0.5, 2.0, m)
        return vals.astype(arr), True
    if kind == "bad":
        return draw(bad_number), False
    if kind == "bad-array":
        vals = np.ones(m)
        vals[draw(st.integers(0, m - 1))] = draw(bad_number)
        return vals, False
    if kind == "wrong":
        return np.ones(m + draw(st.sampled_from([-1, 1, 5]))), False
    return draw(st.sampled_from(["1.0", None, 1 + 1j, True, [1.0, [2.0]], 10**400, {}])), False


@st.composite
def load_values(draw, n):
    """(value, good) for one load f_i."""
    kind = draw(st.sampled_from(["const", "array", "callable", "bad", "wrong", "type"]))
    if kind == "const":
        return draw(st.floats(-10, 10)), True
    if kind == "array":
        return np.random.default_rng(draw(st.integers(0, 99))).normal(size=n), True
    if kind == "callable":
        fn, good = CALLABLES[draw(st.sampled_from(sorted(CALLABLES)))]
        return fn, good
    if kind == "bad":
        arr = np.zeros(n)
        arr[draw(st.integers(0, n - 1))] = draw(st.sampled_from([np.nan, np.inf, -np.inf]))
        return draw(st.sampled_from([np.nan, np.inf, arr])), False
    if kind == "wrong":
        return np.zeros(draw(st.sampled_from([0, 1, n - 1, n + 1]))), False
    return draw(st.sampled_from(["1", None, 2j, np.zeros((n, 2)), 10**400, object()])), False


@st.composite
def g_values(draw, n):
    """(value, good) for the boundary value g."""
    kind = draw(st.sampled_from(["const", "array", "callable", "bad", "type"]))
    if kind == "const":
        return draw(st.floats(0.0, 1.0)), True
    if kind == "array":
        return np.random.default_rng(draw(st.integers(0, 99))).uniform(0, 0.5, n), True
    if kind == "callable":
        return draw(
            st.sampled_from(
                [
                    (lambda x, y: 0.1 + 0.05 * np.cos(x), True),
                    (lambda x, y: x - 10.0, False),
                    (_raise, False),
                    (lambda x, y: np.ones(2), False),
                ]
            )
        )
    if kind == "bad":
        return draw(st.sampled_from([-0.1, np.nan, np.inf, -np.zeros(n) - 1.0])), False
    return draw(st.sampled_from(["0", None, 1j, True, np.zeros(n + 1), 10**400])), False


# ---------------------------------------------------------------------------- properties


def solve_and_check(mesh, scene_kwargs, method="exact", estimate=False, must_work=False):
    """Scene + solve through the guard; check whatever comes back."""
    scene, err = attempt(fm.Scene, mesh, **scene_kwargs)
    if scene is None:
        assert not must_work, f"valid scene refused: {err}"
        return None
    result, err = attempt(fm.solve, scene, method=method, estimate=estimate, max_newton=MAX_NEWTON)
    if result is None:
        assert not must_work, f"valid problem refused: {err}"
        return None
    check_result(result, scene, exact=method != "inexact")
    if must_work and method != "inexact":
        assert result.converged
    return result


@FAST
@given(mesh_data=valid_meshes(), f=st.tuples(st.floats(-5, 5), st.floats(-5, 5)), g=st.floats(0, 1))
def test_valid_meshes_solve(mesh_data, f, g):
    v, t = mesh_data
    mesh, err = attempt(fm.Mesh, v, t)
    assert mesh is not None, f"valid mesh refused: {err}"
    diam2 = float(np.ptp(v, axis=0) @ np.ptp(v, axis=0))
    f = (f[0] / diam2, f[1] / diam2)  # data in the scale of the domain
    solve_and_check(mesh, {"mu": (1.0, 2.0), "f": f, "g": g}, must_work=True)


@FAST
@given(mesh_data=holed_meshes())
def test_holed_meshes_accepted_or_refused(mesh_data):
    v, t = mesh_data
    mesh, err = attempt(fm.Mesh, v, t)
    if mesh is None:
        assert isinstance(err, MeshError)
        return
    scale = float(np.ptp(v, axis=0).max()) ** 2
    solve_and_check(mesh, {"f": (-1 / scale, 1 / scale), "g": 0.05}, must_work=True)


@pytest.mark.parametrize("kind", DEGENERATIONS)
@settings(FAST, max_examples=20)
@given(data=st.data())
def test_degenerate_meshes(kind, data):
    v, t, kind = data.draw(degenerate_meshes(kind))
    mesh, err = attempt(fm.Mesh, v, t)
    if mesh is None:
        assert isinstance(err, MeshError), err
        assert names_field(err, "triangle", "vertex", "vertices", "edge"), err
        return
    # Accepted: it must still be a mesh on which everything works.  Possible for a swap
    # of two vertices that only relabels, a push that did not tangle, or a "collinear"
    # vertex whose rounded midpoint leaves a valid sliver (far from the origin the
    # rounding error of the midpoint exceeds the 1e-13 h^2 area tolerance).
    assert kind not in EXACT_DEGENERATIONS, kind
    solve_and_check(mesh, {"f": (-1.0, 1.0), "g": 0.1}, must_work=True)


@FEW
@given(mesh_data=sliver_meshes(), f=st.tuples(st.floats(-3, 3), st.floats(-3, 3)))
def test_sliver_triangles(mesh_data, f):
    """Nearly flat (but valid) triangles: accepted, or refused as degenerate; never garbage."""
    v, t = mesh_data
    mesh, err = attempt(fm.Mesh, v, t)
    if mesh is None:  # the apex beyond b may overlap a neighbour, or be too flat
        assert isinstance(err, MeshError), err
        return
    solve_and_check(mesh, {"f": f, "g": 0.05}, estimate=True, must_work=True)


@FAST
@given(
    mesh_data=valid_meshes(max_cells=4),
    which=st.sampled_from(["vertices", "triangles"]),
    vkind=st.sampled_from(sorted(MALFORMED_VERTICES)),
    tkind=st.sampled_from(sorted(MALFORMED_TRIANGLES)),
)
def test_malformed_arrays(mesh_data, which, vkind, tkind):
    v, t = mesh_data
    if which == "vertices":
        note(f"vertices: {vkind}")
        v = MALFORMED_VERTICES[vkind](v)
    else:
        note(f"triangles: {tkind}")
        t = MALFORMED_TRIANGLES[tkind](t, len(v))
    mesh, err = attempt(fm.Mesh, v, t)
    if mesh is None:
        assert isinstance(err, (MeshError, InputTypeError)), err
        assert names_field(err, which, "triangle", "vertex", "vertices", "mesh"), err
        return
    # accepted (e.g. a transposed 2x2 vertex array): must be a working mesh
    solve_and_check(mesh, {"f": (-1.0, 1.0), "g": 0.1}, must_work=True)


def test_malformed_tables_are_refused():
    """Every malformed vertex/triangle kind is refused on a mesh where it must be."""
    v, t = grid(3, 2, np.ones(6, dtype=bool), 0.0, np.random.default_rng(0))
    for kind, spoil in MALFORMED_VERTICES.items():
        mesh, err = attempt(fm.Mesh, spoil(v), t)
        assert mesh is None, f"vertices {kind} accepted"
        assert names_field(err, "vertices", "vertex", "triangle"), (kind, err)
    for kind, spoil in MALFORMED_TRIANGLES.items():
        mesh, err = attempt(fm.Mesh, v, spoil(t, len(v)))
        assert mesh is None, f"triangles {kind} accepted"
        assert names_field(err, "triangles", "vertex"), (kind, err)


@FAST
@given(
    mesh_data=valid_meshes(max_cells=5),
    data=st.data(),
)
def test_hostile_data(mesh_data, data):
    v, t = mesh_data
    mesh, err = attempt(fm.Mesh, v, t)
    assert mesh is not None, err
    n, m = mesh.n_vertices, mesh.n_triangles
    mu1, ok1 = data.draw(mu_values(m), label="mu1")
    mu2, ok2 = data.draw(mu_values(m), label="mu2")
    f1, ok3 = data.draw(load_values(n), label="f1")
    f2, ok4 = data.draw(load_values(n), label="f2")
    g, ok5 = data.draw(g_values(n), label="g")
    good = ok1 and ok2 and ok3 and ok4 and ok5
    scene, err = attempt(fm.Scene, mesh, mu=(mu1, mu2), f=(f1, f2), g=g)
    if scene is None:
        assert not good, f"valid data refused: {err}"
        assert names_field(err, "mu", "f1", "f2", "g"), err
        return
    result, err = attempt(fm.solve, scene, method="exact", max_newton=MAX_NEWTON)
    if result is None:
        assert not good, f"valid data refused by solve: {err}"
        assert names_field(err, "f1", "f2", "g"), err
        return
    check_result(result, scene)
    if good:
        assert result.converged


@FEW
@given(
    mesh_data=st.one_of(valid_meshes(max_cells=8), holed_meshes()),
    f=st.tuples(st.floats(-3, 3), st.floats(-3, 3)),
    method=st.sampled_from(["inexact", "exact-amg", "exact"]),
)
def test_methods_with_estimate(mesh_data, f, method):
    v, t = mesh_data
    mesh, _ = attempt(fm.Mesh, v, t)
    if mesh is None:
        return
    scale = float(np.ptp(v, axis=0).max()) ** 2
    result = solve_and_check(
        mesh,
        {"mu": (1.0, 0.5), "f": (f[0] / scale, f[1] / scale), "g": 0.02},
        method=method,
        estimate=True,
        must_work=True,
    )
    assert result.estimate is not None


@FAST
@given(
    mesh_data=valid_meshes(max_cells=5),
    seed=st.integers(0, 2**32 - 1),
    boundary_ok=st.booleans(),
    spoil=st.sampled_from([None, "nan", "short", "strings", "complex", "2d", "list", "huge"]),
)
def test_estimate_any_triple(mesh_data, seed, boundary_ok, spoil):
    v, t = mesh_data
    mesh, _ = attempt(fm.Mesh, v, t)
    scene, _ = attempt(fm.Scene, mesh, mu=(1.0, 3.0), f=(-1.0, 2.0), g=0.1)
    rng = np.random.default_rng(seed)
    n = mesh.n_vertices
    u1, u2, lam = rng.normal(size=(3, n))
    if boundary_ok:
        bnd = mesh.boundary_vertices
        u1[bnd], u2[bnd] = 0.1, 0.0
    triple = [u1, u2, lam]
    k = int(rng.integers(3))
    if spoil == "nan":
        triple[k] = triple[k].copy()
        triple[k][rng.integers(n)] = np.nan
    elif spoil == "short":
        triple[k] = triple[k][:-1]
    elif spoil == "strings":
        triple[k] = triple[k].astype(str)
    elif spoil == "complex":
        triple[k] = triple[k] + 0j
    elif spoil == "2d":
        triple[k] = triple[k][:, None]
    elif spoil == "list":
        triple[k] = triple[k].tolist()
    elif spoil == "huge":
        triple[k] = triple[k] * 1e300
    est, err = attempt(fm.estimate, scene, *triple)
    if est is None:
        assert spoil not in (None, "list") or not boundary_ok, err
        assert names_field(err, "u1", "u2", "lam", "estimate", "eta"), err
        return
    assert np.isfinite(est.eta)
    assert est.eta >= 0
    for value in est.maps.values():
        assert np.isfinite(value).all()


@FEW
@given(mesh_data=valid_meshes(max_cells=5), f=st.tuples(st.floats(-3, 3), st.floats(-3, 3)))
def test_archive_round_trip(mesh_data, f):
    v, t = mesh_data
    mesh, _ = attempt(fm.Mesh, v, t)
    scene, _ = attempt(fm.Scene, mesh, f=f, g=0.05)
    result = fm.solve(scene, method="exact", estimate=True, max_newton=MAX_NEWTON)
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "run.h5")
        _, err = attempt(result.save, path)
        assert err is None, err
        back, err = attempt(fm.load, path)
        assert err is None, err
        assert os.listdir(tmp) == ["run.h5"]
    for name in ("u1", "u2", "lam", "r1", "r2", "active"):
        assert np.array_equal(getattr(back, name), getattr(result, name))
    assert np.array_equal(back.mesh.vertices, mesh.vertices)
    assert np.array_equal(back.mesh.triangles, mesh.triangles)
    assert back.eta == result.eta


@FEW
@given(
    data=st.binary(max_size=2048),
    prefix=st.sampled_from([b"", b"\x89HDF\r\n\x1a\n"]),
)
def test_load_arbitrary_bytes(data, prefix):
    with tempfile.TemporaryDirectory() as tmp, short_probe():
        path = os.path.join(tmp, "junk.h5")
        with open(path, "wb") as fh:
            fh.write(prefix + data)
        result, err = attempt(fm.load, path)
        assert result is None
        assert "junk.h5" in str(err)


# ---------------------------------------------------------------------------- special meshes


@pytest.mark.parametrize(
    ("vertices", "triangles"),
    [
        pytest.param([[0, 0], [1, 0], [0, 1]], [[0, 1, 2]], id="single-triangle"),
        pytest.param([[0, 0], [1, 0], [0, 1]], [[0, 2, 1]], id="single-clockwise"),
        pytest.param(
            [[0, 0], [1, 0], [2, 0], [0, 1], [1, 1], [2, 1]],
            [[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]],
            id="strip-no-interior",
        ),
        pytest.param(
            [[0, 0], [1, 0], [1, 1], [0, 1], [5, 5], [6, 5], [5, 6]],
            [[0, 1, 2], [0, 2, 3], [4, 5, 6]],
            id="two-components",
        ),
    ],
)
@pytest.mark.parametrize("method", ["exact", "exact-amg", "inexact"])
def test_meshes_without_interior_unknowns(vertices, triangles, method):
    mesh, err = attempt(fm.Mesh, np.asarray(vertices, dtype=float), triangles)
    assert mesh is not None, err
    result = solve_and_check(
        mesh, {"f": (-1.0, 1.0), "g": 0.2}, method=method, estimate=True, must_work=True
    )
    assert (result.lam == 0).all()
    assert result.contact_fraction == 0.0


def test_single_interior_vertex():
    v = np.array([[0, 0], [1, 0], [0, 1], [-1, 0], [0, -1]], dtype=float)
    t = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1]])
    mesh = fm.Mesh(v, t)
    assert mesh.interior_vertices.tolist() == [0]
    for f, in_contact in (((-1.0, 1.0), True), ((1.0, -1.0), False)):
        result = solve_and_check(mesh, {"f": f, "g": 0.0}, estimate=True, must_work=True)
        assert bool(result.active[0]) is in_contact


@pytest.mark.parametrize(
    ("factor", "data_factor"),
    [(1e-60, 1e120), (1e60, 1e-120), (1e-100, 1.0), (1e100, 1.0), (1e-200, 1.0)],
)
def test_extreme_mesh_scales(factor, data_factor):
    """Tiny or huge coordinates: solved like the unit mesh, or refused by the mesh check."""
    base = fm.Mesh.square(4, diagonal="right")
    mesh, err = attempt(fm.Mesh, base.vertices * factor, base.triangles)
    if mesh is None:
        assert isinstance(err, MeshError), err
        assert names_field(err, "triangle", "vertices"), err
        return
    ref = fm.solve(fm.Scene(base, f=(-1.0, 0.5), g=0.1), method="exact", estimate=True)
    kwargs = {"f": (-data_factor, 0.5 * data_factor), "g": 0.1}
    result = solve_and_check(mesh, kwargs, estimate=True, must_work=True)
    np.testing.assert_allclose(result.u1, ref.u1, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(result.active, ref.active)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"g": 1e308},
        {"g": 1e200, "f": (-1.0, 1.0)},
        {"f": (-1e307, 1e307)},
        {"f": (-1e200, 0.0), "mu": (1e-200, 1.0)},
        {"mu": (1e-310, 1.0), "f": (-1.0, 1.0)},
        {"mu": (1e300, 1e-300), "f": (1.0, -1.0), "g": 1.0},
        {"f": (lambda x, y: 1e300 * (x + 2), 0.0)},
    ],
    ids=["g-max", "g-1e200", "f-1e307", "f-over-mu", "mu-subnormal", "mu-ratio", "f-callable"],
)
@pytest.mark.parametrize("method", ["exact", "inexact"])
def test_extreme_data_magnitudes(kwargs, method):
    mesh = fm.Mesh.square(4)
    solve_and_check(mesh, kwargs, method=method, estimate=True)


# ---------------------------------------------------------------------------- solve keywords

_SCENE = None


def _scene():
    global _SCENE
    if _SCENE is None:
        _SCENE = fm.Scene(fm.Mesh.square(4), f=(-1.0, 1.0), g=0.1)
    return _SCENE


@pytest.mark.parametrize(
    "kwargs",
    [
        {"method": None},
        {"method": ["exact"]},
        {"method": "EXACT"},
        {"path": 3},
        {"max_newton": 2.5},
        {"max_newton": -1},
        {"max_newton": "10"},
        {"gamma_alg": np.nan},
        {"gamma_lin": -1.0},
        {"max_inner": 0},
        {"check_every": 1.5},
        {"amg_reuse": np.inf},
        {"amg_options": "x"},
        {"amg_options": {"cycle": "Z"}},
        {"blas_threads": "2"},
        {"blas_threads": 0},
        {"estimate": "yes"},
        {"safeguard": None},
        {"initial": "abc"},
        {"initial": (1.0, 2.0, 3.0)},
        {"initial": (np.full(25, np.nan), np.zeros(25), np.zeros(25))},
        {"nested": np.array([1, 2])},
        {"nested": "yes"},
        {"monitor": 3},
        {"amg_options": {"no_such_option": 1}},
    ],
)
def test_bad_solve_keywords(kwargs):
    method = kwargs.pop("method", "inexact")
    result, err = attempt(fm.solve, _scene(), method=method, **kwargs)
    assert result is None
    names = list(kwargs) or ["method"]
    assert names_field(err, *names, *(n.replace("_", " ") for n in names), "initial"), err


# ---------------------------------------------------------------------------- archives


@pytest.fixture(scope="module")
def solved():
    scene = fm.Scene(fm.Mesh.square(6), mu=(1.0, 2.0), f=(-1.0, 1.0), g=0.05)
    return fm.solve(scene, method="exact", estimate=True)


@pytest.fixture(scope="module")
def solved_other():
    scene = fm.Scene(fm.Mesh.square(4), f=(-2.0, 1.0), g=0.0)
    return fm.solve(scene, method="exact")


def same_result(a, b):
    return (
        all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("u1", "u2", "lam", "active"))
        and np.array_equal(a.mesh.vertices, b.mesh.vertices)
        and np.array_equal(a.mesh.triangles, b.mesh.triangles)
        and a.parameters == b.parameters
        and a.timings == b.timings
    )


def _dataset_extents(path):
    """(name, offset, nbytes) of every contiguous dataset of an archive."""
    h5py = pytest.importorskip("h5py")
    out = []
    with h5py.File(path, "r") as f:

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset) and obj.chunks is None:
                offset = obj.id.get_offset()
                if offset is not None and obj.id.get_storage_size() > 0:
                    out.append((name, offset, obj.id.get_storage_size()))

        f.visititems(visit)
    return out


def test_corruption_inside_datasets_is_detected(tmp_path, solved, monkeypatch):
    monkeypatch.setattr(archive, "PROBE_TIMEOUT", 5.0)
    path = tmp_path / "run.h5"
    solved.save(path)
    data = path.read_bytes()
    extents = _dataset_extents(path)
    assert {"mesh/vertices", "solution/u1", "solution/lambda"} <= {e[0] for e in extents}
    rng = np.random.default_rng(20261121)
    for name, offset, nbytes in extents:
        bad = bytearray(data)
        pos = offset + int(rng.integers(nbytes))
        bad[pos] ^= 1 << int(rng.integers(8))  # one flipped bit inside the array
        path.write_bytes(bytes(bad))
        back, err = attempt(fm.load, path)
        assert back is None, f"bit flip in /{name} not detected"
        assert isinstance(err, fm.errors.ArchiveError), err
        assert "checksum" in str(err), err
        assert str(path) in str(err), err


def test_random_byte_corruption_anywhere(tmp_path, solved, monkeypatch):
    """Random bytes anywhere: ArchiveError, or (damage outside the data) the same result."""
    monkeypatch.setattr(archive, "PROBE_TIMEOUT", 5.0)
    path = tmp_path / "run.h5"
    solved.save(path)
    data = path.read_bytes()
    original = fm.load(path)
    rng = np.random.default_rng(7)
    outcomes = {"refused": 0, "same": 0}
    for _ in range(12):
        bad = bytearray(data)
        for pos in rng.integers(0, len(bad), size=int(rng.integers(1, 4))):
            bad[pos] = int(rng.integers(256))
        if bad == data:
            continue
        path.write_bytes(bytes(bad))
        back, err = attempt(fm.load, path)
        if back is None:
            assert isinstance(err, fm.errors.ArchiveError), err
            outcomes["refused"] += 1
        else:
            assert same_result(back, original)
            outcomes["same"] += 1
    assert outcomes["refused"] >= 6, outcomes


def test_corrupt_metadata_that_hangs_hdf5_is_refused(tmp_path, solved, monkeypatch):
    """A damaged global-heap entry made HDF5 loop forever: the probe runs it in a child."""
    monkeypatch.setattr(archive, "PROBE_TIMEOUT", 3.0)
    path = tmp_path / "run.h5"
    solved.save(path)
    bad = bytearray(path.read_bytes())
    i = bad.find(b"res_norm")  # a history column name, stored in the global heap
    assert i > 16
    bad[i - 8] = 0xB6  # its length field
    path.write_bytes(bytes(bad))
    back, err = attempt(fm.load, path)
    assert back is None
    assert isinstance(err, fm.errors.ArchiveError)
    assert str(path) in str(err)
    _, err = attempt(archive.info, path)
    assert isinstance(err, fm.errors.ArchiveError)


def test_modified_archive_is_refused(tmp_path, solved):
    h5py = pytest.importorskip("h5py")
    path = tmp_path / "run.h5"
    solved.save(path)
    with h5py.File(path, "r+") as f:
        f["solution/u1"][0] += 1.0  # a plausible, valid-looking edit
    back, err = attempt(fm.load, path)
    assert back is None
    assert "checksum" in str(err)


def test_archive_without_integrity_header_still_loads(tmp_path, solved):
    """Archives written before the header existed (no user block) load unverified."""
    path = tmp_path / "run.h5"
    solved.save(path)
    legacy = tmp_path / "legacy.h5"
    legacy.write_bytes(path.read_bytes()[archive._USERBLOCK :])  # HDF5 addresses are relative
    back, err = attempt(fm.load, legacy)
    assert err is None, err
    assert same_result(back, solved)
    assert archive.info(legacy)["n_vertices"] == solved.mesh.n_vertices


def _boom(*args, **kwargs):
    raise RuntimeError("simulated crash")


def _interrupt(*args, **kwargs):
    raise KeyboardInterrupt


def _disk_full(*args, **kwargs):
    raise OSError(28, "No space left on device")


@pytest.mark.parametrize(
    "stage",
    [
        "_write_header",
        "_write_mesh",
        "_write_solution",
        "_write_estimate",
        "_write_history",
        "_write_timings",
        "_write_integrity_header",
        "_fsync",
        "os.chmod",
        "os.replace",
    ],
)
@pytest.mark.parametrize(
    ("failure", "expected"),
    [(_boom, RuntimeError), (_interrupt, KeyboardInterrupt), (_disk_full, fm.errors.ArchiveError)],
    ids=["exception", "ctrl-c", "disk-full"],
)
def test_interrupted_overwrite_keeps_old_archive(
    tmp_path, solved, solved_other, monkeypatch, stage, failure, expected
):
    path = tmp_path / "run.h5"
    solved_other.save(path)
    before = path.read_bytes()
    if stage.startswith("os."):
        monkeypatch.setattr(archive_write.os, stage[3:], failure)
    else:
        monkeypatch.setattr(archive_write, stage, failure)
    with pytest.raises(expected):
        solved.save(path)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["run.h5"]  # no temporary file left behind
    assert same_result(fm.load(path), solved_other)


_WRITER = """
import sys
import numpy as np
import fastmem as fm
mesh = fm.Mesh.square(60)
n = mesh.n_vertices
results = []
for k in range(2):
    scene = fm.Scene(mesh, f=(-1.0 - k, 1.0), g=0.05)
    results.append(fm.solve(scene, method="exact"))
results[0].save(sys.argv[1])
print("ready", flush=True)
k = 1
while True:
    results[k].save(sys.argv[1])
    k = 1 - k
"""


@pytest.mark.skipif(not hasattr(os, "kill"), reason="needs os.kill")
def test_killed_writer_never_leaves_half_archive(tmp_path):
    """SIGKILL at arbitrary points of repeated overwrites: the archive stays loadable."""
    import signal as _signal
    import subprocess
    import time

    path = tmp_path / "run.h5"
    proc = subprocess.Popen(
        [sys.executable, "-c", _WRITER, str(path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(0.4)
    finally:
        proc.send_signal(_signal.SIGKILL)
        proc.wait(timeout=30)
    back, err = attempt(fm.load, path)
    assert err is None, err
    assert back.mesh.n_vertices == 61 * 61
    assert back.converged
    leftovers = [p for p in os.listdir(tmp_path) if p != "run.h5"]
    assert all(p.startswith(".run.h5.tmp-") for p in leftovers), leftovers


def test_save_refuses_inconsistent_results(tmp_path, solved):
    import copy

    for field, value, exc in [
        ("u1", solved.u1[:-1], fm.errors.DataError),
        ("lam", np.full_like(solved.lam, np.nan), fm.errors.NumericalError),
        ("active", solved.active.astype(float), fm.errors.InputTypeError),
        ("mesh", None, fm.errors.InputTypeError),
    ]:
        broken = copy.copy(solved)
        setattr(broken, field, value)
        _, err = attempt(broken.save, tmp_path / "run.h5")
        assert isinstance(err, exc), (field, err)
        assert field in str(err)
    _, err = attempt(archive.save, "not a result", tmp_path / "run.h5")
    assert isinstance(err, InputTypeError)
    assert "result" in str(err)
    assert os.listdir(tmp_path) == []


def test_result_refuses_non_finite_values(solved):
    import dataclasses

    for name in ("u1", "u2", "lam", "r1", "r2"):
        bad = getattr(solved, name).copy()
        bad[-1] = np.inf
        _, err = attempt(dataclasses.replace, solved, **{name: bad})
        assert isinstance(err, fm.errors.NumericalError)
        assert name in str(err)
    _, err = attempt(fm.Estimate, totals={"eta": np.nan})
    assert isinstance(err, fm.errors.NumericalError)
    assert "eta" in str(err)


# ---------------------------------------------------------------------------- ranges, immutability

_SQ = fm.Mesh.square(4)
_N = _SQ.n_vertices


@pytest.mark.parametrize(
    ("call", "exc", "field"),
    [
        (lambda: fm.Scene(_SQ, mu=(1e-120, 1.0)), fm.errors.ParameterError, "mu1"),
        (
            lambda: fm.Scene(_SQ, mu=(1.0, np.full(_SQ.n_triangles, 1e150))),
            fm.errors.ParameterError,
            "mu2",
        ),
        (lambda: fm.Scene(_SQ, mu=(10**400, 1.0)), fm.errors.ParameterError, "mu1"),
        (lambda: fm.Scene(_SQ, g=1e95), fm.errors.DataError, "g"),
        (lambda: fm.Scene(_SQ, f=(1e95, 0.0)), fm.errors.DataError, "f1"),
        (lambda: fm.Scene(_SQ, f=(0.0, -(10**400))), fm.errors.DataError, "f2"),
        (lambda: fm.Scene(_SQ, f=(lambda x, y: 1e300 + x, 0.0)).loads, fm.errors.DataError, "f1"),
        (lambda: fm.Scene(_SQ, mu=(1e-100, 1.0), f=(1e20, 0.0)), fm.errors.DataError, "f1"),
        (lambda: fm.Scene(_SQ, mu=(1e100, 1.0), g=1e10), fm.errors.DataError, "mu1"),
        (lambda: fm.Mesh(_SQ.vertices * 1e60, _SQ.triangles), MeshError, "vertices"),
        (lambda: fm.Mesh(_SQ.vertices * 1e-60, _SQ.triangles), MeshError, "triangles"),
        (
            lambda: fm.Mesh(np.longdouble("1e400") * _SQ.vertices, _SQ.triangles),
            MeshError,
            "vertices",
        ),
        (
            lambda: fm.solve(
                fm.Scene(_SQ), initial=(np.full(_N, 1e95), np.zeros(_N), np.zeros(_N))
            ),
            fm.errors.DataError,
            "initial u1",
        ),
        (
            lambda: fm.estimate(fm.Scene(_SQ), np.zeros(_N), np.zeros(_N), np.full(_N, -1e95)),
            fm.errors.DataError,
            "lam",
        ),
        (lambda: fm.Scene(_SQ, mu=([1.0, [2.0]], 1.0)), InputTypeError, "mu1"),
        (lambda: fm.Scene(_SQ, f=(0.0, [[1.0], 2.0])), InputTypeError, "f2"),
        (lambda: fm.Scene(_SQ, mu={"a": 1, "b": 2}), InputTypeError, "mu"),
        (lambda: fm.Scene(_SQ, mu=np.array(1.0)), InputTypeError, "mu"),
        (lambda: fm.Scene(_SQ, f=iter([1.0, 2.0])), InputTypeError, "f"),
        (lambda: fm.Mesh(_SQ.vertices, _SQ.triangles, validate="yes"), InputTypeError, "validate"),
        (lambda: fm.Mesh(_SQ.vertices, []), MeshError, "triangles"),
        (lambda: fm.Mesh(np.zeros((0, 2)), _SQ.triangles), MeshError, "vertices"),
    ],
)
def test_out_of_range_refusals_name_the_field(call, exc, field):
    result, err = attempt(call)
    assert result is None
    assert isinstance(err, exc), err
    assert field in str(err), err


def test_mesh_and_scene_are_immutable():
    mesh = fm.Mesh.square(4)
    scene = fm.Scene(mesh, f=(-1.0, 1.0), g=0.1)
    before = fm.solve(scene, method="exact")
    for obj, name, value in [
        (mesh, "vertices", mesh.vertices * 2),
        (mesh, "triangles", mesh.triangles[:, ::-1]),
        (mesh, "parent", None),
        (scene, "mu1", -1.0),
        (scene, "f1", np.nan),
        (scene, "g", -1.0),
        (scene, "mesh", fm.Mesh.square(2)),
    ]:
        with pytest.raises(fm.errors.ReadOnlyError, match=name):
            setattr(obj, name, value)
    with pytest.raises(ValueError, match="read-only"):
        mesh.vertices[0, 0] = 5.0
    with pytest.raises(ValueError, match="read-only"):
        scene.boundary_values[0] = -1.0
    assert_same = np.testing.assert_array_equal
    assert_same(fm.solve(scene, method="exact").u1, before.u1)
    assert issubclass(fm.errors.ReadOnlyError, AttributeError)
    assert issubclass(fm.errors.NumericalError, ArithmeticError)


@pytest.mark.parametrize(
    ("r1", "r2"),
    [
        pytest.param(np.zeros(3), np.zeros(3), id="short"),
        pytest.param("r1", "r2", id="strings"),
        pytest.param(np.zeros(_N), None, id="r1-only"),
        pytest.param(np.full(_N, np.nan), np.zeros(_N), id="nan"),
    ],
)
def test_estimate_refuses_bad_residuals(r1, r2):
    """Residuals passed to fm.estimate are validated like the triple."""
    scene = fm.Scene(_SQ, g=0.1)
    u1 = scene.boundary_values.copy()
    z = np.zeros(_N)
    result, err = attempt(fm.estimate, scene, u1, z, z, r1=r1, r2=r2)
    assert result is None
    assert names_field(err, "r1", "r2"), err


def test_subnormal_boundary_value_solves():
    """The example hypothesis found: g = 5e-324 made eta_C NaN (fastmath reciprocal)."""
    x, y = np.meshgrid([0.0, 0.5, 1.0], [0.0, 0.5, 1.0])
    vertices = np.column_stack([x.ravel(), y.ravel()])
    triangles = [[0, 1, 3], [1, 4, 3], [1, 2, 4], [2, 5, 4]]
    triangles += [[3, 4, 6], [4, 7, 6], [4, 5, 7], [5, 8, 7]]
    scene = fm.Scene(fm.Mesh(vertices, np.array(triangles)), f=(-1.0, 0.0), g=5e-324)
    for method in ("inexact", "exact"):
        result = fm.solve(scene, method=method)
        assert np.isfinite(result.eta)
        assert result.eta > 0
