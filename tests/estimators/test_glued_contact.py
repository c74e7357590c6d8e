"""Glued contact load of the bound's flux (issue 16; fastmem.estimators.flux.glued_contact_load).

On closed triangles (gap <= 0 at the three vertices) of patches with unequal
tensions the contact load of vertex a is ``s_a psi_a (chi* + gamma_a m_K)^+``
instead of ``lam_a psi_a``.  Checked here against an independent evaluation
of that definition: the exact patch masses ``B_a lam_a`` (solvability), the
moments the kernel receives, the equilibration of both fluxes with
``Pi(f_1 + chi)`` and ``Pi(f_2 - chi)``, normal continuity, ``ell >= 0`` at a
dense set of points, c never above the plain one, ``eta >= error`` at the
extreme tensions (1e-6, 1e6) for exact and perturbed triples, and the
effectivity measured when the glued load landed.
"""

import functools

import naive_flux
import numpy as np
import pytest
from meshes import perturbed_square
from test_bound import _triples
from test_flux import _normal_jump, _quad_points
from test_weighted_flux import _checkerboard, contact_triple

import fastmem as fm
import fastmem.estimators.flux as flux
from fastmem.estimators.bound import evaluate
from fastmem.estimators.terms import local_terms
from fastmem.fem.quadrature import triangle_rule

CASES = {
    # name: (mesh, scene builder, perturb)
    "manufactured-1e-6-1e6": (
        lambda: fm.Mesh.square(16),
        lambda m: fm.Manufactured(mu=(1e-6, 1e6)).scene(m),
        False,
    ),
    "manufactured-1-1e-6": (
        lambda: fm.Mesh.square(16),
        lambda m: fm.Manufactured(mu=(1.0, 1e-6)).scene(m),
        False,
    ),
    "p1-load": (
        lambda: fm.Mesh.square(12),
        lambda m: fm.Scene(
            m, mu=(1e-2, 5.0), f=(-2.0 - m.vertices[:, 0], 1.0 + 0.5 * m.vertices[:, 1]), g=0.1
        ),
        False,
    ),
    "checker-1e-3": (
        lambda: fm.Mesh.square(16),
        lambda m: fm.Scene(m, mu=(_checkerboard(m, 1e-3), 1.0), f=(-4.0, 2.0), g=0.1),
        False,
    ),
    "checker-1e3-perturbed": (
        lambda: perturbed_square(12, 0.3),
        lambda m: fm.Scene(m, mu=(_checkerboard(m, 1e3), 1.0), f=(-4.0, 2.0), g=0.1),
        True,
    ),
}


@functools.cache
def case(name):
    mesh, scene, u1, u2, lam, r1, r2 = contact_triple(*CASES[name], seed=29)
    contact = flux.glued_contact_load(scene, u1, u2, lam)
    assert contact is not None, name
    assert contact.flags.sum() >= 3, name
    fl = flux.reconstruct(scene, u1, u2, lam, r1, r2, redistribute="glued")
    return scene, u1, u2, lam, r1, r2, contact, fl


def _load_at(scene, i, tri, bary):
    """f_i at barycentric points of triangles tri: (len(tri), nq)."""
    mesh = scene.mesh
    f = scene.f1 if i == 1 else scene.f2
    if callable(f):
        pts = _quad_points(mesh, bary)[tri]
        return f(pts[..., 0], pts[..., 1])
    if np.ndim(f) == 0:
        return np.full((tri.size, bary.shape[0]), float(f))
    return np.asarray(f, float)[mesh.triangles[tri]] @ bary.T


def _glued_naive(scene, contact, lam, bary):
    """Independent chi on every triangle at barycentric points: (M, nq).

    Glued vertex a on a closed triangle K: s_a lambda_a (chi* + gamma_a m_K)^+ --
    pointwise for callable loads (the points must then be those of the load
    rule), else the P1 interpolant of the clipped vertex values; everywhere
    else lam_a lambda_a.
    """
    mesh = scene.mesh
    tri = mesh.triangles
    m = mesh.n_triangles
    every = np.arange(m)
    mu1 = np.broadcast_to(np.asarray(scene.mu1, float), (m,))
    mu2 = np.broadcast_to(np.asarray(scene.mu2, float), (m,))
    mk = (mu1 * mu2 / (mu1 + mu2))[:, None]
    cal = callable(scene.f1) or callable(scene.f2)
    if cal:
        star = (
            mu1[:, None] * _load_at(scene, 2, every, bary)
            - mu2[:, None] * _load_at(scene, 1, every, bary)
        ) / (mu1 + mu2)[:, None]
    else:
        eye = np.eye(3)
        star = (
            mu1[:, None] * _load_at(scene, 2, every, eye)
            - mu2[:, None] * _load_at(scene, 1, every, eye)
        ) / (mu1 + mu2)[:, None]  # vertex values
    gap_closed = np.zeros(m, bool)
    gap_closed[contact.tri] = True
    chi = np.zeros((m, bary.shape[0]))
    for k in range(3):
        v = tri[:, k]
        glued = contact.flags[v] & gap_closed
        shifted = np.maximum(star + (contact.gamma[v][:, None] * mk), 0.0)
        zeta = shifted if cal else shifted @ bary.T
        piece = contact.scale[v][:, None] * zeta * bary[None, :, k]
        plain = lam[v][:, None] * bary[None, :, k]
        plain = np.where(contact.flags[v][:, None], 0.0, plain)
        chi += np.where(glued[:, None], piece, plain)
    return chi


