"""Hard meshes for the stress suite (all built here, independent of tests/meshes.py).

Every builder returns a valid :class:`fastmem.Mesh`.  Meshes of the square
``(-1, 1)^2`` keep their boundary vertices exactly on the boundary, so that the
manufactured family (docs/method.md §7) applies to them.
"""

from __future__ import annotations

import contextlib
import io
import os
import tempfile
import warnings

import numpy as np

import fastmem as fm

#: Seed of every random mesh of the suite (reproducible reports).
SEED = 20261121


def square(n):
    """The structured square ``(-1, 1)^2``, symmetric diagonals (an M-matrix mesh)."""
    return fm.Mesh.square(n)


def _grid(xs, ys):
    """Vertices of the tensor grid ``xs x ys`` and the corner indices of every cell."""
    nx, ny = xs.size - 1, ys.size - 1
    X, Y = np.meshgrid(xs, ys)
    vertices = np.stack([X.ravel(), Y.ravel()], axis=1)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny))
    a = (j * (nx + 1) + i).ravel()
    return vertices, a, a + 1, a + nx + 2, a + nx + 1, (i.ravel(), j.ravel())


def tensor(xs, ys):
    """Two triangles per cell of the tensor grid ``xs x ys`` (lower-left to upper-right)."""
    vertices, a, b, c, d, _ = _grid(np.asarray(xs, float), np.asarray(ys, float))
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return fm.Mesh(vertices, tris)


def graded(n, p):
    """Square ``(-1, 1)^2`` with both coordinates graded towards -1: ``t -> -1 + 2 s^p``.

    ``s = (t + 1)/2`` uniform.  The cells near the corner ``(-1, -1)`` are
    ``(2/n^p)``-small, those near the sides ``x = -1`` and ``y = -1`` have
    aspect ratios up to about ``p n^(p-1)`` (the "x -> x^p" grading).
    """
    s = np.linspace(0.0, 1.0, n + 1)
    t = -1.0 + 2.0 * s**p
    return tensor(t, t)


def boundary_layer(n, aspect):
    """Square ``(-1, 1)^2``, uniform in x, y graded symmetrically towards ``y = +-1``.

    ``y = sign(t) (1 - (1 - |t|)^p)`` for a uniform ``t`` in [-1, 1]: the
    boundary cells have height ``(2/n)^p`` and width ``2/n``, an aspect ratio
    ``(n/2)^(p-1)``; ``p`` is chosen to make it ``aspect``.
    """
    p = 1.0 + np.log(aspect) / np.log(n / 2.0)
    t = np.linspace(-1.0, 1.0, n + 1)
    y = np.sign(t) * (1.0 - (1.0 - np.abs(t)) ** p)
    y[0], y[-1] = -1.0, 1.0
    x = np.linspace(-1.0, 1.0, n + 1)
    return tensor(x, y)


def stretched_rectangle(n, length=1000.0):
    """Rectangle ``[0, length] x [0, 1]`` with ``n x n`` cells: aspect ratio ``length``."""
    return fm.Mesh.rectangle(n, n, (0.0, length, 0.0, 1.0), diagonal="right")


def criss_cross(nx, ny):
    """Square ``(-1, 1)^2``, every cell split into four triangles by its centre.

    With ``nx != ny`` the cells are anisotropic and the angles at the centres
    opposite the short cell sides are obtuse, from both sides: the stiffness
    matrix has positive off-diagonal entries (not an M-matrix).
    """
    xs = np.linspace(-1.0, 1.0, nx + 1)
    ys = np.linspace(-1.0, 1.0, ny + 1)
    vertices, a, b, c, d, (i, j) = _grid(xs, ys)
    centres = np.stack(
        [0.5 * (xs[i] + xs[i + 1]), 0.5 * (ys[j] + ys[j + 1])], axis=1
    )  # one new vertex per cell
    m = vertices.shape[0] + np.arange(a.size)
    tris = np.concatenate(
        [np.stack([a, b, m], 1), np.stack([b, c, m], 1), np.stack([c, d, m], 1),
         np.stack([d, a, m], 1)]
    )  # fmt: skip
    return fm.Mesh(np.vstack([vertices, centres]), tris)


def anti_delaunay(n, shift=0.4):
    """Square ``(-1, 1)^2``, obtuse by construction: rows shifted, the longer diagonal taken.

    Interior grid rows are shifted alternately by ``+-shift`` cell widths in x
    (boundary vertices stay on the boundary), and every quadrilateral is split
    along its *longer* diagonal: the two angles opposite that diagonal sum to
    more than pi, so the stiffness matrix has positive off-diagonal entries.
    """
    h = 2.0 / n
    xs = np.linspace(-1.0, 1.0, n + 1)
    vertices, a, b, c, d, _ = _grid(xs, xs)
    vertices = vertices.copy()
    col = np.tile(np.arange(n + 1), n + 1)
    row = np.repeat(np.arange(n + 1), n + 1)
    inner = (col > 0) & (col < n) & (row > 0) & (row < n)
    vertices[inner, 0] += np.where(row[inner] % 2 == 0, shift, -shift) * h
    ac = np.linalg.norm(vertices[a] - vertices[c], axis=1)
    bd = np.linalg.norm(vertices[b] - vertices[d], axis=1)
    use_ac = ac >= bd
    t1 = np.where(use_ac[:, None], np.stack([a, b, c], 1), np.stack([a, b, d], 1))
    t2 = np.where(use_ac[:, None], np.stack([a, c, d], 1), np.stack([b, c, d], 1))
    return fm.Mesh(vertices, np.concatenate([t1, t2]))


