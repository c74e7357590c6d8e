"""Tests of fastmem.mesh: generators, derived topology, refinement, geometry, I/O, validation."""

from __future__ import annotations

import numpy as np
import pytest
from meshes import SYMMETRIES
from numpy.testing import assert_allclose, assert_array_equal

from fastmem.errors import FastmemError, InputTypeError, MeshError, MeshWarning, ParameterError
from fastmem.mesh.mesh import Mesh

meshio = pytest.importorskip("meshio")

SEED = 20261121
DIAGONALS = ("right", "left", "symmetric")

# Unit square split along its diagonal 0-2: the smallest valid mesh used by the checks below.
SQ_V = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
SQ_T = np.array([[0, 1, 2], [0, 2, 3]])


@pytest.fixture
def seed():
    return SEED


def jittered_square(n, seed, amount=0.15):
    """square(n, "right") with interior vertices moved randomly by up to ``amount * h``."""
    base = Mesh.square(n, diagonal="right")
    rng = np.random.default_rng(seed)
    v = base.vertices.copy()
    inner = base.interior_vertices
    v[inner] += rng.uniform(-amount, amount, (inner.size, 2)) * (2.0 / n)
    return Mesh(v, base.triangles)


def tri_coords(mesh):
    """Sorted array of each triangle's vertex coordinates (sorted within each triangle)."""
    p = np.round(mesh.vertices[mesh.triangles], 12)  # (M, 3, 2)
    keys = [tuple(sorted(map(tuple, tri))) for tri in p.tolist()]
    return sorted(keys)


def sorted_rows(a):
    a = np.asarray(a)
    return a[np.lexsort(a.T[::-1])]


