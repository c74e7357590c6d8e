"""Adaptive inexact Newton-min with AMG-CG inner solves (docs/method.md §3.4 and 6)."""

import math

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.testing import assert_allclose

import fastmem as fm
from fastmem.errors import ParameterError
from fastmem.linalg.amg import PCG, amg_preconditioner
from fastmem.solver.nested import (
    coarse_scenes,
    interpolation_matrix,
    prolong_triple,
    warm_active_set,
)

MANUFACTURED = [
    pytest.param({"mu": (1.0, 1.0), "kappa": 1.0}, id="mu11-k1"),
    pytest.param({"mu": (1.0, 1.0), "kappa": 0.0}, id="mu11-k0"),
    pytest.param({"mu": (1.0, 10.0), "kappa": 1.0}, id="mu1_10-k1"),
    pytest.param({"mu": (1.0, 10.0), "kappa": 0.0}, id="mu1_10-k0"),
]


def _default_scene(n):
    return fm.Scene(fm.Mesh.square(n), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)


# --------------------------------------------------------------- building blocks
def test_pcg_matches_a_direct_solve(rng):
    scene = _default_scene(24)
    ii = scene.mesh.interior_vertices
    a = scene.stiffness[ii][:, ii].tocsr()
    b = rng.standard_normal(ii.size)
    cg = PCG(a, b, np.zeros_like(b), amg_preconditioner(a))
    its = cg.solve(1e-12, 200)
    x = spla.spsolve(a.tocsc(), b)
    assert 0 < its < 40
    assert np.abs(cg.x - x).max() <= 1e-9 * np.abs(x).max()
    # the recursive residual stays the true residual
    assert np.linalg.norm(b - a @ cg.x) <= 1e-10 * np.linalg.norm(b)


def test_pcg_exact_start_is_stuck_not_frozen():
    """x0 = the exact solution: the residual is 0, CG cannot step and says so (f = 0 hang)."""
    a = sp.diags([2.0, 3.0, 4.0]).tocsr()
    x = np.array([1.0, -2.0, 0.5])
    cg = PCG(a, a @ x, x, lambda r: r / a.diagonal())
    assert not cg.step()
    assert cg.stuck
    assert cg.at_roundoff(1e-12)
    assert cg.solve(1e-12, 50) == 0
    np.testing.assert_array_equal(cg.x, x)


def test_pcg_wild_start_is_replaced_by_zero(rng):
    scene = _default_scene(16)
    ii = scene.mesh.interior_vertices
    a = scene.stiffness[ii][:, ii].tocsr()
    b = rng.standard_normal(ii.size)
    cg = PCG(a, b, np.full(ii.size, 1e80), amg_preconditioner(a))
    assert np.abs(cg.x).max() == 0.0
    cg.solve(1e-12, 100)
    assert np.linalg.norm(b - a @ cg.x) <= 1e-11 * np.linalg.norm(b)


def test_pcg_checks_the_true_residual(rng):
    """A drifted recursive residual (here: tampered with) does not end the solve."""
    scene = _default_scene(16)
    ii = scene.mesh.interior_vertices
    a = scene.stiffness[ii][:, ii].tocsr()
    b = rng.standard_normal(ii.size)
    jacobi = a.diagonal()
    cg = PCG(a, b, np.zeros_like(b), lambda r: r / jacobi)
    for _ in range(3):
        cg.step()
    cg.r *= 1e-20  # the recursion claims convergence, the iterate is far from it
    assert not cg.at_roundoff(1e-12)
    cg.solve(1e-12, 100)
    assert cg.restarts >= 1
    assert np.linalg.norm(b - a @ cg.x) <= 1e-12 * np.linalg.norm(b) * (1 + 1e-9)


