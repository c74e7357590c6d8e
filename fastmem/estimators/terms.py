r"""Components of the guaranteed a posteriori error bound (docs/method.md §5 and §6).

The bound :math:`|||u - u_h||| \le \eta` holds for any triple
``(u1h, u2h, lam_h)`` (exact, inexact, non-converged or infeasible) with
``u1h = g``, ``u2h = 0`` and ``lam_h = 0`` on the boundary, given equilibrated
fluxes :math:`\sigma_{ih}` (docs/method.md §4).  The flux terms
:math:`\eta_{F,K,i}` come from the flux reconstruction and are passed in;
this module computes everything else and combines it:

.. math::

    \eta_{osc,K,i} &= \frac{h_K}{\pi}\, \mu_{i,K}^{-1/2}\, \|f_i - \Pi_K f_i\|_K
        && \text{(data oscillation; } \Pi_K \text{ the } L^2 \text{ projection onto } P_1(K))\\
    \eta_{nc,K} &= \mu_{2,K}^{1/2} \|\nabla\delta\|_K,\quad \delta = (u_{2h} - u_{1h})^+
        && \text{(non-conformity: the iterate violates } u_1 \ge u_2)\\
    \eta_{C,K} &= (\hat\lambda, (u_{1h} - u_{2h})^+)_K \ge 0,\quad \hat\lambda = \lambda_h^+
        && \text{(complementarity)}\\
    \eta_{glob,1} &= C_F \mu_1^{-1/2} \|\rho_1 + \lambda^-\|_\Omega,\quad
    \eta_{glob,2} = C_F \mu_2^{-1/2} \|\rho_2 - \lambda^-\|_\Omega
        && \text{(algebraic residual and negative multiplier)}

with :math:`\hat\lambda` and :math:`\lambda^- = \hat\lambda - \lambda_h \ge 0` the
P1 functions of nodal values :math:`\max(\lambda_a, 0)` and
:math:`\max(\lambda_a, 0) - \lambda_a`, :math:`\rho_i` the P1 function of nodal
values :math:`R_{i,a} / B_a` (zero on the boundary) and
:math:`C_F = 1 / (\pi \sqrt{1/L_x^2 + 1/L_y^2})` the Friedrichs constant of the
bounding box of :math:`\Omega`.  Then

.. math::

    a &= \Big(\sum_K (\eta_{osc,K,1} + \eta_{F,K,1})^2
          + (\eta_{osc,K,2} + \eta_{F,K,2} + \eta_{nc,K})^2\Big)^{1/2}
         + (\eta_{glob,1}^2 + \eta_{glob,2}^2)^{1/2}, \qquad
    c = \sum_K \eta_{C,K},\\
    \eta &= \frac{a + \sqrt{a^2 + 4c}}{2} + \Big(\sum_K \eta_{nc,K}^2\Big)^{1/2},

and the components used for adaptive stopping (docs/method.md §6)

.. math::

    \eta_{alg} &= \Big(\sum_i (C_F \mu_i^{-1/2} \|\rho_i\|)^2\Big)^{1/2}, \qquad
    \eta_{lin} = C_F (\mu_1^{-1} + \mu_2^{-1})^{1/2} \|\lambda^-\|
                 + 2 \Big(\sum_K \eta_{nc,K}^2\Big)^{1/2},\\
    \eta_{disc} &= \Big(\sum_K \sum_i (\eta_{osc,K,i} + \eta_{F,K,i})^2\Big)^{1/2} + \sqrt{c},

which satisfy :math:`\eta \le \eta_{disc} + \eta_{lin} + \eta_{alg}`.

Exactness.  :math:`\eta_{nc}` and :math:`\eta_C` involve positive parts of P1
functions; they are integrated exactly by cutting every triangle along the
zero line of the gap (:mod:`fastmem.kernels.cut`).  Global norms use the
consistent P1 mass matrix (assembled once, cached on the scene under
``"M"``).  The oscillation is identically zero for constant and per-vertex
(P1) loads and is then not computed; for callable loads it is evaluated with
the quadrature rule of degree ``scene.load_degree``, the rule of the load
vector, so the bound is guaranteed up to that rule's error on the data.

Workflow::

    loc = local_terms(scene, u1, u2, lam)
    glob = global_terms(scene, u1, u2, lam, r1, r2)
    est = combine(eta_F1, eta_F2, loc, glob)   # eta_F from the flux reconstruction
    est["totals"]["eta"], est["maps"]["eta_C"]
"""

from __future__ import annotations

import logging
import math

import numpy as np

from ..errors import DataError
from ..fem.assembly import assemble_mass
from ..fem.loaddata import integrals
from ..kernels import cut as _cut
from ..kernels import pool as _par
from ..kernels import rows as _rows
from ..kernels import sums as _sums
from ..linalg.sparse import THREADED_ROWS, plain_float64, read_only, threaded

__all__ = [
    "check_totals",
    "combine",
    "contact_local_terms",
    "friedrichs_constant",
    "global_terms",
    "local_terms",
    "lumped_norm",
    "mass_matrix",
]

logger = logging.getLogger(__name__)