def check_topology(mesh):
    """Full consistency check of the derived topology against a naive construction."""
    t = mesh.triangles
    n, m = mesh.n_vertices, mesh.n_triangles
    edges = mesh.edges
    te = mesh.triangle_edges
    et = mesh.edge_triangles
    # edges: oriented lo < hi, unique
    assert edges.shape == (mesh.n_edges, 2)
    assert (edges[:, 0] < edges[:, 1]).all()
    assert len({tuple(e) for e in edges.tolist()}) == mesh.n_edges
    # triangle_edges: local edge i joins local vertices (i+1)%3 and (i+2)%3
    assert te.shape == (m, 3)
    for i in range(3):
        a, b = t[:, (i + 1) % 3], t[:, (i + 2) % 3]
        assert_array_equal(edges[te[:, i]], np.stack([np.minimum(a, b), np.maximum(a, b)], 1))
    # every edge is used by the triangles
    assert_array_equal(np.unique(te), np.arange(mesh.n_edges))
    # edge_triangles: each listed triangle has the edge; the number of listed
    # triangles equals the number of (triangle, local edge) slots using the edge
    uses = np.bincount(te.ravel(), minlength=mesh.n_edges)
    assert_array_equal((et >= 0).sum(axis=1), uses)
    assert (et[:, 0] >= 0).all()
    for e in range(mesh.n_edges):
        for k in et[e]:
            if k >= 0:
                assert e in te[k]
    # boundary edges are the edges with one triangle
    assert_array_equal(np.sort(mesh.boundary_edges), np.flatnonzero(uses == 1))
    bmask = np.zeros(n, dtype=bool)
    bmask[edges[mesh.boundary_edges].ravel()] = True
    assert_array_equal(mesh.boundary_vertex_mask, bmask)
    # patches (CSR): every (vertex, triangle) incidence exactly once
    ptr = mesh.patch_ptr
    assert ptr.shape == (n + 1,)
    assert ptr[0] == 0
    assert ptr[-1] == 3 * m
    assert (np.diff(ptr) >= 1).all()
    owner = np.repeat(np.arange(n), np.diff(ptr))
    got = sorted_rows(np.stack([owner, mesh.patch_triangles], 1))
    want = sorted_rows(np.stack([t.ravel(), np.repeat(np.arange(m), 3)], 1))
    assert_array_equal(got, want)
    assert_array_equal(t[mesh.patch_triangles, mesh.patch_local], owner)
    # all triangles counter-clockwise
    p = mesh.vertices[t]
    signed = 0.5 * (
        (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
        - (p[:, 2, 0] - p[:, 0, 0]) * (p[:, 1, 1] - p[:, 0, 1])
    )
    assert (signed > 0).all()
    assert_allclose(mesh.areas, signed, rtol=1e-14, atol=0)


# ---------------------------------------------------------------------------- generators


@pytest.mark.parametrize("diagonal", DIAGONALS)
@pytest.mark.parametrize("n", [1, 2, 3, 4, 7])
def test_square_counts_and_topology(n, diagonal):
    mesh = Mesh.square(n, diagonal=diagonal)
    assert mesh.n_vertices == (n + 1) ** 2
    assert mesh.n_triangles == 2 * n**2
    assert mesh.n_edges == 3 * n**2 + 2 * n
    assert mesh.vertices.dtype == np.float64
    assert mesh.triangles.dtype == np.int64
    assert_allclose(mesh.areas.sum(), 4.0, rtol=1e-14)
    assert_allclose(mesh.areas, 2.0 / n**2, rtol=1e-12)
    assert mesh.boundary_vertices.size == 4 * n
    assert mesh.boundary_edges.size == 4 * n
    assert mesh.interior_vertices.size == (n - 1) ** 2
    on_bnd = np.isclose(np.abs(mesh.vertices), 1.0, rtol=0, atol=1e-14).any(axis=1)
    assert_array_equal(mesh.boundary_vertex_mask, on_bnd)
    assert mesh.bounding_box == (-1.0, 1.0, -1.0, 1.0)
    assert_allclose(mesh.h, 2.0 * np.sqrt(2.0) / n, rtol=1e-14)
    check_topology(mesh)


def test_diagonal_choice_changes_triangles():
    right = Mesh.square(2, diagonal="right")
    left = Mesh.square(2, diagonal="left")

    # the cell [-1, 0]^2: "right" joins (-1,-1)-(0,0), "left" joins (0,-1)-(-1,0)
    def has_edge(mesh, p, q):
        i = int(np.flatnonzero((mesh.vertices == p).all(1))[0])
        j = int(np.flatnonzero((mesh.vertices == q).all(1))[0])
        return [min(i, j), max(i, j)] in mesh.edges.tolist()

    assert has_edge(right, (-1, -1), (0, 0))
    assert not has_edge(right, (0, -1), (-1, 0))
    assert has_edge(left, (0, -1), (-1, 0))
    assert not has_edge(left, (-1, -1), (0, 0))


def is_invariant(mesh, sym):
    index = {tuple(p): i for i, p in enumerate(mesh.vertices.tolist())}
    x, y = mesh.vertices[:, 0], mesh.vertices[:, 1]
    sx, sy = sym(x, y)
    try:
        perm = np.array([index[(a, b)] for a, b in zip(sx.tolist(), sy.tolist(), strict=True)])
    except KeyError:
        return False
    original = {tuple(sorted(tri)) for tri in mesh.triangles.tolist()}
    mapped = {tuple(sorted(tri)) for tri in perm[mesh.triangles].tolist()}
    return mapped == original


@pytest.mark.parametrize("n", [2, 4, 6, 10])
@pytest.mark.parametrize("k", range(8))
def test_symmetric_square_invariant_under_dihedral_group(n, k):
    mesh = Mesh.square(n)  # default diagonal="symmetric"
    assert is_invariant(mesh, SYMMETRIES[k])


def test_right_diagonal_is_not_symmetric():
    # the invariance check discriminates: the "right" mesh is not mirror-symmetric
    mesh = Mesh.square(4, diagonal="right")
    assert is_invariant(mesh, SYMMETRIES[3])  # point symmetry holds
    assert not is_invariant(mesh, SYMMETRIES[1])
    assert not is_invariant(mesh, SYMMETRIES[6])


@pytest.mark.parametrize("diagonal", DIAGONALS)
def test_rectangle_bounds(diagonal):
    bounds = (1.0, 4.0, -2.0, 0.5)
    mesh = Mesh.rectangle(3, 5, bounds=bounds, diagonal=diagonal)
    assert mesh.n_vertices == 4 * 6
    assert mesh.n_triangles == 2 * 15
    assert mesh.n_edges == 3 * 15 + 3 + 5
    assert mesh.bounding_box == pytest.approx(bounds, rel=0, abs=1e-14)
    assert_allclose(mesh.areas.sum(), 3.0 * 2.5, rtol=1e-14)
    assert_allclose(mesh.areas, 1.0 * 0.5 / 2, rtol=1e-12)
    assert_allclose(np.unique(np.round(mesh.vertices[:, 0], 12)), [1, 2, 3, 4], atol=1e-12)
    assert_allclose(
        np.unique(np.round(mesh.vertices[:, 1], 12)), [-2, -1.5, -1, -0.5, 0, 0.5], atol=1e-12
    )
    assert mesh.boundary_vertices.size == 2 * (3 + 5)
    check_topology(mesh)


def _rectangle_reference(nx, ny, bounds, diagonal):
    """Cell by cell in plain Python: vertices row by row, two triangles per cell."""
    x0, x1, y0, y1 = bounds
    xs, ys = np.linspace(x0, x1, nx + 1), np.linspace(y0, y1, ny + 1)
    if diagonal == "symmetric":
        xs = 0.5 * (xs - xs[::-1]) + 0.5 * (x0 + x1)
        ys = 0.5 * (ys - ys[::-1]) + 0.5 * (y0 + y1)
    vertices = [(x, y) for y in ys for x in xs]
    tris = []
    for j in range(ny):
        for i in range(nx):
            a = j * (nx + 1) + i
            b, c, d = a + 1, a + nx + 2, a + nx + 1
            if diagonal == "right":
                slash = True
            elif diagonal == "left":
                slash = False
            else:  # towards the centre: lower-left / upper-right quadrants use a-c
                slash = (2 * i + 1 - nx) * (2 * j + 1 - ny) >= 0
            tris += [(a, b, c), (a, c, d)] if slash else [(a, b, d), (b, c, d)]
    return np.array(vertices), np.array(tris)


@pytest.mark.parametrize("diagonal", DIAGONALS)
@pytest.mark.parametrize("nx, ny", [(1, 1), (2, 3), (5, 4), (6, 6), (7, 2)])
def test_rectangle_matches_cell_by_cell_reference(nx, ny, diagonal):
    bounds = (-3.0, 2.0, 0.5, 0.75)
    mesh = Mesh.rectangle(nx, ny, bounds=bounds, diagonal=diagonal)
    v, t = _rectangle_reference(nx, ny, bounds, diagonal)
    np.testing.assert_array_equal(mesh.vertices, v)
    np.testing.assert_array_equal(mesh.triangles, t)
    assert mesh.triangles.dtype == np.int64


def test_rectangle_ny_defaults_to_nx():
    mesh = Mesh.rectangle(3)
    assert mesh.n_vertices == 16
    assert mesh.bounding_box == (0.0, 1.0, 0.0, 1.0)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"nx": 0}, "nx"),
        ({"nx": 2, "ny": -1}, "ny"),
        ({"nx": 2.5}, "nx"),
        ({"nx": True}, "nx"),
        ({"nx": 2, "bounds": (1.0, 0.0, 0.0, 1.0)}, "bounds"),
        ({"nx": 2, "bounds": (0.0, np.inf, 0.0, 1.0)}, "bounds"),
        ({"nx": 2, "diagonal": "up"}, "diagonal"),
    ],
)
def test_rectangle_bad_parameters(kwargs, match):
    with pytest.raises(ParameterError, match=match):
        Mesh.rectangle(**kwargs)


