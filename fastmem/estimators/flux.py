r"""Equilibrated flux reconstruction (docs/method.md §4).

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

Per-triangle tensions (issue 16, docs/heterogeneous.md): the patch problems
minimise the mu-weighted norm ``||mu_i^(-1/2)(tau_i^a + v)||`` that eta_F
measures, and on patches in closed contact between membranes of unequal
tension the contact load ``lam_a psi_a`` is replaced by a redistributed load
of the same mass (:func:`contact_redistribution`, the default of
:func:`reconstruct`; the bound uses the glued contact load of
:func:`glued_contact_load` instead, ``redistribute="glued"``); none of this
changes the guarantee, all of it makes the bound sharper when the tensions
differ by orders of magnitude.

Data: constant loads enter exactly (no quadrature); per-vertex (P1) and
callable loads through the moments :math:`\int_K f\lambda_i\lambda_j` computed
with the same rule as the load vector, so the Neumann compatibility of
interior patches holds to round-off.  With callable data the bound is
guaranteed up to the quadrature error of these data integrals.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import numba
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import LinearOperator, cg, splu

from ..errors import DataError
from ..fem.assembly import assemble_stiffness
from ..fem.callables import evaluate_callable
from ..fem.loaddata import integrals
from ..fem.quadrature import quadrature_points, triangle_rule
from ..fem.residual import residuals
from ..kernels import flux as _kf
from ..linalg.amg import amg_preconditioner
from ..mesh.pattern import csr_structure

__all__ = [
    "Fluxes",
    "contact_load",
    "contact_redistribution",
    "cross_point_correction",
    "cross_point_vertices",
    "reconstruct",
]

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
    #: the glued contact load the fluxes equilibrate (``redistribute="glued"``), else None
    contact: object = None

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


#: meshes from this many vertices on reconstruct their patches in sweep order
#: (:func:`_coloring`).  Adapted L-shape mesh of 218k vertices, 7 alternating runs:
#: one thread 0.41 s instead of 0.57 s per reconstruction, two threads 0.26 against
#: 0.27 s.  Below, the order's kernel (0.8 s to compile) would cost more than it saves.
SWEEP_MIN_VERTICES = 100_000


def _colors(mesh):
    """Return ``(order, color_ptr)``: the vertices by colour, in vertex order within each.

    A greedy colouring of the vertex graph (no two vertices of one colour share a
    triangle).  Cached on the mesh.
    """
    cache = mesh._cache
    if "vertex_colors" not in cache:
        indptr, indices, _ = csr_structure(mesh)
        _, n_colors, order, ptr = _kf.color_vertices(mesh.n_vertices, indptr, indices)
        if n_colors >= 64:
            raise DataError(f"vertex colouring needs {n_colors} colours; at most 63 supported")
        cache["vertex_colors"] = (order, ptr)
    return cache["vertex_colors"]


def _coloring(mesh):
    """Return ``(order, color_ptr)`` of :func:`_colors`, each colour in sweep order.

    On meshes of :data:`SWEEP_MIN_VERTICES` and more the vertices of a colour
    follow the smallest triangle of their patch
    (:func:`fastmem.kernels.flux.sweep_order`: the same bits as any other order).
    Made when the fluxes are stored (the banded estimators order their bands
    themselves).  Cached on the mesh.
    """
    order, ptr = _colors(mesh)
    if mesh.n_vertices < SWEEP_MIN_VERTICES:
        return order, ptr
    cache = mesh._cache
    if "vertex_sweep" not in cache:
        args = (mesh.patch_ptr, mesh.patch_triangles, mesh.n_triangles)
        cache["vertex_sweep"] = _kf.sweep_order(order, ptr, *args)
    return cache["vertex_sweep"], ptr


#: meshes from this many vertices on look for patch classes (reused patch factorisations,
#: :func:`fastmem.kernels.flux.patch_classes`).  Below, a flux takes a few tenths of a
#: second and the classes save about half of it, while their kernels cost a first run
#: 10-20 s of compilation (an adaptive test reaching 34k vertices: 36 s cold instead of 15)
PATCH_CLASS_MIN_VERTICES = 100_000
#: ... and from this many vertices on when their kernels are already in the process
#: (``fastmem.warm_up(large=True)``, or an earlier flux on a large mesh): then they cost
#: no compilation.  Adaptive L-shape, f = (-1, -1), alternating in one process after
#: ``warm_up(adaptive=True, large=True)``, medians of 5 with 100,000 and with 5,000: at
#: the eta of uniform n = 512 0.65 -> 0.53 s, n = 1024 1.76 -> 1.59 s, n = 2048
#: 3.49 -> 3.18 s (the same meshes and bits)
PATCH_CLASS_WARM_MIN_VERTICES = 5_000


def patch_arrays(mesh) -> tuple:
    """Return the mesh arrays that :func:`fastmem.kernels.flux.patch_classes` reads."""
    return (
        mesh.vertices,
        mesh.triangles,
        mesh.diameters,
        mesh.triangle_edges,
        mesh.edge_triangles,
        np.ascontiguousarray(mesh.boundary_vertex_mask),
        mesh.patch_ptr,
        mesh.patch_triangles,
        mesh.patch_local,
    )


def find_patch_classes(mesh):
    """Search the mesh's patch classes (:func:`fastmem.kernels.flux.patch_classes`), uncached."""
    max_nt = int(np.diff(mesh.patch_ptr).max())
    return _kf.patch_classes(patch_arrays(mesh), max_nt, numba.get_num_threads())


def patch_classes(mesh, mu1, mu2):
    """Return the mesh's patch classes for a reconstruction with tensions mu1, mu2, or None.

    Only constant tensions share factorisations between patches, and only meshes of
    :data:`PATCH_CLASS_MIN_VERTICES` and more are searched (of
    :data:`PATCH_CLASS_WARM_MIN_VERTICES` and more once the class kernels are in the
    process); the classes (and the factors stored in them on first use) are cached on
    the mesh.  The result has the same bits with or without classes.
    """
    if np.ndim(mu1) or np.ndim(mu2):
        return None
    cache = mesh._cache
    if "patch_classes" in cache:  # (fastmem.warm_up sets them on a small mesh)
        return cache["patch_classes"]
    if mesh.n_vertices < PATCH_CLASS_MIN_VERTICES and (
        mesh.n_vertices < PATCH_CLASS_WARM_MIN_VERTICES or not _kf.classes_compiled()
    ):
        return None
    if "patch_classes" not in cache:
        cache["patch_classes"] = find_patch_classes(mesh)
    return cache["patch_classes"]


def load_moments(scene, i: int):
    """``int_K f_i lambda_j lambda_k`` per triangle, shape (M, 3, 3), or None for constants.

    Cached on the scene by :func:`fastmem.fem.loaddata.integrals` (one evaluation of
    a callable load per mesh, shared with the load vector and the oscillation).
    """
    return integrals(scene, i, moments=True)["moments"]


def _mu_array(mu):
    return np.ascontiguousarray(np.atleast_1d(np.asarray(mu, dtype=np.float64)))


def _closed_contact_vertices(mesh, gap) -> np.ndarray:
    """Interior vertices whose whole patch has ``gap <= 0`` at every vertex (bool (N,)).

    On such a patch :math:`(u_{1h} - u_{2h})^+ = 0`, so redistributing the
    contact load there leaves the complementarity term unchanged.
    """
    closed_tri = (gap[mesh.triangles] <= 0.0).all(axis=1)
    open_count = np.bincount(mesh.triangles[~closed_tri].ravel(), minlength=mesh.n_vertices)
    return (open_count == 0) & ~mesh.boundary_vertex_mask


