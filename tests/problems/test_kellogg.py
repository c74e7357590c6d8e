"""Kellogg's cross-point solution (fastmem.problems.kellogg) and the bound's effectivity on it.

The exact error of a checkerboard cross point: no reference solution resolves
the r^gamma singularity (gamma = 0.1 at contrast 161, 0.04 at 1e3), the closed
form does.  The bound must stay above it, and, with the global stream-function
correction of fastmem.estimators.flux.cross_point_correction, close to it.
"""

import math

import numpy as np
import pytest

import fastmem as fm
from fastmem.errors import ParameterError
from fastmem.estimators import flux
from fastmem.problems.kellogg import Kellogg

CONTRASTS = (10.0, 161.4476387975881, 1e3, 1e6)


@pytest.mark.parametrize("contrast", CONTRASTS)
def test_continuous_with_continuous_flux_and_harmonic(contrast):
    k = Kellogg(contrast)
    assert math.isclose(k.gamma, 4.0 / math.pi * math.atan(contrast**-0.5), rel_tol=1e-15)
    eps = 1e-12
    for t0 in (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi):
        lo, hi = (t0 - eps) % (2.0 * math.pi), t0 + eps
        (m_lo, m_hi), (d_lo, d_hi) = k.angular(np.array([lo, hi]))
        a_lo = k.tension(math.cos(lo), math.sin(lo))
        a_hi = k.tension(math.cos(hi), math.sin(hi))
        assert a_lo != a_hi
        assert abs(m_lo - m_hi) <= 1e-10
        # the normal flux a m' / r is continuous across the half-axis
        assert abs(a_lo * d_lo - a_hi * d_hi) <= 1e-9 * abs(a_lo * d_lo)
    # harmonic inside each quadrant (finite differences off the axes)
    rng = np.random.default_rng(0)
    pts = rng.uniform(0.3, 0.9, size=(20, 2)) * rng.choice([-1.0, 1.0], size=(20, 2))
    h = 1e-4
    x, y = pts[:, 0], pts[:, 1]
    lap = (k.u(x + h, y) + k.u(x - h, y) + k.u(x, y + h) + k.u(x, y - h) - 4 * k.u(x, y)) / h**2
    gx, gy = k.grad(x, y)
    assert np.abs(lap).max() <= 1e-5
    # the gradient against central differences
    fx = (k.u(x + h, y) - k.u(x - h, y)) / (2 * h)
    fy = (k.u(x, y + h) - k.u(x, y - h)) / (2 * h)
    assert np.abs(gx - fx).max() <= 1e-6
    assert np.abs(gy - fy).max() <= 1e-6


def test_the_classical_parameters():
    k = Kellogg()
    assert math.isclose(k.gamma, 0.1, rel_tol=1e-12)
    assert math.isclose(k.sigma, -14.92256510455152, rel_tol=1e-12)
    with pytest.raises(ParameterError, match="contrast"):
        Kellogg(0.5)
    with pytest.raises(ParameterError, match="shift"):
        Kellogg(shift=0.5)


def test_energy_error_identity():
    """The boundary-integral error against direct quadrature (a mild contrast) and orthogonality."""
    from fastmem.fem.quadrature import quadrature_points, triangle_rule

    # contrast 1.5: gamma = 0.87, the gradient r^-0.13 is integrated well by a rule of degree 12
    k = Kellogg(1.5)
    mesh = fm.Mesh.square(16)
    r = fm.solve(k.scene(mesh), method="exact")
    bary, w = triangle_rule(12)
    x, y = quadrature_points(mesh.vertices, mesh.triangles, bary)
    gx, gy = k.grad(x, y)
    gh = np.einsum("tk,tkd->td", r.u1[mesh.triangles], mesh.gradients)
    e2 = ((gx - gh[:, 0, None]) ** 2 + (gy - gh[:, 1, None]) ** 2) @ w
    direct = math.sqrt(float((k.mu(mesh) * e2 * mesh.areas).sum()))
    assert math.isclose(k.energy_error(mesh, r.u1, r.u2), direct, rel_tol=2e-3)
    # Galerkin orthogonality for nested meshes (the boundary data differ by O(h^2) only)
    k = Kellogg(1e3)
    fine = mesh.refine()
    rf = fm.solve(k.scene(fine), method="exact")
    r = fm.solve(k.scene(mesh), method="exact")
    e = np.concatenate([r.u1, 0.5 * (r.u1[mesh.edges[:, 0]] + r.u1[mesh.edges[:, 1]])])
    from fastmem.fem.assembly import assemble_stiffness

    d = rf.u1 - e
    d2 = float(d @ (assemble_stiffness(fine, k.mu(fine)) @ d))
    coarse2 = k.energy_error(mesh, r.u1) ** 2
    fine2 = k.energy_error(fine, rf.u1) ** 2
    assert math.isclose(coarse2, fine2 + d2, rel_tol=1e-3)