def test_square_bad_n_names_n():
    with pytest.raises(ParameterError, match=r"^n must"):
        Mesh.square(0)


@pytest.mark.parametrize("n", [2, 4, 8])
def test_lshape(n):
    mesh = Mesh.lshape(n)
    assert_allclose(mesh.areas.sum(), 3.0, rtol=1e-14)
    assert mesh.n_triangles == 3 * n**2 // 2
    assert mesh.n_vertices == (n + 1) ** 2 - (n // 2) ** 2
    check_topology(mesh)
    # reentrant corner at the origin, on the boundary, with interior angle 3 pi / 2
    origin = np.flatnonzero((mesh.vertices == 0.0).all(axis=1))
    assert origin.size == 1
    o = int(origin[0])
    assert mesh.boundary_vertex_mask[o]
    ptr = mesh.patch_ptr
    angle = 0.0
    for k in range(ptr[o], ptr[o + 1]):
        tri = mesh.triangles[mesh.patch_triangles[k]]
        i = mesh.patch_local[k]
        p = mesh.vertices[tri[i]]
        a = mesh.vertices[tri[(i + 1) % 3]] - p
        b = mesh.vertices[tri[(i + 2) % 3]] - p
        angle += np.arccos(a @ b / np.linalg.norm(a) / np.linalg.norm(b))
    assert_allclose(angle, 1.5 * np.pi, rtol=1e-12)
    # nothing in the removed quadrant
    cen = mesh.vertices[mesh.triangles].mean(axis=1)
    assert not ((cen[:, 0] > 0) & (cen[:, 1] < 0)).any()


def test_lshape_odd_n_refused():
    with pytest.raises(ParameterError, match="even"):
        Mesh.lshape(3)


# ---------------------------------------------------------------------------- refinement


@pytest.mark.parametrize(
    "make",
    [
        lambda: Mesh.square(3, diagonal="right"),
        lambda: Mesh.square(4),
        lambda: Mesh.lshape(4),
        lambda: jittered_square(5, SEED),
    ],
    ids=["square-right", "square-symmetric", "lshape", "jittered"],
)
def test_refine(make):
    coarse = make()
    fine = coarse.refine()
    n, m, e = coarse.n_vertices, coarse.n_triangles, coarse.n_edges
    assert fine.n_triangles == 4 * m
    assert fine.n_vertices == n + e
    assert fine.parent is coarse
    assert_allclose(fine.areas.sum(), coarse.areas.sum(), rtol=1e-13)
    assert_array_equal(fine.vertices[:n], coarse.vertices)
    mid = 0.5 * (coarse.vertices[coarse.edges[:, 0]] + coarse.vertices[coarse.edges[:, 1]])
    assert_allclose(fine.vertices[n:], mid, rtol=0, atol=1e-15)
    # each child has a quarter of some parent's area: the multiset of areas matches
    assert_allclose(np.sort(fine.areas), np.sort(np.repeat(coarse.areas / 4, 4)), rtol=1e-12)
    # euler: refined edges = 2 E + 3 M
    assert fine.n_edges == 2 * e + 3 * m
    # full validation of the refined arrays: no warning (CW) and no error
    again = Mesh(fine.vertices, fine.triangles, orientation="raise", validate=True)
    assert_array_equal(again.triangles, fine.triangles)
    check_topology(fine)


@pytest.mark.parametrize("n", [1, 2, 5])
def test_refine_square_equals_square_2n(n):
    fine = Mesh.square(n, diagonal="right").refine()
    direct = Mesh.square(2 * n, diagonal="right")
    c1 = sorted_rows(np.round(fine.vertices[fine.triangles].mean(axis=1), 12))
    c2 = sorted_rows(np.round(direct.vertices[direct.triangles].mean(axis=1), 12))
    assert_allclose(c1, c2, rtol=0, atol=1e-12)
    assert tri_coords(fine) == tri_coords(direct)


def test_refine_twice_keeps_chain():
    mesh = Mesh.lshape(2)
    fine = mesh.refine().refine()
    assert fine.parent.parent is mesh
    assert fine.n_triangles == 16 * mesh.n_triangles
    assert_allclose(fine.areas.sum(), 3.0, rtol=1e-13)


# ---------------------------------------------------------------------------- geometry


@pytest.mark.parametrize(
    ("make", "area"),
    [
        (lambda: Mesh.square(5), 4.0),
        (lambda: Mesh.lshape(6), 3.0),
        (lambda: Mesh.rectangle(3, 2, bounds=(0, 3, 0, 0.5)), 1.5),
        (lambda: jittered_square(6, SEED), 4.0),
    ],
    ids=["square", "lshape", "rectangle", "jittered"],
)
def test_lumped_mass(make, area):
    mesh = make()
    b = mesh.lumped_mass
    assert b.shape == (mesh.n_vertices,)
    assert (b > 0).all()
    assert_allclose(b.sum(), area, rtol=1e-13)
    naive = np.zeros(mesh.n_vertices)
    for tri, a in zip(mesh.triangles, mesh.areas, strict=True):
        naive[tri] += a / 3.0
    assert_allclose(b, naive, rtol=1e-13, atol=0)


@pytest.mark.parametrize(
    "make",
    [lambda: Mesh.square(3), lambda: Mesh.lshape(4), lambda: jittered_square(6, SEED)],
    ids=["square", "lshape", "jittered"],
)
def test_gradients_are_barycentric(make):
    mesh = make()
    g = mesh.gradients
    assert g.shape == (mesh.n_triangles, 3, 2)
    p = mesh.vertices[mesh.triangles]  # (M, 3, 2)
    scale = 1.0 / mesh.diameters.min()
    assert_allclose(g.sum(axis=1), 0.0, rtol=0, atol=1e-13 * scale)
    # phi_i(x_j) - phi_i(x_0) = grad phi_i . (x_j - x_0) = delta_ij - delta_i0
    d = np.einsum("kid,kjd->kij", g, p - p[:, :1, :])
    want = np.eye(3)[None] - np.eye(3)[:, :1][None]
    assert_allclose(d, np.broadcast_to(want, d.shape), rtol=0, atol=1e-12)
    # naive reference: coefficients of phi_i from the inverse of [1, x_j, y_j]
    mat = np.concatenate([np.ones((mesh.n_triangles, 3, 1)), p], axis=2)
    coef = np.linalg.inv(mat)  # column i holds (c, a, b) with phi_i = c + a x + b y
    assert_allclose(g, np.transpose(coef[:, 1:, :], (0, 2, 1)), rtol=1e-10, atol=1e-12 * scale)


# ---------------------------------------------------------------------------- I/O


@pytest.mark.parametrize(
    ("name", "file_format"),
    [("m.msh", None), ("m22.msh", "gmsh22"), ("m.vtu", None), ("m.xdmf", None)],
)
def test_write_read_round_trip(tmp_path, seed, name, file_format):
    mesh = jittered_square(4, seed)
    path = tmp_path / name
    mesh.write(path, file_format=file_format)
    back = Mesh.read(path)
    assert back.n_vertices == mesh.n_vertices
    assert back.n_triangles == mesh.n_triangles
    assert_allclose(back.vertices, mesh.vertices, rtol=0, atol=1e-14)
    assert_array_equal(back.triangles, mesh.triangles)
    check_topology(back)


def _gmsh_mesh(path, shape):
    gmsh = pytest.importorskip("gmsh")
    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add(shape)
        if shape == "square":
            gmsh.model.occ.addRectangle(0.0, 0.0, 0.0, 1.0, 1.0)
        else:  # regular 16-gon of radius 1
            angles = 2 * np.pi * np.arange(16) / 16
            pts = [gmsh.model.occ.addPoint(np.cos(a), np.sin(a), 0.0) for a in angles]
            lines = [gmsh.model.occ.addLine(pts[i], pts[(i + 1) % 16]) for i in range(16)]
            loop = gmsh.model.occ.addCurveLoop(lines)
            gmsh.model.occ.addPlaneSurface([loop])
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMin", 0.2)
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.2)
        gmsh.model.mesh.generate(2)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()


