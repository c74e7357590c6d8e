"""The stepwise PCG of fastmem against the textbook recurrence, and its preconditioner count.

:class:`fastmem.linalg.amg.PCG` forms the preconditioned residual of an
iteration, and the direction it feeds, in the *next* :meth:`~PCG.step`, so a
CG stopped after k iterations has applied the preconditioner k times (an
inexact Newton step stops after one or two).  Deferring must change no bit
of the iterates: they are compared here with the textbook loop written out
in NumPy, on a small and on a threaded (kernel-updated) system.
"""

import numpy as np
import pytest

import fastmem as fm
from fastmem.fem.assembly import assemble_stiffness
from fastmem.linalg import amg
from fastmem.linalg.sparse import threaded


def _system(n, seed):
    mesh = fm.Mesh.square(n)
    ii = mesh.interior_vertices
    a = assemble_stiffness(mesh)[ii][:, ii].tocsr()
    a.eliminate_zeros()
    a.sort_indices()
    rng = np.random.default_rng(seed)
    return a, rng.standard_normal(a.shape[0]), rng.standard_normal(a.shape[0])


def _textbook(a, b, x0, m, k):
    """k iterations of preconditioned CG exactly as printed; every iterate x_1..x_k."""
    x = x0.copy()
    r = b - a @ x
    z = m(r)
    p = z.copy()
    rz = float(r @ z)
    out = []
    for _ in range(k):
        ap = a @ p
        alpha = rz / float(p @ ap)
        x += alpha * p
        r -= alpha * ap
        out.append((x.copy(), r.copy()))
        z = m(r)
        rz_new = float(r @ z)
        p = p * (rz_new / rz) + z
        rz = rz_new
    return out


@pytest.mark.parametrize(("n", "seed"), [(24, 3), (200, 4)])  # 529 and 39,601 unknowns
def test_pcg_is_the_textbook_recurrence(n, seed):
    a, b, x0 = _system(n, seed)
    if n == 200:
        assert a.shape[0] >= amg.THREADED_ROWS  # the kernel-updated vectors
        mat = threaded(a)
    else:
        mat = a
    inv = 1.0 / a.diagonal()

    def jacobi(r):
        return inv * r

    want = _textbook(a, b, x0, jacobi, 7)
    cg = amg.PCG(mat, b, x0, jacobi)
    for i, (x, r) in enumerate(want):
        assert cg.step()
        np.testing.assert_array_equal(cg.x, x, err_msg=f"x after iteration {i + 1}")
        np.testing.assert_array_equal(cg.r, r, err_msg=f"r after iteration {i + 1}")


def test_pcg_applies_the_preconditioner_once_per_iteration():
    """k iterations, k preconditioner calls: none for a direction no iteration uses."""
    a, b, x0 = _system(16, 5)
    inv = 1.0 / a.diagonal()
    calls = []

    def counting(r):
        calls.append(r.shape[0])
        return inv * r

    cg = amg.PCG(a, b, x0, counting)
    assert not calls  # set up, not advanced: no preconditioner yet
    for k in range(1, 5):
        assert cg.step()
        assert len(calls) == k
    cg.restart()  # a restart forms the direction afresh from the true residual
    assert cg.step()
    assert len(calls) == 5
    # and the solve converges as CG does: the true residual meets the tolerance
    cg.solve(1e-10, 500)
    assert np.linalg.norm(b - a @ cg.x) <= 1e-10 * np.linalg.norm(b)


def test_error_estimate_tracks_the_energy_error():
    """PCG.error_estimate against the A-norm error to the exact solution, iterate by iterate.

    With an AMG preconditioner (a contraction of about 0.1 per iteration): the
    estimate lies above the current iterate's error (it estimates the previous
    iterate's) and within a factor of 3 of the previous iterate's error, until the
    error reaches round-off.  An estimate, not a bound: with a slow preconditioner
    (Jacobi) the first estimates fall below the error.
    """
    import scipy.sparse.linalg as spla

    a, b, _ = _system(48, 7)
    exact = spla.spsolve(a.tocsc(), b)
    cg = amg.PCG(a, b, np.zeros_like(b), amg.amg_preconditioner(a, {}))
    assert cg.error_estimate() is None  # no step yet

    def err2(x):
        e = exact - x
        return float(e @ (a @ e))

    first = prev = err2(cg.x)
    steps = 0
    while prev > 1e-16 * first:
        cg.step()
        steps += 1
        now = err2(cg.x)
        est = cg.error_estimate()
        assert now <= est <= 3.0 * prev, (steps, now, est, prev)
        prev = now
    assert 4 <= steps <= 20
