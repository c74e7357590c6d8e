import numpy as np
import pytest
from meshes import circle_mesh


@pytest.fixture
def seed():
    return 20261121


@pytest.fixture
def rng(seed):
    return np.random.default_rng(seed)


@pytest.fixture(scope="module")
def unstructured_mesh():
    """An unstructured mesh of the unit disk from scikit-fem (independent generator)."""
    return circle_mesh(3)