@pytest.mark.parametrize(
    ("shape", "area"),
    [("square", 1.0), ("polygon", 0.5 * 16 * np.sin(2 * np.pi / 16))],
)
def test_read_gmsh_api_mesh(tmp_path, shape, area):
    path = tmp_path / f"{shape}.msh"
    _gmsh_mesh(path, shape)
    raw = meshio.read(path)
    mesh = Mesh.read(path)
    # an unstructured mesh: at least some interior vertices, area right, valid topology
    assert mesh.n_triangles > 20
    assert mesh.interior_vertices.size > 0
    assert mesh.n_vertices <= raw.points.shape[0]
    assert_allclose(mesh.areas.sum(), area, rtol=1e-12)
    assert mesh.h < 0.2 * 1.5
    check_topology(mesh)
    # boundary vertices lie on the boundary of the shape
    bv = mesh.vertices[mesh.boundary_vertices]
    if shape == "square":
        on = np.isclose(bv, 0.0, atol=1e-12) | np.isclose(bv, 1.0, atol=1e-12)
        assert on.any(axis=1).all()
    else:
        r = np.linalg.norm(bv, axis=1)
        assert (r <= 1.0 + 1e-12).all()
        assert (r >= np.cos(np.pi / 16) - 1e-12).all()


def test_read_3d_points_with_zero_z(tmp_path):
    mesh = Mesh.square(2)
    pts = np.column_stack([mesh.vertices, np.zeros(mesh.n_vertices)])
    path = tmp_path / "z0.vtu"
    meshio.write_points_cells(path, pts, [("triangle", mesh.triangles)])
    back = Mesh.read(path)
    assert back.vertices.shape == (mesh.n_vertices, 2)
    assert_array_equal(back.vertices, mesh.vertices)
    assert_array_equal(back.triangles, mesh.triangles)


