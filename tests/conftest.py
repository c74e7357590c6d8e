import warnings

import numpy as np
import pytest

import fastmem as fm


@pytest.fixture
def seed():
    return 20261121


@pytest.fixture
def rng(seed):
    return np.random.default_rng(seed)


@pytest.fixture(scope="module")
def unstructured_mesh():
    """An unstructured mesh of the unit disk from scikit-fem (independent generator)."""
    skfem = pytest.importorskip("skfem")
    m = skfem.MeshTri.init_circle(3)
    with warnings.catch_warnings():  # scikit-fem's circle has clockwise triangles
        warnings.simplefilter("ignore", fm.errors.MeshWarning)
        return fm.Mesh(m.p.T, m.t.T)