@pytest.mark.parametrize("kind", ["square", "lshape", "refined"])
def test_interpolation_is_exact_for_linear_functions(kind):
    if kind == "square":
        fine = fm.Mesh.square(16)
    elif kind == "lshape":
        fine = fm.Mesh.lshape(16)
    else:
        fine = fm.Mesh.square(6, diagonal="right").refine()
    coarse = fine.coarser()
    assert coarse is not None
    assert coarse.n_vertices < fine.n_vertices
    mat = interpolation_matrix(coarse, fine)
    lin = lambda v: 0.3 - 2.0 * v[:, 0] + 5.0 * v[:, 1]  # noqa: E731
    assert np.abs(mat @ lin(coarse.vertices) - lin(fine.vertices)).max() <= 1e-13
    assert np.allclose(mat.sum(axis=1), 1.0, rtol=0, atol=1e-14)


def _located_interpolation(coarse, fine):
    """The interpolation by point location (the path of meshes that are not nested)."""
    from fastmem.mesh.coarsen import locate

    tri, bary = locate(coarse, fine.vertices)
    rows = np.repeat(np.arange(fine.n_vertices), 3)
    cols = coarse.triangles[tri].ravel()
    shape = (fine.n_vertices, coarse.n_vertices)
    mat = sp.csr_matrix((bary.ravel(), (rows, cols)), shape=shape)
    mat.eliminate_zeros()
    return mat


NESTED = pytest.mark.parametrize(
    ("make", "dyadic"),
    [
        (lambda: fm.Mesh.square(16), True),
        (lambda: fm.Mesh.square(12), False),
        (lambda: fm.Mesh.square(6), False),
        (lambda: fm.Mesh.square(8, diagonal="right"), True),
        (lambda: fm.Mesh.square(10, diagonal="left"), False),
        (lambda: fm.Mesh.rectangle(12, 8, bounds=(0.1, 3.3, -0.7, 1.9)), False),
        (lambda: fm.Mesh.lshape(16), True),
        (lambda: fm.Mesh.lshape(12), False),
        (lambda: fm.Mesh.square(16).refine(), True),
        (lambda: fm.Mesh.rectangle(5, 3, bounds=(0.1, 3.3, -0.7, 1.9)).refine(), False),
    ],
    ids=["sq16", "sq12", "sq6", "right", "left", "rect", "L16", "L12", "red", "red-rect"],
)


def _both_paths(monkeypatch, coarse, fine):
    """The nested interpolation by the threaded kernels and by NumPy (None: not nested)."""
    import fastmem.solver.nested as nested

    monkeypatch.setattr(nested, "KERNELS_FROM", 0)
    threaded = nested._nested_interpolation(coarse, fine)
    monkeypatch.setattr(nested, "KERNELS_FROM", 1 << 62)
    return threaded, nested._nested_interpolation(coarse, fine)


@NESTED
@pytest.mark.parametrize("threads", [1, 2])
def test_threaded_nested_interpolation_is_the_numpy_matrix(monkeypatch, make, dyadic, threads):
    """The kernels of large meshes give the NumPy path's matrix entry for entry (index
    types, sorted columns, weights), for any thread count."""
    fine = make()
    coarse = fine.coarser()
    with _threads(threads):
        got, want = _both_paths(monkeypatch, coarse, fine)
    assert want is not None
    assert got.indptr.dtype == want.indptr.dtype
    assert got.indices.dtype == want.indices.dtype
    assert got.has_sorted_indices
    want.sort_indices()
    assert np.array_equal(got.indptr, want.indptr)
    assert np.array_equal(got.indices, want.indices)
    assert np.array_equal(got.data, want.data)


def _threads(k):
    import contextlib

    import numba

    @contextlib.contextmanager
    def scope():
        old = numba.get_num_threads()
        numba.set_num_threads(k)
        try:
            yield
        finally:
            numba.set_num_threads(old)

    return scope()


