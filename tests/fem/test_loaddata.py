"""Callable loads: one evaluation per mesh for the load vector, flux moments and oscillation."""

import numpy as np
import pytest
from meshes import perturbed_square
from numpy.testing import assert_allclose

import fastmem as fm
from fastmem.fem import callables, loaddata
from fastmem.fem.assembly import assemble_load
from fastmem.fem.quadrature import quadrature_points, triangle_rule


class Counting:
    """A load f(x, y) = exp(x) sin(3 y) + x y that counts the points it is evaluated at."""

    def __init__(self):
        self.points = 0
        self.calls = 0

    def __call__(self, x, y):
        self.points += np.size(x)
        self.calls += 1
        return np.exp(x) * np.sin(3.0 * y) + x * y


def _reference(mesh, f, degree, mu):
    """Moments and oscillation from f at the quadrature points, plain NumPy, no blocks."""
    bary, w = triangle_rule(degree)
    x, y = quadrature_points(mesh.vertices, mesh.triangles, bary)
    fv = f(x, y)
    mom = np.einsum("mq,qi,qj->mij", fv * w, bary, bary) * mesh.areas[:, None, None]
    # L2(K) projection onto P1 from the local mass matrix, triangle by triangle
    avg = (fv * w) @ bary * mesh.areas[:, None]  # (f, phi_j)_K
    mass = mesh.areas[:, None, None] / 12.0 * (np.ones((3, 3)) + np.eye(3))
    coef = np.linalg.solve(mass, avg[:, :, None])[:, :, 0]
    diff = fv - coef @ bary.T
    norm = np.sqrt(((diff**2) @ w) * mesh.areas)
    return mom, mesh.diameters / np.pi * norm / np.sqrt(mu)


@pytest.mark.parametrize("block", [callables.BLOCK, 7])
def test_integrals_match_plain_reference(rng, block, monkeypatch):
    monkeypatch.setattr(callables, "BLOCK", block)
    mesh = perturbed_square(9, 0.3)
    f = Counting()
    scene = fm.Scene(mesh, mu=(1.0, 2.5), f=(1.0, f), load_degree=6)
    out = loaddata.integrals(scene, 2, moments=True)
    mom, osc = _reference(mesh, f, 6, 2.5)
    assert_allclose(out["F"], assemble_load(mesh, f, 6), rtol=1e-13, atol=1e-15)
    assert_allclose(out["moments"], mom, rtol=1e-12, atol=1e-16)
    assert_allclose(out["osc"], osc, rtol=1e-9, atol=1e-16)
    # the moments sum to the local load integrals (sum_k lambda_k = 1)
    local = out["moments"].sum(axis=2)
    rebuilt = np.bincount(mesh.triangles.ravel(), local.ravel(), minlength=mesh.n_vertices)
    assert_allclose(rebuilt, out["F"], rtol=1e-12, atol=1e-15)
    constant = loaddata.integrals(scene, 1, moments=True)
    assert constant["moments"] is None
    assert np.all(constant["osc"] == 0.0)


def _bary_integral(powers):
    """int_K l_1^a l_2^b l_3^c / |K| = 2 a! b! c! / (a + b + c + 2)!."""
    fact = [1, 1, 2, 6, 24, 120]
    a, b, c = powers
    return 2.0 * fact[a] * fact[b] * fact[c] / fact[a + b + c + 2]


def test_p1_load_moments_are_exact_and_cached(rng):
    mesh = perturbed_square(6, 0.3)
    fv = rng.standard_normal(mesh.n_vertices)
    scene = fm.Scene(mesh, f=(fv, 0.0))
    out = loaddata.integrals(scene, 1, moments=True)
    ft = fv[mesh.triangles]  # f = sum_k f_k l_k on each triangle
    ref = np.zeros((mesh.n_triangles, 3, 3))
    for i in range(3):
        for j in range(3):
            for k in range(3):
                powers = np.bincount([i, j, k], minlength=3)
                ref[:, i, j] += ft[:, k] * _bary_integral(powers)
    ref *= mesh.areas[:, None, None]
    assert_allclose(out["moments"], ref, rtol=1e-12, atol=1e-16)
    # ... and match the degree-5 quadrature of the product (exact for cubics)
    bary, w = triangle_rule(5)
    fw = (ft @ bary.T) * w
    quad = np.einsum("mq,qi,qj->mij", fw, bary, bary) * mesh.areas[:, None, None]
    assert_allclose(out["moments"], quad, rtol=1e-12, atol=1e-16)
    assert np.all(out["osc"] == 0.0)
    # nothing per triangle is kept for P1 data; the load vector is
    assert "moments" not in scene._cache["load_integrals1"]
    assert loaddata.integrals(scene, 1, moments=False)["F"] is out["F"]


