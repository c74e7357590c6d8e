"""mu-weighted flux reconstruction (docs/method.md §4, per-triangle tensions; issue 16).

The patch problems minimise ``||mu_i^(-1/2) (tau_i^a + v)||``; the kernel must
agree with the independent dense reference ``naive_flux`` (which weights its
mass matrix and flux target by 1 / mu_K) for tensions that jump by up to 1e6
between neighbouring triangles, reduce to today's unweighted reconstruction
for constant tensions, and stay H(div)-conforming and equilibrated whatever
the weights.
"""

import functools

import naive_flux
import numpy as np
import pytest
from meshes import perturbed_square
from test_flux import (
    _check_conforming_and_equilibrated,
    _equilibration_defect,
    _normal_jump,
    _perturb,
)

import fastmem as fm
import fastmem.estimators.flux as flux
from fastmem.estimators.flux import Fluxes
from fastmem.fem.residual import residuals

MESHES = {
    "square4": lambda: fm.Mesh.square(4),
    "perturbed": lambda: perturbed_square(5, 0.3),
    "lshape": lambda: fm.Mesh.lshape(4),
}


def _checkerboard(mesh, c, blocks=4):
    """Per-triangle values: 1 and c on a blocks x blocks checkerboard of the bounding box."""
    cen = mesh.vertices[mesh.triangles].mean(axis=1)
    x0, x1, y0, y1 = mesh.bounding_box
    i = np.floor((cen[:, 0] - x0) / (x1 - x0) * blocks)
    j = np.floor((cen[:, 1] - y0) / (y1 - y0) * blocks)
    return np.where((i + j) % 2 == 0, 1.0, c)


def _random_jumps(mesh, c, seed):
    """Per-triangle values 1 or c at random (every patch mixes both)."""
    rng = np.random.default_rng(seed)
    return np.where(rng.random(mesh.n_triangles) < 0.5, 1.0, c)


TENSIONS = {
    # name: mesh -> (mu1, mu2)
    "checker-1e6": lambda m: (_checkerboard(m, 1e6), 1.0),
    "checker-1e-6": lambda m: (_checkerboard(m, 1e-6), 1.0),
    "random-both": lambda m: (_random_jumps(m, 1e-6, 5), _random_jumps(m, 1e6, 6)),
    "proportional": lambda m: (_random_jumps(m, 1e3, 7), 3.0 * _random_jumps(m, 1e3, 7)),
}


@functools.cache
def case(mesh_name, tension_name):
    mesh = MESHES[mesh_name]()
    mu = TENSIONS[tension_name](mesh)
    f2 = 1.0 + 0.5 * mesh.vertices[:, 0]  # a P1 load on membrane 2
    scene = fm.Scene(mesh, mu=mu, f=(-1.0, f2), g=0.1)
    sol = fm.solve(scene, method="exact")
    u1, u2, lam = _perturb(mesh, sol.u1, sol.u2, sol.lam, seed=13, amount=0.01)
    r1, r2 = residuals(scene, u1, u2, lam)
    return scene, u1, u2, lam, r1, r2


CASES = [(m, t) for m in MESHES for t in TENSIONS]


#: Agreement with the dense reference, relative to the largest coefficient of the
#: membrane.  The weighted local matrices have condition numbers proportional to
#: the contrast of mu on the patch, and so has the round-off of both solvers:
#: measured at most 3.6e-9 for contrast 1e6 (the reference's dense KKT system is
#: the less accurate of the two) and 2e-12 for contrast 1e3.
REFERENCE_RTOL = {
    "checker-1e6": 1e-8,
    "checker-1e-6": 1e-8,
    "random-both": 1e-8,
    "proportional": 1e-10,
}


@pytest.mark.parametrize(("mesh_name", "tension_name"), CASES)
def test_kernel_matches_weighted_reference(mesh_name, tension_name):
    scene, u1, u2, lam, r1, r2 = case(mesh_name, tension_name)
    ref = naive_flux.naive_reconstruct(scene, u1, u2, lam, r1, r2)
    fl = flux.reconstruct(scene, u1, u2, lam, r1, r2)
    rtol = REFERENCE_RTOL[tension_name]
    for i in range(2):
        assert np.abs(fl.coef[i] - ref[i]).max() <= rtol * np.abs(ref[i]).max()