def contact_redistribution(scene, u1, u2, lam):
    r"""Vertices whose contact load is redistributed, and its mass corrections.

    Parameters
    ----------
    scene : Scene
    u1, u2 : ndarray of shape (N,)
    lam : ndarray of shape (N,)
        Nodal multiplier, zero on the boundary.

    Returns
    -------
    flags : ndarray of bool, shape (N,), or None when no vertex qualifies
    gamma : ndarray of shape (N,), or None

    Notes
    -----
    Only the mass :math:`B_a \lambda_a` of the contact load :math:`\chi^a` of
    patch a is fixed (by the compatibility of both membranes' patch problems);
    its shape is free.  A vertex a is redistributed when it is interior, its
    patch is in closed contact (gap ``<= 0`` at every patch vertex) and
    :math:`\mu_{1,K} \ne \mu_{2,K}` on some patch triangle; then, on each
    patch triangle K, :math:`\chi^a|_K = p_{a,K} + \gamma_a m_K \psi_a` with
    :math:`p_{a,K}` the L2 projection onto P1(K) of

    .. math::

        \psi_a \chi^*, \qquad \chi^* = \frac{\mu_{1,K} f_2 - \mu_{2,K} f_1}
                                      {\mu_{1,K} + \mu_{2,K}}

    with negative vertex values cut to zero, :math:`m_K = \mu_{1,K}\mu_{2,K} /
    (\mu_{1,K} + \mu_{2,K})` and :math:`\gamma_a` restoring the mass (a mass
    defect :math:`\delta` costs about :math:`(\mu_1^{-1} + \mu_2^{-1})\delta^2` in
    the flux terms, so it goes where :math:`m_K` is large: across a material
    interface, to the side where both membranes are stiff).  :math:`\chi^*` is the
    pointwise minimiser of :math:`\mu_1^{-1}|g_1 +
    \chi|^2 + \mu_2^{-1}|g_2 - \chi|^2` (the contact pressure of two glued
    membranes): membrane i receives the fraction :math:`\mu_i / (\mu_1 +
    \mu_2)` of the glued patch data, so a floppy membrane no longer carries,
    with the weight :math:`\mu_{floppy}^{-1/2}` of its flux term, the mismatch
    between the lumped :math:`\lambda_a \psi_a` and the pressure the stiff
    membrane exerts.  The vertex keeps :math:`\lambda_a \psi_a` unless
    :math:`p_{a,K}(x_a) + \gamma_a m_K \ge 0` on every patch triangle: every piece
    is then a non-negative P1 function, so the contact load of the bound,
    :math:`\ell = \sum_{a\ \mathrm{redistributed}} (\chi^a + \lambda^-_a \psi_a)
    + \sum_{\mathrm{others}} \max(\lambda_a, 0) \psi_a`, is P1 and
    non-negative on every triangle (checked once more on the vertex values).
    Equal tensions (:math:`\mu_1 = \mu_2` on the whole patch) are left alone:
    the gain measured there was 1e-6 of eta (manufactured family, mu = (1, 1)),
    and equal-tension results stay those of docs/method.md §4 as written.

    Why the bound holds (docs/heterogeneous.md): with :math:`\chi = \sum_a
    \chi^a`, :math:`\nabla\cdot\sigma_{1h} = \Pi f_1 + \chi - \rho_1` and
    :math:`\nabla\cdot\sigma_{2h} = \Pi f_2 - \chi - \rho_2`; the proof of
    docs/method.md §5 runs with :math:`\ell = \chi + \lambda^- \ge 0` in place
    of :math:`\hat\lambda`: :math:`r_1 = f_1 + \ell - \nabla\cdot\sigma_{1h} =
    (f_1 - \Pi f_1) + \rho_1 + \lambda^-` and :math:`r_2 = (f_2 - \Pi f_2) +
    \rho_2 - \lambda^-` are unchanged (:math:`\ell` is P1 per triangle), the
    contact part gives :math:`(\lambda - \ell, e_1 - e_2) \le (\ell, (u_{1h} -
    u_{2h})^+)`, and :math:`\ell` differs from :math:`\hat\lambda` only on
    triangles of closed patches, where :math:`(u_{1h} - u_{2h})^+ = 0`: c is
    unchanged too.  Only :math:`\eta_F` changes.
    """
    mesh = scene.mesh
    if np.ndim(scene.mu1) == 0 and np.ndim(scene.mu2) == 0 and scene.mu1 == scene.mu2:
        return None, None  # equal constant tensions: nothing to redistribute
    n = mesh.n_vertices
    mu1 = np.broadcast_to(np.asarray(scene.mu1, dtype=np.float64), (mesh.n_triangles,))
    mu2 = np.broadcast_to(np.asarray(scene.mu2, dtype=np.float64), (mesh.n_triangles,))
    unequal = np.bincount(mesh.triangles[mu1 != mu2].ravel(), minlength=n) > 0
    cand = _closed_contact_vertices(mesh, u1 - u2) & unequal
    if not cand.any():
        return None, None
    # only the triangles of candidate patches matter (all of them are here)
    sub = np.flatnonzero(cand[mesh.triangles].any(axis=1))
    tri = mesh.triangles[sub]
    area = mesh.areas[sub]
    mu1, mu2 = mu1[sub], mu2[sub]
    mij = area[:, None, None] / 12.0 * (1.0 + np.eye(3))[None]  # int lambda_i lambda_j
    mom = []
    for i in (1, 2):
        m = load_moments(scene, i)
        mom.append(float(scene.f1 if i == 1 else scene.f2) * mij if m is None else m[sub])
    # (psi_a chi*, lambda_j)_K for a = triangles[K, i]: (M, 3, 3)
    glued = (mu1[:, None, None] * mom[1] - mu2[:, None, None] * mom[0]) / (mu1 + mu2)[:, None, None]
    # vertex values of its L2 projection onto P1(K), M_K^-1 = (12 / |K|) (I - 1 1^T / 4),
    # negative values cut to zero (the kernel does the same)
    pieces = 12.0 / area[:, None, None] * (glued - 0.25 * glued.sum(axis=2, keepdims=True))
    pieces = np.maximum(pieces, 0.0)
    bmass = mesh.lumped_mass
    piece_mass = pieces.sum(axis=2) * (area[:, None] / 3.0)  # (M, 3)
    total = np.bincount(tri.ravel(), weights=piece_mass.ravel(), minlength=n)
    # the mass correction gamma_a m_K psi_a goes where it costs least: the defect
    # delta costs about (1/mu_1 + 1/mu_2) delta^2 in the flux terms, so m_K
    # = mu_1 mu_2 / (mu_1 + mu_2) (all on the stiff side of an interface)
    m_k = mu1 * mu2 / (mu1 + mu2)
    weight = np.bincount(tri.ravel(), weights=np.repeat(m_k * area / 3.0, 3), minlength=n)
    gamma = np.divide(bmass * lam - total, weight, out=np.zeros(n), where=weight > 0.0)
    # the piece of a on K is >= 0 iff its value at a is
    own = pieces[:, [0, 1, 2], [0, 1, 2]] + gamma[tri] * m_k[:, None]  # (M, 3)
    negative = np.bincount(tri[own < 0.0], minlength=n) > 0
    flags = cand & ~negative
    if not flags.any():
        return None, None
    # every piece is >= 0, so ell >= 0; checked anyway (vertex values per triangle)
    lam_hat = np.maximum(lam, 0.0)
    eye = np.eye(3)[None]
    redist = pieces + (gamma[tri] * m_k[:, None] + (lam_hat - lam)[tri])[:, :, None] * eye
    plain = lam_hat[tri][:, :, None] * eye
    ell = np.where(flags[tri][:, :, None], redist, plain).sum(axis=1)
    if (ell < 0.0).any():  # pragma: no cover - excluded by construction
        raise AssertionError("redistributed contact load is negative")
    return flags, gamma


def contact_load(scene, fluxes, rho1, lam_minus) -> np.ndarray:
    """Nodal values per triangle, shape (M, 3), of ``ell = div sigma_1h - Pi f_1 + rho_1 + lam^-``.

    ``ell`` is the contact load the flux of membrane 1 equilibrates plus the
    negative part of lam_h; the bound needs ``ell >= 0`` (it is ``max(lam_h, 0)``
    without redistribution).  P1 on each triangle, so its vertex values decide.
    """
    mesh = scene.mesh
    tri = mesh.triangles
    m = mesh.n_triangles
    tt = np.repeat(np.arange(m), 3)
    pts = mesh.vertices[tri.ravel()]
    div = fluxes.divergence(0, tt, pts[:, 0], pts[:, 1]).reshape(m, 3)
    mom = load_moments(scene, 1)
    if mom is None:
        pif = np.full((m, 3), float(scene.f1))
    else:
        b = mom.sum(axis=1)  # int_K f lambda_j
        pif = 12.0 / mesh.areas[:, None] * (b - 0.25 * b.sum(axis=1, keepdims=True))
    return div - pif + rho1[tri] + lam_minus[tri]


def reconstruct(scene, u1, u2, lam, r1=None, r2=None, redistribute=True, layer=None) -> Fluxes:
    """Equilibrated RT1 fluxes ``sigma_1h``, ``sigma_2h`` of any triple (docs/method.md §4).

    Parameters
    ----------
    scene : Scene
    u1, u2, lam : ndarray of shape (N,)
        Nodal values of the triple (any values: inexact, infeasible, ...).
    r1, r2 : ndarray of shape (N,), optional
        Algebraic residuals of the triple; computed by
        :func:`fastmem.fem.residual.residuals` when omitted.
    redistribute : bool or "glued"
        Redistribute the contact load between the membranes on patches in
        closed contact (default; see Notes).  ``False``: the contact load of
        patch a is ``lam_a psi_a`` everywhere.  ``"glued"``: the glued contact
        load of :func:`glued_contact_load` (what the bound uses, docs/method.md
        §4); the returned ``Fluxes.contact`` then holds it (None when no vertex
        qualifies), and the bound's oscillation and c must be taken with it
        (:func:`fastmem.estimators.terms.contact_local_terms`).
    layer : fastmem.estimators.layers.LayerLoad, optional
        The layer contact load (:func:`fastmem.estimators.layers.layer_load`): the patch
        problems are solved for ``u_i + z_i`` with the contact load chi on its
        triangles and the residuals ``r_i + eps_i``; ``redistribute`` is
        ignored.

    Returns
    -------
    Fluxes

    Notes
    -----
    Convenience wrapper around the Numba kernel ``reconstruct_colored``
    (parallel over the vertices of each colour class).

    Contact load: with ``redistribute`` (default) the contact load of patches
    in closed contact between membranes of unequal tension is redistributed
    (:func:`contact_redistribution`); the bound keeps its guarantee and only
    the flux terms change.  Then ``div sigma_1h = Pi f_1 + chi - rho_1``,
    ``div sigma_2h = Pi f_2 - chi - rho_2`` with ``chi`` P1 on each triangle and
    ``(chi, psi_a) = B_a lam_a`` at every interior vertex.
    """
    order, color_ptr = _coloring(scene.mesh)
    contact, inputs, extra = _patch_inputs(scene, u1, u2, lam, r1, r2, redistribute, layer)
    coef = _kf.reconstruct_colored(order, color_ptr, *inputs, **extra)
    return Fluxes(mesh=scene.mesh, coef=coef, contact=contact)