@pytest.mark.parametrize("name", list(CASES))
def test_patch_masses_and_moments(name):
    """(chi^a, 1) = B_a lam_a to round-off; the kernel's moments are the definition's."""
    scene, u1, u2, lam, r1, r2, contact, fl = case(name)
    mesh = scene.mesh
    tri = mesh.triangles[contact.tri]
    gap = u1 - u2
    assert (gap[tri] <= 0.0).all()  # glued load only on closed triangles
    mass = np.bincount(tri.ravel(), weights=contact.moments.sum(axis=2).ravel(), minlength=len(u1))
    target = mesh.lumped_mass * lam
    g = contact.flags
    assert np.abs(mass[g] - target[g]).max() <= 1e-13 * np.abs(target[g]).max()
    assert (contact.scale[g] > 0.0).all()
    # moments against the definition (load rule for callables, degree 8 otherwise)
    cal = callable(scene.f1) or callable(scene.f2)
    bary, w = triangle_rule(scene.load_degree) if cal else (naive_flux.QUAD_BARY, naive_flux.QUAD_W)
    mom = np.zeros_like(contact.moments)
    for i in range(3):
        # the piece of local vertex i, from the definition
        v = tri[:, i]
        sel = contact.flags[v]
        mu1 = np.broadcast_to(np.asarray(scene.mu1, float), (mesh.n_triangles,))[contact.tri]
        mu2 = np.broadcast_to(np.asarray(scene.mu2, float), (mesh.n_triangles,))[contact.tri]
        mk = (mu1 * mu2 / (mu1 + mu2))[:, None]
        if cal:
            star = (
                mu1[:, None] * _load_at(scene, 2, contact.tri, bary)
                - mu2[:, None] * _load_at(scene, 1, contact.tri, bary)
            ) / (mu1 + mu2)[:, None]
            zeta = np.maximum(star + contact.gamma[v][:, None] * mk, 0.0)
        else:
            eye = np.eye(3)
            star = (
                mu1[:, None] * _load_at(scene, 2, contact.tri, eye)
                - mu2[:, None] * _load_at(scene, 1, contact.tri, eye)
            ) / (mu1 + mu2)[:, None]
            zeta = np.maximum(star + contact.gamma[v][:, None] * mk, 0.0) @ bary.T
        own = np.where(sel[:, None], contact.scale[v][:, None] * zeta * bary[None, :, i], 0.0)
        mom[:, i, :] = (mesh.areas[contact.tri][:, None] * (own * w)) @ bary
    scale = np.abs(contact.moments).max()
    assert np.abs(mom - contact.moments).max() <= 1e-12 * scale


@pytest.mark.parametrize("name", list(CASES))
def test_fluxes_equilibrated_and_conforming(name):
    """div sigma_1h = Pi(f1 + chi) - rho1, div sigma_2h = Pi(f2 - chi) - rho2; normal continuity."""
    scene, u1, u2, lam, r1, r2, contact, fl = case(name)
    mesh = scene.mesh
    m = mesh.n_triangles
    cal = callable(scene.f1) or callable(scene.f2)
    bary, w = triangle_rule(scene.load_degree) if cal else (naive_flux.QUAD_BARY, naive_flux.QUAD_W)
    chi = _glued_naive(scene, contact, lam, bary)
    area = mesh.areas[:, None]
    pts = _quad_points(mesh, bary)
    tt = np.repeat(np.arange(m), len(w))
    for i, sgn in ((1, 1.0), (2, -1.0)):
        div = fl.divergence(i - 1, tt, pts[..., 0].ravel(), pts[..., 1].ravel()).reshape(m, -1)
        rho = (np.where(mesh.boundary_vertex_mask, 0.0, (r1 if i == 1 else r2) / mesh.lumped_mass))[
            mesh.triangles
        ] @ bary.T
        f = _load_at(scene, i, np.arange(m), bary)
        terms = [area * ((v * w) @ bary) for v in (f, sgn * chi, -rho, -div)]
        defect = np.abs(sum(terms)).max()
        size = max(np.abs(t).max() for t in terms)
        assert defect <= 1e-11 * size, (i, defect, size)
        jump, scale = _normal_jump(lambda t, x, y, i=i: fl.evaluate(i - 1, t, x, y), mesh)
        assert jump <= 1e-11 * scale