def test_constructor_accepts_3d_points_with_zero_z():
    mesh = Mesh.square(2)
    pts = np.column_stack([mesh.vertices, np.zeros(mesh.n_vertices)])
    back = Mesh(pts, mesh.triangles)
    assert_array_equal(back.vertices, mesh.vertices)


def test_read_nonplanar_refused(tmp_path):
    mesh = Mesh.square(2)
    pts = np.column_stack([mesh.vertices, np.zeros(mesh.n_vertices)])
    pts[4, 2] = 0.25
    path = tmp_path / "z.vtu"
    meshio.write_points_cells(path, pts, [("triangle", mesh.triangles)])
    with pytest.raises(MeshError, match="planar"):
        Mesh.read(path)
    with pytest.raises(MeshError, match="planar"):
        Mesh(pts, mesh.triangles)


@pytest.mark.parametrize(
    ("cells", "name", "file_format"),
    [
        ([("quad", np.array([[0, 1, 2, 3]]))], "q.vtu", None),
        ([("line", np.array([[0, 1], [1, 2], [2, 3], [3, 0]]))], "l.msh", "gmsh22"),
        ([("quad", np.array([[0, 1, 2, 3]]))], "q.msh", "gmsh22"),
    ],
)
def test_read_without_triangles_refused(tmp_path, cells, name, file_format):
    pts = np.column_stack([SQ_V, np.zeros(4)])
    path = tmp_path / name
    meshio.write_points_cells(path, pts, cells, file_format=file_format)
    with pytest.raises(MeshError, match="triangle"):
        Mesh.read(path)


def test_read_drops_unused_vertices(tmp_path):
    mesh = jittered_square(3, SEED)
    # unused points before, between and after the used ones
    extra = np.array([[7.0, 7.0], [8.0, -3.0], [-9.0, 0.5]])
    pts = np.vstack([extra[:1], mesh.vertices[:5], extra[1:2], mesh.vertices[5:], extra[2:]])
    old_to_new = np.concatenate([np.arange(1, 6), np.arange(7, mesh.n_vertices + 2)])
    tris = old_to_new[mesh.triangles]
    path = tmp_path / "unused.vtu"
    meshio.write_points_cells(
        path, np.column_stack([pts, np.zeros(len(pts))]), [("triangle", tris)]
    )
    back = Mesh.read(path)
    assert back.n_vertices == mesh.n_vertices
    assert_array_equal(back.vertices, mesh.vertices)
    assert_array_equal(back.triangles, mesh.triangles)


