"""The patch kernels' two ways to the patch data (g_i^a, lambda_j)_K give the same bits.

The kernels call :func:`fastmem.kernels.flux._plain_loads` (small, inlined) on a
triangle without a glued or redistributed contact load and the general
:func:`fastmem.kernels.flux._patch_loads` elsewhere; where both apply they must
agree bit for bit, or a flux would depend on which path a triangle took.
"""

import numpy as np
import pytest
from fastmem.kernels import flux as kf


@pytest.mark.parametrize("moments", [False, True], ids=["constant", "moments"])
def test_plain_loads_match_the_general_path_bit_for_bit(moments):
    rng = np.random.default_rng(7)
    m = 5
    load1 = rng.normal(size=(m, 3, 3)) if moments else np.zeros((1, 3, 3))
    load2 = rng.normal(size=(m, 3, 3)) if moments else np.zeros((1, 3, 3))
    chi_row = np.full(1, -1, dtype=np.int32)
    chi_mom = np.zeros((1, 3, 3))
    gloc = np.empty((3, 2))
    kapj = np.empty(3)
    checked = 0
    for _ in range(40):
        t = int(rng.integers(m))
        i = int(rng.integers(3))
        area = float(rng.uniform(1e-4, 1.0))
        m1, m2 = rng.uniform(0.1, 10.0, size=2)
        du = rng.normal(size=6)  # du1x, du1y, du2x, du2y, gax, gay
        f1c, f2c, r1a, r2a, lam_a = rng.normal(size=5)
        kf._patch_loads(
            i, t, area, m1, m2, *du, f1c, f2c, load1, load2, chi_row, chi_mom,
            False, r1a, r2a, lam_a, False, 0.0, gloc, kapj,
        )  # fmt: skip
        plain = kf._plain_loads(
            i, t, area, m1, m2, *du, f1c, f2c, load1, load2, r1a, r2a, lam_a
        )  # fmt: skip
        np.testing.assert_array_equal(np.array(plain).reshape(3, 2), gloc)
        assert np.array(plain).view(np.int64).tolist() == gloc.ravel().view(np.int64).tolist()
        checked += 1
    assert checked == 40