@pytest.mark.parametrize("case", ["moved-fine", "moved-coarse", "hole", "not-nested", "red-moved"])
def test_threaded_nested_interpolation_refuses_what_numpy_refuses(monkeypatch, case):
    """Both paths return None (point location then) for a vertex off the pattern."""
    if case == "not-nested":
        coarse, fine = fm.Mesh.square(4), fm.Mesh.square(16)
    elif case == "red-moved":
        coarse = fm.Mesh.square(6)
        fine = coarse.refine()
        v = fine.vertices.copy()
        v[coarse.n_vertices + 3] += 1e-3  # a midpoint off its edge
        moved = fm.Mesh(v, fine.triangles)
        moved._parent = coarse
        fine = moved
    else:
        fine = fm.Mesh.square(16)
        coarse = fine.coarser()
        if case == "moved-fine":
            v = fine.vertices.copy()
            v[40] += (2e-3, -1e-3)  # still on the grid by rounding, off by the check
            moved = fm.Mesh(v, fine.triangles)
            moved._grid = fine._grid
            fine = moved
        elif case == "moved-coarse":
            v = coarse.vertices.copy()
            v[7] += (3e-3, 0.0)
            moved = fm.Mesh(v, coarse.triangles)
            moved._grid = coarse._grid
            coarse = moved
        else:  # a coarse cell missing: the fine centre vertex there has no diagonal
            centroids = coarse.vertices[coarse.triangles].mean(axis=1)
            keep = np.abs(centroids - 0.125).max(axis=1) >= 0.125  # the cell (0, 0.25)^2
            assert (~keep).sum() == 2
            holed = fm.Mesh(coarse.vertices, coarse.triangles[keep])
            holed._grid = coarse._grid
            coarse = holed
    got, want = _both_paths(monkeypatch, coarse, fine)
    assert want is None
    assert got is None


@NESTED
def test_nested_interpolation_without_point_location(monkeypatch, make, dyadic):
    """Nested meshes: weights from the indices, as point location gives them up to round-off.

    On dyadic coordinates (n a power of two on (-1, 1)^2) the same bits; point
    location is not called at all (its kernels are not compiled for such runs).
    """
    import fastmem.solver.nested

    fine = make()
    coarse = fine.coarser()
    want = _located_interpolation(coarse, fine)
    monkeypatch.setattr(fastmem.solver.nested, "locate", None)  # any call fails
    got = interpolation_matrix(coarse, fine)
    diff = abs(got - want)
    assert (diff.max() if diff.nnz else 0.0) <= 1e-15
    assert np.array_equal(got.sum(axis=1).A.ravel(), np.ones(fine.n_vertices))
    if dyadic:
        assert (got != want).nnz == 0


def test_structured_solve_locates_no_point(monkeypatch):
    import fastmem.solver.nested

    monkeypatch.setattr(fastmem.solver.nested, "locate", None)
    res = fm.solve(_default_scene(64))
    assert len(res.parameters["solver"]["levels"]) == 3
    assert res.converged


def test_meshes_without_a_coarser_version():
    assert fm.Mesh.square(5).coarser() is None  # odd number of cells
    mesh = fm.Mesh.square(8)
    plain = fm.Mesh(mesh.vertices, mesh.triangles)  # arrays only: no recipe
    assert plain.coarser() is None
    # per-vertex data cannot move to a non-parent coarse mesh: no chain
    scene = fm.Scene(mesh, f=(np.ones(mesh.n_vertices), 0.0))
    assert coarse_scenes(scene, min_vertices=10) == []
    # ... but they can move to a parent
    fine = mesh.refine()
    scene = fm.Scene(
        fine, f=(np.ones(fine.n_vertices), 0.0), mu=(np.full(fine.n_triangles, 2.0), 1.0)
    )
    chain = coarse_scenes(scene, min_vertices=10)
    assert chain[-1].mesh is mesh
    assert np.allclose(chain[-1].mu1, 2.0)


