"""The callable-load block kernel against the plain NumPy expressions of the same integrals."""

import numpy as np
import pytest
from fastmem.kernels import assembly as ka

from fastmem.fem.quadrature import triangle_rule


def _numpy_block(fv, w, bary, areas):
    """Load vector parts, moments and oscillation norms of one block, in NumPy."""
    fw = fv * w
    avg = fw @ bary
    local = avg * areas[:, None]
    outer = (bary[:, :, None] * bary[:, None, :]).reshape(-1, 9)
    mom = ((fw @ outer) * areas[:, None]).reshape(-1, 3, 3)
    scale = np.abs(fv).max(axis=1)
    scale[scale == 0.0] = 1.0
    avg_s = avg / scale[:, None]
    coef = 12.0 * avg_s - 3.0 * avg_s.sum(axis=1, keepdims=True)
    diff = fv / scale[:, None] - coef @ bary.T
    norm = scale * np.sqrt(((diff * diff) @ w) * areas)
    return local, mom, norm


def _args(degree):
    bary, w = triangle_rule(degree)
    bary, w = np.array(bary), np.array(w)
    return bary, w, (bary[:, :, None] * bary[:, None, :]).reshape(-1, 9)


@pytest.mark.parametrize("degree", [2, 5, 8])
def test_load_block_matches_numpy(degree):
    """Rows start..start+k of the outputs, to round-off; the rows outside are not touched."""
    bary, w, outer = _args(degree)
    rng = np.random.default_rng(degree)
    m, start, k = 40, 7, 25
    fv = rng.standard_normal((k, bary.shape[0])) * 10.0 ** rng.integers(-150, 150, (k, 1))
    fv[3] = 0.0  # a zero load on a triangle: scale 1, norm 0
    fv[4] = 2.5  # a constant one: no oscillation up to round-off
    areas = rng.random(m) + 0.1
    local = np.full((m, 3), -7.0)
    mom = np.full((m, 3, 3), -7.0)
    norm = np.full(m, -7.0)
    ka.load_block(fv, w, bary, outer, areas, start, local, mom, norm)
    ref_local, ref_mom, ref_norm = _numpy_block(fv, w, bary, areas[start : start + k])
    rows = slice(start, start + k)
    np.testing.assert_allclose(local[rows], ref_local, rtol=1e-13, atol=0.0)
    np.testing.assert_allclose(mom[rows], ref_mom, rtol=1e-13, atol=0.0)
    # in units of each triangle's largest value (the rows span 300 decades)
    unit = np.abs(fv).max(axis=1) * np.sqrt(areas[rows])
    unit[unit == 0.0] = 1.0
    np.testing.assert_allclose(norm[rows] / unit, ref_norm / unit, rtol=1e-10, atol=1e-14)
    assert norm[start + 3] == 0.0
    assert norm[start + 4] <= 1e-14 * 2.5
    for arr in (local, mom, norm):
        assert (arr[:start] == -7.0).all()
        assert (arr[start + k :] == -7.0).all()


def test_load_block_without_moments_writes_the_load_vector_only():
    bary, w, outer = _args(5)
    rng = np.random.default_rng(1)
    fv = rng.standard_normal((9, bary.shape[0]))
    areas = rng.random(9) + 0.5
    local = np.zeros((9, 3))
    ka.load_block(fv, w, bary, outer, areas, 0, local, np.empty((0, 3, 3)), np.empty(0))
    np.testing.assert_allclose(local, _numpy_block(fv, w, bary, areas)[0], rtol=1e-13)
