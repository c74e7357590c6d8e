"""The per-vertex passes of a Newton step in the kernel threads give NumPy's bits.

Each pass has a NumPy path (meshes below ``THREADED_ROWS`` vertices) and a
kernel path (from there on).  Here the threshold is lowered to 0 in the
modules that read it, so that a small mesh takes the kernel path, and each
result is compared bit for bit with the NumPy path's on the same input.
"""

import numpy as np
import pytest
import scipy.sparse as sp

import fastmem as fm
from fastmem.estimators import terms as terms_module
from fastmem.fem import scene as scene_module
from fastmem.linalg import sparse as sparse_module
from fastmem.linalg.amg import PCG
from fastmem.linalg.sparse import ThreadedCSR, csr_diagonal, threaded
from fastmem.solver import linear as linear_module
from fastmem.solver import nested as nested_module
from fastmem.solver import steps as steps_module
from fastmem.solver.linear import DecoupledStep
from fastmem.solver.nested import warm_active_set
from fastmem.solver.steps import DecoupledCG

MODULES = (scene_module, sparse_module, linear_module, nested_module, steps_module, terms_module)


@pytest.fixture
def kernel_path(monkeypatch):
    """Lower ``THREADED_ROWS`` to 0 wherever it is read: every size takes the kernels."""

    def switch(on):
        for mod in MODULES:
            monkeypatch.setattr(mod, "THREADED_ROWS", 0 if on else 10**12)

    return switch


def _scene(mu=(1.0, 2.0), n=20):
    return fm.Scene(fm.Mesh.square(n), mu=mu, f=(-1.0, 1.0), g=0.1)


def _triple(scene, rng):
    n = scene.mesh.n_vertices
    return tuple(rng.standard_normal(n) for _ in range(3))


def _same(a, b):
    a, b = np.asarray(a), np.asarray(b)
    assert a.dtype == b.dtype
    assert a.shape == b.shape
    np.testing.assert_array_equal(a.view(np.uint8), b.view(np.uint8))  # bits, signed zeros too


def test_diagonal_sums_duplicates_and_gives_zero_without_entry(kernel_path, rng):
    kernel_path(True)
    n = 50
    rows = np.concatenate([np.arange(n), np.arange(n), rng.integers(0, n, 200)])
    cols = np.concatenate([np.arange(n), np.arange(n), rng.integers(0, n, 200)])
    vals = rng.standard_normal(rows.size)
    vals[:3] = 0.0
    a = sp.csr_matrix((vals, (rows, cols)), shape=(n, n))
    a.sum_duplicates()
    # a row without its diagonal entry, and one with two stored diagonal entries
    dup = sp.csr_matrix(
        (np.array([1.5, 2.25, -0.5]), np.array([0, 0, 0]), np.array([0, 2, 3])), shape=(2, 2)
    )
    for m in (a, dup):
        _same(csr_diagonal(m), sp.csr_matrix.diagonal(m))
        t = ThreadedCSR((m.data, m.indices, m.indptr), shape=m.shape)
        _same(t.diagonal(), sp.csr_matrix.diagonal(m))
    assert csr_diagonal(dup)[0] == 3.75
    assert csr_diagonal(dup)[1] == 0.0


def test_threaded_residual_is_b_minus_a_x(rng):
    scene = _scene(n=200)
    ii = scene.mesh.interior_vertices
    a = sparse_module.submatrix(scene.stiffness, ii, ii)
    t = threaded(a)
    assert isinstance(t, ThreadedCSR)
    x, b = rng.standard_normal(ii.size), rng.standard_normal(ii.size)
    _same(t.residual(x, b), b - a @ x)
    # not a plain float64 vector: scipy's and NumPy's operations
    _same(t.residual(x.astype(np.float32), b), b - a @ x.astype(np.float32))
    # the CG's residual replacement uses it: the same true residual either way
    cg_t = PCG(t, b, x, lambda r: r)
    cg_p = PCG(a, b, x, lambda r: r)
    _same(cg_t.r, cg_p.r)
    assert cg_t.true_residual_norm() == cg_p.true_residual_norm()