def test_prolonged_triple_keeps_boundary_values():
    scene = _default_scene(16)
    coarse = coarse_scenes(scene, min_vertices=10)[-1]
    r = fm.solve(coarse, method="exact")
    u1, u2, lam = prolong_triple(scene, coarse, (r.u1, r.u2, r.lam))
    bnd = scene.mesh.boundary_vertices
    assert np.all(u1[bnd] == 0.1)
    assert np.all(u2[bnd] == 0.0)
    assert np.all(lam[bnd] == 0.0)
    # vertices shared by both meshes keep their coarse values exactly
    fine_key = {tuple(v): k for k, v in enumerate(scene.mesh.vertices.round(12))}
    idx = np.array([fine_key[tuple(v)] for v in coarse.mesh.vertices.round(12)])
    for fine_vals, coarse_vals in ((u1, r.u1), (u2, r.u2), (lam, r.lam)):
        np.testing.assert_allclose(fine_vals[idx], coarse_vals, rtol=0, atol=1e-14)
    # new vertices (midpoints of coarse edges here) get the average of the end values
    new = np.setdiff1d(np.arange(scene.mesh.n_vertices), idx)
    assert new.size > 0
    assert np.isfinite(u1[new]).all()
    assert u1[new].max() <= r.u1.max() + 1e-14


# --------------------------------------------------------------- the required tests
@pytest.mark.parametrize("params", MANUFACTURED)
def test_inexact_error_within_five_percent_of_exact(params):
    ms = fm.Manufactured(**params)
    for n in (16, 32, 64):
        mesh = fm.Mesh.square(n)
        scene = ms.scene(mesh)
        exact = fm.solve(scene, method="exact")
        inexact = fm.solve(scene, method="inexact")
        assert inexact.converged
        e_exact = ms.energy_error(mesh, exact.u1, exact.u2)
        e_inexact = ms.energy_error(mesh, inexact.u1, inexact.u2)
        assert abs(e_inexact - e_exact) <= 0.05 * e_exact, (n, e_exact, e_inexact)


@pytest.mark.parametrize("path", ["decoupled", "general"])
@pytest.mark.parametrize("params", MANUFACTURED[::3])
def test_bound_holds_at_every_recorded_iterate(params, path):
    ms = fm.Manufactured(**params)
    mesh = fm.Mesh.square(32)
    scene = ms.scene(mesh)
    r = fm.solve(
        scene, method="inexact", path=path, full_history=True, keep_iterates=True, nested=False
    )
    h = r.history
    assert len(r.iterates) == h["eta"].size >= 3
    assert np.isfinite(h["eta"]).all()
    assert np.all(h["fresh_disc"] == 1)
    infeasible = 0
    for row, (u1, u2, lam) in enumerate(r.iterates):
        err = ms.energy_error(mesh, u1, u2)
        assert h["eta"][row] >= err, (row, h["eta"][row], err)
        interior = mesh.interior_vertices
        infeasible += bool(
            (lam[interior] < 0).any() or (u1 - u2)[interior].min() < 0 or h["eta_lin"][row] > 0
        )
    assert infeasible >= 1  # early iterates are infeasible and still bounded


def test_bound_holds_at_nested_iterates():
    ms = fm.Manufactured()
    mesh = fm.Mesh.square(32)
    r = fm.solve(ms.scene(mesh), method="inexact", full_history=True, keep_iterates=True)
    h = r.history
    finest = h["level"] == h["level"].max()
    assert h["level"].max() >= 1
    rows = np.flatnonzero(finest)
    for row in rows:
        u1, u2, _ = r.iterates[row]
        assert h["eta"][row] >= ms.energy_error(mesh, u1, u2)


@pytest.mark.parametrize("path", ["decoupled", "general"])
@pytest.mark.parametrize("params", MANUFACTURED[:3])
def test_stopping_criteria_hold_at_exit(params, path):
    ms = fm.Manufactured(**params)
    scene = ms.scene(fm.Mesh.square(32))
    gamma_alg, gamma_lin = 0.1, 0.2
    r = fm.solve(scene, method="inexact", path=path, gamma_alg=gamma_alg, gamma_lin=gamma_lin)
    assert r.converged
    # recomputed from scratch, independently of the solver's bookkeeping
    est = fm.estimate(scene, r.u1, r.u2, r.lam)
    t = est.totals
    assert t["eta_alg"] <= gamma_alg * max(t["eta_disc"], t["eta_lin"])
    assert t["eta_lin"] <= gamma_lin * t["eta_disc"]
    assert math.isclose(r.eta, est.eta, rel_tol=1e-10)