#: eta / exact error on Kellogg's solution, structured meshes (measured 2026-11-26 with
#: the global stream-function correction; limits = measured + 1 %, never to be loosened).
#: The rings alone (glob=False) gave 1.29 / 3.04 / 6.74 / 198 at n = 16.
KELLOGG_EFFECTIVITY = {
    (10.0, 16, "exact"): 1.174,
    (10.0, 32, "exact"): 1.179,
    (10.0, 32, "inexact"): 1.293,
    (161.4476387975881, 16, "exact"): 1.144,
    (161.4476387975881, 32, "exact"): 1.165,
    (161.4476387975881, 32, "inexact"): 1.263,
    (1e3, 16, "exact"): 1.069,
    (1e3, 32, "exact"): 1.081,
    (1e3, 32, "inexact"): 1.114,
    (1e6, 16, "exact"): 1.003,
    (1e6, 32, "exact"): 1.003,
    (1e6, 32, "inexact"): 1.057,
}


@pytest.mark.parametrize(("contrast", "n", "method"), list(KELLOGG_EFFECTIVITY))
def test_bound_is_guaranteed_and_sharp_at_a_cross_point(contrast, n, method):
    k = Kellogg(contrast)
    mesh = fm.Mesh.square(n)
    r = fm.solve(k.scene(mesh), method=method, estimate=True)
    assert np.abs(r.u2).max() == 0.0
    assert np.abs(r.lam).max() == 0.0  # the membranes never touch
    err = k.energy_error(mesh, r.u1, r.u2)
    eff = r.eta / err
    assert eff >= 1.0
    assert eff <= KELLOGG_EFFECTIVITY[(contrast, n, method)] * 1.01, eff


@pytest.mark.parametrize("diagonal", ["right", "left"])
def test_bound_holds_on_other_diagonals(diagonal):
    k = Kellogg(1e6)
    mesh = fm.Mesh.square(16, diagonal=diagonal)
    r = fm.solve(k.scene(mesh), method="exact", estimate=True)
    err = k.energy_error(mesh, r.u1, r.u2)
    assert err <= r.eta <= 1.5 * err


def test_the_global_step_is_what_makes_it_sharp():
    k = Kellogg(1e3)
    mesh = fm.Mesh.square(16)
    scene = k.scene(mesh)
    r = fm.solve(scene, method="exact")
    base = flux.reconstruct(scene, r.u1, r.u2, r.lam)
    rings = flux.cross_point_correction(scene, r.u1, r.u2, base, glob=False)
    full = flux.cross_point_correction(scene, r.u1, r.u2, base)
    from fastmem.estimators.bound import flux_terms

    f_rings = np.sqrt((flux_terms(scene, r.u1, r.u2, rings)[0] ** 2).sum())
    f_full = np.sqrt((flux_terms(scene, r.u1, r.u2, full)[0] ** 2).sum())
    err = k.energy_error(mesh, r.u1, r.u2)
    assert f_rings > 5.0 * err  # 6.74: the rings cannot carry the singular flux
    assert err <= f_full <= 1.1 * err  # 1.07


def test_large_mesh_path_agrees_with_the_direct_one(monkeypatch):
    """Above CROSS_POINT_DIRECT_VERTICES the joint system is solved by 10 AMG-CG steps."""
    k = Kellogg(1e3)
    mesh = fm.Mesh.square(32)
    scene = k.scene(mesh)
    r = fm.solve(scene, method="exact", estimate=True)
    direct = r.eta
    monkeypatch.setattr(flux, "CROSS_POINT_DIRECT_VERTICES", 1)
    iterative = fm.estimate(k.scene(mesh), r.u1, r.u2, r.lam, r1=r.r1, r2=r.r2).eta
    err = k.energy_error(mesh, r.u1, r.u2)
    assert err <= direct <= iterative  # the direct solve is the minimiser
    assert iterative <= direct * (1 + 1e-3)  # measured: 1.08138 vs 1.08144
