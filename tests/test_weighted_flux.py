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
from test_flux import _check_conforming_and_equilibrated, _perturb

import fastmem as fm
import fastmem.flux as flux
from fastmem.linear import residuals

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


def test_weighting_changes_the_flux_only_where_mu_varies():
    """Checkerboard of 1 and 1e3: the weighted and unweighted reconstructions differ."""
    scene, u1, u2, lam, r1, r2 = case("square4", "checker-1e6")
    unweighted = naive_flux.naive_reconstruct(scene, u1, u2, lam, r1, r2, weighted=False)
    fl = flux.reconstruct(scene, u1, u2, lam, r1, r2)
    # membrane 2 has a constant tension: unchanged; membrane 1 jumps: changed
    assert np.abs(fl.coef[1] - unweighted[1]).max() <= 1e-10 * np.abs(unweighted[1]).max()
    assert np.abs(fl.coef[0] - unweighted[0]).max() >= 1e-3 * np.abs(unweighted[0]).max()
