r"""Linear steps of Newton-min: given an active set, return the next full triple.

Two formulations (docs/method.md §3.2 and 3.3) with the same interface::

    step = GeneralStep(scene)            # or DecoupledStep(scene)
    u1, u2, lam = step.solve(active)     # active: bool mask over interior vertices

Both return nodal vectors on all vertices (``u1 = g``, ``u2 = 0``, ``lam = 0``
on the boundary), ``lam = 0`` on the inactive set and ``lam`` recovered from
the first equation on the active set, so that with exact solves they produce
identical iterates.

General path (any mu, also per triangle): with :math:`K = \mathrm{diag}(A_1, A_2)`,
:math:`A_i = \mu_i A` on interior vertices and :math:`P` copying
:math:`u_{1,a}` into :math:`u_{2,a}` on the active set,

.. math::  P^T K P\,x = P^T (F - K_{IB} u_B), \qquad
           \lambda_a = ((A_1 u_1)_a - F_{1,a}) / B_a \ (a \in \mathcal A).

Decoupled path (constant mu): :math:`s = \mu_1 u_1 + \mu_2 u_2` solves one
Poisson problem, the gap :math:`w = u_1 - u_2` an obstacle problem whose
Newton-min step is :math:`A_{\mathcal I\mathcal I} w_{\mathcal I} = \dots`, :math:`w = 0` on
:math:`\mathcal A`, and :math:`\lambda_a = ((A w)_a - F^w_a) / (\kappa B_a)`.

Exact solves use SuperLU (scipy) in a nested-dissection order computed from
the vertex of every unknown (:func:`fastmem.linalg.direct.factorize`), so that their
cost does not depend on how the mesh numbers its vertices (refined, gmsh and
adaptively refined meshes factor as fast as structured ones); the
factorisation of the interior Laplacian is computed once and reused for ``s``
and for every step whose active set is empty.
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp

from ..errors import ParameterError
from ..fem.residual import fused_residuals
from ..fem.scene import Scene
from ..kernels import pool as _par
from ..kernels import rows as _rows
from ..linalg.direct import factorize
from ..linalg.sparse import (
    THREADED_ROWS,
    as_unsigned,
    plain_float64,
    read_only,
    submatrix,
    threaded_submatrix,
)
from ..mesh.mesh import Mesh

__all__ = ["DecoupledStep", "GeneralStep", "make_step"]

logger = logging.getLogger(__name__)


class _NoUnknowns:
    """Factors of a 0 x 0 system (a mesh without interior vertices)."""

    def solve(self, rhs):
        return np.zeros(0)


def _factor(mat, coordinates):
    """Sparse LU factors of an SPD matrix, ordered from the unknowns' vertices."""
    if mat.shape[0] == 0:
        return _NoUnknowns()
    lu = factorize(mat, coordinates)
    logger.debug("factorised %r", lu)
    return lu


class _Base:
    def __init__(self, scene):
        self.scene = scene
        mesh = scene.mesh
        self.interior = mesh.interior_vertices
        self.boundary = mesh.boundary_vertices
        self.n = mesh.n_vertices
        self.b_int = mesh.lumped_mass[self.interior]
        self.g_full = scene.boundary_values
        self.factorizations = 0

    @property
    def xy(self):
        """Coordinates of the interior vertices (the direct solver's ordering; not kept)."""
        return self.scene.mesh.vertices[self.interior]

    def _full(self, interior_values, boundary_values=0.0):
        out = np.empty(self.n)
        ii = self.interior
        if ii.size >= THREADED_ROWS and plain_float64((interior_values,), ii.size):
            _par.parallel_for(_rows.spread_range, ii.size, ii, read_only(interior_values), out)
        else:
            out[ii] = interior_values
        out[self.boundary] = (
            boundary_values if np.isscalar(boundary_values) else (boundary_values[self.boundary])
        )
        return out