def test_read_merges_triangle_blocks(tmp_path):
    mesh = Mesh.square(2)
    pts = np.column_stack([mesh.vertices, np.zeros(mesh.n_vertices)])
    cells = [
        ("triangle", mesh.triangles[:3]),
        ("line", np.array([[0, 1]])),
        ("triangle", mesh.triangles[3:]),
    ]
    path = tmp_path / "blocks.vtu"
    meshio.write_points_cells(path, pts, cells)
    back = Mesh.read(path)
    assert_array_equal(back.triangles, mesh.triangles)


def test_read_missing_file(tmp_path):
    with pytest.raises(MeshError, match="not found"):
        Mesh.read(tmp_path / "missing.msh")


def test_read_passes_keywords(tmp_path):
    path = tmp_path / "cw.vtu"
    meshio.write_points_cells(
        path, np.column_stack([SQ_V, np.zeros(4)]), [("triangle", SQ_T[:, ::-1])]
    )
    with pytest.raises(MeshError, match="clockwise"):
        Mesh.read(path, orientation="raise")
    with pytest.warns(MeshWarning, match="clockwise"):
        back = Mesh.read(path)
    assert (back.areas > 0).all()


def test_read_unparsable_file_raises_mesh_error(tmp_path):
    path = tmp_path / "truncated.msh"
    path.write_text("$MeshFormat\nnonsense\n")
    with pytest.raises(MeshError, match="truncated.msh"):
        Mesh.read(path)


def test_read_corrupt_file_raises_mesh_error(tmp_path):
    path = tmp_path / "corrupt.msh"
    path.write_text("this is not a gmsh file\n")
    try:
        with pytest.raises(MeshError, match="corrupt.msh"):
            Mesh.read(path)
    except SystemExit as exc:
        pytest.fail(f"Mesh.read raised SystemExit({exc.code})")


@pytest.mark.parametrize("bad", [7, -1])
def test_read_out_of_range_index_raises_mesh_error(tmp_path, bad):
    path = tmp_path / "bad_index.vtu"
    tris = np.array([[0, 1, 2], [0, 2, bad]])
    meshio.write_points_cells(path, np.column_stack([SQ_V, np.zeros(4)]), [("triangle", tris)])
    with pytest.raises(MeshError, match="index"):
        Mesh.read(path)


# ---------------------------------------------------------------------------- validation

BOWTIE_V = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])