def test_inexact_needs_fewer_inner_iterations_than_exact_amg():
    scene = _default_scene(128)
    inexact = fm.solve(scene, method="inexact")
    exact = fm.solve(scene, method="exact-amg")
    assert inexact.converged
    assert exact.converged
    n_inexact = int(inexact.history["inner_total"][-1])
    n_exact = int(exact.history["inner_total"][-1])
    assert n_inexact < n_exact, (n_inexact, n_exact)


@pytest.mark.parametrize("params", MANUFACTURED[::2])
def test_decoupled_and_general_inexact_agree(params):
    ms = fm.Manufactured(**params)
    mesh = fm.Mesh.square(48)
    scene = ms.scene(mesh)
    errs = [
        ms.energy_error(mesh, r.u1, r.u2)
        for r in (fm.solve(scene, path=p) for p in ("decoupled", "general"))
    ]
    assert abs(errs[0] - errs[1]) <= 0.05 * min(errs), errs


# --------------------------------------------------------------- exact-amg and options
@pytest.mark.parametrize("path", ["decoupled", "general"])
def test_exact_amg_matches_the_direct_solver(path):
    scene = _default_scene(32)
    a = fm.solve(scene, method="exact", path=path)
    b = fm.solve(scene, method="exact-amg", path=path)
    assert b.converged
    assert np.array_equal(a.active, b.active)
    scale = np.abs(a.u1).max()
    for x, y in ((a.u1, b.u1), (a.u2, b.u2)):
        assert np.abs(x - y).max() <= 1e-9 * scale
    assert np.abs(a.lam - b.lam).max() <= 1e-7 * np.abs(a.lam).max()


def test_nested_iteration_keeps_newton_steps_bounded():
    steps = []
    for n in (32, 64, 128):
        r = fm.solve(_default_scene(n), method="inexact")
        levels = r.parameters["solver"]["levels"]
        assert len(levels) >= 2
        steps.append(max(lv["newton"] for lv in levels))
    assert max(steps) <= 6, steps
    plain = fm.solve(_default_scene(128), method="exact-amg", nested=False)
    assert plain.n_newton > max(steps)


@pytest.mark.parametrize("reuse", [0.0, 0.05, 1.0])
def test_amg_reuse_policy_does_not_change_the_answer(reuse):
    scene = _default_scene(32)
    ref = fm.solve(scene, method="exact")
    r = fm.solve(scene, method="exact-amg", amg_reuse=reuse, nested=False)
    assert np.array_equal(ref.active, r.active)
    assert np.abs(ref.u1 - r.u1).max() <= 1e-9
    setups = r.parameters["solver"]["levels"][-1]["amg_setups"]
    if reuse == 1.0:
        assert setups == 1  # the Laplacian's hierarchy serves every step
    if reuse == 0.0:
        assert setups >= r.n_newton  # one per changed active set (+ the Laplacian)


def test_history_monitor_and_archive(tmp_path):
    rows = []
    scene = _default_scene(32)
    r = fm.solve(scene, monitor=rows.append)
    assert len(rows) == r.history["k"].size > 0
    assert set(rows[0]) == set(r.history)
    assert np.all(np.diff(r.history["inner_total"]) >= 0)
    assert r.estimate is not None  # inexact always carries its bound
    path = tmp_path / "r.h5"
    r.save(path)
    back = fm.load(path)
    for name, col in r.history.items():
        np.testing.assert_array_equal(back.history[name], col)