def friedrichs_constant(mesh) -> float:
    r"""Friedrichs constant of :math:`H^1_0(\Omega)` from the bounding box of the mesh.

    Parameters
    ----------
    mesh : Mesh

    Returns
    -------
    float
        :math:`C_F = 1 / (\pi \sqrt{1/L_x^2 + 1/L_y^2})` with :math:`L_x, L_y`
        the sides of ``mesh.bounding_box``, so that
        :math:`\|v\|_\Omega \le C_F \|\nabla v\|_\Omega` for
        :math:`v \in H^1_0(\Omega)` (Ω lies in the box; the constant of the box
        is its smallest Dirichlet eigenvalue to the power -1/2).

    Examples
    --------
    >>> import fastmem as fm
    >>> round(friedrichs_constant(fm.Mesh.square(2)), 12)  # 2 / (pi sqrt 2)
    0.450158158079
    """
    xmin, xmax, ymin, ymax = mesh.bounding_box
    lx, ly = xmax - xmin, ymax - ymin
    return 1.0 / (math.pi * math.sqrt(1.0 / lx**2 + 1.0 / ly**2))


def _nodal(mesh, x, name) -> np.ndarray:
    """Validate a nodal vector and return it as contiguous float64."""
    arr = np.asarray(x)
    if arr.dtype.kind not in "iuf":
        raise DataError(f"{name} must be real numbers, got dtype {arr.dtype}")
    if arr.shape != (mesh.n_vertices,):
        raise DataError(
            f"{name} must have one value per vertex, shape ({mesh.n_vertices},), got {arr.shape}"
        )
    arr = np.ascontiguousarray(arr, dtype=np.float64)
    if not np.isfinite(arr).all():
        raise DataError(f"{name} contains NaN or inf at {int((~np.isfinite(arr)).sum())} vertices")
    return arr


def _lambda_parts(mesh, lam):
    """Nodal ``(lam_hat, lam_minus)`` = ``(max(lam, 0), max(lam, 0) - lam)``, 0 on the boundary.

    From :data:`~fastmem.linalg.sparse.THREADED_ROWS` vertices on, one pass of the
    kernel threads (:func:`fastmem.kernels.rows.lambda_parts_range`, the same bits).
    """
    n = mesh.n_vertices
    if n >= THREADED_ROWS and plain_float64((lam,), n):
        lam_hat, lam_minus = np.empty(n), np.empty(n)
        _par.parallel_for(
            _rows.lambda_parts_range, n, read_only(lam), mesh.boundary_vertex_mask,
            lam_hat, lam_minus,
        )  # fmt: skip
        return lam_hat, lam_minus
    lam = lam.copy()
    lam[mesh.boundary_vertex_mask] = 0.0
    lam_hat = np.maximum(lam, 0.0)
    return lam_hat, lam_hat - lam


def _oscillation(scene, i) -> np.ndarray:
    r"""Per-triangle :math:`\eta_{osc,K,i}`, shape (M,); zeros for constant and P1 data.

    For callable :math:`f_i`, with the rule :math:`(x_q, w_q)` of degree
    ``scene.load_degree``: :math:`b_{K,j} = |K| \sum_q w_q f(x_q) \phi_j(x_q)`,
    :math:`\Pi_K f = \sum_j c_j \phi_j` with :math:`M_K c = b_K`, and
    :math:`\|f - \Pi_K f\|_K^2 = |K| \sum_q w_q (f - \Pi_K f)^2(x_q)`.  For a
    rule of degree >= 2 this equals :math:`Q(f^2) - (\Pi_K f, \Pi_K f)_K`
    exactly (``Q(f Π f) = c·b = c·M c``), but it is evaluated in the form
    above: a sum of squares, free of cancellation and never negative.
    Computed by :func:`fastmem.fem.loaddata.integrals` from the same values of
    :math:`f_i` as the load vector and the flux moments, cached on the scene.
    """
    return integrals(scene, i, moments=True)["osc"]