@pytest.mark.parametrize("mu", [(1.0, 1.0), (1.0, 2.0), (3.0, 0.5)])
def test_active_weight_and_rules(kernel_path, rng, mu):
    scene = _scene(mu)
    u1, u2, lam = _triple(scene, rng)
    lam[::3] = 0.0
    u2[::5] = u1[::5]  # gap 0: the comparisons' ties
    out = {}
    for on in (False, True):
        kernel_path(on)
        s = fm.Scene(scene.mesh, mu=mu, f=(-1.0, 1.0), g=0.1)
        out[on] = (
            s.active_weight,
            s.active_rule(u1, u2, lam),
            warm_active_set(s, (u1, u2, lam)),
        )
    for a, b in zip(out[False], out[True], strict=True):
        _same(a, b)
    assert 0 < out[True][1].sum() < out[True][1].size  # both sides of the rule occur


def test_decoupled_right_hand_sides(kernel_path):
    scene = _scene((2.0, 0.5))
    steps = {}
    for on in (False, True):
        kernel_path(on)
        steps[on] = DecoupledStep(scene)
    _same(steps[False].rhs_w, steps[True].rhs_w)
    _same(steps[False].rhs_s, steps[True].rhs_s)
    assert np.abs(steps[True].rhs_w).max() > 0
    assert np.abs(steps[True].rhs_s).max() > 0


def test_gap_start(kernel_path, rng):
    scene = _scene((1.0, 1.0))
    step = DecoupledStep(scene)
    u1, u2, _ = _triple(scene, rng)
    active = rng.random(step.interior.size) < 0.3

    class Options:
        amg_options = {}

    cg = DecoupledCG(step, Options(), {}, None)
    out = {}
    for on in (False, True):
        kernel_path(on)
        out[on] = cg._gap_start(active, u1, u2)
    for a, b in zip(out[False], out[True], strict=True):
        _same(a, b)
    assert np.all(out[True][0][active] == 0.0)
    assert np.all(out[True][1][active] == 0.0)


def test_full_vectors_from_interior_values(kernel_path, rng):
    scene = _scene((1.0, 1.0))
    step = DecoupledStep(scene)
    inner = rng.standard_normal(step.interior.size)
    out = {}
    for on in (False, True):
        kernel_path(on)
        out[on] = (step._full(inner), step._full(inner, step.g_full))
    for a, b in zip(out[False], out[True], strict=True):
        _same(a, b)
    np.testing.assert_array_equal(out[True][0][step.interior], inner)
    assert np.all(out[True][0][step.boundary] == 0.0)


def test_lambda_parts(kernel_path, rng):
    mesh = fm.Mesh.square(20)
    lam = rng.standard_normal(mesh.n_vertices)
    lam[::4] = -0.0
    lam[1::9] = 0.0
    out = {}
    for on in (False, True):
        kernel_path(on)
        out[on] = terms_module._lambda_parts(mesh, lam)
    for a, b in zip(out[False], out[True], strict=True):
        _same(a, b)
    lam_hat, lam_minus = out[True]
    assert np.all(lam_hat[mesh.boundary_vertex_mask] == 0.0)
    np.testing.assert_array_equal(lam_hat - lam_minus, np.where(mesh.boundary_vertex_mask, 0, lam))


def test_cg_started_in_the_callers_vector(rng):
    """``copy=False``: the CG iterates in the start it was given, with the same iterates."""
    scene = _scene(n=30)
    ii = scene.mesh.interior_vertices
    a = sparse_module.submatrix(scene.stiffness, ii, ii)
    b, x0 = rng.standard_normal(ii.size), rng.standard_normal(ii.size)
    mine = x0.copy()
    start = x0.copy()
    own = PCG(a, b, mine, lambda r: r / a.diagonal(), copy=False)
    ref = PCG(a, b, x0, lambda r: r / a.diagonal())
    assert own.x is mine
    assert ref.x is not x0
    for _ in range(5):
        own.step()
        ref.step()
    _same(own.x, ref.x)
    _same(x0, start)  # the copied start is left as it was
    frozen = x0.copy()
    frozen.flags.writeable = False
    assert PCG(a, b, frozen, lambda r: r, copy=False).x is not frozen  # read-only: copied
