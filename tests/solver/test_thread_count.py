"""Whole solves give the same numbers with one and with two kernel threads.

Each parallel kernel writes only its own rows, over chunks that depend on the
size and never on the thread count, so a result must not depend on how many
threads ran it.  The kernel tests check this kernel by kernel (the submatrix
and gap kernels, the fused residuals, the block sums, the nested interpolation,
the banded flux, ...); these check the whole chain, on meshes large enough to
take every threaded path: the banded flux estimators and the patch classes
(100,000 vertices), the block sums (131,072 triangles), the nested
interpolation (65,536 vertices) and the geometric multigrid.  ``bench.manycore``
records the same comparison at every thread count it times.
"""

import numba
import numpy as np
import pytest

import fastmem as fm

pytestmark = pytest.mark.skipif(
    numba.config.NUMBA_NUM_THREADS < 2, reason="needs at least two Numba threads"
)


def _with_threads(k, run):
    old = fm.get_threads()["numba"]
    fm.set_threads(numba=k)
    try:
        return run()
    finally:
        fm.set_threads(numba=old)


def _same_result(one, two):
    assert one.eta == two.eta
    values = [k for k in one.estimate.totals if not k.startswith("seconds")]
    assert values
    for k in values:
        assert one.estimate.totals[k] == two.estimate.totals[k], k
    for name in ("u1", "u2", "lam"):
        assert np.array_equal(getattr(one, name), getattr(two, name)), name
    for name, values in one.estimate.maps.items():
        assert np.array_equal(values, two.estimate.maps[name]), name


def test_a_uniform_solve_does_not_depend_on_the_thread_count():
    mesh = fm.Mesh.square(512)
    assert mesh.n_vertices >= 100_000  # every threaded path of a uniform solve

    def run():
        return fm.solve(fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1))

    one, two = _with_threads(1, run), _with_threads(2, run)
    assert one.converged
    assert two.converged
    _same_result(one, two)


def test_an_adaptive_loop_does_not_depend_on_the_thread_count():
    """The same meshes (marking compares indicators: one bit would change them) and bits."""

    def run():
        scene = fm.Scene(fm.Mesh.lshape(8), mu=(1.0, 1.0), f=(-1.0, -1.0), g=0.1)
        return fm.solve(scene, tol=5.52e-3)  # about the bound of uniform n = 1024

    one, two = _with_threads(1, run), _with_threads(2, run)
    assert one.converged
    assert two.converged
    assert one.mesh.n_vertices >= 65_536  # the last meshes take the threaded paths
    assert np.array_equal(one.adaptivity["n_vertices"], two.adaptivity["n_vertices"])
    assert np.array_equal(one.mesh.vertices, two.mesh.vertices)
    assert np.array_equal(one.mesh.triangles, two.mesh.triangles)
    _same_result(one, two)
