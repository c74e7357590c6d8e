"""The adaptive loop's resolution limit (fastmem.adapt.loop.RESOLUTION_LIMIT).

On a checkerboard of contrast 1e3 the cross points carry a singularity r^alpha
with alpha ~ 0.04: the loop refined them to diameters of 1e-16, where round-off
in the nodal residuals (divided by lumped masses ~ h^2) made eta_alg grow to
2e3 while eta_disc kept falling.  Triangles at the limit are no longer marked,
and the loop stops, saying why, when they alone hold more than the target.
"""

import numpy as np

import fastmem as fm
from fastmem.adapt import loop as afem
from fastmem.adapt.loop import RESOLUTION_LIMIT, indicators, resolution_limit
from fastmem.mesh.refine import refine_marked


def _checkerboard(mesh, c, blocks=4):
    x0, x1, y0, y1 = mesh.bounding_box
    cen = mesh.vertices[mesh.triangles].mean(axis=1)
    cells = np.floor((cen - [x0, y0]) / [x1 - x0, y1 - y0] * blocks)
    return np.where(cells.sum(axis=1) % 2 == 0, 1.0, c)


def _graded(levels=6):
    """square(4) refined ``levels`` times at the triangles touching the origin."""
    mesh = fm.Mesh.square(4)
    for _ in range(levels):
        at0 = (np.linalg.norm(mesh.vertices[mesh.triangles], axis=2) < 1e-12).any(axis=1)
        mesh, _ = refine_marked(mesh, at0)
    return mesh


def test_the_limit_is_relative_to_the_domain():
    assert RESOLUTION_LIMIT == 2.0**-26
    assert resolution_limit(fm.Mesh.square(8)) == 2.0 * 2.0**-26
    wide = fm.Mesh.rectangle(8, 4, bounds=(0.0, 10.0, 0.0, 1.0))
    assert resolution_limit(wide) == 10.0 * 2.0**-26


def test_triangles_at_the_limit_are_not_marked(monkeypatch):
    mesh = _graded()
    d = mesh.diameters
    # floor the triangles of the two finest sizes
    cut = np.unique(d)[1]
    monkeypatch.setattr(afem, "RESOLUTION_LIMIT", cut / 2.0 * 1.000001)
    small = d <= cut * 1.000001
    assert 0 < small.sum() < d.size
    eta2 = np.ones(d.size)
    out, reason = afem._markable(mesh, eta2, target=10.0 * np.sqrt(d.size))
    assert reason is None
    np.testing.assert_array_equal(out, np.where(small, 0.0, 1.0))
    assert eta2.min() == 1.0  # the caller's array is untouched
    # the floored triangles alone above the target: stop, naming the limit
    target = 0.5 * np.sqrt(small.sum())
    out, reason = afem._markable(mesh, eta2, target)
    assert reason is not None
    assert f"{int(small.sum())} of them" in reason
    assert "resolution limit" in reason
    assert f"{target:.4e}" in reason
    # everything at the limit: nothing left to refine
    monkeypatch.setattr(afem, "RESOLUTION_LIMIT", 10.0)
    out, reason = afem._markable(mesh, eta2, target=1e9)
    assert not out.any()
    assert "nothing else is left to refine" in reason


def test_no_triangle_below_the_limit_is_made(monkeypatch):
    # a coarse limit, so that the cross-point singularity reaches it in a few meshes
    monkeypatch.setattr(afem, "RESOLUTION_LIMIT", 2.0**-9)
    mesh = fm.Mesh.square(8)
    scene = fm.Scene(mesh, mu=(_checkerboard(mesh, 1e3), 1.0), f=(-4.0, 2.0), g=0.1)
    rows = []
    r = fm.solve(scene, tol=1e-3, level_monitor=rows.append, max_levels=60)
    reason = r.parameters["adaptivity"]["stop_reason"]
    assert not r.converged
    assert "resolution limit" in reason, reason
    limit = 2.0 * 2.0**-9
    # marked triangles are above the limit; the closure halves a diameter at most once more
    assert r.mesh.diameters.min() >= limit / 2.0 * (1 - 1e-12)
    # the bound of the returned triple is fresh and its solver part small
    assert np.isfinite(r.eta)
    assert r.eta > 0.0
    t = r.estimate.totals
    assert t["eta_alg"] <= 0.2 * t["eta_disc"]
    # the indicators of the floored triangles: the reason's number
    small = r.mesh.diameters <= limit
    stuck = float(np.sqrt(indicators(r.estimate)[small].sum()))
    assert f"{stuck:.4e}" in reason
    assert stuck > 1e-3


def test_a_true_singularity_stops_at_the_limit_with_a_sane_bound():
    # Kellogg's cross point (contrast 161, u ~ r^0.1): the energy of u within radius h
    # falls like h^0.2, so an error of 0.03 would need diameters of about 1e-16; the
    # loop must stop at the limit (about 50 meshes, 1 s) with eta and the true error
    # of the last mesh within the measured effectivity (before the limit: diameters of 1e-16 and
    # round-off in eta_alg, seen on a checkerboard)
    from fastmem.problems.kellogg import Kellogg

    k = Kellogg()
    mesh = fm.Mesh.square(8)
    r = fm.solve(k.scene(mesh), tol=3e-2, max_levels=200)
    reason = r.parameters["adaptivity"]["stop_reason"]
    assert "resolution limit" in reason, reason
    assert r.mesh.diameters.min() >= resolution_limit(mesh) / 2.0 * (1 - 1e-12)
    eta = np.asarray(r.adaptivity["eta"])
    disc = np.asarray(r.adaptivity["eta_disc"])
    alg, lin = np.asarray(r.adaptivity["eta_alg"]), np.asarray(r.adaptivity["eta_lin"])
    # the returned triple's solver part is small (its mesh solved on by the solver's
    # criterion); the intermediate meshes' CGs stopped by their own error estimate
    # (adapt.loop.INTERMEDIATE_ALG), so only their bound's other parts are compared
    assert eta[-1] <= 1.2 * disc[-1]
    assert (eta - alg - lin <= 1.2 * disc).all()
    # exact error 0.1266, eta 0.1911 (effectivity 1.509, measured; limit + 1 %)
    err = k.energy_error(r.mesh, r.u1, r.u2)
    assert err <= r.eta <= 1.525 * err, (err, r.eta)
