"""Test meshes shared by several test modules."""

import warnings

import numpy as np

import fastmem as fm


def perturbed_square(n, amount, seed=20261121):
    """Structured square mesh with interior vertices moved randomly (still valid).

    Each coordinate moves by up to ``amount`` cells.  From ``amount`` = 1/4 on a
    triangle can turn over (its three vertices moved towards each other); the
    vertices of triangles turned over or nearly flat (area below a tenth of a
    cell's triangle) get half their displacement until none is left.  The meshes
    of the default seed drawn with ``amount`` <= 0.3 are unchanged by this
    (hypothesis found seed 60220 at n = 5 turning one triangle over).
    """
    base = fm.Mesh.square(n, diagonal="right")
    rng = np.random.default_rng(seed)
    interior = base.interior_vertices
    disp = np.zeros_like(base.vertices)
    disp[interior] = rng.uniform(-amount, amount, size=(interior.size, 2)) * (2.0 / n)
    t = base.triangles
    for _ in range(64):
        v = base.vertices + disp
        e1, e2 = v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]
        bad = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] <= 0.1 * (2.0 / n) ** 2
        if not bad.any():
            break
        disp[np.unique(t[bad])] *= 0.5
    return fm.Mesh(v, t)


#: The eight symmetries of the square (-1, 1)^2 as maps of coordinates.
SYMMETRIES = [
    lambda x, y: (x, y),
    lambda x, y: (-x, y),
    lambda x, y: (x, -y),
    lambda x, y: (-x, -y),
    lambda x, y: (y, x),
    lambda x, y: (-y, x),
    lambda x, y: (y, -x),
    lambda x, y: (-y, -x),
]


def circle_mesh(refinements):
    """Unstructured mesh of the unit disk from scikit-fem (an independent generator)."""
    import pytest

    skfem = pytest.importorskip("skfem")
    m = skfem.MeshTri.init_circle(refinements)
    with warnings.catch_warnings():  # scikit-fem's circle has clockwise triangles
        warnings.simplefilter("ignore", fm.errors.MeshWarning)
        return fm.Mesh(m.p.T, m.t.T)


def gmsh_square(size, tmp_path):
    """gmsh mesh of (-1, 1)^2 with element size ``size``, read back through Mesh.read."""
    import pytest

    gmsh = pytest.importorskip("gmsh")
    path = tmp_path / "square.msh"
    gmsh.initialize(["-noenv"], readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("square")
        gmsh.model.occ.addRectangle(-1.0, -1.0, 0.0, 2.0, 2.0)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMin", size)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.model.mesh.generate(2)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()
    return fm.Mesh.read(path)