@pytest.mark.parametrize(("mesh_name", "tension_name"), CASES)
def test_conforming_and_equilibrated_for_jumping_mu(mesh_name, tension_name):
    """Normal continuity and div sigma_ih = Pi f +- lam_h - rho to round-off, jumps up to 1e6."""
    scene, u1, u2, lam, r1, r2 = case(mesh_name, tension_name)
    fl = flux.reconstruct(scene, u1, u2, lam, r1, r2)
    _check_conforming_and_equilibrated(scene, fl, lam, r1, r2)


@pytest.mark.parametrize("mesh_name", list(MESHES))
def test_constant_mu_is_the_unweighted_reconstruction(mesh_name):
    """For constant tensions the weight is a scalar: the same fluxes as the unweighted problem."""
    mesh = MESHES[mesh_name]()
    scene = fm.Scene(mesh, mu=(1e-3, 50.0), f=(-1.0, 1.0), g=0.1)
    sol = fm.solve(scene, method="exact")
    u1, u2, lam = _perturb(mesh, sol.u1, sol.u2, sol.lam, seed=17, amount=0.01)
    unweighted = naive_flux.naive_reconstruct(scene, u1, u2, lam, weighted=False)
    weighted = naive_flux.naive_reconstruct(scene, u1, u2, lam)
    fl = flux.reconstruct(scene, u1, u2, lam)
    for i in range(2):
        scale = np.abs(unweighted[i]).max()
        assert np.abs(weighted[i] - unweighted[i]).max() <= 1e-11 * scale
        assert np.abs(fl.coef[i] - unweighted[i]).max() <= 1e-10 * scale


def test_per_triangle_array_of_a_constant_is_the_constant():
    """mu given per triangle but constant: same fluxes as the scalar (shared factorisation)."""
    mesh = perturbed_square(6, 0.3)
    scalar = fm.Scene(mesh, mu=(2.0, 0.5), f=(-1.0, 1.0), g=0.1)
    arrays = fm.Scene(
        mesh,
        mu=(np.full(mesh.n_triangles, 2.0), np.full(mesh.n_triangles, 0.5)),
        f=(-1.0, 1.0),
        g=0.1,
    )
    sol = fm.solve(scalar, method="exact")
    a = flux.reconstruct(scalar, sol.u1, sol.u2, sol.lam)
    b = flux.reconstruct(arrays, sol.u1, sol.u2, sol.lam)
    assert np.abs(a.coef - b.coef).max() <= 1e-13 * np.abs(a.coef).max()


@pytest.mark.parametrize("redistribute", [True, False, "glued"])
def test_weighted_kernel_with_unit_weights_gives_the_constant_kernels_bits(
    monkeypatch, redistribute
):
    """The two patch kernels of kernels/flux.py on one problem, compared bit for bit.

    Constant tensions passed as per-triangle arrays take the weighted kernel (a
    Scene would turn them back into scalars, so the arrays are made where the
    reconstruction converts them); its weights are then exactly 1.
    """
    from fastmem.kernels import flux as kf

    mesh = perturbed_square(6, 0.3)
    scene = fm.Scene(mesh, mu=(2.0, 0.5), f=(-4.0, 1.0), g=0.1)
    sol = fm.solve(scene, method="exact")
    u1, u2, lam = _perturb(mesh, sol.u1, sol.u2, sol.lam, seed=5, amount=0.01)
    a = flux.reconstruct(scene, u1, u2, lam, redistribute=redistribute)
    m = mesh.n_triangles
    monkeypatch.setattr(flux, "_mu_array", lambda mu: np.full(m, float(mu)))
    b = flux.reconstruct(scene, u1, u2, lam, redistribute=redistribute)
    assert len(kf._reconstruct_chunk_weighted.signatures) == 1  # it ran
    assert np.array_equal(a.coef, b.coef)
    assert np.abs(a.coef).max() > 0.0


def test_weighting_changes_the_flux_only_where_mu_varies():
    """Checkerboard of 1 and 1e3: the weighted and unweighted reconstructions differ."""
    scene, u1, u2, lam, r1, r2 = case("square4", "checker-1e6")
    unweighted = naive_flux.naive_reconstruct(scene, u1, u2, lam, r1, r2, weighted=False)
    fl = flux.reconstruct(scene, u1, u2, lam, r1, r2)
    # membrane 2 has a constant tension: unchanged; membrane 1 jumps: changed
    assert np.abs(fl.coef[1] - unweighted[1]).max() <= 1e-10 * np.abs(unweighted[1]).max()
    assert np.abs(fl.coef[0] - unweighted[0]).max() >= 1e-3 * np.abs(unweighted[0]).max()