@pytest.mark.parametrize(
    ("vertices", "triangles", "exc", "match"),
    [
        pytest.param(np.zeros((4, 4)), SQ_T, MeshError, "vertices.*shape", id="vertices-N4"),
        pytest.param(np.zeros((4, 1)), SQ_T, MeshError, "vertices.*shape", id="vertices-N1"),
        pytest.param(np.zeros(8), SQ_T, MeshError, "vertices.*shape", id="vertices-1d"),
        pytest.param(SQ_V, [[0, 1, 2, 3]], MeshError, "triangles.*shape", id="triangles-M4"),
        pytest.param(SQ_V, [0, 1, 2], MeshError, "triangles.*shape", id="triangles-1d"),
        pytest.param(SQ_V, SQ_T.astype(float), InputTypeError, "integer", id="float-triangles"),
        pytest.param(SQ_V, SQ_T.astype(bool), InputTypeError, "integer", id="bool-triangles"),
        pytest.param(SQ_V, SQ_T.astype(str), InputTypeError, "integer", id="str-triangles"),
        pytest.param(SQ_V.astype(str), SQ_T, InputTypeError, "vertices", id="str-vertices"),
        pytest.param(None, SQ_T, InputTypeError, "vertices", id="none-vertices"),
        pytest.param([[0, 0], [1]], SQ_T, InputTypeError, "vertices", id="ragged-vertices"),
        pytest.param(np.where(SQ_V == 1.0, np.nan, SQ_V), SQ_T, MeshError, "NaN", id="nan-vertex"),
        pytest.param(np.where(SQ_V == 1.0, np.inf, SQ_V), SQ_T, MeshError, "inf", id="inf-vertex"),
        pytest.param(SQ_V, [[0, 1, 2], [0, 2, -1]], MeshError, "index -1", id="index-negative"),
        pytest.param(SQ_V, [[0, 1, 2], [0, 2, 4]], MeshError, "index 4", id="index-too-large"),
        pytest.param(
            SQ_V, [[0, 1, 2], [0, 2, 2]], MeshError, "repeat a vertex", id="repeated-vertex"
        ),
        pytest.param([[0, 0], [1, 0], [2, 0]], [[0, 1, 2]], MeshError, "zero area", id="collinear"),
        pytest.param(
            [[0, 0], [1, 0], [0.5, 1e-16]],
            [[0, 1, 2]],
            MeshError,
            "zero area",
            id="nearly-collinear",
        ),
        pytest.param(
            np.vstack([SQ_V, [[0.0, 0.0]]]),
            [[0, 1, 2], [4, 2, 3]],
            MeshError,
            "duplicate",
            id="duplicate-coordinates",
        ),
        pytest.param(
            np.vstack([SQ_V, [[5.0, 5.0]]]), SQ_T, MeshError, "unused", id="unused-vertex"
        ),
        pytest.param(
            [[0, 0], [1, 0], [0.5, 1], [0.5, -1], [0.6, 2]],
            [[0, 1, 2], [1, 0, 3], [0, 1, 4]],
            MeshError,
            "non-manifold edge",
            id="non-manifold-edge",
        ),
        pytest.param(
            [[0, 0], [1, 0], [0.5, 1], [0.3, 0.5]],
            [[0, 1, 2], [0, 1, 3]],
            MeshError,
            "folded",
            id="folded",
        ),
        pytest.param(
            SQ_V[:3], [[0, 1, 2], [0, 1, 2]], MeshError, "folded|duplicate", id="duplicate-triangle"
        ),
        pytest.param(
            BOWTIE_V, [[0, 1, 2], [0, 3, 4]], MeshError, "non-manifold vertex 0", id="bow-tie"
        ),
        pytest.param(SQ_V, np.empty((0, 3), dtype=np.int64), MeshError, "empty", id="no-triangles"),
    ],
)
def test_invalid_mesh_refused(vertices, triangles, exc, match):
    with pytest.raises(exc, match=match) as info:
        Mesh(vertices, triangles)
    assert isinstance(info.value, FastmemError)
    assert isinstance(info.value, ValueError if exc is MeshError else TypeError)


def test_folded_after_orientation_fix():
    # the second triangle is clockwise; re-oriented it lies on the same side of edge 0-1
    v = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 1.0], [0.4, 0.5]])
    with pytest.warns(MeshWarning, match="clockwise"), pytest.raises(MeshError, match="folded"):
        Mesh(v, [[0, 1, 2], [1, 0, 3]])


def test_bad_orientation_keyword():
    with pytest.raises(ParameterError, match="orientation"):
        Mesh(SQ_V, SQ_T, orientation="flip")


def test_clockwise_triangles_reoriented_with_warning():
    ref = Mesh.square(3)
    t = ref.triangles.copy()
    flip = np.arange(ref.n_triangles) % 3 == 0
    t[flip] = t[flip][:, [0, 2, 1]]
    with pytest.warns(MeshWarning, match=f"{int(flip.sum())} of {ref.n_triangles}"):
        mesh = Mesh(ref.vertices, t)
    assert_array_equal(mesh.triangles, ref.triangles)
    assert (mesh.areas > 0).all()
    check_topology(mesh)
    with pytest.raises(MeshError, match="clockwise"):
        Mesh(ref.vertices, t, orientation="raise")


def test_fully_clockwise_mesh_reoriented():
    ref = Mesh.lshape(4)
    with pytest.warns(MeshWarning, match="clockwise"):
        mesh = Mesh(ref.vertices, ref.triangles[:, ::-1])
    assert_allclose(mesh.areas, ref.areas, rtol=1e-14)
    assert_allclose(mesh.areas.sum(), 3.0, rtol=1e-14)
    check_topology(mesh)