def test_callable_raising_in_a_later_block_leaves_no_partial_cache(monkeypatch):
    monkeypatch.setattr(callables, "BLOCK", 16)
    mesh = fm.Mesh.square(8)
    calls = []

    def f(x, y):
        calls.append(1)
        if len(calls) == 3:
            raise ValueError("boom")
        return x + y

    scene = fm.Scene(mesh, f=(f, 0.0))
    with pytest.raises(fm.errors.DataError, match="f1"):
        loaddata.integrals(scene, 1, moments=True)
    assert "load_integrals1" not in scene._cache


def test_oscillation_of_huge_data_does_not_overflow():
    mesh = fm.Mesh.square(6)
    base = fm.Scene(mesh, f=(lambda x, y: np.exp(x) * y, 0.0))
    huge = fm.Scene(mesh, f=(lambda x, y: 1e300 * np.exp(x) * y, 0.0))
    small = loaddata.integrals(base, 1, moments=True)["osc"]
    with np.errstate(over="raise"):
        big = loaddata.integrals(huge, 1, moments=True)["osc"]
    assert np.isfinite(big).all()
    assert_allclose(big, 1e300 * small, rtol=1e-12)


def test_solve_evaluates_a_callable_load_once_per_mesh():
    mesh = fm.Mesh.square(24)
    f = Counting()
    scene = fm.Scene(mesh, f=(-1.0, f), g=0.1)
    nq = triangle_rule(scene.load_degree)[0].shape[0]
    r = fm.solve(scene, nested=False, estimate=True)
    assert r.estimate is not None
    assert r.estimate.totals["eta_disc"] > 0
    assert f.points == mesh.n_triangles * nq
    # a second bound on the same scene reuses the cached moments and oscillation
    fm.estimate(scene, r.u1, r.u2, r.lam)
    assert f.points == mesh.n_triangles * nq