class GeneralStep(_Base):
    """Newton-min linear step on the reduced SPD system (docs/method.md §3.2)."""

    name = "general"

    def __init__(self, scene):
        super().__init__(scene)
        ii = self.interior
        a1 = scene.weighted_stiffness(1)
        self.a1_ii = submatrix(a1, ii, ii)
        f1, f2 = scene.loads
        lift = a1 @ self.g_full  # u1 = g on the boundary, u2 = 0
        self.rhs1 = f1[ii] - lift[ii]
        self.rhs2 = f2[ii].copy()
        # A2_II only enters K (not kept: 84 bytes per vertex)
        self.k_ii = self.reduced_stiffness()
        self._lu_empty = None

    def reduced_stiffness(self):
        """Return ``K_II = diag(A1_II, A2_II)``, CSR (a new matrix, the same bits each call).

        The step's :attr:`k_ii`; rebuilt by :meth:`fastmem.solver.steps.GeneralCG.restore` after
        a flux reconstruction that ran without it.
        """
        ii = self.interior
        a2_ii = submatrix(self.scene.weighted_stiffness(2), ii, ii)
        return sp.block_diag([self.a1_ii, a2_ii], format="csr")

    def prolongation(self, active):
        """Build the injection P from reduced unknowns (u1 on I, u2 on inactive) to (u1, u2)."""
        ni = self.interior.size
        inactive = ~active
        n_in = int(inactive.sum())
        cols2 = np.empty(ni, dtype=np.int64)
        cols2[inactive] = ni + np.arange(n_in)
        cols2[active] = np.flatnonzero(active)
        cols = np.concatenate([np.arange(ni), cols2])
        return sp.csr_matrix(
            (np.ones(2 * ni), cols, np.arange(2 * ni + 1)), shape=(2 * ni, ni + n_in)
        )

    def solve(self, active):
        """Solve the step for the active set ``active`` (bool, interior vertices)."""
        p = self.prolongation(active)
        rhs = p.T @ np.concatenate([self.rhs1, self.rhs2])
        if not active.any() and self._lu_empty is not None:
            lu = self._lu_empty
        else:
            lu = _factor(p.T @ self.k_ii @ p, np.vstack([self.xy, self.xy[~active]]))
            self.factorizations += 1
            if not active.any():
                self._lu_empty = lu
        return self.triple(active, p @ lu.solve(rhs))

    def triple(self, active, x):
        """Full triple from interior values ``x = (u1_I, u2_I)`` (u2 = u1 on the active set)."""
        ni = self.interior.size
        u1_i, u2_i = x[:ni], x[ni:]
        lam_i = np.zeros(ni)
        # (A1 u1)_a - F1_a = (A1_II u1_I)_a - rhs1_a, since rhs1 = F1_I - A1_IB g_B
        lam_i[active] = ((self.a1_ii @ u1_i) - self.rhs1)[active] / self.b_int[active]
        return self._full(u1_i, self.g_full), self._full(u2_i), self._full(lam_i)


