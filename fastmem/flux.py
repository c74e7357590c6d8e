r"""Equilibrated flux reconstruction (MATH.md section 4).

For every vertex a and membrane i a mixed RT1 problem on the patch of a is
solved (:mod:`fastmem.kernels.flux`, parallel over vertices); the sum of the
patch solutions is an H(div)-conforming flux :math:`\sigma_{ih}` with

.. math::

    \nabla\cdot\sigma_{1h} = \Pi_K f_1 + \lambda_h - \rho_1, \qquad
    \nabla\cdot\sigma_{2h} = \Pi_K f_2 - \lambda_h - \rho_2 \quad\text{on every } K,

for ANY triple :math:`(u_{1h}, u_{2h}, \lambda_h)`, where
:math:`\rho_i = \sum_a (R_{i,a}/B_a)\psi_a` carries the algebraic residual.

Patch conventions (as in the issue and the standard Ern-Vohralik
construction): interior vertices have zero normal flux on the whole patch
boundary and a mean-zero multiplier; boundary vertices have free normal flux
on patch edges that lie on the boundary of the domain and no mean constraint.

Data: constant loads enter exactly (no quadrature); per-vertex (P1) and
callable loads through the moments :math:`\int_K f\lambda_i\lambda_j` computed
with the same rule as the load vector, so the Neumann compatibility of
interior patches holds to round-off.  With callable data the bound is
guaranteed up to the quadrature error of these data integrals.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numba
import numpy as np

from .assembly import csr_structure
from .errors import DataError
from .kernels import flux as _kf
from .linear import residuals
from .loaddata import integrals

__all__ = ["Fluxes", "reconstruct"]

logger = logging.getLogger(__name__)


@dataclass
class Fluxes:
    """Equilibrated fluxes of both membranes in the canonical RT1 representation.

    Attributes
    ----------
    mesh : Mesh
    coef : ndarray of shape (2, M, 8)
        ``coef[i, K] = [a0, a1, a2, b0, b1, b2, c1, c2]`` of membrane i on
        triangle K, with scaled coordinates ``xi = (x - xc) / h_K``,
        ``eta = (y - yc) / h_K`` about the centroid: ``sigma_x = a0 + a1 xi +
        a2 eta + xi (c1 xi + c2 eta)``, ``sigma_y = b0 + b1 xi + b2 eta + eta
        (c1 xi + c2 eta)``.
    """

    mesh: object
    coef: np.ndarray

    def _scaled(self, tri, x, y):
        mesh = self.mesh
        tri = np.asarray(tri, dtype=np.int64)
        cen = mesh.vertices[mesh.triangles[tri]].mean(axis=1)
        h = mesh.diameters[tri]
        return tri, (np.asarray(x) - cen[:, 0]) / h, (np.asarray(y) - cen[:, 1]) / h, h

    def evaluate(self, i: int, tri, x, y) -> np.ndarray:
        """Values of sigma_i at points (x, y) inside triangles ``tri``; shape (P, 2)."""
        tri, xi, eta, _ = self._scaled(tri, x, y)
        c = self.coef[i, tri]
        quad = c[:, 6] * xi + c[:, 7] * eta
        sx = c[:, 0] + c[:, 1] * xi + c[:, 2] * eta + xi * quad
        sy = c[:, 3] + c[:, 4] * xi + c[:, 5] * eta + eta * quad
        return np.stack([sx, sy], axis=-1)

    def divergence(self, i: int, tri, x, y) -> np.ndarray:
        """Divergence of sigma_i at points (x, y) inside triangles ``tri``; shape (P,)."""
        tri, xi, eta, h = self._scaled(tri, x, y)
        c = self.coef[i, tri]
        return (c[:, 1] + c[:, 5] + 3.0 * c[:, 6] * xi + 3.0 * c[:, 7] * eta) / h


def _coloring(mesh):
    cache = mesh._cache
    if "vertex_colors" not in cache:
        indptr, indices, _ = csr_structure(mesh)
        colors, n_colors = _kf.color_vertices(mesh.n_vertices, indptr, indices)
        if n_colors >= 64:
            raise DataError(f"vertex colouring needs {n_colors} colours; at most 63 supported")
        order = np.argsort(colors, kind="stable")
        ptr = np.zeros(n_colors + 1, dtype=np.int64)
        np.cumsum(np.bincount(colors, minlength=n_colors), out=ptr[1:])
        cache["vertex_colors"] = (order, ptr)
    return cache["vertex_colors"]


def load_moments(scene, i: int):
    """``int_K f_i lambda_j lambda_k`` per triangle, shape (M, 3, 3), or None for constants.

    Cached on the scene by :func:`fastmem.loaddata.integrals` (one evaluation of
    a callable load per mesh, shared with the load vector and the oscillation).
    """
    return integrals(scene, i, moments=True)["moments"]


def _mu_array(mu):
    return np.ascontiguousarray(np.atleast_1d(np.asarray(mu, dtype=np.float64)))


def reconstruct(scene, u1, u2, lam, r1=None, r2=None) -> Fluxes:
    """Equilibrated RT1 fluxes ``sigma_1h``, ``sigma_2h`` of any triple (MATH.md section 4).

    Parameters
    ----------
    scene : Scene
    u1, u2, lam : ndarray of shape (N,)
        Nodal values of the triple (any values: inexact, infeasible, ...).
    r1, r2 : ndarray of shape (N,), optional
        Algebraic residuals of the triple; computed by
        :func:`fastmem.linear.residuals` when omitted.

    Returns
    -------
    Fluxes

    Notes
    -----
    Convenience wrapper around the Numba kernel ``reconstruct_colored``
    (parallel over the vertices of each colour class).
    """
    mesh = scene.mesh
    u1, u2, lam = (np.ascontiguousarray(v, dtype=np.float64) for v in (u1, u2, lam))
    if r1 is None or r2 is None:
        r1, r2 = residuals(scene, u1, u2, lam)
    b = mesh.lumped_mass
    bnd = mesh.boundary_vertex_mask
    rho1 = np.where(bnd, 0.0, r1 / b)
    rho2 = np.where(bnd, 0.0, r2 / b)
    lam_i = np.where(bnd, 0.0, lam)
    moments = []
    consts = []
    for i in (1, 2):
        mom = load_moments(scene, i)
        f = scene.f1 if i == 1 else scene.f2
        consts.append(float(f) if mom is None else 0.0)
        moments.append(np.zeros((1, 3, 3)) if mom is None else mom)
    order, color_ptr = _coloring(mesh)
    coef = _kf.reconstruct_colored(
        order,
        color_ptr,
        mesh.vertices,
        mesh.triangles,
        mesh.diameters,
        mesh.triangle_edges,
        mesh.edge_triangles,
        np.ascontiguousarray(bnd),
        mesh.patch_ptr,
        mesh.patch_triangles,
        mesh.patch_local,
        u1,
        u2,
        lam_i,
        rho1,
        rho2,
        _mu_array(scene.mu1),
        _mu_array(scene.mu2),
        consts[0],
        consts[1],
        moments[0],
        moments[1],
        int(np.diff(mesh.patch_ptr).max()),
        numba.get_num_threads(),
    )
    return Fluxes(mesh=mesh, coef=coef)