def _patch_inputs(scene, u1, u2, lam, r1, r2, redistribute, layer):
    """Return the patch kernels' inputs for :func:`reconstruct`: ``(contact, inputs, extra)``.

    ``inputs``: the positional arguments of :func:`fastmem.kernels.flux.reconstruct_colored`
    after the colouring; ``extra``: its keywords.
    """
    mesh = scene.mesh
    u1, u2, lam = (np.ascontiguousarray(v, dtype=np.float64) for v in (u1, u2, lam))
    if r1 is None or r2 is None:
        r1, r2 = residuals(scene, u1, u2, lam)
    if layer is not None:
        redistribute = False
        r1, r2 = r1 + layer.eps1, r2 + layer.eps2
    b = mesh.lumped_mass
    bnd = mesh.boundary_vertex_mask
    rho1 = r1 / b
    rho2 = r2 / b
    lam_i = lam.copy()
    for v in (rho1, rho2, lam_i):  # zeroed by index: one pass over N each, not three
        v[mesh.boundary_vertices] = 0.0
    moments = []
    consts = []
    for i in (1, 2):
        mom = load_moments(scene, i)
        f = scene.f1 if i == 1 else scene.f2
        consts.append(float(f) if mom is None else 0.0)
        moments.append(np.zeros((1, 3, 3)) if mom is None else mom)
    contact = None
    chi_row = chi_mom = None
    if redistribute == "glued":
        flags = gamma = None
        contact = glued_contact_load(scene, u1, u2, lam_i)
        if contact is not None:
            # the kernel adds chi^a's moments (chi^a, lambda_j)_K of the S triangles in
            # contact to membrane 1's load and takes them from membrane 2's; the glued
            # vertices get lam 0 (their contact load is chi^a, not lam_a psi_a)
            chi_row = np.full(mesh.n_triangles, -1, dtype=np.int32)
            chi_row[contact.tri] = np.arange(len(contact.tri), dtype=np.int32)
            chi_mom = contact.moments
            lam_i = np.where(contact.flags, 0.0, lam_i)
    elif redistribute:
        flags, gamma = contact_redistribution(scene, u1, u2, lam_i)
    else:
        flags = gamma = None
    if layer is not None:
        chi_row = np.full(mesh.n_triangles, -1, dtype=np.int32)
        chi_row[layer.tri] = np.arange(len(layer.tri), dtype=np.int32)
        chi_mom = layer.moments
        u1, u2 = u1 + layer.z1, u2 + layer.z2
        for i, extra in enumerate((layer.extra1, layer.extra2)):
            if extra is None:
                continue
            # z broken at cross points: its rest enters membrane i's load moments
            rows, add = extra
            if moments[i].shape[0] == 1:
                mass = (np.eye(3) + 1.0) / 12.0
                full = consts[i] * mesh.areas[:, None, None] * mass
            else:
                full = np.array(moments[i], dtype=np.float64)
            full[rows] += add
            moments[i], consts[i] = full, 0.0
    inputs = (
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
        np.zeros(1, dtype=np.bool_) if flags is None else flags,
        np.zeros(1) if gamma is None else gamma,
        int(np.diff(mesh.patch_ptr).max()),
        numba.get_num_threads(),
    )
    extra = {"chi_row": chi_row, "chi_mom": chi_mom}
    extra["classes"] = patch_classes(mesh, scene.mu1, scene.mu2)
    return contact, inputs, extra


#: the banded estimators (:func:`flux_norms`) need at least this many bands; below, the
#: fluxes are stored (the ring would hold a large part of the mesh anyway)
BAND_MIN = 4
#: ... and meshes of this many vertices (the large meshes' kernels, compiled by
#: ``fastmem.warm_up(large=True)``; below, the stored fluxes take at most 26 MB)
BAND_MIN_VERTICES = 100_000


def band_plan(mesh, band=None):
    """Return the band plan of :func:`fastmem.kernels.flux.band_plan` for ``mesh``, or None.

    Bands of :data:`~fastmem.kernels.flux.BAND_TRIANGLES` triangles (more with many
    threads: :data:`~fastmem.kernels.flux.BAND_TRIANGLES_PER_THREAD` per thread).  None
    when there would be fewer than :data:`BAND_MIN` bands, or when the ring (48 doubles
    per live triangle) would take more than half the memory of the stored fluxes (16
    doubles per triangle): meshes whose patches span far apart triangle numbers, as
    refined meshes do (new triangles are numbered last).
    None also below :data:`BAND_MIN_VERTICES`.
    Cached on the mesh per thread count.  With ``band`` (triangles per band): that
    plan, uncached and whatever its ring (tests, warm-up).
    """
    if band is not None:
        order, color_ptr = _colors(mesh)
        m = mesh.n_triangles
        return _kf.band_plan(order, color_ptr, mesh.patch_ptr, mesh.patch_triangles, m, band)
    threads = numba.get_num_threads()
    cache = mesh._cache.setdefault("flux_bands", {})
    if threads not in cache:
        m = mesh.n_triangles
        band = max(_kf.BAND_TRIANGLES, _kf.BAND_TRIANGLES_PER_THREAD * threads)
        plan = None
        if (
            mesh.n_vertices >= BAND_MIN_VERTICES
            and m >= BAND_MIN * band
            and _sampled_span(mesh) <= m // 6
        ):
            order, color_ptr = _colors(mesh)
            plan = _kf.band_plan(order, color_ptr, mesh.patch_ptr, mesh.patch_triangles, m, band)
            if 48 * plan[3] > 8 * m:
                plan = None
        cache[threads] = plan
    return cache[threads]