class DecoupledStep(_Base):
    """Newton-min linear step on the decoupled sum/gap system (docs/method.md §3.3)."""

    name = "decoupled"

    def __init__(self, scene):
        if not scene.constant_mu:
            raise ParameterError(
                "path='decoupled' needs constant mu1 and mu2; this scene has per-triangle "
                "values (use path='general' or 'auto')"
            )
        super().__init__(scene)
        ii = self.interior
        mu1, mu2 = scene.mu1, scene.mu2
        self.mu1, self.mu2 = mu1, mu2
        self.kappa = 1.0 / mu1 + 1.0 / mu2
        a = scene.stiffness
        self.a_ii = self.interior_laplacian()
        f1, f2 = scene.loads
        # s = mu1 g on the boundary; w = g on the boundary.
        g = self.g_full
        if (
            ii.size >= THREADED_ROWS
            and plain_float64((f1, f2, g), self.n)
            and a.dtype == np.float64
            and a.indptr.dtype == a.indices.dtype
        ):  # one pass of the kernel threads over the interior rows, the same bits
            self.rhs_w, self.rhs_s = np.empty(ii.size), np.empty(ii.size)
            _par.parallel_for(
                _rows.decoupled_rhs_range, ii.size, read_only(ii), as_unsigned(a.indptr),
                as_unsigned(a.indices), a.data, read_only(g), read_only(f1), read_only(f2),
                float(mu1), float(mu2), self.rhs_w, self.rhs_s,
            )  # fmt: skip
        else:
            lift = a @ g  # A restricted to boundary columns applied to g
            fw = f1 / mu1 - f2 / mu2
            self.rhs_w = fw[ii] - lift[ii]
            self.rhs_s = (f1 + f2)[ii] - mu1 * lift[ii]
        self._lu = None
        self._s = None

    def interior_laplacian(self):
        """Return ``A`` restricted to the interior vertices, CSR (new, the same bits each call).

        The step's :attr:`a_ii`; rebuilt by :meth:`fastmem.solver.steps.DecoupledCG.restore` after
        a flux reconstruction that ran without it.
        """
        ii = self.interior
        return submatrix(self.scene.stiffness, ii, ii)

    @property
    def s_boundary(self):
        """``mu1 g`` on all vertices (the boundary values of s; computed on use, not kept)."""
        return self.mu1 * self.g_full

    @property
    def _lu_all(self):
        """SuperLU factors of the interior Laplacian, computed on first use."""
        if self._lu is None:
            self._lu = _factor(self.a_ii, self.xy)
            self.factorizations += 1
        return self._lu

    @property
    def s(self):
        """The sum ``s = mu1 u1 + mu2 u2`` on all vertices (exact solve, first use)."""
        if self._s is None:
            self._s = self._full(self._lu_all.solve(self.rhs_s), self.s_boundary)
        return self._s

    def solve(self, active):
        """Solve the step for the active set ``active`` (bool, interior vertices)."""
        inactive = ~active
        w_i = np.zeros(self.interior.size)
        if active.any():
            sub = self.a_ii[inactive][:, inactive]
            if sub.shape[0]:
                w_i[inactive] = _factor(sub, self.xy[inactive]).solve(self.rhs_w[inactive])
                self.factorizations += 1
        else:
            w_i[:] = self._lu_all.solve(self.rhs_w)
        return self.triple(active, self.s, w_i)

    def triple(self, active, s, w_i):
        """Full triple from the sum ``s`` and the interior gap ``w_i``.

        ``s`` holds all vertices or the interior ones (its boundary values do not
        enter).  From :data:`~fastmem.linalg.sparse.THREADED_ROWS` interior vertices
        on, one pass of the kernel threads (:mod:`fastmem.kernels.rows`) with the
        same operations, so the same bits.
        """
        fused = self._triple_threaded(active, s, w_i)
        if fused is not None:
            return fused
        if s.shape[0] != self.n:
            s = self._full(s, self.s_boundary)
        lam_i = np.zeros_like(w_i)
        lam_i[active] = ((self.a_ii @ w_i)[active] - self.rhs_w[active]) / (
            self.kappa * self.b_int[active]
        )
        w = self._full(w_i, self.g_full)
        m = self.mu1 + self.mu2
        u1 = (s + self.mu2 * w) / m
        u2 = (s - self.mu1 * w) / m
        u1[self.boundary] = self.g_full[self.boundary]
        u2[self.boundary] = 0.0
        return u1, u2, self._full(lam_i)

    def _triple_threaded(self, active, s, w_i):
        """:meth:`triple` in the kernel threads, or None (small, or arrays it does not take)."""
        ni, a = self.interior.size, self.a_ii
        if (
            ni < THREADED_ROWS
            or not plain_float64((w_i,), ni)
            or not (plain_float64((s,), self.n) or plain_float64((s,), ni))
            or not isinstance(a, sp.csr_matrix)
            or a.indices.dtype not in (np.int32, np.int64)
            or a.indptr.dtype != a.indices.dtype
        ):
            return None
        return threaded_triple(self, active, s, w_i)