def test_mesh_arrays_read_only():
    mesh = Mesh(SQ_V.astype(np.float32), SQ_T.astype(np.int32))  # converted copies
    with pytest.raises(ValueError, match="read-only"):
        mesh.vertices[0, 0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        mesh.triangles[0, 0] = 1


def test_input_arrays_not_aliased():
    base = SQ_V.ravel().copy()
    v = base.reshape(4, 2)  # a C-contiguous float64 view of base
    t = SQ_T.copy()
    mesh = Mesh(v, t)
    assert v.flags.writeable
    assert t.flags.writeable
    base[4] = 3.0  # vertex 2 moves in the caller's data
    assert_array_equal(mesh.vertices[2], [1.0, 1.0])
    assert_allclose(mesh.areas.sum(), 1.0, rtol=1e-14)


@pytest.mark.parametrize(
    "dtype", [np.int8, np.int16, np.int32, np.uint16, np.uint32, np.int64, np.uint8, np.uint64]
)
def test_integer_dtypes_accepted(dtype):
    ref = Mesh.square(4)
    mesh = Mesh(ref.vertices, ref.triangles.astype(dtype))
    assert mesh.triangles.dtype == np.int64
    assert mesh.triangles.flags.c_contiguous
    assert_array_equal(mesh.triangles, ref.triangles)
    assert_array_equal(mesh.edges, ref.edges)
    assert_array_equal(mesh.triangle_edges, ref.triangle_edges)
    assert_array_equal(mesh.patch_triangles, ref.patch_triangles)


@pytest.mark.parametrize("layout", ["fortran", "strided", "reversed-view", "list"])
def test_memory_layouts_accepted(layout):
    ref = Mesh.square(4)
    v, t = ref.vertices.copy(), ref.triangles.copy()
    if layout == "fortran":
        v, t = np.asfortranarray(v), np.asfortranarray(t)
    elif layout == "strided":
        vv = np.zeros((v.shape[0], 4))
        vv[:, ::2] = v
        tt = np.zeros((t.shape[0] * 2, 3), dtype=np.int32)
        tt[::2] = t
        v, t = vv[:, ::2], tt[::2]
        assert not v.flags.c_contiguous
        assert not t.flags.c_contiguous
    elif layout == "reversed-view":
        v = v[::-1][::-1]
        t = t[::-1][::-1]
    else:
        v, t = v.tolist(), t.tolist()
    mesh = Mesh(v, t)
    assert mesh.vertices.flags.c_contiguous
    assert mesh.triangles.flags.c_contiguous
    assert_array_equal(mesh.vertices, ref.vertices)
    assert_array_equal(mesh.triangles, ref.triangles)
    assert_array_equal(mesh.edges, ref.edges)
    assert_allclose(mesh.lumped_mass, ref.lumped_mass, rtol=0, atol=0)


@pytest.mark.parametrize("dtype", [np.float32, np.float16, np.int32, np.int64])
def test_vertex_dtypes_accepted(dtype):
    # square(4) coordinates are multiples of 0.5: exact in every dtype above
    ref = Mesh.square(4)
    mesh = (
        Mesh(ref.vertices.astype(dtype), ref.triangles)
        if dtype in (np.float32, np.float16)
        else Mesh((2 * ref.vertices).astype(dtype), ref.triangles)
    )
    assert mesh.vertices.dtype == np.float64
    scale = 1.0 if dtype in (np.float32, np.float16) else 2.0
    assert_array_equal(mesh.vertices, scale * ref.vertices)
    assert_array_equal(mesh.triangles, ref.triangles)
    assert_allclose(mesh.areas.sum(), 4.0 * scale**2, rtol=1e-14)


def test_float32_vertices_generic():
    mesh64 = jittered_square(4, SEED)
    v32 = mesh64.vertices.astype(np.float32)
    mesh = Mesh(v32, mesh64.triangles)
    assert mesh.vertices.dtype == np.float64
    assert_array_equal(mesh.vertices, v32.astype(np.float64))
    assert_allclose(mesh.areas, mesh64.areas, rtol=1e-5)


def test_validate_false_still_runs_cheap_checks():
    with pytest.raises(MeshError, match="zero area"):
        Mesh([[0, 0], [1, 0], [2, 0]], [[0, 1, 2]], validate=False)
    with pytest.raises(MeshError, match="unused"):
        Mesh(np.vstack([SQ_V, [[5.0, 5.0]]]), SQ_T, validate=False)
    # the duplicate-vertex check is the full validation's job
    v = np.vstack([SQ_V, [[0.0, 0.0]]])
    Mesh(v, [[0, 1, 2], [4, 2, 3]], validate=False)
    with pytest.raises(MeshError, match="duplicate"):
        Mesh(v, [[0, 1, 2], [4, 2, 3]], validate=True)


def test_area_and_diameter_kernel_matches_numpy():
    """The one-pass Numba kernel used by Mesh validation vs a plain NumPy reference."""
    from fastmem.kernels.assembly import area2_and_diameter2

    rng = np.random.default_rng(7)
    base = Mesh.square(12)
    v = base.vertices + rng.uniform(-0.02, 0.02, base.vertices.shape)
    t = np.ascontiguousarray(base.triangles[:, [0, 2, 1]])  # clockwise: negative areas
    area2, h2 = area2_and_diameter2(v, t)
    p = v[t]
    ref_area2 = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (
        p[:, 2, 0] - p[:, 0, 0]
    ) * (p[:, 1, 1] - p[:, 0, 1])
    edges = p[:, [1, 2, 0]] - p[:, [0, 1, 2]]
    ref_h2 = (edges**2).sum(axis=2).max(axis=1)
    assert (area2 < 0).all()
    np.testing.assert_allclose(area2, ref_area2, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(h2, ref_h2, rtol=1e-12)