def perturbed(n, amount=0.24, seed=SEED):
    """Square ``(-1, 1)^2`` with interior vertices moved by up to ``amount`` cells at random.

    Each coordinate moves by at most ``amount`` cell widths; below 1/4 no triangle
    of the right-diagonal grid can fold.  The right angles become acute or obtuse
    at random: the stiffness matrix has positive off-diagonal entries.
    """
    base = fm.Mesh.square(n, diagonal="right")
    rng = np.random.default_rng(seed)
    v = base.vertices.copy()
    ii = base.interior_vertices
    v[ii] += rng.uniform(-amount, amount, size=(ii.size, 2)) * (2.0 / n)
    return fm.Mesh(v, base.triangles)


def scaled(mesh, sx, sy):
    """The mesh with its coordinates multiplied by ``(sx, sy)`` (anisotropic scaling)."""
    return fm.Mesh(mesh.vertices * np.array([sx, sy]), mesh.triangles)


def lshape(n):
    """The L-shaped domain of fastmem (reentrant corner at the origin)."""
    return fm.Mesh.lshape(n)


def gmsh_available() -> tuple[bool, str]:
    """Whether the python ``gmsh`` module imports (and why not)."""
    try:
        import gmsh  # noqa: F401
    except Exception as exc:  # ImportError, or a missing shared library (OSError)
        return False, f"gmsh python package unavailable: {type(exc).__name__}: {exc}"
    return True, ""


def gmsh_mesh(shape, h_fine, h_coarse):
    """A gmsh mesh with mixed element sizes, generated headless, written as .msh, read back.

    ``shape`` is ``"square"`` (``(-1, 1)^2``; elements of size ``h_fine`` near
    the corner ``(-1, -1)`` and the centre, ``h_coarse`` elsewhere) or
    ``"disk"`` (unit disk; ``h_fine`` near the point ``(0.5, 0)``).  The file
    goes through :meth:`fastmem.Mesh.read` (meshio), as a user would do.
    """
    import gmsh

    gmsh.initialize(["-noenv"], readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.Verbosity", 0)
        gmsh.model.add(f"stress_{shape}")
        occ = gmsh.model.occ
        if shape == "square":
            occ.addRectangle(-1.0, -1.0, 0.0, 2.0, 2.0)
            attractors = [occ.addPoint(-1.0, -1.0, 0.0), occ.addPoint(0.0, 0.0, 0.0)]
        elif shape == "disk":
            occ.addDisk(0.0, 0.0, 0.0, 1.0, 1.0)
            attractors = [occ.addPoint(0.5, 0.0, 0.0)]
        else:
            raise ValueError(f"unknown gmsh shape {shape!r}")
        occ.synchronize()
        field = gmsh.model.mesh.field
        dist = field.add("Distance")
        field.setNumbers(dist, "PointsList", attractors)
        thr = field.add("Threshold")
        field.setNumber(thr, "InField", dist)
        field.setNumber(thr, "SizeMin", h_fine)
        field.setNumber(thr, "SizeMax", h_coarse)
        field.setNumber(thr, "DistMin", 2 * h_fine)
        field.setNumber(thr, "DistMax", 0.6)
        field.setAsBackgroundMesh(thr)
        for name in ("MeshSizeExtendFromBoundary", "MeshSizeFromPoints", "MeshSizeFromCurvature"):
            gmsh.option.setNumber(f"Mesh.{name}", 0)
        gmsh.option.setNumber("Mesh.Algorithm", 6)  # Frontal-Delaunay
        gmsh.option.setNumber("Mesh.RandomSeed", 1.0)
        gmsh.model.mesh.generate(2)
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, f"{shape}.msh")
            gmsh.write(path)
            # gmsh may write clockwise triangles; meshio's msh reader prints a blank line
            with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
                warnings.simplefilter("ignore", fm.errors.MeshWarning)
                mesh = fm.Mesh.read(path)
    finally:
        gmsh.finalize()
    if shape == "square":  # snap round-off so that the manufactured family applies
        v = mesh.vertices.copy()
        for k in (0, 1):
            near = np.abs(np.abs(v[:, k]) - 1.0) < 1e-12
            v[near, k] = np.sign(v[near, k])
        mesh = fm.Mesh(v, mesh.triangles)
    return mesh


# ---------------------------------------------------------------------------- properties


def positive_offdiagonals(mesh, rel_tol=1e-12):
    """Positive off-diagonal entries of the interior block of the stiffness matrix.

    The interior block is the matrix of the discrete obstacle problem
    (docs/method.md §3.3); any positive entry means it is not an M-matrix.
    """
    from fastmem.fem.assembly import assemble_stiffness

    ii = mesh.interior_vertices
    a = assemble_stiffness(mesh)[ii][:, ii].tocoo()
    off = a.row != a.col
    scale = np.abs(a.data).max()
    return int(np.count_nonzero(a.data[off] > rel_tol * scale))


def max_aspect_ratio(mesh):
    """Largest ``h_K^2 / (2 |K|)`` (diameter over the height on the longest edge)."""
    return float((mesh.diameters**2 / (2.0 * mesh.areas)).max())


def max_angle_degrees(mesh):
    """Largest interior angle of the mesh, in degrees."""
    v = mesh.vertices[mesh.triangles]
    worst = 0.0
    for k in range(3):
        e1 = v[:, (k + 1) % 3] - v[:, k]
        e2 = v[:, (k + 2) % 3] - v[:, k]
        cos = (e1 * e2).sum(1) / (np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1))
        worst = max(worst, float(np.degrees(np.arccos(np.clip(cos, -1, 1))).max()))
    return worst