def threaded_triple(step, active, s, w_i):
    """:meth:`DecoupledStep.triple` by the kernels of :mod:`fastmem.kernels.rows`, any size.

    (:func:`fastmem.warm_up` compiles them on a tiny mesh.)
    """
    ni, a = step.interior.size, step.a_ii
    active = read_only(np.ascontiguousarray(active, dtype=np.bool_))
    s, w_i = read_only(np.ascontiguousarray(s)), read_only(np.ascontiguousarray(w_i))
    u1, u2, lam = np.empty(step.n), np.empty(step.n), np.empty(step.n)
    _par.parallel_for(
        _rows.decoupled_triple_range, ni, step.interior, active, s, s.shape[0] == step.n,
        w_i, as_unsigned(a.indptr), as_unsigned(a.indices), np.ascontiguousarray(a.data),
        read_only(step.rhs_w), float(step.kappa), read_only(step.b_int), float(step.mu1),
        float(step.mu2), u1, u2, lam,
    )  # fmt: skip
    _par.parallel_for(
        _rows.boundary_triple_range, step.boundary.size, step.boundary,
        read_only(step.g_full), u1, u2, lam,
    )  # fmt: skip
    return u1, u2, lam


def precompile() -> None:
    """Compile (or load) the linear steps' threaded passes, with the types of a solve.

    The interior block (:func:`fastmem.linalg.sparse.submatrix`), the residuals of a
    triple (:func:`fastmem.fem.residual.residuals`) and the decoupled step's triple,
    which run in the kernel threads from
    :data:`~fastmem.linalg.sparse.THREADED_ROWS` vertices on: here on a tiny mesh.
    :func:`fastmem.warm_up` calls it for large meshes and solves to a tolerance (in
    its helper process, with the bisection kernels, where it has one).
    """
    mesh = Mesh.square(4)
    scene = Scene(mesh, mu=(1.0, 2.0), f=(-1.0, 1.0), g=0.1)
    ii = mesh.interior_vertices
    threaded_submatrix(scene.stiffness, ii, ii)
    z = np.zeros(mesh.n_vertices)
    fused_residuals(
        scene.weighted_stiffness(1), scene.weighted_stiffness(2), z, z, z, *scene.loads,
        mesh.lumped_mass, mesh.boundary_vertex_mask,
    )  # fmt: skip
    step = DecoupledStep(scene)
    threaded_triple(step, np.zeros(ii.size, dtype=bool), z, z[ii])
    # the gap CG's start (fastmem.solver.steps.DecoupledCG) and the weight of the first
    # active set of a prolonged triple (fastmem.fem.scene.Scene.active_weight)
    frozen = read_only(z)
    index = read_only(np.asarray(ii, dtype=np.int64))
    mask = read_only(np.zeros(ii.size, dtype=bool))
    out, out2 = np.empty(ii.size), np.empty(ii.size)
    _rows.gap_start_range(0, ii.size, index, mask, read_only(z[ii]), frozen, frozen, out, out2)
    ones = read_only(np.ones(mesh.n_vertices))
    _rows.active_weight_range(0, ii.size, index, ones, ones, ones, ones, out)
    flags = np.empty(ii.size, dtype=np.bool_)
    _rows.active_rule_range(0, ii.size, index, 1.0, frozen, frozen, frozen, flags)
    _rows.warm_active_range(0, ii.size, index, read_only(out), frozen, frozen, frozen, flags)
    _rows.spread_range(0, ii.size, index, read_only(out2), np.empty(mesh.n_vertices))
    full = np.empty(mesh.n_vertices)
    _rows.lambda_parts_range(0, z.size, frozen, mesh.boundary_vertex_mask, full, np.empty(z.size))
    a = scene.stiffness
    _rows.decoupled_rhs_range(
        0, ii.size, index, as_unsigned(a.indptr), as_unsigned(a.indices), a.data, frozen,
        frozen, frozen, 1.0, 2.0, out, out2,
    )  # fmt: skip


def make_step(scene, path: str = "auto"):
    """Build the linear-step object for ``path`` in {"auto", "general", "decoupled"}."""
    if path == "auto":
        path = "decoupled" if scene.constant_mu else "general"
    if path == "general":
        return GeneralStep(scene)
    if path == "decoupled":
        return DecoupledStep(scene)
    raise ParameterError(f"path must be 'auto', 'general' or 'decoupled', got {path!r}")
