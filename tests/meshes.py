"""Test meshes shared by several test modules."""

import warnings

import numpy as np

import fastmem as fm


def perturbed_square(n, amount, seed=20261121):
    """Structured square mesh with interior vertices moved randomly (still valid)."""
    base = fm.Mesh.square(n, diagonal="right")
    rng = np.random.default_rng(seed)
    v = base.vertices.copy()
    interior = base.interior_vertices
    v[interior] += rng.uniform(-amount, amount, size=(interior.size, 2)) * (2.0 / n)
    return fm.Mesh(v, base.triangles)


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
