"""Patch classes of the flux reconstruction: shared factorisations give the same bits.

:func:`fastmem.kernels.flux.patch_classes` groups the vertex patches whose patch
problems have the same geometric part; the patch kernel then takes their
factors from the class storage.  Every test compares against the kernel run
without classes, which computes every patch in full.
"""

import numpy as np
import pytest
from fastmem.kernels import flux as kf

import fastmem as fm
import fastmem.estimators.flux as flux


@pytest.fixture
def always(monkeypatch):
    """Classes on every mesh (the solver uses them from 100,000 vertices on)."""
    monkeypatch.setattr(flux, "PATCH_CLASS_MIN_VERTICES", 0)


def _classes(mesh):
    return flux.find_patch_classes(mesh)


def _geo(mesh):
    """(mesh arrays, largest patch) as the class kernels take them."""
    return flux.patch_arrays(mesh), int(np.diff(mesh.patch_ptr).max())


def _fluxes_both_ways(scene, triple, redistribute):
    """Coefficients with the classes (cached on the mesh) and without them."""
    mesh = scene.mesh
    mesh._cache.pop("patch_classes", None)
    with_classes = flux.reconstruct(scene, *triple, redistribute=redistribute).coef
    assert mesh._cache["patch_classes"] is not None
    mesh._cache["patch_classes"] = None  # the kernel computes every patch in full
    full = flux.reconstruct(scene, *triple, redistribute=redistribute).coef
    mesh._cache.pop("patch_classes")
    return with_classes, full


@pytest.mark.parametrize("redistribute", [True, False, "glued"])
def test_structured_square_shares_factors_bit_for_bit(always, redistribute):
    mesh = fm.Mesh.square(32)
    scene = fm.Scene(mesh, mu=(1.0, 3.0), f=(-1.0, 1.0), g=0.1)
    res = fm.solve(scene, estimate=False)
    # an inexact triple: the residual and contact terms of every patch are exercised
    rng = np.random.default_rng(0)
    triple = (res.u1 + 1e-3 * rng.standard_normal(mesh.n_vertices), res.u2, res.lam)
    cls, reps, cint, _, _ = _classes(mesh)
    # translated copies of a patch: a few classes cover nearly every vertex
    assert reps.size <= 16
    assert np.count_nonzero(cls >= 0) >= mesh.n_vertices - 16
    got, full = _fluxes_both_ways(scene, triple, redistribute)
    assert np.array_equal(got, full)
    assert np.abs(full).max() > 0.0


def test_adapted_mesh_and_the_solver_bound(always, monkeypatch):
    """An NVB mesh (many classes), and the bound a solve reports: the same bits."""
    monkeypatch.setattr(kf, "CLASS_MIN_COVERAGE", 0.0)  # search however few patches recur
    coarse = fm.Scene(fm.Mesh.lshape(8), mu=(1, 1), f=(-1, -1), g=0.1)
    mesh = fm.solve(coarse, tol=3e-2).mesh
    scene = fm.Scene(mesh, mu=(1, 1), f=(-1, -1), g=0.1)
    cls, reps, _, _, _ = _classes(mesh)
    assert reps.size > 16
    assert 0 < np.count_nonzero(cls >= 0) < mesh.n_vertices
    res = fm.solve(scene)
    got, full = _fluxes_both_ways(scene, (res.u1, res.u2, res.lam), "glued")
    assert np.array_equal(got, full)
    mesh._cache["patch_classes"] = None
    plain = fm.solve(fm.Scene(mesh, mu=(1, 1), f=(-1, -1), g=0.1))
    assert plain.eta == res.eta