@pytest.mark.parametrize("name", list(CASES))
def test_contact_load_nonnegative_and_c_not_larger(name, monkeypatch):
    """ell = chi + lam^- >= 0 at vertices and a degree-10 rule's points; c <= the plain c.

    The glued bound itself: the layer bound (fastmem.estimators.layers), which evaluate returns
    when it is smaller, trades c for the squeeze terms and is tested in test_layers.
    """
    monkeypatch.setattr(fm.estimators.layers, "LAYER_BOUND", False)
    scene, u1, u2, lam, r1, r2, contact, fl = case(name)
    mesh = scene.mesh
    cal = callable(scene.f1) or callable(scene.f2)
    rules = [triangle_rule(scene.load_degree)[0]] if cal else [triangle_rule(10)[0], np.eye(3)]
    lam_minus = np.maximum(lam, 0.0) - lam
    for bary in rules:
        ell = _glued_naive(scene, contact, lam, bary) + lam_minus[mesh.triangles] @ bary.T
        assert ell.min() >= -1e-13 * np.abs(ell).max()
    assert contact.ell_min >= 0.0
    plain = local_terms(scene, u1, u2, lam)["eta_C"].sum()
    est = evaluate(scene, u1, u2, lam, r1, r2)
    assert est.totals["c"] <= plain * (1.0 + 1e-12) + 1e-300
    assert (est.maps["eta_osc1"] >= 0.0).all()
    assert (est.maps["eta_osc2"] >= 0.0).all()


def test_equal_tensions_are_left_alone():
    """mu1 = mu2: no glued load, the bound's flux is reconstruct()'s (bit for bit)."""
    ms = fm.Manufactured(mu=(1.0, 1.0))
    mesh = fm.Mesh.square(8)
    scene = ms.scene(mesh)
    r = fm.solve(scene, method="exact", estimate=False)
    assert flux.glued_contact_load(scene, r.u1, r.u2, r.lam) is None
    a = flux.reconstruct(scene, r.u1, r.u2, r.lam, redistribute="glued")
    b = flux.reconstruct(scene, r.u1, r.u2, r.lam)
    assert np.array_equal(a.coef, b.coef)


@pytest.mark.parametrize("mu", [(1e-6, 1e6), (1e6, 1e-6), (1.0, 1e-6)])
def test_bound_guaranteed_at_extreme_tensions(mu, rng):
    """eta >= |||u - u_h||| for exact solves (n = 8, 16, 32) and perturbed triples (n = 8, 16)."""
    ms = fm.Manufactured(mu=mu)
    for n in (8, 16, 32):
        mesh = fm.Mesh.square(n)
        scene = ms.scene(mesh)
        exact = fm.solve(scene, estimate=True, method="exact")
        err = ms.energy_error(mesh, exact.u1, exact.u2)
        assert exact.eta >= err, (n, exact.eta, err)
        if n == 32:
            continue
        for name, (u1, u2, lam) in _triples(ms, mesh, scene, exact, rng).items():
            est = fm.estimate(scene, u1, u2, lam)
            e = ms.energy_error(mesh, u1, u2)
            assert est.eta >= e, (n, name, est.eta, e)
    inexact = fm.solve(ms.scene(fm.Mesh.square(32)), method="inexact")
    assert inexact.eta >= ms.energy_error(fm.Mesh.square(32), inexact.u1, inexact.u2)


#: Effectivities of exact solves measured when the glued contact load landed (issue 16;
#: before: 1978 / 897 / 401 for (1e-6, 1e6) at n = 16 / 32 / 64 and 3.05 / 1.57 / 1.17 for
#: (1, 1e-6)); limits = measured + 1 %, never to be loosened.
EXTREME_EFFECTIVITY = {
    ((1e-6, 1e6), 16): 1.5199,
    ((1e-6, 1e6), 32): 1.1806,
    ((1e-6, 1e6), 64): 1.0860,
    ((1e6, 1e-6), 32): 1.1806,
    ((1.0, 1e-6), 32): 1.0456,
    ((1e-6, 1.0), 64): 1.0452,
}


@pytest.mark.parametrize(("mu", "n"), list(EXTREME_EFFECTIVITY))
def test_effectivity_at_extreme_tensions(mu, n):
    ms = fm.Manufactured(mu=mu)
    mesh = fm.Mesh.square(n)
    r = fm.solve(ms.scene(mesh), method="exact", estimate=True)
    eff = r.eta / ms.energy_error(mesh, r.u1, r.u2)
    assert 1.0 <= eff <= 1.01 * EXTREME_EFFECTIVITY[(mu, n)]