def local_terms(scene, u1, u2, lam, oscillation=True) -> dict:
    r"""Per-triangle estimators that need no flux: non-conformity, complementarity, oscillation.

    Parameters
    ----------
    scene : Scene
        The problem; ``scene.mu1``, ``scene.mu2`` may be floats or per-triangle
        arrays (M,) (the value :math:`\mu_{i,K}` of each triangle is used).
    u1, u2, lam : ndarray of shape (N,)
        Nodal values of the iterate.  ``lam`` may have any sign; its entries at
        boundary vertices are ignored (:math:`\lambda_h \in X_{0h}`).
    oscillation : bool
        Compute the data oscillation (default).  ``False`` leaves ``eta_osc1``
        and ``eta_osc2`` as None: they depend on the data only and enter
        :math:`\eta_{disc}` alone, so the adaptive solver's frequent checks of
        :math:`\eta_{lin}, \eta_{alg}` skip them (with callable loads, one
        evaluation of each load at every quadrature point);
        :func:`fastmem.estimators.bound.evaluate` fills them in when needed.

    Returns
    -------
    dict of str to ndarray of shape (M,)
        ``eta_nc``
            :math:`\mu_{2,K}^{1/2} \|\nabla\delta\|_K` with
            :math:`\delta = (u_{2h} - u_{1h})^+`, i.e.
            :math:`\|\nabla\delta\|_K^2 = |\nabla(u_{2h} - u_{1h})|^2_K\,
            |\{u_{2h} - u_{1h} > 0\} \cap K|`.
        ``eta_C``
            :math:`(\hat\lambda, (u_{1h} - u_{2h})^+)_K \ge 0`,
            :math:`\hat\lambda` the P1 function of nodal values
            :math:`\max(\lambda_a, 0)`.
        ``eta_osc1``, ``eta_osc2``
            :math:`(h_K/\pi)\, \mu_{i,K}^{-1/2} \|f_i - \Pi_K f_i\|_K`: zeros
            (not computed) for constant and per-vertex loads; for callables,
            evaluated with the quadrature rule of degree ``scene.load_degree``.

    Notes
    -----
    The positive parts are integrated exactly by the Numba kernel
    :func:`fastmem.kernels.cut.contact_terms` (parallel over triangles, one
    pass for both terms), which splits each triangle along the zero line of
    the gap.
    """
    mesh = scene.mesh
    u1 = _nodal(mesh, u1, "u1")
    u2 = _nodal(mesh, u2, "u2")
    lam = _nodal(mesh, lam, "lam")
    gap = u1 - u2
    lam_hat, _ = _lambda_parts(mesh, lam)
    mu2 = np.ascontiguousarray(np.atleast_1d(np.asarray(scene.mu2, dtype=np.float64)))
    eta_nc, eta_c = _cut.contact_terms(mesh.vertices, mesh.triangles, gap, lam_hat, mu2)
    return {
        "eta_nc": eta_nc,
        "eta_C": eta_c,
        "eta_osc1": _oscillation(scene, 1) if oscillation else None,
        "eta_osc2": _oscillation(scene, 2) if oscillation else None,
    }


def contact_local_terms(scene, u1, u2, lam, contact, local) -> dict:
    r"""``local`` with c and the oscillation of the glued contact load (issue 16).

    With the contact load :math:`\chi` of :func:`fastmem.estimators.flux.glued_contact_load`
    the proof of docs/method.md §5 runs with :math:`\ell = \chi + \lambda^-` in
    place of :math:`\hat\lambda` (proof there):

    - ``eta_C``: :math:`(\ell, (u_{1h} - u_{2h})^+)_K`; :math:`\ell` is the P1
      function of nodal values ``contact.open_load(lam)`` on every triangle
      where the gap is positive somewhere (on the closed triangles the product
      vanishes whatever :math:`\ell` is), so the same exact cut integration
      applies with these nodal values;
    - ``eta_osc1``, ``eta_osc2``: on the triangles ``contact.tri`` the oscillation
      of :math:`f_1 + \chi` and :math:`f_2 - \chi` (``contact.osc1``,
      ``contact.osc2``); elsewhere :math:`\chi` is P1 and the data oscillation
      of ``local`` applies.
    """
    mesh = scene.mesh
    lam = _nodal(mesh, lam, "lam").copy()
    lam[mesh.boundary_vertex_mask] = 0.0
    gap = _nodal(mesh, u1, "u1") - _nodal(mesh, u2, "u2")
    mu2 = np.ascontiguousarray(np.atleast_1d(np.asarray(scene.mu2, dtype=np.float64)))
    ell = np.ascontiguousarray(contact.open_load(lam))
    _, eta_c = _cut.contact_terms(mesh.vertices, mesh.triangles, gap, ell, mu2)
    osc1 = np.array(local["eta_osc1"], dtype=np.float64)
    osc2 = np.array(local["eta_osc2"], dtype=np.float64)
    osc1[contact.tri] = contact.osc1
    osc2[contact.tri] = contact.osc2
    return {**local, "eta_C": eta_c, "eta_osc1": osc1, "eta_osc2": osc2}


def mass_matrix(scene):
    """Consistent P1 mass matrix of the scene's mesh, cached on ``scene._cache["M"]``."""
    if "M" not in scene._cache:
        scene._cache["M"] = assemble_mass(scene.mesh)
    return scene._cache["M"]