def test_class_members_have_equal_keys_and_collisions_are_refused(monkeypatch):
    monkeypatch.setattr(kf, "CLASS_MIN_COVERAGE", 0.0)
    mesh = fm.Mesh.square(8)
    cls, reps, cint, cflt, coff = _classes(mesh)
    assert cint[:, 0].max() == 0  # storage empty until the first reconstruction
    assert coff[0] == 0
    assert np.all(np.diff(coff) > 0)
    assert cflt.size > coff[-1]
    # members only of classes of at least CLASS_MIN_PATCHES
    sizes = np.bincount(cls[cls >= 0], minlength=reps.size)
    assert sizes.min() >= kf.CLASS_MIN_PATCHES
    assert np.array_equal(cls[reps], np.arange(reps.size))
    # a key differs as soon as one vertex moves by a few ulps of the edge lengths:
    # its patch and its neighbours' leave their classes
    moved = mesh.vertices.copy()
    a = int(mesh.interior_vertices[len(mesh.interior_vertices) // 2])
    moved[a, 0] += 1e-15
    other = fm.Mesh(moved, mesh.triangles)
    cls2 = _classes(other)[0]
    neighbours = np.unique(other.triangles[np.any(other.triangles == a, axis=1)])
    assert np.all(cls2[neighbours] == -1)
    far = np.setdiff1d(np.flatnonzero(cls >= 0), neighbours)
    assert np.count_nonzero(cls2[far] >= 0) == far.size


def test_hash_collisions_leave_patches_unclassed():
    """All hashes equal (a forced collision): only patches equal to the first one are kept."""
    mesh = fm.Mesh.square(8)
    rep = np.empty(mesh.n_vertices, dtype=np.int64)
    distinct = kf._group_hashes(np.zeros(mesh.n_vertices, dtype=np.uint64), rep)
    assert distinct == 1
    assert np.all(rep == 0)
    ids = np.full(mesh.n_vertices, -1, dtype=np.int32)
    ids[0] = 0
    args = _geo(mesh)
    width = 2 + 10 * args[1]
    keys, lengths = np.empty((1, width)), np.empty(1, dtype=np.int64)
    kf._class_keys(*args, np.zeros(1, dtype=np.int64), keys, lengths)
    cls = np.empty(mesh.n_vertices, dtype=np.int32)
    kf._verify_range(*args, rep, ids, keys, lengths, cls, 0, mesh.n_vertices)
    # vertex 0 is a corner: only corners of the same shape and orientation share its key
    assert cls[0] == 0
    assert 1 <= np.count_nonzero(cls == 0) <= 2
    assert np.all(mesh.boundary_vertex_mask[cls == 0])


def test_per_triangle_tensions_use_no_classes(always):
    mesh = fm.Mesh.square(8)
    mu1 = np.where(mesh.vertices[mesh.triangles, 0].mean(axis=1) < 0.5, 1.0, 10.0)
    assert flux.patch_classes(mesh, mu1, 1.0) is None
    assert flux.patch_classes(mesh, 1.0, 2.0) is not None


def test_no_search_where_few_patches_recur():
    """Coordinates that are not dyadic: translated patches differ in their last bits."""
    mesh = fm.Mesh.square(16)
    assert _classes(mesh) is not None
    # x -> x / 3 + x^3 / 7: no two patches keep equal edge vectors, bit for bit
    v = mesh.vertices / 3.0 + mesh.vertices**3 / 7.0
    assert _classes(fm.Mesh(v, mesh.triangles)) is None


def test_sweep_order_changes_no_bit(monkeypatch):
    """Patches of a colour by their smallest triangle: a reordering within colours, same bits."""
    coarse = fm.Scene(fm.Mesh.lshape(8), mu=(1, 1), f=(-1, -1), g=0.1)
    mesh = fm.solve(coarse, tol=3e-2).mesh
    scene = fm.Scene(mesh, mu=(1, 1), f=(-1, -1), g=0.1)
    res = fm.solve(scene)
    triple = (res.u1, res.u2, res.lam)
    monkeypatch.setattr(flux, "SWEEP_MIN_VERTICES", 0)
    swept, ptr = flux._coloring(mesh)
    got = flux.reconstruct(scene, *triple).coef
    monkeypatch.setattr(flux, "SWEEP_MIN_VERTICES", mesh.n_vertices + 1)
    plain, ptr2 = flux._coloring(mesh)
    full = flux.reconstruct(scene, *triple).coef
    assert np.array_equal(ptr, ptr2)
    # NumPy's version of the order: each colour's vertices sorted by their smallest triangle
    first = np.minimum.reduceat(mesh.patch_triangles, mesh.patch_ptr[:-1])
    assert not np.array_equal(swept, plain)  # a refined mesh: the orders differ
    for c in range(ptr.size - 1):
        seg = plain[ptr[c] : ptr[c + 1]]
        assert np.array_equal(swept[ptr[c] : ptr[c + 1]], seg[np.argsort(first[seg])])
    assert np.array_equal(got, full)
    assert np.abs(full).max() > 0.0


def test_smaller_meshes_use_classes_once_their_kernels_are_loaded(monkeypatch):
    mesh = fm.Mesh.square(80)  # 6561 vertices: between the two thresholds
    assert flux.PATCH_CLASS_WARM_MIN_VERTICES <= mesh.n_vertices < flux.PATCH_CLASS_MIN_VERTICES
    monkeypatch.setattr(kf, "classes_compiled", lambda: False)
    assert flux.patch_classes(mesh, 1.0, 1.0) is None
    assert "patch_classes" not in mesh._cache
    monkeypatch.undo()
    _classes(fm.Mesh.square(8))  # the search's kernels, then a reconstruction with classes
    scene = fm.Scene(fm.Mesh.square(16), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    scene.mesh._cache["patch_classes"] = _classes(scene.mesh)
    zero = np.zeros(scene.mesh.n_vertices)
    flux.reconstruct(scene, zero, zero, zero)
    assert kf.classes_compiled()
    assert flux.patch_classes(mesh, 1.0, 1.0) is not None
    small = fm.Mesh.square(16)
    assert small.n_vertices < flux.PATCH_CLASS_WARM_MIN_VERTICES
    assert flux.patch_classes(small, 1.0, 1.0) is None