def _sampled_span(mesh, samples=4096) -> int:
    """Return the largest ``max - min`` triangle number of a patch, over a strided sample.

    A lower bound of the ring a band plan needs (:func:`band_plan`): on a refined mesh,
    where old vertices have new triangles, it is of the order of the mesh and the plan
    is not made (nor its kernel compiled).  NumPy, O(samples).
    """
    ptr, tri = mesh.patch_ptr, mesh.patch_triangles
    a = np.arange(0, mesh.n_vertices, max(1, mesh.n_vertices // samples))
    lens = ptr[a + 1] - ptr[a]
    offsets = np.cumsum(lens) - lens
    idx = np.repeat(ptr[a] - offsets, lens) + np.arange(int(lens.sum()))
    vals = tri[idx]
    return int((np.maximum.reduceat(vals, offsets) - np.minimum.reduceat(vals, offsets)).max())


def flux_norms(scene, u1, u2, lam, r1=None, r2=None, plan=None):
    """Return ``(eta_F1, eta_F2, contact)`` of the glued fluxes, or None (then store them).

    The per-triangle flux estimators of :func:`fastmem.estimators.bound.flux_terms`
    for ``reconstruct(scene, u1, u2, lam, r1, r2, redistribute="glued")``, bit for
    bit, computed band by band without storing the fluxes
    (:func:`fastmem.kernels.flux.flux_norms_banded`): 48 doubles per triangle of one
    band instead of 16 per triangle of the mesh (at n = 1024 the fluxes are 268 MB,
    new memory at every evaluation).  For constant tensions only (per-triangle
    tensions may need the cross-point correction, which changes the fluxes); None
    there and on meshes without a band plan (:func:`band_plan`).  ``plan``: a plan
    to use instead of the mesh's (tests).
    """
    mesh = scene.mesh
    if np.ndim(scene.mu1) or np.ndim(scene.mu2):
        return None
    if plan is None:
        plan = band_plan(mesh)
        if plan is None:
            return None
    contact, inputs, extra = _patch_inputs(scene, u1, u2, lam, r1, r2, "glued", None)
    norms = banded_norms(mesh, plan, inputs, extra)
    return norms[0], norms[1], contact


def banded_norms(mesh, plan, inputs, extra) -> np.ndarray:
    """Run :func:`fastmem.kernels.flux.flux_norms_banded` with the mesh's ring; norms (2, M).

    ``inputs``, ``extra``: the arguments of :func:`fastmem.kernels.flux.reconstruct_colored`
    after its colouring, and its keywords; the rule of :func:`~fastmem.estimators.bound.flux_terms`.
    The ring is taken from the mesh's cache while in use (a concurrent evaluation
    makes its own) and put back, all zero again, for the next evaluation.
    """
    bary, w = triangle_rule(5)
    rule = np.ascontiguousarray(bary), np.ascontiguousarray(w)
    window = mesh._cache.pop("flux_window", None)
    norms, window = _kf.flux_norms_banded(plan, *rule, *inputs, window=window, **extra)
    mesh._cache["flux_window"] = window
    return norms


# --- divergence-free correction at non-quasi-monotone vertices (issue 16) -------------

#: patch contrast max/min from which a checkerboard-like vertex is corrected
CROSS_POINT_CONTRAST = 10.0
#: triangle rings grown around a corrected vertex (measured: the gain grows like log k)
CROSS_POINT_RINGS = 3
#: the correction is skipped when its region exceeds this many triangles and this
#: fraction of the mesh (random per-triangle tensions: nearly every vertex qualifies)
CROSS_POINT_MAX_TRIANGLES = 20000
CROSS_POINT_MAX_FRACTION = 0.05
#: the stream functions of the correction include the global P1 ones (Kellogg's cross
#: point, contrast 1e3, n = 32: eta_F / error 6.28 with the rings alone, 1.08 with them)
CROSS_POINT_GLOBAL = True
#: the joint system is factorised up to this many vertices, else solved by AMG-CG
CROSS_POINT_DIRECT_VERTICES = 300_000
#: relative residual and iteration cap of that CG (any iterate is a valid correction;
#: checkerboard 1e3, n = 256: eta_F1 within 0.5 % of the minimiser after 5 iterations,
#: within 1e-4 after 10)
CROSS_POINT_CG_TOL = 1e-6
CROSS_POINT_CG_MAXITER = 10


def cross_point_vertices(mesh, mu, contrast=CROSS_POINT_CONTRAST) -> np.ndarray:
    r"""Interior vertices where the tension is not quasi-monotone (bool (N,)).

    Around vertex a, call a patch triangle high if
    :math:`\mu_K \ge (\max_{\omega_a}\mu\,\min_{\omega_a}\mu)^{1/2}`.  The vertex
    is marked when the high triangles form at least two separate runs in the
    cyclic order around a (checkerboard cross points: the stiff material
    touches a only through the vertex itself) and :math:`\max/\min \ge`
    ``contrast``.

    Around an interior vertex the runs of high triangles are counted without
    sorting by angle: every edge (a, b) separates two consecutive triangles of
    the patch of a, and each run of high triangles begins and ends at such an
    edge, so the number of runs is half the number of edges at a whose two
    triangles differ (high/low with a's threshold).  One pass over the edges
    (O(E), no loop over vertices, no sort); tests/estimators/test_cross_point.py checks it
    against an angle-sorting reference.
    """
    mu = np.asarray(mu, dtype=np.float64)
    n = mesh.n_vertices
    if mu.ndim == 0:
        return np.zeros(n, dtype=bool)
    ptr = mesh.patch_ptr
    mus = mu[mesh.patch_triangles]
    starts = ptr[:-1]
    big = np.maximum.reduceat(mus, starts)
    small = np.minimum.reduceat(mus, starts)
    del mus
    candidate = (big >= contrast * small) & ~mesh.boundary_vertex_mask
    if not candidate.any():
        return np.zeros(n, dtype=bool)
    thresh = np.sqrt(big * small)
    et = mesh.edge_triangles
    ev = mesh.edges
    inner = np.flatnonzero((et[:, 1] >= 0) & (candidate[ev[:, 0]] | candidate[ev[:, 1]]))
    mu_a = mu[et[inner, 0]]
    mu_b = mu[et[inner, 1]]
    transitions = np.zeros(n, dtype=np.int64)
    for end in (0, 1):
        v = ev[inner, end]
        th = thresh[v]
        differ = (mu_a >= th) != (mu_b >= th)
        transitions += np.bincount(v[differ], minlength=n)
    return candidate & (transitions >= 4)


def _p2_gradients(grads, bary):
    """Gradients of the six P2 basis functions at barycentric points: (R, nq, 6, 2).

    Order: the vertex functions ``l_i (2 l_i - 1)``, then the edge functions
    ``4 l_j l_k`` of local edge i (opposite vertex i: (1, 2), (2, 0), (0, 1)).
    """
    lam = np.asarray(bary, dtype=np.float64)  # (nq, 3)
    gv = (4.0 * lam - 1.0)[None, :, :, None] * grads[:, None, :, :]
    return np.concatenate([gv, _bubble_gradients(grads, lam)], axis=2)


def _bubble_gradients(grads, lam):
    """Gradients of the edge bubbles 4 l_j l_k (edges (1, 2), (2, 0), (0, 1)): (R, nq, 3, 2)."""
    ge = [
        4.0
        * (
            lam[None, :, j, None] * grads[:, None, k, :]
            + lam[None, :, k, None] * grads[:, None, j, :]
        )
        for j, k in ((1, 2), (2, 0), (0, 1))
    ]
    return np.stack(ge, axis=2)


def _cross_point_setup(scene, i: int, rings: int):
    """Return the part of :func:`cross_point_correction` that depends on mesh and tension only.

    Membrane ``i`` (0 or 1): the region, its P2 numbering and the factorised
    weighted P2 stiffness matrix on the free degrees of freedom, or None when
    no vertex qualifies or the region is too large.  Cached on the scene (a
    Scene is immutable), so the estimator evaluations of a solve classify the
    vertices and factorise once.
    """
    cache = getattr(scene, "_cache", None)
    key = ("cross_point", i, rings)
    if cache is not None and key in cache:
        return cache[key]
    setup = _build_cross_point_setup(scene.mesh, (scene.mu1, scene.mu2)[i], rings, i)
    if cache is not None:
        cache[key] = setup
    return setup


def _build_cross_point_setup(mesh, mu, rings: int, i: int):

    marked = cross_point_vertices(mesh, mu)
    if not marked.any():
        return None
    tri_all = mesh.triangles
    vm = marked.copy()
    for _ in range(rings):
        vm[tri_all[vm[tri_all].any(axis=1)].ravel()] = True
    region = vm[tri_all].any(axis=1)
    nreg = int(region.sum())
    if nreg > CROSS_POINT_MAX_TRIANGLES and nreg > CROSS_POINT_MAX_FRACTION * mesh.n_triangles:
        logger.debug("cross-point correction, membrane %d: skipped (%d triangles)", i + 1, nreg)
        return None
    rt = np.flatnonzero(region)
    tri = tri_all[rt]
    n = mesh.n_vertices
    dofs = np.concatenate([tri, n + mesh.triangle_edges[rt].astype(np.int64)], axis=1)
    out = np.flatnonzero(~region)
    fixed = np.zeros(n + mesh.n_edges, dtype=bool)
    fixed[tri_all[out].ravel()] = True
    fixed[n + mesh.triangle_edges[out].ravel().astype(np.int64)] = True
    mu_k = np.broadcast_to(np.asarray(mu, dtype=np.float64), (mesh.n_triangles,))[rt]
    wt = mesh.areas[rt] / mu_k
    bary, w = triangle_rule(4)
    g = _p2_gradients(mesh.gradients[rt], bary)  # (R, nq, 6, 2)
    kloc = np.einsum("r,q,rqid,rqjd->rij", wt, w, g, g)
    used, local = np.unique(dofs, return_inverse=True)
    local = local.reshape(dofs.shape)
    free = ~fixed[used]
    if free.all():
        free[0] = False  # the region is the whole mesh: phi up to a constant
    idx = np.flatnonzero(free)
    if idx.size == 0:
        return None
    nu = used.size
    rows = np.repeat(local, 6, axis=1).ravel()
    cols = np.tile(local, (1, 6)).ravel()
    a = sp.csr_matrix((kloc.ravel(), (rows, cols)), shape=(nu, nu))
    # factorised on the first ring step only: the default joint correction
    # (_joint_setup) uses the region, not this matrix
    inner = a[idx][:, idx].tocsc()
    return {
        "rt": rt,
        "tri": tri,
        "local": local,
        "idx": idx,
        "wt": wt,
        "mu_k": mu_k,
        "n_dofs": nu,
        "matrix": inner,
        "lu": None,
    }


def cross_point_correction(
    scene, u1, u2, fluxes: Fluxes, rings=CROSS_POINT_RINGS, glob=None
) -> Fluxes:
    r"""Lower :math:`\eta_F` at non-quasi-monotone vertices by a divergence-free correction.

    Parameters
    ----------
    scene : Scene
    u1, u2 : ndarray of shape (N,)
    fluxes : Fluxes
        Equilibrated fluxes (:func:`reconstruct`); not modified.
    rings : int
        Triangle rings grown around each marked vertex.
    glob : bool, optional
        Add the global P1 stream functions to the rings' P2 ones (below);
        default :data:`CROSS_POINT_GLOBAL`; False for the rings alone.

    Returns
    -------
    Fluxes
        ``fluxes`` itself when no vertex qualifies, else corrected fluxes with
        the same divergence and normal traces on every edge outside the
        corrected regions.

    Notes
    -----
    Why (docs/heterogeneous.md §3): at a checkerboard cross point the patch
    problems localise with the hat function of one vertex, whose patch joins
    the two stiff sectors only through the soft ones; the sum of the patch
    fluxes then carries an O(1) mismatch in the first ring of triangles that
    does not decrease with h (checkerboard c = 1e3: 0.047 of eta_F = 0.048 at
    n = 128), while the best RT1 flux with the same divergence spreads it over
    the neighbourhood (0.032 globally).

    What: on the region :math:`\omega` of ``rings`` triangle rings around the
    marked vertices (:func:`cross_point_vertices`, per membrane with
    per-triangle tension), minimise

    .. math::

        \|\mu_i^{-1/2}(\mu_i\nabla u_{ih} + \sigma_{ih} + \mathrm{curl}\,\phi)\|_\omega
        \quad\text{over } \phi \in P_2(\omega)\cap C^0,\ \phi = 0 \text{ at every
        degree of freedom shared with a triangle outside } \omega,

    with :math:`\mathrm{curl}\,\phi = (\partial_y\phi, -\partial_x\phi)` (normal
    equations: the P2 stiffness matrix with weight :math:`\mu_i^{-1}`), and add
    :math:`\mathrm{curl}\,\phi` to :math:`\sigma_{ih}`.

    Why the bound is unchanged (proof).  :math:`\mathrm{curl}\,\phi` is a P1
    vector field on each triangle, hence in RT1(K), and :math:`\nabla\cdot
    \mathrm{curl}\,\phi = 0` on every triangle: the divergence identities of
    docs/method.md §4 hold as before.  Its normal component on an edge is the
    tangential derivative of :math:`\phi` along the edge, which is single-valued
    because :math:`\phi` is continuous (normal continuity inside
    :math:`\omega`), and zero on every edge of a triangle outside
    :math:`\omega` because :math:`\phi` vanishes on that whole edge (all three
    P2 degrees of freedom of the edge are fixed to 0).  Extended by zero,
    :math:`\mathrm{curl}\,\phi \in H(\mathrm{div}, \Omega)` with zero
    divergence, so :math:`\sigma_{ih} + \mathrm{curl}\,\phi` is as admissible
    as :math:`\sigma_{ih}` in the proof of docs/method.md §5 (on
    :math:`\partial\Omega` the normal flux is free: the error vanishes there).
    :math:`\phi = 0` is admissible, so :math:`\sum_{K\subset\omega}\eta_{F,K,i}^2`
    cannot increase (up to round-off) and outside :math:`\omega` nothing
    changes.

    Global part (``glob``).  The rings cannot carry what a cross point needs:
    the error of :math:`u_{ih}` there is Kellogg's singular function
    (:mod:`fastmem.problems.kellogg`), whose flux spreads over every dyadic annulus up
    to the boundary, while the patch fluxes put the whole mismatch into the
    first ring (Kellogg, contrast 1e6, n = 32: 3.4e4 of :math:`\eta_F^2` =
    3.4e4 there; the best RT1 flux with the same divergence has 0.27 there and
    about 0.11 in each annulus, against an error of 0.70).  A stream function
    that vanishes on the rings' boundary pays for that with a cut-off that
    decays only like 1/log(rings).  So :math:`\phi` ranges over the continuous
    P1 functions on the whole mesh, free on :math:`\partial\Omega`, plus the
    P2 edge bubbles of the rings (hierarchical basis: the rings' P2 space with
    its vertex values in the P1 part), one joint SPD system with weight
    :math:`\mu_i^{-1}` and one vertex pinned (:func:`_joint_setup`).  Measured
    on Kellogg's solution, n = 32: η_F / error 1.165, 1.081, 1.003 at
    contrasts 161, 1e3, 1e6, equal to the global P2 minimiser to 3 digits
    (rings alone: 2.87, 6.28, 182).  The proof above holds for this
    :math:`\phi`: continuous, P2 on each triangle, so :math:`\mathrm{curl}\,
    \phi` is in RT1, divergence-free, with single-valued normal components;
    no boundary condition is needed because the normal flux on
    :math:`\partial\Omega` is free.  The system is solved exactly up to
    :data:`CROSS_POINT_DIRECT_VERTICES` vertices, else by CG from 0 (which
    lowers the quadratic from its first iterate on); a solution whose gain
    :math:`2b^T\phi - \phi^TK\phi` is not positive is dropped, so
    :math:`\eta_F` never increases.

    The regions of all marked vertices form one sparse SPD system
    (no loop over vertices); it is skipped when they cover more than
    ``CROSS_POINT_MAX_FRACTION`` of the mesh and ``CROSS_POINT_MAX_TRIANGLES``
    triangles (random per-triangle tensions, where every vertex qualifies and
    a global solve would cost more than the reconstruction).
    """
    if glob is None:
        glob = CROSS_POINT_GLOBAL
    mesh = scene.mesh
    coef = None
    bary, w = triangle_rule(4)
    for i, u in enumerate((u1, u2)):
        setup = _cross_point_setup(scene, i, rings)
        if setup is None:
            continue
        if coef is None:
            coef = fluxes.coef.copy()
        u = np.asarray(u, dtype=np.float64)
        if glob:
            _joint_step(mesh, coef, i, u, _joint_setup(scene, i, rings, setup))
        else:
            _ring_step(mesh, coef, i, u, setup, bary, w)
    return fluxes if coef is None else Fluxes(mesh=mesh, coef=coef, contact=fluxes.contact)


def _add_p1_field(coef_i, rt, h, mean, slope):
    """Add a P1 vector field (centroid value, gradient) to RT1 coefficients of triangles rt.

    ``rt = None``: every triangle, in place (no gather/scatter copies).
    """
    if rt is None:
        coef_i[:, 0] += mean[:, 0]
        coef_i[:, 3] += mean[:, 1]
        return
    c = coef_i[rt]
    c[:, 0] += mean[:, 0]
    c[:, 3] += mean[:, 1]
    if slope is not None:
        c[:, 1] += h * slope[:, 0, 0]
        c[:, 2] += h * slope[:, 0, 1]
        c[:, 4] += h * slope[:, 1, 0]
        c[:, 5] += h * slope[:, 1, 1]
    coef_i[rt] = c


def _ring_step(mesh, coef, i, u, setup, bary, w):
    r"""Minimise over the P2 stream functions of the rings; add curl phi; return the gain.

    The gain is the decrease of :math:`\|\mu_i^{-1/2}(\mu_i\nabla u_{ih} +
    \sigma_{ih})\|^2`, :math:`b^T\phi` for the exact minimiser.
    """
    rt, tri, local, idx, wt = (setup[k] for k in ("rt", "tri", "local", "idx", "wt"))
    mu_k = setup["mu_k"]
    g = _p2_gradients(mesh.gradients[rt], bary)  # (R, nq, 6, 2)
    x, y = quadrature_points(mesh.vertices, tri, bary)
    nq = x.shape[1]
    current = Fluxes(mesh=mesh, coef=coef)
    sig = current.evaluate(i, np.repeat(rt, nq), x.ravel(), y.ravel()).reshape(-1, nq, 2)
    gu = np.einsum("rk,rkd->rd", u[tri], mesh.gradients[rt])
    s = mu_k[:, None, None] * gu[:, None, :] + sig
    # -(mu^-1 s, curl psi_j), curl psi = (d_y psi, -d_x psi)
    bloc = -np.einsum("r,q,rqj->rj", wt, w, s[..., 0:1] * g[..., 1] - s[..., 1:2] * g[..., 0])
    nu = setup["n_dofs"]
    b = np.bincount(local.ravel(), weights=bloc.ravel(), minlength=nu)
    phi = np.zeros(nu)
    if setup["lu"] is None:
        setup["lu"] = splu(setup.pop("matrix"))
    phi[idx] = setup["lu"].solve(b[idx])
    ph = phi[local]  # (R, 6)
    gv = np.einsum("rj,rkjd->rkd", ph, _p2_gradients(mesh.gradients[rt], np.eye(3)))
    curl = np.stack([gv[..., 1], -gv[..., 0]], axis=-1)  # (R, 3 vertices, 2)
    mean = curl.mean(axis=1)  # value at the centroid
    slope = np.einsum("rkc,rkd->rcd", curl, mesh.gradients[rt])  # d(curl_c)/dx_d
    _add_p1_field(coef[i], rt, mesh.diameters[rt], mean, slope)
    return max(float(b[idx] @ phi[idx]), 0.0)


def _joint_setup(scene, i: int, rings: int, ring_setup):
    r"""Joint system of the global P1 stream functions and the rings' edge bubbles (cached).

    Unknowns: the N vertex values (vertex 0 pinned) and one bubble
    :math:`4\lambda_j\lambda_k` per ring edge that the P2 ring space leaves free.
    Matrix: :math:`(\mu_i^{-1}\,\mathrm{curl}\,\psi, \mathrm{curl}\,\chi)`, i.e. the
    P1 stiffness matrix with weight :math:`\mu_i^{-1}` bordered by the bubbles'
    rows on the ring triangles (exact with the 3-point rule: the integrands are
    quadratic).
    """
    cache = getattr(scene, "_cache", None)
    key = ("cross_point_joint", i, rings)
    if cache is not None and key in cache:
        return cache[key]

    mesh = scene.mesh
    n = mesh.n_vertices
    mu = np.broadcast_to(
        np.asarray((scene.mu1, scene.mu2)[i], dtype=np.float64), (mesh.n_triangles,)
    )
    rt = ring_setup["rt"]
    region = np.zeros(mesh.n_triangles, dtype=bool)
    region[rt] = True
    fixed = np.zeros(mesh.n_edges, dtype=bool)
    fixed[mesh.triangle_edges[~region].ravel()] = True
    te = mesh.triangle_edges[rt].astype(np.int64)  # (R, 3): edge i opposite vertex i
    free_edges = np.flatnonzero(np.bincount(te.ravel(), minlength=mesh.n_edges) > 0)
    free_edges = free_edges[~fixed[free_edges]]
    bubble = np.full(mesh.n_edges, -1, dtype=np.int64)
    bubble[free_edges] = n + np.arange(free_edges.size)
    nb = free_edges.size
    bary, w = triangle_rule(2)
    g = _hier_gradients(mesh.gradients[rt], bary)  # (R, nq, 6, 2)
    wt = mesh.areas[rt] / mu[rt]
    kloc = np.einsum("r,q,rqid,rqjd->rij", wt, w, g, g)
    dofs = np.concatenate([mesh.triangles[rt], bubble[te]], axis=1)  # -1: fixed bubble
    keep = np.zeros((rt.size, 6, 6), dtype=bool)
    keep[:, :, 3:] = dofs[:, None, 3:] >= 0
    keep[:, 3:, :] |= dofs[:, 3:, None] >= 0
    keep &= (dofs[:, :, None] >= 0) & (dofs[:, None, :] >= 0)
    rows = np.broadcast_to(dofs[:, :, None], keep.shape)[keep]
    cols = np.broadcast_to(dofs[:, None, :], keep.shape)[keep]
    a = assemble_stiffness(mesh, 1.0 / mu).tocsr()
    k = sp.block_diag([a, sp.csr_matrix((nb, nb))], format="csr")
    k = (k + sp.csr_matrix((kloc[keep], (rows, cols)), shape=k.shape)).tocsr()
    inner = k[1:, 1:].tocsr()
    if n <= CROSS_POINT_DIRECT_VERTICES:
        solve = splu(inner.tocsc()).solve
    else:
        ml = amg_preconditioner(a[1:, 1:].tocsr())  # the solver's SA setup and V-cycle
        bb = k[n:, n:].tocsc()
        lu_b = splu(bb) if nb else None
        m1 = n - 1

        def prec(r):
            out = np.empty_like(r)
            out[:m1] = ml(r[:m1])
            if nb:
                out[m1:] = lu_b.solve(r[m1:])
            return out

        pre = LinearOperator(inner.shape, matvec=prec, dtype=np.float64)

        def solve(b):
            x, _ = cg(inner, b, rtol=CROSS_POINT_CG_TOL, maxiter=CROSS_POINT_CG_MAXITER, M=pre)
            return x

    setup = {
        "k": k,
        "solve": solve,
        "mu": mu,
        "rt": rt,
        "dofs": dofs,
        "n_dofs": n + nb,
        "moments": _second_moments(mesh),
    }
    if cache is not None:
        cache[key] = setup
    return setup


def _hier_gradients(grads, bary):
    """Gradients of the hierarchical P2 basis (lambda_i, 4 lambda_j lambda_k): (R, nq, 6, 2)."""
    lam = np.asarray(bary, dtype=np.float64)
    gv = np.broadcast_to(grads[:, None, :, :], (grads.shape[0], lam.shape[0], 3, 2))
    return np.concatenate([gv, _bubble_gradients(grads, lam)], axis=2)


def _second_moments(mesh):
    """``<xi^2>, <xi eta>, <eta^2>`` per triangle in the scaled coordinates of :class:`Fluxes`."""
    v = mesh.vertices[mesh.triangles]
    d = (v - v.mean(axis=1, keepdims=True)) / mesh.diameters[:, None, None]
    xx = (d[:, :, 0] * d[:, :, 0]).sum(axis=1) / 12.0
    xy = (d[:, :, 0] * d[:, :, 1]).sum(axis=1) / 12.0
    yy = (d[:, :, 1] * d[:, :, 1]).sum(axis=1) / 12.0
    return xx, xy, yy


def _rt1_means(mesh, c, moments=None):
    r"""Triangle means of the RT1 fields with coefficients ``c`` (M, 8) of :class:`Fluxes`.

    In the scaled coordinates about the centroid the mean of xi is 0 and the
    second moments are :math:`\frac1{12}\sum_k d_k d_k^T / h^2` (d_k the vertices
    relative to the centroid), so sigma_x averages to ``a0 + c1 <xi^2> + c2 <xi eta>``
    and sigma_y to ``b0 + c1 <xi eta> + c2 <eta^2>``.
    """
    xx, xy, yy = _second_moments(mesh) if moments is None else moments
    return np.stack(
        [c[:, 0] + c[:, 6] * xx + c[:, 7] * xy, c[:, 3] + c[:, 6] * xy + c[:, 7] * yy], axis=1
    )


def _joint_step(mesh, coef, i, u, setup):
    r"""Minimise over the joint stream functions; add :math:`\mathrm{curl}\,\phi`; return the gain.

    Right-hand side :math:`-(\mu_i^{-1} s, \mathrm{curl}\,\psi)` with
    :math:`s = \mu_i\nabla u_{ih} + \sigma_{ih}`: for the P1 part only the
    triangle means of s enter (its curl is constant; :func:`_rt1_means`), for the bubbles the
    4-point-exact rule on the ring triangles (s quadratic, curl linear).
    """
    mu, rt, dofs = setup["mu"], setup["rt"], setup["dofs"]
    grads = mesh.gradients
    current = Fluxes(mesh=mesh, coef=coef)
    gu = np.einsum("rk,rkd->rd", u[mesh.triangles], grads)
    s = _rt1_means(mesh, coef[i], setup["moments"]) + mu[:, None] * gu
    wt = mesh.areas / mu
    bloc = -wt[:, None] * (s[:, 0:1] * grads[:, :, 1] - s[:, 1:2] * grads[:, :, 0])
    b = np.zeros(setup["n_dofs"])
    b[: mesh.n_vertices] = np.bincount(
        mesh.triangles.ravel(), weights=bloc.ravel(), minlength=mesh.n_vertices
    )
    # bubbles: s at the points of a rule exact for degree 3 on the ring triangles
    b4, w4 = triangle_rule(4)
    xr, yr = quadrature_points(mesh.vertices, mesh.triangles[rt], b4)
    nr = xr.shape[1]
    sr = current.evaluate(i, np.repeat(rt, nr), xr.ravel(), yr.ravel()).reshape(rt.size, nr, 2)
    sr = sr + (mu[rt, None] * gu[rt])[:, None, :]
    gb = _hier_gradients(grads[rt], b4)[:, :, 3:, :]  # (R, nq, 3, 2)
    cb = sr[..., 0:1] * gb[..., 1] - sr[..., 1:2] * gb[..., 0]  # (R, nq, 3)
    bb = -np.einsum("r,q,rqj->rj", wt[rt], w4, cb)
    own = dofs[:, 3:] >= 0
    b += np.bincount(dofs[:, 3:][own], weights=bb[own], minlength=setup["n_dofs"])
    phi = np.zeros(setup["n_dofs"])
    phi[1:] = setup["solve"](b[1:])
    gain = 2.0 * float(b @ phi) - float(phi @ (setup["k"] @ phi))
    if not gain > 0.0:
        return 0.0
    # P1 part: constant curl on every triangle
    gp = np.einsum("rk,rkd->rd", phi[mesh.triangles], grads)
    _add_p1_field(coef[i], None, None, np.stack([gp[:, 1], -gp[:, 0]], axis=1), None)
    # bubbles: linear curl on the ring triangles, from its vertex values
    pb = np.where(own, phi[np.maximum(dofs[:, 3:], 0)], 0.0)  # (R, 3)
    gv = np.einsum("rj,rkjd->rkd", pb, _hier_gradients(grads[rt], np.eye(3))[:, :, 3:, :])
    curl = np.stack([gv[..., 1], -gv[..., 0]], axis=-1)  # (R, 3 vertices, 2)
    slope = np.einsum("rkc,rkd->rcd", curl, grads[rt])
    _add_p1_field(coef[i], rt, mesh.diameters[rt], curl.mean(axis=1), slope)
    return gain


# --- glued contact load for the bound (issue 16, constant and per-triangle tensions) ---

#: bisection steps for the shift gamma_a of the vertices whose shifted glued
#: pressure is clipped at 0 (the final mass is made exact by a rescaling)
GLUED_BISECTION_STEPS = 30
#: partially closed patches: constant of the cost model of :func:`_keep_plain`
#: (smaller glues more).  Measured at n = 16, 32, 64: the manufactured (1e-6, 1e6)
#: and (1, 1e-6) effectivities are the same for every value in 0.01 ... 100; the
#: checkerboard c = 1e-3, f = (-1, 1) needs >= 1 at n = 64 (0.1: eta 0.163 instead
#: of 0.135, boundary-layer vertices glued); 10 is the middle of the common range
GLUED_COST = 10.0


@dataclass
class ContactLoad:
    r"""The contact load :math:`\chi` of the bound's flux (:func:`glued_contact_load`).

    Attributes
    ----------
    flags : ndarray of bool, shape (N,)
        Glued vertices a: :math:`\chi^a = s_a\psi_a(\zeta + \gamma_a m_K)^+` on
        the closed triangles of their patch and 0 on the others; every other
        vertex keeps :math:`\lambda_a \psi_a`.
    gamma, scale : ndarray of shape (N,)
        :math:`\gamma_a` and :math:`s_a > 0` on glued vertices (0 elsewhere).
    tri : ndarray of int, shape (S,)
        The closed triangles with at least one glued vertex (where :math:`\chi`
        is not :math:`\sum_a \lambda_a\psi_a`).
    moments : ndarray of shape (S, 3, 3)
        ``(chi^a, lambda_j)_K`` for a = ``triangles[K, i]`` glued (row i), 0 in
        the rows of the other vertices.
    osc1, osc2 : ndarray of shape (S,)
        :math:`\frac{h_K}{\pi}\mu_{i,K}^{-1/2}\|q_i - \Pi_K q_i\|_K` with
        :math:`q_1 = f_1 + \chi`, :math:`q_2 = f_2 - \chi` on those triangles.
    ell_min : float
        Smallest value of :math:`\ell = \chi + \lambda^-` at the points where it
        was evaluated on ``tri`` (vertices and quadrature points): >= 0.
    """

    flags: np.ndarray
    gamma: np.ndarray
    scale: np.ndarray
    tri: np.ndarray
    moments: np.ndarray
    osc1: np.ndarray
    osc2: np.ndarray
    ell_min: float

    def open_load(self, lam) -> np.ndarray:
        r"""Nodal values of :math:`\ell` on the triangles that are not closed.

        There :math:`\ell = \sum_{a\ \mathrm{plain}} \max(\lambda_a, 0)\psi_a`
        (glued vertices put nothing on open triangles and have
        :math:`\lambda_a > 0`): the P1 function whose product with the gap is c.
        """
        return np.where(self.flags, 0.0, np.maximum(lam, 0.0))


def _load_values(scene, i, tri, x, y, bary):
    """Values of f_i at the points ``(x, y)`` (S, nq) of triangles ``tri``."""
    f = scene.f1 if i == 1 else scene.f2
    kind = scene.data_kind(f"f{i}")
    if kind == "callable":
        return evaluate_callable(f, x, y, f"f{i}")
    if kind == "constant":
        return np.full(x.shape, float(f))
    return np.asarray(f, dtype=np.float64)[scene.mesh.triangles[tri]] @ bary.T


#: int_K lambda_i lambda_k lambda_j / |K| = 2 a! b! c! / (a + b + c + 2)!
_T3 = np.array(
    [
        [
            [1 / 10 if i == j == k else 1 / 30 if len({i, j, k}) == 2 else 1 / 60 for j in range(3)]
            for k in range(3)
        ]
        for i in range(3)
    ]
)


def _any3(b):
    """Row-wise any of a bool (S, 3) array.

    Column by column: ``.any(axis=1)`` on rows of three is several times slower
    (and the glued contact load runs on every evaluation of the bound).
    """
    return b[:, 0] | b[:, 1] | b[:, 2]


def _sum3(v):
    """``v.sum(axis=-1)`` for a last axis of length 3, in the same order (bit for bit)."""
    return v[..., 0] + v[..., 1] + v[..., 2]


def _moments_p1(v):
    """``einsum("sik,ikj->sij", v, _T3)`` (the same products, summed in order over k)."""
    t = _T3
    return v[:, :, 0, None] * t[:, 0] + v[:, :, 1, None] * t[:, 1] + v[:, :, 2, None] * t[:, 2]


class _Glued:
    r"""The glued pressure :math:`\zeta \ge 0` on a set of triangles, shifted per vertex.

    :math:`\chi^* = (\mu_{1,K} f_2 - \mu_{2,K} f_1)/(\mu_{1,K} + \mu_{2,K})`.
    Callable loads: values at the points of the load rule (degree
    ``scene.load_degree``), and the shifted pressure of vertex a is
    :math:`(\chi^* + \gamma_a m_K)^+` at those points.  Constant and per-vertex
    loads: :math:`\chi^*` is P1 on each triangle and the shifted pressure is the
    P1 interpolant of its clipped vertex values :math:`(\chi^*(x_k) + \gamma_a
    m_K)^+`; its masses and moments are exact closed forms
    (:math:`\int_K\lambda_i\lambda_k\lambda_j`), and point values (the rule
    of degree 4, exact for the oscillation of a quadratic) are built only for
    per-vertex loads.  Either way it is >= 0 everywhere and its moments are
    what the kernel gets.
    """

    def __init__(self, scene, tri, mu1, mu2):

        mesh = scene.mesh
        kinds = (scene.data_kind("f1"), scene.data_kind("f2"))
        self.callable = "callable" in kinds
        #: point values needed (callables: everything; per-vertex loads: the oscillation)
        self.with_points = any(k != "constant" for k in kinds)
        self.bary, self.w = triangle_rule(scene.load_degree if self.callable else 4)
        t = mesh.triangles[tri]
        m1, m2 = mu1[:, None], mu2[:, None]
        if self.with_points:
            x, y = quadrature_points(mesh.vertices, t, self.bary)
            self.f1 = _load_values(scene, 1, tri, x, y, self.bary)
            self.f2 = _load_values(scene, 2, tri, x, y, self.bary)
        else:
            self.f1 = self.f2 = np.zeros((tri.size, 1))
        if self.callable:
            self.nodes = (m1 * self.f2 - m2 * self.f1) / (m1 + m2)  # (S, nq) point values
        else:
            # constant and per-vertex loads are evaluated without the coordinates
            # (only their shape is used), so the corners are not computed
            corners = np.eye(3)
            xc = yc = np.empty((tri.size, 3))
            g1 = _load_values(scene, 1, tri, xc, yc, corners)
            g2 = _load_values(scene, 2, tri, xc, yc, corners)
            self.nodes = (m1 * g2 - m2 * g1) / (m1 + m2)  # (S, 3) vertex values
        self.m = mu1 * mu2 / (mu1 + mu2)
        self.areas = mesh.areas[tri]

    def restrict(self, rows):
        """Return the same pressure on the triangles ``tri[rows]`` only."""
        out = _Glued.__new__(_Glued)
        out.__dict__.update(self.__dict__)
        out.nodes, out.m, out.areas = self.nodes[rows], self.m[rows], self.areas[rows]
        out.f1, out.f2 = self.f1[rows], self.f2[rows]
        return out

    def _shifted(self, shift):
        """Clipped values per vertex i: (S, 3, nq) at points, or (S, 3, 3) at the vertices."""
        return np.maximum(self.nodes[:, None, :] + (shift * self.m[:, None])[:, :, None], 0.0)

    def points(self, shift):
        """Shifted, clipped pressure at the rule's points: shift (S, 3) -> (S, 3, nq)."""
        v = self._shifted(shift)
        return v if self.callable else v @ self.bary.T

    def masses(self, shift):
        """``(psi_i zeta_i, 1)_K`` for the three vertices: (S, 3)."""
        v = self._shifted(shift)
        if self.callable:
            wb = self.w[:, None] * self.bary  # (nq, 3)
            out = np.stack([v[:, i, :] @ wb[:, i] for i in range(3)], axis=1)
            return out * self.areas[:, None]
        # int_K lambda_i lambda_k = |K| (1 + [i = k]) / 12
        own = v[:, [0, 1, 2], [0, 1, 2]]
        return (_sum3(v) + own) * (self.areas / 12.0)[:, None]

    def moments(self, shift):
        """``(psi_i zeta_i, lambda_j)_K``: (S, 3, 3)."""
        v = self._shifted(shift)
        if self.callable:
            b, w = self.bary, self.w
            out = np.stack([v[:, i, :] @ ((w * b[:, i])[:, None] * b) for i in range(3)], axis=1)
            return out * self.areas[:, None, None]
        return _moments_p1(v) * self.areas[:, None, None]


def _keep_plain(scene, u1, u2, lam, closed, partial, mu1, mu2) -> np.ndarray:
    r"""Return the partially closed patches that keep :math:`\lambda_a\psi_a` (bool (N,)).

    Gluing a vertex a whose patch also has open triangles (gap > 0 somewhere)
    moves its load off those triangles.  That saves
    :math:`\lambda_a(\psi_a, (u_{1h} - u_{2h})^+)` in c (which enters η like
    twice a squared flux term), and changes how much of membrane i's patch
    data :math:`g_i^a` (docs/method.md §4) sits on the open triangles,
    :math:`I_i = \sum_{K\ open}(g_i^a, 1)_K`, which the flux has to carry
    across to the closed ones: about ``GLUED_COST`` :math:`\sum_i
    I_i^2/\mu_i` in the squared flux terms.  The vertex stays plain when
    gluing costs more there than it saves in c.  Manufactured family: the
    open triangles are out of contact, their data balance without load and
    c is large relative to the error, so the free-boundary vertices are glued;
    a floppy boundary layer (checkerboard, small c) is in contact on the open
    triangles too, where removing the load would unbalance the floppy
    membrane.  The choice only affects sharpness; any choice keeps the
    guarantee.
    """
    mesh = scene.mesh
    n = mesh.n_vertices
    triangles = mesh.triangles
    osub = np.flatnonzero(~closed & _any3(partial[triangles]))
    ot = triangles[osub]
    areas = mesh.areas[osub]
    grads = mesh.gradients[osub]  # (S, 3, 2)
    own = partial[ot]
    imb = []
    for i, (u, mu) in enumerate(((u1, mu1), (u2, mu2)), start=1):
        mom = load_moments(scene, i)
        f = scene.f1 if i == 1 else scene.f2
        if mom is None:
            load = np.repeat(float(f) * areas[:, None] / 3.0, 3, axis=1)
        else:
            load = mom[osub].sum(axis=2)  # (psi_a f, 1)_K
        gu = np.einsum("sk,skd->sd", u[ot], grads)
        stiff = mu[osub, None] * np.einsum("skd,sd->sk", grads, gu) * areas[:, None]
        data = np.where(own, load - stiff, 0.0)
        imb.append(np.bincount(ot.ravel(), weights=data.ravel(), minlength=n))
    contact = np.where(own, lam[ot] * areas[:, None] / 3.0, 0.0)  # (lam_a psi_a, 1)_K
    load_open = np.bincount(ot.ravel(), weights=contact.ravel(), minlength=n)
    inv1 = np.zeros(n)
    inv2 = np.zeros(n)
    np.maximum.at(inv1, ot.ravel(), np.repeat(1.0 / mu1[osub], 3))
    np.maximum.at(inv2, ot.ravel(), np.repeat(1.0 / mu2[osub], 3))
    glued = imb[0] ** 2 * inv1 + imb[1] ** 2 * inv2
    plain = (imb[0] + load_open) ** 2 * inv1 + (imb[1] - load_open) ** 2 * inv2
    # (psi_a, gap^+)_K by the vertex-weighted rule (|K|/12)(sum + own) on the positive part
    gp = np.maximum((u1 - u2)[ot], 0.0)
    gpsi = (gp.sum(axis=1, keepdims=True) + gp) * (areas / 12.0)[:, None]
    g_open = np.bincount(ot.ravel(), weights=np.where(own, gpsi, 0.0).ravel(), minlength=n)
    return partial & (GLUED_COST * (glued - plain) > 2.0 * lam * g_open)


def _oscillation_at_points(q, bary, w, areas):
    """``||q - Pi_K q||_K`` from point values q (S, nq), as in fastmem.fem.callables."""
    scale = np.abs(q).max(axis=1)
    scale[scale == 0.0] = 1.0
    qs = q / scale[:, None]
    avg = (qs * w) @ bary
    coef = 12.0 * avg - 3.0 * avg.sum(axis=1, keepdims=True)
    diff = qs - coef @ bary.T
    return scale * np.sqrt(np.maximum((diff * diff) @ w, 0.0) * areas)


def glued_contact_load(scene, u1, u2, lam) -> ContactLoad | None:
    r"""Contact load of the bound's flux: the glued pressure, patch by patch, exact masses.

    Parameters
    ----------
    scene : Scene
    u1, u2 : ndarray of shape (N,)
    lam : ndarray of shape (N,)
        Nodal multiplier, zero on the boundary.

    Returns
    -------
    ContactLoad, or None when no vertex qualifies (then the load is
    :math:`\lambda_a\psi_a` everywhere, docs/method.md §4 as written).

    Notes
    -----
    Only the mass :math:`B_a\lambda_a` of the contact load :math:`\chi^a` of an
    interior patch is fixed (both membranes' patch problems need it); its shape
    and its support inside the patch are free.  Call a triangle *closed* when
    the gap :math:`u_{1h} - u_{2h}` is :math:`\le 0` at its three vertices (then
    :math:`(u_{1h} - u_{2h})^+ = 0` on it).  A vertex a is *glued* when it is
    interior, :math:`\lambda_a > 0`, :math:`\mu_{1,K} \ne \mu_{2,K}` on some
    triangle of its patch and the patch has a closed triangle (if it also has
    open ones, unless the cost model of :func:`_keep_plain` prefers the plain
    load); then

    .. math::

        \chi^a = s_a\,\psi_a\,(\chi^* + \gamma_a m_K)^+ \text{ on the closed
        triangles of } \omega_a, \quad 0 \text{ on the others},

    with :math:`\chi^* = (\mu_{1,K} f_2 - \mu_{2,K} f_1)/(\mu_{1,K} + \mu_{2,K})`
    the pressure two glued membranes exert on each other (the pointwise
    minimiser of :math:`\mu_1^{-1}|f_1 + \chi|^2 + \mu_2^{-1}|f_2 - \chi|^2`),
    :math:`m_K = \mu_{1,K}\mu_{2,K}/(\mu_{1,K} + \mu_{2,K})`, the shift
    :math:`\gamma_a` solving :math:`(\chi^a, 1) = B_a\lambda_a` with
    :math:`s_a = 1` (closed form when nothing is clipped, else bisection) and
    :math:`s_a > 0` making that mass exact to round-off.  (For constant and
    per-vertex loads the clipped function is the P1 interpolant of its vertex
    values, see :class:`_Glued`.)  Every other vertex keeps
    :math:`\chi^a = \lambda_a\psi_a`.

    Why it is sharp.  The sum of the two nodal equations at a vertex in
    contact gives :math:`B_a\lambda_a = (\psi_a\chi^*, 1) + m(A w_h)_a`
    (constant tensions, :math:`w_h` the discrete gap): the glued pressure has
    the right mass up to a defect of the size of the floppy tension
    :math:`m \approx \mu_{floppy}`, which :math:`\gamma_a m_K \psi_a` spreads
    as a P1 function.  The data of membrane i become :math:`\mu_i/(\mu_1 +
    \mu_2)` times those of the glued membrane plus that defect: the floppy
    membrane no longer equilibrates the lumping mismatch of
    :math:`\lambda_a\psi_a` (flux term) nor the kink of the pressure
    (oscillation: :math:`f_1 + \chi^* = \mu_1(f_1 + f_2)/(\mu_1 + \mu_2)`),
    which the estimator weights by :math:`\mu_{floppy}^{-1/2}`.  Nothing is
    cut from a projected piece (the old mass defect), and no load sits on open
    triangles, where it would meet a positive gap in c.

    Why the bound holds (the proof of docs/method.md §5 with
    :math:`\ell = \chi + \lambda^-` in place of :math:`\hat\lambda`):

    1. Compatibility: :math:`(\chi^a, 1)_{\omega_a} = B_a\lambda_a`, so every
       interior patch problem is solvable as before, and, since
       :math:`\sum_a\psi_a = 1`, :math:`\nabla\cdot\sigma_{1h} = \Pi(f_1 + \chi)
       - \rho_1`, :math:`\nabla\cdot\sigma_{2h} = \Pi(f_2 - \chi) - \rho_2`
       (Π the L2 projection onto P1 on each triangle).
    2. Residuals: :math:`r_1 = f_1 + \ell - \nabla\cdot\sigma_{1h} = [(f_1 + \chi)
       - \Pi(f_1 + \chi)] + \rho_1 + \lambda^-` and :math:`r_2 = [(f_2 - \chi) -
       \Pi(f_2 - \chi)] + \rho_2 - \lambda^-`.  The brackets are orthogonal to
       P1(K): Poincaré on K gives the oscillation
       :math:`\frac{h_K}{\pi}\mu_{i,K}^{-1/2}\|q_i - \Pi_K q_i\|_K` of
       :math:`q_1 = f_1 + \chi`, :math:`q_2 = f_2 - \chi` (that of
       :math:`f_i` wherever :math:`\chi` is P1, i.e. off ``tri``).  The P1
       remainders are those of §5: :math:`\eta_{glob}` is unchanged.
    3. Contact: :math:`\ell \ge 0` pointwise (:math:`s_a > 0`, the clipped
       pressure is >= 0, plain vertices contribute
       :math:`\hat\lambda_a\psi_a`), so :math:`(\lambda - \ell, e_1 - e_2) \le
       (\ell, (u_{1h} - u_{2h})^+)`.  On closed triangles the gap part
       vanishes; on the others :math:`\ell` is the P1 function of nodal values
       :meth:`ContactLoad.open_load` (:math:`\hat\lambda_a` at plain vertices,
       0 at glued ones), so c is computed exactly as in §5 with these values,
       and never exceeds the c of :math:`\hat\lambda`.
    4. Flux terms: Cauchy–Schwarz as in §5.  Hence :math:`|||e|||^2 \le
       a|||e||| + c` with the oscillation of step 2 and the c of step 3.

    Exactness: for constant and per-vertex loads every integral above is exact;
    for callable loads the moments, the oscillation and the pressure use the
    points of the load rule, so the bound holds up to that rule's error on
    the data, as everywhere else with callable loads.
    """
    mesh = scene.mesh
    if np.ndim(scene.mu1) == 0 and np.ndim(scene.mu2) == 0 and scene.mu1 == scene.mu2:
        return None
    n = mesh.n_vertices
    mu1 = np.broadcast_to(np.asarray(scene.mu1, dtype=np.float64), (mesh.n_triangles,))
    mu2 = np.broadcast_to(np.asarray(scene.mu2, dtype=np.float64), (mesh.n_triangles,))
    triangles = mesh.triangles
    unequal = np.bincount(triangles[mu1 != mu2].ravel(), minlength=n) > 0
    lam = np.asarray(lam, dtype=np.float64)
    u1 = np.asarray(u1, dtype=np.float64)
    u2 = np.asarray(u2, dtype=np.float64)
    gap = u1 - u2
    closed = gap[triangles] <= 0.0
    closed = closed[:, 0] & closed[:, 1] & closed[:, 2]
    flags = unequal & (lam > 0.0) & ~mesh.boundary_vertex_mask
    flags &= np.bincount(triangles[closed].ravel(), minlength=n) > 0
    partial = flags & (np.bincount(triangles[~closed].ravel(), minlength=n) > 0)
    if partial.any():
        flags &= ~_keep_plain(scene, u1, u2, lam, closed, partial, mu1, mu2)
    if not flags.any():
        return None
    sub = np.flatnonzero(closed & _any3(flags[triangles]))
    tri = triangles[sub]
    gl = _Glued(scene, sub, mu1[sub], mu2[sub])
    target = mesh.lumped_mass * lam
    zero = np.zeros((sub.size, 3))
    d0 = np.bincount(tri.ravel(), weights=gl.masses(zero).ravel(), minlength=n)
    wsum = np.bincount(tri.ravel(), weights=np.repeat(gl.m * gl.areas / 3.0, 3), minlength=n)
    gamma = np.where(flags, (target - d0) / np.where(wsum > 0.0, wsum, 1.0), 0.0)
    # clipped somewhere on the patch?  then the mass is not linear in gamma: bisection
    # smallest value of chi* per triangle (points or vertices)
    low = functools.reduce(np.minimum, gl.nodes.T)
    clip_k = low[:, None] + gamma[tri] * gl.m[:, None] < 0.0  # (S, 3)
    clip = np.zeros(n, dtype=bool)
    clip[tri[clip_k]] = True
    clip &= flags
    if clip.any():
        rows = np.flatnonzero(_any3(clip[tri]))
        rt = tri[rows]
        high = functools.reduce(np.maximum, gl.nodes[rows].T)
        # all of the patch clipped (mass 0) at gamma = -max chi*/m_K: a bracket
        lo = np.full(n, np.inf)
        np.minimum.at(lo, rt.ravel(), np.repeat(-np.maximum(high, 0.0) / gl.m[rows], 3))
        lo = np.where(clip, lo, 0.0)
        hi = np.where(clip, gamma, 0.0)
        sub_gl = gl.restrict(rows)
        for _ in range(GLUED_BISECTION_STEPS):
            mid = 0.5 * (lo + hi)
            mass = np.bincount(rt.ravel(), weights=sub_gl.masses(mid[rt]).ravel(), minlength=n)
            over = mass > target
            hi = np.where(clip & over, mid, hi)
            lo = np.where(clip & ~over, mid, lo)
        gamma = np.where(clip, hi, gamma)  # mass >= target: the rescaling below is <= 1
    shift = np.where(flags[tri], gamma[tri], 0.0)
    mom = gl.moments(shift)
    d = np.bincount(tri.ravel(), weights=_sum3(mom).ravel(), minlength=n)
    flags &= d > 0.0
    scale = np.zeros(n)
    scale[flags] = target[flags] / d[flags]
    keep = _any3(flags[tri])
    sub, tri, mom, shift = sub[keep], tri[keep], mom[keep], shift[keep]
    s_loc = np.where(flags[tri], scale[tri], 0.0)  # (S, 3)
    moments = s_loc[:, :, None] * mom
    # chi at the points: sum_glued s_a lambda_a zeta_a + sum_plain lam_a lambda_a
    gl = gl.restrict(keep)
    plain = np.where(flags[tri], 0.0, lam[tri])
    lam_minus = np.maximum(lam, 0.0) - lam
    # ell = chi + lam^- at the vertices (P1 pressure) and at the points: >= 0 by construction
    ell = []
    if not gl.callable:
        own = np.maximum(gl.nodes + shift * gl.m[:, None], 0.0)  # _shifted(shift)[:, i, i]
        ell.append(s_loc * own + plain + lam_minus[tri])
    osc1 = np.zeros(sub.size)
    osc2 = np.zeros(sub.size)
    if gl.with_points:
        # chi at the points: sum_glued s_a lambda_a zeta_a + sum_plain lam_a lambda_a
        bary, w = gl.bary, gl.w
        zi = gl.points(shift)
        chi = sum(s_loc[:, i, None] * zi[:, i, :] * bary[:, i] for i in range(3))
        chi = chi + plain @ bary.T
        areas = mesh.areas[sub]
        h = mesh.diameters[sub] / np.pi
        osc1 = h * _oscillation_at_points(gl.f1 + chi, bary, w, areas) / np.sqrt(mu1[sub])
        osc2 = h * _oscillation_at_points(gl.f2 - chi, bary, w, areas) / np.sqrt(mu2[sub])
        ell.append(chi + lam_minus[tri] @ bary.T)
    # (constant loads: chi is P1 on each triangle and f constant, so no oscillation)
    ell = np.concatenate(ell, axis=1)
    ell_min = float(ell.min()) if ell.size else 0.0
    if ell_min < -1e-12 * max(float(np.abs(ell).max()), 1e-300):  # pragma: no cover
        raise AssertionError(f"glued contact load is negative: {ell_min:.3e}")
    return ContactLoad(
        flags=flags,
        gamma=np.where(flags, gamma, 0.0),
        scale=scale,
        tri=sub,
        moments=moments,
        osc1=osc1,
        osc2=osc2,
        ell_min=ell_min,
    )