def lumped_norm(scene, r) -> float | None:
    """``||rho||`` (L2) of the P1 function ``rho = r / B`` at interior vertices, 0 on the boundary.

    ``r``: a residual vector of one value per vertex (boundary entries ignored), ``B``
    the lumped mass.  From one pass of the kernel threads over the triangles
    (:func:`fastmem.kernels.sums.lumped_blocks`: the element mass matrices, no assembled
    mass matrix), or None on meshes below :data:`BLOCK_SUM_TRIANGLES` triangles and
    for a vector that is not contiguous float64 of the right length or not finite
    (then use :func:`mass_matrix`).  Equal to the mass-matrix product up to round-off.
    """
    mesh = scene.mesh
    m = mesh.n_triangles
    if m < BLOCK_SUM_TRIANGLES or not plain_float64((r,), mesh.n_vertices):
        return None
    blocks = -(-m // _sums.BLOCK)
    out = np.empty((blocks, 2))
    _par.parallel_for(
        _sums.lumped_blocks, blocks, _sums.BLOCK, mesh.triangles, mesh.areas, read_only(r),
        mesh.lumped_mass, mesh.boundary_vertex_mask, out, grain=1,
    )  # fmt: skip
    if out[:, 1].any():
        return None
    return math.sqrt(max(float(out[:, 0].sum()), 0.0))


def global_terms(scene, u1, u2, lam, r1, r2) -> dict:
    r"""Global estimators: algebraic residual and negative part of the multiplier.

    Parameters
    ----------
    scene : Scene
    u1, u2 : ndarray of shape (N,)
        Nodal values of the iterate (checked, not otherwise used: the global
        terms depend on ``lam`` and the residuals only).
    lam : ndarray of shape (N,)
        Nodal multiplier, any sign; boundary entries are ignored.
    r1, r2 : ndarray of shape (N,)
        Algebraic residuals ``R_i`` of the iterate (:func:`fastmem.fem.residual.residuals`);
        boundary entries are ignored.

    Returns
    -------
    dict of str to float
        ``eta_glob1``, ``eta_glob2``
            :math:`C_F \mu_1^{-1/2} \|\rho_1 + \lambda^-\|_\Omega` and
            :math:`C_F \mu_2^{-1/2} \|\rho_2 - \lambda^-\|_\Omega`, with
            :math:`\rho_i` the P1 function of nodal values :math:`R_{i,a}/B_a`
            (0 on the boundary) and :math:`\lambda^-` that of
            :math:`\max(\lambda_a, 0) - \lambda_a`.
        ``rho_norm1``, ``rho_norm2``, ``lam_minus_norm``
            :math:`\|\rho_1\|_\Omega`, :math:`\|\rho_2\|_\Omega`,
            :math:`\|\lambda^-\|_\Omega`.
        ``C_F``
            The Friedrichs constant (:func:`friedrichs_constant`).
        ``mu1``, ``mu2``
            The tensions used here: the constants, or for per-triangle
            tensions their **minimum** over the triangles.

    Notes
    -----
    Norms use the consistent P1 mass matrix, assembled once and cached in
    ``scene._cache["M"]``.  With per-triangle tensions the Friedrichs step
    reads :math:`(r, e) \le \|r\| C_F \|\nabla e\| \le \|r\| C_F
    \mu_{\min}^{-1/2} \|\mu^{1/2} \nabla e\|`, so using
    :math:`\min_K \mu_{i,K}` keeps the bound guaranteed (but may make it
    pessimistic for strongly varying tensions).

    Review for per-triangle tensions (issue 16, docs/heterogeneous.md).  The
    sharp constant is :math:`\Lambda^{-1/2}` with :math:`\Lambda` the
    smallest eigenvalue of :math:`-\nabla\cdot(\mu\nabla)` on
    :math:`H^1_0(\Omega)`; :math:`\Lambda \ge \mu_{\min} \pi^2 (L_x^{-2} +
    L_y^{-2})` (Rayleigh quotients, Ω inside its bounding box) is the best
    bound that holds for every piecewise-constant μ with these extremes: a
    μ equal to :math:`\mu_{\min}` except on a set of small measure has
    :math:`\Lambda` as close to it as wanted.  A larger guaranteed
    :math:`\Lambda` for a given μ needs a guaranteed eigenvalue lower bound
    (Lehmann-Goerisch, nonconforming bounds), not attempted: these terms vanish
    at feasible iterates with exact solves (:math:`\rho = \lambda^- = 0`) and
    enter only through :math:`\eta_{alg}, \eta_{lin}` otherwise, which the
    adaptive solver keeps below :math:`\gamma\,\eta_{disc}`.  The constant is
    unchanged: :math:`\min_K \mu_{i,K}`.  With the redistributed contact
    load of :func:`fastmem.estimators.flux.contact_redistribution` the residuals
    :math:`\rho_i`, :math:`\lambda^-` are the same functions (proof there), so
    these terms are unchanged too.
    """
    mesh = scene.mesh
    c_f = friedrichs_constant(mesh)
    mu1 = float(np.min(scene.mu1))
    mu2 = float(np.min(scene.mu2))
    squares = _global_blocks(mesh, u1, u2, lam, r1, r2)
    if squares is not None:  # a large mesh: one pass of the kernel threads
        return _glob_from_squares(squares[:5], c_f, mu1, mu2)
    _nodal(mesh, u1, "u1")
    _nodal(mesh, u2, "u2")
    lam = _nodal(mesh, lam, "lam")
    r1 = _nodal(mesh, r1, "r1")
    r2 = _nodal(mesh, r2, "r2")
    interior = ~mesh.boundary_vertex_mask
    b = mesh.lumped_mass
    rho1 = np.where(interior, r1 / b, 0.0)
    rho2 = np.where(interior, r2 / b, 0.0)
    _, lam_minus = _lambda_parts(mesh, lam)
    mass = threaded(mass_matrix(scene))  # products in the kernel threads, scipy's sums
    # three products for the five norms: M (rho_i -/+ lam^-) = M rho_i -/+ M lam^-, each
    # norm the dot product of its own vector with its own product (no expanded squares,
    # so no cancellation between them)
    m_rho1, m_rho2, m_lam = mass @ rho1, mass @ rho2, mass @ lam_minus

    def norm(x, mx):
        return math.sqrt(max(float(x @ mx), 0.0))

    return {
        "eta_glob1": c_f / math.sqrt(mu1) * norm(rho1 + lam_minus, m_rho1 + m_lam),
        "eta_glob2": c_f / math.sqrt(mu2) * norm(rho2 - lam_minus, m_rho2 - m_lam),
        "rho_norm1": norm(rho1, m_rho1),
        "rho_norm2": norm(rho2, m_rho2),
        "lam_minus_norm": norm(lam_minus, m_lam),
        "C_F": c_f,
        "mu1": mu1,
        "mu2": mu2,
    }


def _glob_from_squares(squares, c_f, mu1, mu2) -> dict:
    """Return the dict of :func:`global_terms` from its five squared norms."""
    glob1, glob2, rho1, rho2, lam_minus = (math.sqrt(max(x, 0.0)) for x in squares)
    return {
        "eta_glob1": c_f / math.sqrt(mu1) * glob1,
        "eta_glob2": c_f / math.sqrt(mu2) * glob2,
        "rho_norm1": rho1,
        "rho_norm2": rho2,
        "lam_minus_norm": lam_minus,
        "C_F": c_f,
        "mu1": mu1,
        "mu2": mu2,
    }


def _global_blocks(mesh, u1, u2, lam, r1, r2, mu2=None):
    """Return the squared norms of :func:`global_terms` (and S) from two passes of the threads.

    ``(|rho1 + lam^-|^2, |rho2 - lam^-|^2, |rho1|^2, |rho2|^2, |lam^-|^2, S)`` summed
    triangle by triangle with the element mass matrices
    (:func:`fastmem.kernels.sums.global_blocks`: fixed blocks, so the same for
    every thread count; equal to the mass-matrix products of the NumPy path up to
    round-off; the vertex values first, :func:`fastmem.kernels.sums.vertex_values`),
    or None on meshes below :data:`BLOCK_SUM_TRIANGLES` triangles, for
    vectors that are not contiguous float64 of one value per vertex, and when a
    value is not finite (the NumPy path then names it).  ``S``: with ``mu2`` (the
    tension of membrane 2, one value or one per triangle) the sum of the squared
    ``eta_nc`` of :func:`local_terms`, bit for bit the one :func:`combine` forms from
    its map; without, 0.
    """
    m = mesh.n_triangles
    vectors = (u1, u2, lam, r1, r2)
    if m < BLOCK_SUM_TRIANGLES or not plain_float64(vectors, mesh.n_vertices):
        return None
    if mu2 is None:  # no eta_nc: an empty vertex array tells the kernel
        vertices, mu2 = mesh.vertices[:0], np.ones(1)
    else:
        vertices = mesh.vertices
        mu2 = np.ascontiguousarray(np.atleast_1d(np.asarray(mu2, dtype=np.float64)))
    n = mesh.n_vertices
    rho1, rho2, lam_minus, gap = (np.empty(n) for _ in range(4))
    flags = np.empty(n, dtype=np.uint8)
    _par.parallel_for(
        _sums.vertex_values, n, *(read_only(x) for x in vectors), mesh.lumped_mass,
        mesh.boundary_vertex_mask, rho1, rho2, lam_minus, gap, flags,
    )  # fmt: skip
    blocks = -(-m // _sums.BLOCK)
    out = np.empty((blocks, len(_sums.GLOBAL_SUMS)))
    _par.parallel_for(
        _sums.global_blocks, blocks, _sums.BLOCK, mesh.triangles, mesh.areas,
        rho1, rho2, lam_minus, gap, flags, vertices, read_only(mu2), out, grain=1,
    )  # fmt: skip
    if out[:, 6].any():
        return None
    # column by column in block order (NumPy's reduction over the first axis), as combine
    return tuple(float(t) for t in out[:, :6].sum(axis=0))


def check_totals(scene, u1, u2, lam, r1, r2):
    r"""``(eta_lin, eta_alg, glob)`` of an iterate in one pass of the threads, or None.

    What the solver's frequent checks need: :math:`\eta_{lin}` and
    :math:`\eta_{alg}` (docs/method.md §6) depend on the global terms and on
    :math:`\sum_K \eta_{nc,K}^2` only, so no per-triangle map is formed.  One
    pass of :func:`fastmem.kernels.sums.global_blocks` sums both; the values are
    bit for bit those of :func:`global_terms`, :func:`local_terms` and
    :func:`combine` (``glob`` is the dict of :func:`global_terms`).  None where
    :func:`global_terms` would not take its kernel path (small meshes, vectors that
    are not contiguous float64, values that are not finite): then use those.
    """
    mesh = scene.mesh
    squares = _global_blocks(mesh, u1, u2, lam, r1, r2, mu2=scene.mu2)
    if squares is None:
        return None
    c_f = friedrichs_constant(mesh)
    glob = _glob_from_squares(squares[:5], c_f, float(np.min(scene.mu1)), float(np.min(scene.mu2)))
    eta_lin, eta_alg = _lin_alg(glob, math.sqrt(squares[5]))
    return eta_lin, eta_alg, glob


def _lin_alg(glob, nc_total):
    """``(eta_lin, eta_alg)`` from the global terms and ``(sum_K eta_nc,K^2)^(1/2)``."""
    c_f, mu1, mu2 = float(glob["C_F"]), float(glob["mu1"]), float(glob["mu2"])
    eta_alg = c_f * math.sqrt(glob["rho_norm1"] ** 2 / mu1 + glob["rho_norm2"] ** 2 / mu2)
    eta_lin = c_f * math.sqrt(1.0 / mu1 + 1.0 / mu2) * glob["lam_minus_norm"] + 2.0 * nc_total
    return eta_lin, eta_alg


_LOCAL_KEYS = ("eta_osc1", "eta_osc2", "eta_nc", "eta_C")
_GLOBAL_KEYS = ("eta_glob1", "eta_glob2", "rho_norm1", "rho_norm2", "lam_minus_norm", "C_F")


def _map(x, name, m) -> np.ndarray:
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 1 or (m is not None and arr.shape[0] != m):
        raise DataError(f"{name} must be a per-triangle array of shape ({m},), got {arr.shape}")
    if not (np.isfinite(arr).all() and (arr >= 0).all()):
        raise DataError(f"{name} must be finite and non-negative")
    return arr


#: Triangles from which :func:`combine` sums the maps in the kernel threads (smaller
#: meshes: NumPy, and no kernel to compile for them).
BLOCK_SUM_TRIANGLES = 1 << 17


def _block_sums(eta_F1, eta_F2, local):
    """Return the six maps and their sums for :func:`combine`, from one pass of the threads.

    Returns ``(osc1, osc2, nc, eta_c, f1, f2, (sum d1^2, sum d2^2, sum (d2 + nc)^2,
    sum nc^2, sum eta_c))``, or None when the maps are small or not contiguous
    float64 arrays of one length (:func:`combine` then takes the NumPy path,
    which also names a map with a bad entry).  The sums run over fixed blocks
    (:mod:`fastmem.kernels.sums`): the same for every thread count, equal to
    NumPy's up to round-off.
    """
    arrays = [
        local["eta_osc1"],
        local["eta_osc2"],
        local["eta_nc"],
        local["eta_C"],
        eta_F1,
        eta_F2,
    ]
    m = getattr(arrays[0], "shape", (0,))[0] if getattr(arrays[0], "ndim", 0) == 1 else 0
    if m < BLOCK_SUM_TRIANGLES or not plain_float64(arrays, m):
        return None
    blocks = -(-m // _sums.BLOCK)
    out = np.empty((blocks, len(_sums.COMBINE_SUMS)))
    _par.parallel_for(_sums.combine_blocks, blocks, _sums.BLOCK, *arrays, out, grain=1)
    if out[:, 5].any():
        return None  # a bad entry: the NumPy path finds and names it
    totals = out[:, :5].sum(axis=0)
    return (*arrays, tuple(float(t) for t in totals))


def split_form(a0, d, c):
    r"""Return the second form of the layer bound (:mod:`fastmem.estimators.layers`).

    :math:`\tfrac12[(a_0 + D) + ((a_0 + D)^2 + 4(a_0 D + c))^{1/2}]`, where

    ``a0`` is the a of the fluxes measured against :math:`u_h` (no :math:`\eta_{nc}`,
    no :math:`\eta_w`); ``d`` :math:`= D = |||\tilde u - u_h||| = (\sum_K
    \eta_{nc,K}^2 + \eta_{w,K}^2)^{1/2}`; ``c`` as in the first form.  Proof:
    test the equation of the error :math:`u - u_h` with :math:`v = u - \tilde u`
    (the first form tests :math:`u - \tilde u` with itself).  The flux and residual terms give
    :math:`\le a_0|||v|||` (fluxes against :math:`u_h`) and the contact part
    :math:`\le c` as before, so with :math:`x = |||u - u_h|||` and
    :math:`|||v||| \le x + D`:
    :math:`x^2 = (\mu\nabla(u - u_h), \nabla v) + (\mu\nabla(u - u_h),
    \nabla(\tilde u - u_h)) \le a_0(x + D) + c + xD`, a quadratic whose
    positive root is this form.  It charges the squeeze about half of what the
    first form does where c dominates (:math:`\approx \sqrt c + (a_0 + D)/2`
    against :math:`\sqrt c + a/2 + D`); :func:`fastmem.estimators.terms.combine`
    returns the smaller of the two.
    """
    big = a0 + d
    return 0.5 * (big + math.sqrt(big * big + 4.0 * (a0 * d + c)))


def combine(eta_F1, eta_F2, local, glob) -> dict:
    r"""Combine all estimators into the guaranteed bound and its components.

    Parameters
    ----------
    eta_F1, eta_F2 : ndarray of shape (M,)
        Flux estimators :math:`\eta_{F,K,i} = \|\mu_i^{1/2}\nabla u_{ih} +
        \mu_i^{-1/2}\sigma_{ih}\|_K` from the flux reconstruction.
    local : dict
        Output of :func:`local_terms` (``eta_osc1``, ``eta_osc2``, ``eta_nc``, ``eta_C``).
    glob : dict
        Output of :func:`global_terms`.

    Returns
    -------
    dict
        ``totals`` (dict of str to float):

        - ``eta``: the guaranteed bound
          :math:`(a + \sqrt{a^2 + 4c})/2 + (\sum_K \eta_{nc,K}^2)^{1/2}`;
        - ``eta_disc``, ``eta_lin``, ``eta_alg``: the components of docs/method.md
          §6 (:math:`\eta \le \eta_{disc} + \eta_{lin} + \eta_{alg}`);
        - ``a``, ``c``: the coefficients of :math:`x^2 \le a x + c`;
        - ``eta_nc`` :math:`= (\sum_K \eta_{nc,K}^2)^{1/2}`, ``eta_glob1``,
          ``eta_glob2``, ``C_F``;
        - ``eta_unguaranteed_slides``:
          :math:`\{\sum_K [\sum_i (\eta_{osc,K,i} + \eta_{F,K,i})^2 + \eta_{C,K}]\}^{1/2}`,
          the form of the seed slides.  **Not a guaranteed bound**: from
          :math:`x^2 \le a x + c` it does not follow that
          :math:`x \le \sqrt{a^2 + c}` (``a = c = 1`` admits
          :math:`x = (1 + \sqrt 5)/2 \approx 1.618 > \sqrt 2`).  For comparison only.

        ``maps`` (dict of str to ndarray of shape (M,)): ``eta_F1``,
        ``eta_F2``, ``eta_osc1``, ``eta_osc2``, ``eta_nc``, ``eta_C``.

    Notes
    -----
    With :math:`a` and :math:`c` as in the module docstring, the theorem of
    docs/method.md §5 states :math:`|||u - u_h||| \le \eta` for every
    :math:`u_h \in X_{gh} \times X_{0h}` and every :math:`\lambda_h \in X_{0h}`
    of any sign, with no assumption on the iterate.

    Proof sketch.  Let :math:`\delta = (u_{2h} - u_{1h})^+` and
    :math:`\tilde u = (u_{1h}, u_{2h} - \delta)`, which lies in the convex
    set :math:`K_g` (:math:`\delta \in H^1_0` since :math:`g \ge 0`).  Then
    :math:`|||u - u_h||| \le |||u - \tilde u||| + |||\tilde u - u_h|||`, and
    the last term is :math:`(\sum_K \eta_{nc,K}^2)^{1/2}`.  With
    :math:`e = u - \tilde u`, the weak form and :math:`\sigma_{ih}` give

    .. math::

        |||e|||^2 = \sum_i (r_i, e_i) - \sum_i (\mu_i \nabla\tilde u_i
                    + \sigma_{ih}, \nabla e_i) + (\lambda - \hat\lambda, e_1 - e_2)

    with :math:`r_1 = f_1 + \hat\lambda - \operatorname{div}\sigma_{1h}
    = (f_1 - \Pi f_1) + \rho_1 + \lambda^-` and
    :math:`r_2 = (f_2 - \Pi f_2) + \rho_2 - \lambda^-`.  The oscillation
    part is orthogonal to :math:`P_1(K)`: Poincaré on convex :math:`K`
    (:math:`h_K/\pi`).  The P1 part: Friedrichs on :math:`\Omega`
    (:math:`C_F`).  The flux part: Cauchy–Schwarz, with
    :math:`\nabla\tilde u_2 = \nabla u_{2h} - \nabla\delta` giving the
    :math:`+\eta_{nc,K}`.  The contact part: :math:`(\lambda, u_1 - u_2) = 0`,
    :math:`-(\lambda, \tilde u_1 - \tilde u_2) \le 0`,
    :math:`-(\hat\lambda, u_1 - u_2) \le 0`, leaving
    :math:`(\hat\lambda, (u_{1h} - u_{2h})^+) = c`.  Hence
    :math:`|||e|||^2 \le a |||e||| + c`, whose positive root
    :math:`(a + \sqrt{a^2 + 4c})/2` bounds :math:`|||e|||`.

    For per-triangle tensions the global terms use :math:`\min_K \mu_{i,K}`
    (see :func:`global_terms`) and the oscillation :math:`\mu_{i,K}^{-1/2}` of
    its own triangle: the Poincaré step is local,
    :math:`(f - \Pi_K f, e)_K \le \frac{h_K}{\pi}\|f - \Pi_K f\|_K
    \|\nabla e\|_K = \frac{h_K}{\pi}\mu_{i,K}^{-1/2}\|f - \Pi_K f\|_K
    \|\mu_i^{1/2}\nabla e\|_K`, and the sum over K is then bounded by
    Cauchy-Schwarz together with the flux terms (issue 16 review: correct as
    implemented, nothing sharper without changing the term's form).

    Contact load (issue 16).  The proof uses :math:`\hat\lambda` only as some
    :math:`\ell \ge 0` with :math:`\nabla\cdot\sigma_{1h} = \Pi f_1 + \ell -
    \lambda^- - \rho_1` and :math:`\nabla\cdot\sigma_{2h} = \Pi f_2 - \ell +
    \lambda^- - \rho_2`: then :math:`r_1, r_2` are as above and the contact
    part gives :math:`(\lambda - \ell, e_1 - e_2) \le (\ell, (u_{1h} -
    u_{2h})^+)`.  :func:`fastmem.estimators.bound.evaluate` replaces :math:`\hat\lambda`
    by the glued contact load :math:`\ell = \chi + \lambda^- \ge 0` of
    :func:`fastmem.estimators.flux.glued_contact_load` when the tensions differ: not P1
    on the closed triangles it changes, so there the oscillation is that of
    :math:`f_1 + \chi` and :math:`f_2 - \chi`, and c is :math:`(\ell, (u_{1h} -
    u_{2h})^+)` with the nodal values of :meth:`~fastmem.estimators.flux.ContactLoad.open_load`
    (:func:`contact_local_terms`); the global terms are unchanged.
    """
    missing = [k for k in (*_GLOBAL_KEYS, "mu1", "mu2") if k not in glob]
    if missing:
        raise DataError(f"glob lacks {missing}; pass the output of global_terms")
    g1, g2 = float(glob["eta_glob1"]), float(glob["eta_glob2"])
    c_f = float(glob["C_F"])
    layered = local.get("eta_w1") is not None or local.get("eta_w2") is not None
    sums = None if layered else _block_sums(eta_F1, eta_F2, local)
    if sums is not None:  # one pass in the kernel threads (large meshes)
        osc1, osc2, nc, eta_c, f1, f2, sums = sums
        m = osc1.shape[0]
        w1 = w2 = None
        sum_d1, sum_d2, sum_d2nc, nc_sq, c = sums
        w_sq = 0.0
    else:
        osc1 = _map(local["eta_osc1"], "eta_osc1", None)
        m = osc1.shape[0]
        osc2 = _map(local["eta_osc2"], "eta_osc2", m)
        nc = _map(local["eta_nc"], "eta_nc", m)
        eta_c = _map(local["eta_C"], "eta_C", m)
        f1 = _map(eta_F1, "eta_F1", m)
        f2 = _map(eta_F2, "eta_F2", m)
        # squeeze terms of the layer bound (fastmem.estimators.layers), zero otherwise
        w1 = _map(local["eta_w1"], "eta_w1", m) if local.get("eta_w1") is not None else None
        w2 = _map(local["eta_w2"], "eta_w2", m) if local.get("eta_w2") is not None else None
        d1 = osc1 + f1  # membrane 1 per triangle
        d2 = osc2 + f2  # membrane 2 per triangle, without the non-conformity
        if w1 is not None:
            d1 = d1 + w1
        if w2 is not None:
            d2 = d2 + w2
        sum_d1 = float(d1 @ d1)
        sum_d2 = float(d2 @ d2)
        d2nc = d2 + nc
        sum_d2nc = float(d2nc @ d2nc)
        nc_sq = float(nc @ nc)
        w_sq = sum(float(w @ w) for w in (w1, w2) if w is not None)
        c = float(eta_c.sum())
    nc_total = math.sqrt(nc_sq)
    w_total = math.sqrt(w_sq)
    a = math.sqrt(sum_d1 + sum_d2nc) + math.hypot(g1, g2)
    root = 0.5 * (a + math.sqrt(a * a + 4.0 * c))  # positive root of x^2 = a x + c
    eta = root + math.sqrt(nc_total**2 + w_sq)
    split = None
    if w1 is not None or w2 is not None:
        # the layer bound: also its second form (split_form), the smaller is returned
        p1, p2 = osc1 + f1, osc2 + f2
        a0 = math.sqrt(float(p1 @ p1) + float(p2 @ p2)) + math.hypot(g1, g2)
        split = split_form(a0, math.sqrt(nc_total**2 + w_sq), c)
        split_won = split < eta
        eta = min(eta, split)

    eta_lin, eta_alg = _lin_alg(glob, nc_total)
    eta_disc = math.sqrt(sum_d1 + sum_d2) + math.sqrt(c) + w_total
    slides = math.sqrt(sum_d1 + sum_d2 + c)

    totals = {
        "eta": eta,
        "eta_disc": eta_disc,
        "eta_lin": eta_lin,
        "eta_alg": eta_alg,
        "a": a,
        "c": c,
        "eta_nc": nc_total,
        "eta_glob1": g1,
        "eta_glob2": g2,
        "C_F": c_f,
        "eta_unguaranteed_slides": slides,
    }
    if split is not None:
        totals["split_form"] = float(split_won)
    maps = {
        "eta_F1": f1,
        "eta_F2": f2,
        "eta_osc1": osc1,
        "eta_osc2": osc2,
        "eta_nc": nc,
        "eta_C": eta_c,
    }
    if w1 is not None or w2 is not None:
        maps["eta_w1"] = np.zeros(m) if w1 is None else w1
        maps["eta_w2"] = np.zeros(m) if w2 is None else w2
    logger.debug(
        "estimators: eta=%.3e disc=%.3e lin=%.3e alg=%.3e (a=%.3e c=%.3e)",
        eta,
        eta_disc,
        eta_lin,
        eta_alg,
        a,
        c,
    )
    return {"totals": totals, "maps": maps}


def refinement_indicators(maps) -> np.ndarray:
    r"""Per-triangle refinement indicators :math:`\eta_K^2` from estimator maps.

    :math:`\sum_i (\eta_{osc,K,i} + \eta_{F,K,i})^2 + \eta_{nc,K}^2 + \eta_{C,K}`,
    plus the squeeze terms :math:`\eta_{w,K,1}^2 + \eta_{w,K,2}^2` of the layer
    bound when the maps have them (:mod:`fastmem.estimators.layers`).
    """
    out = (
        (maps["eta_osc1"] + maps["eta_F1"]) ** 2
        + (maps["eta_osc2"] + maps["eta_F2"]) ** 2
        + maps["eta_nc"] ** 2
        + maps["eta_C"]
    )
    if "eta_w1" in maps:
        out = out + maps["eta_w1"] ** 2 + maps["eta_w2"] ** 2
    return out