def test_step_limit_is_reported(caplog):
    r = fm.solve(_default_scene(32), method="inexact", max_newton=1, nested=False)
    assert not r.converged
    assert "max_newton" in r.parameters["solver"]["stop_reason"]
    assert any("without meeting" in rec.message for rec in caplog.records)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"gamma_alg": 0.0}, "gamma_alg"),
        ({"gamma_lin": -1.0}, "gamma_lin"),
        ({"gamma_lin": float("nan")}, "gamma_lin"),
        ({"max_inner": 0}, "max_inner"),
        ({"check_every": 1.5}, "check_every"),
        ({"amg_reuse": -0.1}, "amg_reuse"),
        ({"nested": "yes"}, "nested"),
        ({"amg_options": "fast"}, "amg_options"),
        ({"amg_options": {"cycle": "X"}}, "cycle"),
        ({"method": "amg"}, "method"),
    ],
)
def test_bad_options_are_refused(kwargs, field):
    with pytest.raises(ParameterError, match=field):
        fm.solve(_default_scene(4), **kwargs)


def test_warm_active_weight_is_the_lambda_term_of_the_gap_equation():
    mesh = fm.Mesh.square(12)
    ii = mesh.interior_vertices
    scene = fm.Scene(mesh, mu=(2.0, 3.0), f=(-1.0, 1.0))
    assert_allclose(scene.active_weight, (1 / 2 + 1 / 3) * mesh.lumped_mass[ii], rtol=1e-13)
    # per-triangle tensions: kappa_a = A_aa / (mu1 A)_aa + A_aa / (mu2 A)_aa
    mu1 = 1.0 + mesh.vertices[mesh.triangles].mean(axis=1)[:, 0] ** 2
    per_tri = fm.Scene(mesh, mu=(mu1, 3.0), f=(-1.0, 1.0))
    assert not isinstance(per_tri.mu1, float)
    grads = mesh.gradients  # (M, 3, 2): local stiffness diagonal |K| |grad phi_i|^2
    local = mesh.areas[:, None] * (grads**2).sum(axis=2)
    a_plain = np.bincount(mesh.triangles.ravel(), local.ravel(), minlength=mesh.n_vertices)
    a_mu1 = np.bincount(
        mesh.triangles.ravel(), (mu1[:, None] * local).ravel(), minlength=mesh.n_vertices
    )
    kappa = a_plain[ii] / a_mu1[ii] + 1.0 / 3.0
    assert_allclose(per_tri.active_weight, kappa * mesh.lumped_mass[ii], rtol=1e-12)
    # kappa B lam > gap: on a vertex with lam > 0 and gap > 0 the lengths decide
    u1 = np.zeros(mesh.n_vertices)
    lam = np.zeros(mesh.n_vertices)
    lam[ii] = 1.0
    u1[ii] = 0.5 * scene.active_weight  # gap = half the lam term: active
    u1[ii[0]] = 2.0 * scene.active_weight[0]  # gap twice the lam term: inactive
    act = warm_active_set(scene, (u1, np.zeros(mesh.n_vertices), lam))
    assert not act[0]
    assert act[1:].all()
    # the rule of docs/method.md §3.1 with c = 1 calls every one of them active (lam = 1 > gap)
    assert scene.active_rule(u1, np.zeros(mesh.n_vertices), lam).all()


@pytest.mark.slow
def test_warm_active_set_saves_newton_steps_on_the_manufactured_scene(monkeypatch):
    """The prolonged triple's first active set by lengths, not by c = 1 (fewer finest steps)."""
    import fastmem.solver.newton as adaptive

    ms = fm.Manufactured()
    scene = ms.scene(fm.Mesh.square(256))
    new = fm.solve(scene)
    monkeypatch.setattr(adaptive, "warm_active_set", lambda sc, t: sc.active_rule(*t))
    old = fm.solve(scene)
    assert new.n_newton < old.n_newton
    assert new.n_newton <= 4
    e_new = ms.energy_error(scene.mesh, new.u1, new.u2)
    e_old = ms.energy_error(scene.mesh, old.u1, old.u2)
    assert abs(e_new - e_old) <= 0.01 * e_old


