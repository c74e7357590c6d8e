"""The class members' kernel gives every patch the bits it has when solved alone.

Its patch data (g_i^a, lambda_j)_K: the kernel calls
:func:`fastmem.kernels.flux._plain_loads` (small, inlined) on a triangle without
a glued or redistributed contact load and the general
:func:`fastmem.kernels.flux._patch_loads` elsewhere; where both apply they must
agree bit for bit, or a flux would depend on which path a triangle took.  Its
solves: :func:`fastmem.kernels.flux._lanes_solve` solves ``LANES`` patches of one
class side by side, each column with the operations of its own solve.
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


def _factor(a):
    """Lower Cholesky factor with the reciprocals of its diagonal, as the patch kernels keep it."""
    lo = np.linalg.cholesky(a)
    np.fill_diagonal(lo, 1.0 / np.diag(lo))
    return lo


def test_lanes_solve_gives_each_patch_the_bits_of_its_own_solve():
    """:func:`_lanes_solve` (the class members side by side) against one patch at a time."""
    rng = np.random.default_rng(3)
    n_e, nt, lanes = 12, 6, kf.LANES
    g = rng.normal(size=(n_e, n_e))
    mred = _factor(g @ g.T + n_e * np.eye(n_e))
    cmat = rng.normal(size=(nt, n_e))
    cstart = np.array([0, 0, 2, 2, 4, 6], dtype=np.int64)
    for p in range(nt):
        cmat[p, : cstart[p]] = 0.0
    h = rng.normal(size=(nt, nt))
    smat = _factor(h @ h.T + nt * np.eye(nt))
    fred0 = rng.normal(size=(n_e, 2 * lanes))
    crhs0 = rng.normal(size=(nt, 2 * lanes))
    fred, crhs = fred0.copy(), crhs0.copy()
    kf._lanes_solve(mred, fred, cmat, crhs, smat, cstart, n_e, nt, np.empty(2 * lanes))
    for lane in range(lanes):
        f1 = np.zeros((n_e, 3))
        f1[:, :2] = fred0[:, 2 * lane : 2 * lane + 2]
        c1 = crhs0[:, 2 * lane : 2 * lane + 2].copy()
        kf._reduced_solve2(mred, f1, cmat, c1, smat, cstart, n_e, nt, True, 0, 2, 2)
        assert f1[:, :2].tobytes() == fred[:, 2 * lane : 2 * lane + 2].copy().tobytes()
        assert c1.tobytes() == crhs[:, 2 * lane : 2 * lane + 2].copy().tobytes()
