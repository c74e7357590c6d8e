"""Galerkin update of the gap system's AMG hierarchy (decoupled path, issue 15).

Between Newton steps the active set changes in a band along the free boundary.
:meth:`fastmem.linalg.amg.AMGPreconditioner.update` keeps the setup's prolongators and
replaces every coarse operator by the Galerkin product of the new gap matrix;
:func:`fastmem.solver.steps.gap_delta` gives the change on the rows it touches.  Checked
here against explicit products, for independence of the update history, for the
convergence it buys (against the stale hierarchy and a fresh setup), and for
bit-identical results when a spill frees an updated hierarchy and rebuilds it.
"""

import weakref

import numpy as np
import pytest
import scipy.sparse as sp

import fastmem as fm
from fastmem.fem.assembly import assemble_stiffness
from fastmem.linalg.amg import AMG_DEFAULTS, PCG, amg_preconditioner
from fastmem.solver import inexact as adaptive
from fastmem.solver import steps
from fastmem.solver.steps import gap_delta, gap_matrix


def _laplacian(n, jitter=0.0):
    mesh = fm.Mesh.square(n)
    if jitter:
        v = mesh.vertices.copy()
        rng = np.random.default_rng(3)
        inner = ~np.isin(np.arange(len(v)), mesh.boundary_vertices)
        v[inner] += jitter * (2.0 / n) * (rng.random((inner.sum(), 2)) - 0.5)
        mesh = fm.Mesh(v, mesh.triangles)
    ii = mesh.interior_vertices
    a = assemble_stiffness(mesh)[ii][:, ii].tocsr()
    a.sort_indices()
    x, y = mesh.vertices[ii].T
    return a, x, y


def _disc(x, y, r2):
    return x * x + 0.7 * y * y < r2


@pytest.mark.parametrize("jitter", [0.0, 0.3])
def test_gap_delta_is_the_difference_of_the_gap_matrices(jitter):
    a, x, y = _laplacian(48, jitter)
    old, new = _disc(x, y, 0.30), _disc(x, y, 0.34) ^ (x > 0.8)
    index, delta = gap_delta(a, old, new)
    full = (gap_matrix(a, new) - gap_matrix(a, old)).tocoo()
    embedded = sp.coo_matrix(
        (delta.tocoo().data, (index[delta.tocoo().row], index[delta.tocoo().col])), shape=a.shape
    )
    diff = (full.tocsr() - embedded.tocsr()).tocsr()
    diff.eliminate_zeros()
    assert diff.nnz == 0
    flipped = np.flatnonzero(old != new)
    assert np.isin(flipped, index).all()
    assert len(index) < 0.5 * a.shape[0]  # only the band around the change


@pytest.mark.parametrize("jitter", [0.0, 0.3])
def test_update_gives_the_galerkin_operators_of_the_new_matrix(jitter):
    a, x, y = _laplacian(128, jitter)
    old, new = _disc(x, y, 0.30), _disc(x, y, 0.33)
    pre = amg_preconditioner(gap_matrix(a, old), dict(AMG_DEFAULTS))
    assert len(pre.ml.levels) >= 3  # at least two coarse operators to check
    setup_ops = [lv.A.copy() for lv in pre.ml.levels[1:]]
    new_mat = gap_matrix(a, new)
    pre.update(new_mat, *gap_delta(a, old, new))
    levels = pre.ml.levels
    op = new_mat.tocsr()
    assert (levels[0].A != op).nnz == 0
    for lev in range(len(levels) - 1):
        p = levels[lev].P.tocsr()
        op = (p.T @ op @ p).tocsr()
        got = levels[lev + 1].A
        scale = abs(op).max()
        assert abs(got - op).max() <= 1e-13 * scale
        # and the operator did change where the active set did
        assert abs(got - setup_ops[lev]).max() > 1e-6 * scale
    # the setup's operators are kept unchanged for the next update
    for kept, orig in zip(pre._setup_ops, setup_ops, strict=True):
        assert (kept != orig).nnz == 0