def test_per_triangle_tensions_get_a_coarse_chain_on_the_generators():
    """Tensions move to Mesh.coarser() by the fine triangle under each coarse centroid.

    Without the chain Newton-min moves the contact front about one cell per step:
    checkerboard mu1 in {1, 1e-3}, n = 64, exact-amg: 12 steps cold, 4 nested (measured).
    """
    from fastmem.mesh.coarsen import locate

    mesh = fm.Mesh.square(64)
    cen = mesh.vertices[mesh.triangles].mean(axis=1)
    cells = np.floor((cen + 1.0) / 2.0 * 4)
    mu1 = np.where(cells.sum(axis=1) % 2 == 0, 1.0, 1e-3)
    scene = fm.Scene(mesh, mu=(mu1, 1.0), f=(-1.0, 1.0), g=0.1)
    chain = coarse_scenes(scene, min_vertices=10)
    assert len(chain) >= 3
    top = chain[-1]
    tri, _ = locate(mesh, top.mesh.vertices[top.mesh.triangles].mean(axis=1))
    np.testing.assert_array_equal(top.mu1, mu1[tri])
    warm = fm.solve(scene, method="exact-amg", estimate=False)
    cold = fm.solve(scene, method="exact-amg", estimate=False, nested=False)
    assert warm.n_newton <= 4 < 10 <= cold.n_newton
    scale = np.abs(cold.u1).max()
    assert np.abs(warm.u1 - cold.u1).max() <= 1e-8 * scale


@pytest.mark.parametrize("mu", [(1.0, 1.0), (1.0, 2.0)])
def test_one_pass_checks_change_no_result(monkeypatch, mu):
    """On large meshes the checks take eta_lin, eta_alg from one pass of sums
    (estimators.terms.check_totals) instead of the maps: every history row and the
    returned bound have the bits of the maps' path."""
    from fastmem.solver import newton

    scene = fm.Scene(fm.Mesh.square(256), mu=mu, f=(-1.0, 1.0), g=0.1)  # 131,072 triangles
    real = newton.check_totals
    calls = []

    def counting(*args):
        out = real(*args)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(newton, "check_totals", counting)
    one_pass = fm.solve(scene, nested=False)
    assert calls
    assert all(calls)  # every check of the level took the one pass
    monkeypatch.setattr(newton, "check_totals", lambda *args: None)
    maps = fm.solve(scene, nested=False)
    assert one_pass.eta == maps.eta
    assert set(one_pass.history) == set(maps.history)
    for col in ("eta_lin", "eta_alg", "eta_disc", "eta", "inner_total", "n_active"):
        np.testing.assert_array_equal(one_pass.history[col], maps.history[col])


def test_vector_kernels_change_no_result(monkeypatch):
    """The kernel-thread vector updates of the CGs and of the gap preconditioner
    (meshes of THREADED_ROWS interior vertices and more) leave every history row and
    the bound as NumPy's updates give them."""
    from fastmem.linalg import amg
    from fastmem.solver import steps as st

    calls = {"cg": 0, "mask": 0}
    for mod, name, key in ((amg, "cg_update_range", "cg"), (st, "masked_rhs_range", "mask")):
        real = getattr(mod, name)

        def counting(*args, _real=real, _key=key):
            calls[_key] += 1
            return _real(*args)

        monkeypatch.setattr(mod, name, counting)
    scene = fm.Scene(fm.Mesh.square(256), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    fused = fm.solve(scene, nested=False)
    assert calls["cg"] > 0  # both kernel paths were taken
    assert calls["mask"] > 0
    monkeypatch.setattr(amg, "THREADED_ROWS", 1 << 60)
    monkeypatch.setattr(st, "THREADED_ROWS", 1 << 60)
    calls.update(cg=0, mask=0)
    plain = fm.solve(scene, nested=False)
    assert calls == {"cg": 0, "mask": 0}
    assert fused.eta == plain.eta
    for col in ("eta_lin", "eta_alg", "eta_disc", "res_norm", "inner_total", "n_active"):
        np.testing.assert_array_equal(fused.history[col], plain.history[col])