def test_nested_solve_evaluates_a_callable_once_per_level():
    mesh = fm.Mesh.square(64)
    f = Counting()
    scene = fm.Scene(mesh, f=(-1.0, f), g=0.1)
    nq = triangle_rule(scene.load_degree)[0].shape[0]
    r = fm.solve(scene, estimate=True)
    levels = r.parameters["solver"]["levels"]
    assert len(levels) >= 2
    # level l is Mesh.square(64 / 2^(L-1-l)) with 2 n^2 triangles: one pass each
    sizes = [2 * (64 // 2 ** (len(levels) - 1 - k)) ** 2 for k in range(len(levels))]
    assert sizes[-1] == mesh.n_triangles
    assert f.points == sum(sizes) * nq


def test_loads_first_then_moments():
    """Without expect_estimates the loads come alone; the moments cost one more pass."""
    mesh = fm.Mesh.square(8)
    f = Counting()
    scene = fm.Scene(mesh, f=(f, 0.0))
    nq = triangle_rule(scene.load_degree)[0].shape[0]
    load = scene.loads[0]
    assert f.points == mesh.n_triangles * nq
    out = loaddata.integrals(scene, 1, moments=True)
    assert f.points == 2 * mesh.n_triangles * nq
    assert out["F"] is load
    assert out["moments"].shape == (mesh.n_triangles, 3, 3)


def test_estimate_on_a_fresh_scene_evaluates_a_callable_once():
    """``fm.estimate`` declares the moments before its residuals: one pass, the same bits."""
    mesh = fm.Mesh.square(24)
    r = fm.solve(fm.Scene(mesh, f=(-1.0, Counting()), g=0.1))
    f = Counting()
    scene = fm.Scene(mesh, f=(-1.0, f), g=0.1)
    nq = triangle_rule(scene.load_degree)[0].shape[0]
    one_pass = fm.estimate(scene, r.u1, r.u2, r.lam)
    assert f.points == mesh.n_triangles * nq
    # the two-pass way: the load vector alone first, the moments in a second pass
    f2 = Counting()
    scene2 = fm.Scene(mesh, f=(-1.0, f2), g=0.1)
    scene2.loads  # noqa: B018  (the load vector alone: no estimate declared yet)
    two_pass = fm.estimate(scene2, r.u1, r.u2, r.lam)
    assert f2.points == 2 * mesh.n_triangles * nq
    assert one_pass.eta == two_pass.eta
    for name, values in two_pass.maps.items():
        np.testing.assert_array_equal(one_pass.maps[name], values)


def test_exact_solve_without_estimate_builds_no_moments():
    mesh = fm.Mesh.square(8)
    f = Counting()
    scene = fm.Scene(mesh, f=(-1.0, f), g=0.1)
    fm.solve(scene, method="exact", estimate=False)
    assert "moments" not in scene._cache["load_integrals2"]


def test_blocks_integrated_beside_the_evaluation_give_the_same_bits(monkeypatch):
    """Two threads (integrals of a block in a pool thread) and one thread agree bit for bit.

    The callable is only ever called from the calling thread (user callables need not
    be thread-safe).
    """
    import threading

    import numba

    monkeypatch.setattr(callables, "BLOCK", 37)
    mesh = perturbed_square(12, 0.3)
    caller = threading.get_ident()
    threads_seen = set()

    def f(x, y):
        threads_seen.add(threading.get_ident())
        return np.sin(3.0 * x) * np.exp(y) + x * y

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one CPU: no pool thread to compare with")
    before = numba.get_num_threads()
    out = {}
    try:
        for k in (1, 2):
            fm.set_threads(numba=k)
            out[k] = callables.callable_integrals(mesh, f, 5, want_all=True)
    finally:
        fm.set_threads(numba=before)
    assert threads_seen == {caller}
    for key in ("F", "moments", "osc_norm"):
        np.testing.assert_array_equal(out[1][key].view(np.uint64), out[2][key].view(np.uint64))


def _two_threads_or_skip():
    import numba

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one CPU: no second thread")
    return numba.get_num_threads()


def test_parallel_callables_are_evaluated_in_several_threads_with_the_same_bits(monkeypatch):
    """``parallel_callables``: the blocks go to all threads, f included; the numbers do not move."""
    import threading
    import time

    monkeypatch.setattr(callables, "BLOCK", 37)
    mesh = perturbed_square(12, 0.3)
    seen = set()
    lock = threading.Lock()

    def f(x, y):
        with lock:
            seen.add(threading.get_ident())
        time.sleep(0.005)  # (the GIL is let go: the second thread gets blocks too)
        return np.sin(3.0 * x) * np.exp(y) + x * y

    before = _two_threads_or_skip()
    try:
        fm.set_threads(numba=1)
        ref = callables.callable_integrals(mesh, f, 5, want_all=True)
        fm.set_threads(numba=2)
        seen.clear()
        out = callables.callable_integrals(mesh, f, 5, want_all=True, parallel=True)
    finally:
        fm.set_threads(numba=before)
    assert len(seen) == 2
    for key in ("F", "moments", "osc_norm"):
        np.testing.assert_array_equal(out[key].view(np.uint64), ref[key].view(np.uint64))


def test_parallel_callables_raise_the_error_of_the_first_failing_block(monkeypatch):
    """Two threads report the failure that one thread reports, whatever the scheduling."""
    monkeypatch.setattr(callables, "BLOCK", 16)
    mesh = fm.Mesh.square(16)

    def f(x, y):  # NaN right of x = 0.2: the first failing block has its own NaN count
        return np.where(x > 0.2 + 0.01 * y, np.nan, x * y)

    before = _two_threads_or_skip()
    messages = set()
    try:
        fm.set_threads(numba=1)
        with pytest.raises(fm.errors.DataError, match="f2") as serial:
            callables.callable_integrals(mesh, f, 5, name="f2")
        fm.set_threads(numba=2)
        for _ in range(5):
            with pytest.raises(fm.errors.DataError, match="f2") as err:
                callables.callable_integrals(mesh, f, 5, name="f2", parallel=True)
            messages.add(str(err.value))
    finally:
        fm.set_threads(numba=before)
    assert messages == {str(serial.value)}


def test_parallel_callables_is_checked_and_inherited():
    from fastmem.adapt.loop import refine_scene
    from fastmem.mesh.refine import refine_marked
    from fastmem.problems import Manufactured
    from fastmem.solver.nested import coarse_scene

    mesh = fm.Mesh.square(8)
    with pytest.raises(fm.errors.ParameterError, match="parallel_callables"):
        fm.Scene(mesh, f=(np.sin, 0.0), parallel_callables="yes")
    scene = fm.Scene(mesh, f=(lambda x, y: x * y, 0.0), parallel_callables=True)
    assert coarse_scene(scene).parallel_callables
    fine, refinement = refine_marked(mesh, np.arange(4))
    assert refine_scene(scene, fine, refinement).parallel_callables
    assert not fm.Scene(mesh).parallel_callables
    assert Manufactured().scene(mesh).parallel_callables
    assert not Manufactured().scene(mesh, parallel_callables=False).parallel_callables


def test_serial_callable_pass_hints_at_parallel_callables_once(monkeypatch, caplog):
    import logging

    before = _two_threads_or_skip()
    monkeypatch.setattr(callables, "HINT_TRIANGLES", 16)
    monkeypatch.setattr(callables, "_hinted", False)
    mesh = fm.Mesh.square(8)
    try:
        fm.set_threads(numba=2)
        with caplog.at_level(logging.INFO, logger="fastmem.fem.callables"):
            callables.callable_integrals(mesh, np.hypot, 5, parallel=True)
            assert "parallel_callables=True" not in caplog.text
            callables.callable_integrals(mesh, np.hypot, 5, name="f2")
            callables.callable_integrals(mesh, np.hypot, 5, name="f2")
    finally:
        fm.set_threads(numba=before)
    assert caplog.text.count("parallel_callables=True") == 1
    assert "f2(x, y) is evaluated in the calling thread only" in caplog.text