def test_update_does_not_depend_on_the_updates_before():
    a, x, y = _laplacian(64)
    sets = [_disc(x, y, r) for r in (0.30, 0.31, 0.325, 0.335)]
    chained = amg_preconditioner(gap_matrix(a, sets[0]), dict(AMG_DEFAULTS))
    for act in sets[1:]:
        chained.update(gap_matrix(a, act), *gap_delta(a, sets[0], act))
    direct = amg_preconditioner(gap_matrix(a, sets[0]), dict(AMG_DEFAULTS))
    direct.update(gap_matrix(a, sets[-1]), *gap_delta(a, sets[0], sets[-1]))
    assert chained.updates == 3
    assert direct.updates == 1
    for la, lb in zip(chained.ml.levels[1:], direct.ml.levels[1:], strict=True):
        for name in ("data", "indices", "indptr"):
            np.testing.assert_array_equal(getattr(la.A, name), getattr(lb.A, name))
    r = np.random.default_rng(0).standard_normal(a.shape[0])
    np.testing.assert_array_equal(chained(r), direct(r))


def test_updated_hierarchy_converges_like_a_fresh_one():
    a, x, y = _laplacian(128)
    old, new = _disc(x, y, 0.30), _disc(x, y, 0.33)
    mat = gap_matrix(a, new)
    b = np.random.default_rng(1).standard_normal(a.shape[0])
    b[new] = 0.0

    def iterations(pre):
        return PCG(mat, b, np.zeros_like(b), pre).solve(1e-8, 500)

    stale = iterations(amg_preconditioner(gap_matrix(a, old), dict(AMG_DEFAULTS)))
    fresh = iterations(amg_preconditioner(mat, dict(AMG_DEFAULTS)))
    updated_pre = amg_preconditioner(gap_matrix(a, old), dict(AMG_DEFAULTS))
    updated_pre.update(mat, *gap_delta(a, old, new))
    updated = iterations(updated_pre)
    assert updated <= fresh + 2
    assert updated < stale


def test_solver_updates_instead_of_reusing_a_stale_hierarchy():
    """The manufactured scene: Newton steps after the first update the gap hierarchy."""
    scene = fm.Manufactured().scene(fm.Mesh.square(64))
    res = fm.solve(scene, method="exact-amg", path="decoupled", multigrid="algebraic")
    levels = res.parameters["solver"]["levels"]
    assert sum(lv.get("amg_updates", 0) for lv in levels) > 0
    # exact-amg solves every step to round-off: the triple is the exact method's
    ref = fm.solve(fm.Manufactured().scene(fm.Mesh.square(64)), method="exact")
    scale = np.abs(ref.u1).max()
    assert np.abs(res.u1 - ref.u1).max() <= 1e-9 * scale
    assert np.array_equal(res.active, ref.active)


def test_spill_after_an_update_changes_no_result(monkeypatch):
    """A spill frees an updated gap hierarchy; the restore must rebuild the same one."""
    # keyed by the object, not id(): a level's solver is freed when its level ends, and a
    # later level's solver may get the same id (a stale entry of an unrestored spill)
    saved, compared = weakref.WeakKeyDictionary(), []
    spill, restore = steps.DecoupledCG.spill, steps.DecoupledCG.restore

    def operators(cg):
        return [(lv.A.data.copy(), lv.A.indices.copy()) for lv in cg.pre_w.ml.levels]

    def saving_spill(self):
        updated = self.a_ii is not None and self.pre_w is not self.pre_all
        updated = updated and not np.array_equal(self.update_active, self.setup_active)
        saved[self] = operators(self) if updated else None
        return spill(self)

    def comparing_restore(self):
        restore(self)
        before = saved.pop(self, None)
        if before is not None:
            after = operators(self)
            assert len(after) == len(before)
            for (d0, i0), (d1, i1) in zip(before, after, strict=True):
                np.testing.assert_array_equal(i0, i1)
                np.testing.assert_array_equal(d0, d1)
            compared.append(True)

    monkeypatch.setattr(steps.DecoupledCG, "spill", saving_spill)
    monkeypatch.setattr(steps.DecoupledCG, "restore", comparing_restore)

    def solve():  # a flux at every check: spills and restores between the Newton steps
        scene = fm.Scene(fm.Mesh.square(128), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
        return fm.solve(scene, full_history=True, multigrid="algebraic")

    monkeypatch.setattr(adaptive, "SPILL", True)
    spilled = solve()
    assert compared, "no updated hierarchy was freed and rebuilt: the test proves nothing"
    monkeypatch.setattr(adaptive, "SPILL", False)
    kept = solve()
    for name in ("u1", "u2", "lam"):
        np.testing.assert_array_equal(getattr(spilled, name), getattr(kept, name))
    assert spilled.eta == kept.eta
    for col in ("inner_total", "eta_alg", "eta_lin"):
        np.testing.assert_array_equal(spilled.history[col], kept.history[col])