# --------------------------------------------------- redistributed contact load


def _checker_scene(mesh, c, f=(-4.0, 2.0)):
    return fm.Scene(mesh, mu=(_checkerboard(mesh, c), 1.0), f=f, g=0.1)


REDIST = {
    # name: (mesh, scene builder, perturb); all have closed-contact patches with mu1 != mu2
    "manufactured-1e-3": (
        lambda: fm.Mesh.square(8),
        lambda m: fm.Manufactured(mu=(1e-3, 1e3)).scene(m),
        False,
    ),
    "checker-1e-3": (lambda: fm.Mesh.square(8), lambda m: _checker_scene(m, 1e-3), False),
    "checker-1e3-perturbed": (
        lambda: perturbed_square(8, 0.3),
        lambda m: _checker_scene(m, 1e3),
        True,
    ),
    "p1-load": (
        lambda: fm.Mesh.square(8),
        lambda m: fm.Scene(
            m, mu=(1e-2, 5.0), f=(-2.0 - m.vertices[:, 0], 1.0 + 0.5 * m.vertices[:, 1]), g=0.1
        ),
        False,
    ),
}


def contact_triple(mesh_fn, scene_fn, perturb, seed):
    """Scene and exact triple (lam zero on the boundary) with its residuals.

    ``perturb``: the same noise (1e-4, ``seed``) on both membranes' interior
    values, an inexact triple (R != 0) with the gap kept.
    """
    mesh = mesh_fn()
    scene = scene_fn(mesh)
    sol = fm.solve(scene, method="exact", estimate=False)
    u1, u2, lam = sol.u1, sol.u2, sol.lam
    if perturb:
        rng = np.random.default_rng(seed)
        inner = mesh.interior_vertices
        noise = 1e-4 * rng.standard_normal(inner.size)
        u1, u2 = u1.copy(), u2.copy()
        u1[inner] += noise
        u2[inner] += noise
    lam = np.where(mesh.boundary_vertex_mask, 0.0, lam)
    r1, r2 = residuals(scene, u1, u2, lam)
    return mesh, scene, u1, u2, lam, r1, r2


@functools.cache
def redist_case(name):
    mesh, scene, u1, u2, lam, r1, r2 = contact_triple(*REDIST[name], seed=23)
    flags, gamma = flux.contact_redistribution(scene, u1, u2, lam)
    assert flags is not None, name
    assert flags.sum() >= 3, name
    fl = flux.reconstruct(scene, u1, u2, lam, r1, r2)
    return scene, u1, u2, lam, r1, r2, flags, gamma, fl


@pytest.mark.parametrize("name", list(REDIST))
def test_redistributed_contact_load_is_admissible(name):
    """ell >= 0, ell = max(lam_h, 0) off the redistributed patches, patch masses B_a lam_a."""
    scene, u1, u2, lam, r1, r2, flags, gamma, fl = redist_case(name)
    mesh = scene.mesh
    tri = mesh.triangles
    b = mesh.lumped_mass
    inner = ~mesh.boundary_vertex_mask
    rho1 = np.where(inner, r1 / b, 0.0)
    lam_minus = np.maximum(lam, 0.0) - lam
    ell = flux.contact_load(scene, fl, rho1, lam_minus)  # (M, 3) vertex values per triangle
    scale = np.abs(ell).max()
    assert ell.min() >= -1e-11 * scale
    touched = flags[tri].any(axis=1)
    assert touched.any()
    assert not touched.all()
    plain = np.maximum(lam, 0.0)[tri]
    assert np.abs(ell[~touched] - plain[~touched]).max() <= 1e-11 * scale
    assert np.abs(ell[touched] - plain[touched]).max() >= 1e-6 * scale  # really redistributed
    # total mass (chi, 1) = sum_a B_a lam_a, chi = ell - lam^- (each patch keeps its
    # mass B_a lam_a; the pieces themselves are checked by the reference test)
    chi = ell - lam_minus[tri]
    total = float((mesh.areas * chi.sum(axis=1)).sum() / 3.0)
    assert abs(total - float(b @ lam)) <= 1e-12 * float(b @ np.abs(lam))


@pytest.mark.parametrize("name", list(REDIST))
def test_redistributed_fluxes_conforming_and_sum_equilibrated(name):
    """Normal continuity; div(sigma_1 + sigma_2) = Pi(f1 + f2) - rho1 - rho2 (lam-free)."""
    scene, u1, u2, lam, r1, r2, flags, gamma, fl = redist_case(name)
    mesh = scene.mesh
    for i in range(2):
        jump, scale = _normal_jump(lambda t, x, y, i=i: fl.evaluate(i, t, x, y), mesh)
        assert jump <= 1e-11 * scale
    total = Fluxes(mesh=mesh, coef=(fl.coef[0] + fl.coef[1])[None])
    both = fm.Scene(
        mesh,
        mu=(scene.mu1, scene.mu2),
        f=(_sum_load(scene), 0.0),
        g=0.1,
        load_degree=scene.load_degree,
    )
    zero = np.zeros(mesh.n_vertices)
    defect, size = _equilibration_defect(
        both, zero, r1 + r2, 0, lambda t, x, y: total.divergence(0, t, x, y)
    )
    assert defect <= 1e-12 * size


def _sum_load(scene):
    f1, f2 = scene.f1, scene.f2
    if callable(f1) or callable(f2):
        return lambda x, y: (f1(x, y) if callable(f1) else f1) + (f2(x, y) if callable(f2) else f2)
    return np.asarray(f1) + np.asarray(f2)


@pytest.mark.parametrize("name", ["checker-1e-3", "checker-1e3-perturbed", "p1-load"])
def test_redistribution_matches_reference(name):
    """Kernel vs the dense reference fed with contact pieces computed here, independently.

    Piece of a redistributed vertex a on triangle K: the L2 projection onto P1(K)
    of psi_a (mu1 f2 - mu2 f1) / (mu1 + mu2) (reference quadrature, dense 3 x 3
    solve), negative vertex values cut to 0, plus gamma_a m_K psi_a with
    m_K = mu1 mu2 / (mu1 + mu2) and gamma_a restoring the mass B_a lam_a.
    """
    scene, u1, u2, lam, r1, r2, flags, _, fl = redist_case(name)
    mesh = scene.mesh
    bary, w = naive_flux.QUAD_BARY, naive_flux.QUAD_W
    mu1 = np.broadcast_to(np.asarray(scene.mu1, float), (mesh.n_triangles,))
    mu2 = np.broadcast_to(np.asarray(scene.mu2, float), (mesh.n_triangles,))
    pieces = {}
    for a in np.flatnonzero(flags):
        own, weight = {}, 0.0
        for k in np.flatnonzero((mesh.triangles == a).any(axis=1)):
            t = mesh.triangles[k]
            la = int(np.flatnonzero(t == a)[0])
            area = mesh.areas[k]
            f_q = [
                bary @ np.asarray(f, float)[t] if np.ndim(f) else np.full(len(w), float(f))
                for f in (scene.f1, scene.f2)
            ]
            glued = (mu1[k] * f_q[1] - mu2[k] * f_q[0]) / (mu1[k] + mu2[k])
            rhs = area * (w * bary[:, la] * glued) @ bary
            mass = area * np.einsum("q,qi,qj->ij", w, bary, bary)
            nodal = np.maximum(np.linalg.solve(mass, rhs), 0.0)
            m_k = mu1[k] * mu2[k] / (mu1[k] + mu2[k])
            own[k] = (nodal, la, m_k)
            weight += m_k * area / 3.0
        total = sum(mesh.areas[k] * nodal.sum() / 3.0 for k, (nodal, _, _) in own.items())
        gamma = (mesh.lumped_mass[a] * lam[a] - total) / weight
        pieces[a] = {k: nodal + gamma * m_k * np.eye(3)[la] for k, (nodal, la, m_k) in own.items()}
    contact = {a: (lambda k, p=p: p[k]) for a, p in pieces.items()}
    ref = naive_flux.naive_reconstruct(scene, u1, u2, lam, r1, r2, contact=contact)
    for i in range(2):
        assert np.abs(fl.coef[i] - ref[i]).max() <= 1e-9 * np.abs(ref[i]).max()
