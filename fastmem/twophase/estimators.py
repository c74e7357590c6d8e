r"""Estimators of the liquid–gas time steps: discretisation, linearisation, algebraic parts.

Derivation and choices: docs/twophase.md §4.  In short, for one backward
Euler step and a Newton-min iterate ``x = x_base + alpha d`` (``d`` the
linear solver's answer to ``J d = -R(x_base)``, ``alpha`` the step length,
then the projection on the admissible box):

* the component residuals ``R_c(x)`` (kg/s per cell) split exactly into what
  the linear solver left, ``r_alg = alpha (R(x_base) + J d)`` (the algebraic
  part), and the remainder ``R_c(x) - r_alg`` (the linearisation part);
* each cell residual ``s`` becomes a face flux ``sigma(s)`` with
  ``div sigma(s) = s`` cell by cell, the two-point flux of the potential
  ``L^{-1} s`` (``L`` the grid's Laplacian with the geometric factors and the
  Dirichlet faces); its squared norm ``sum_f sigma_f^2 / g_f = s . L^{-1} s``
  is the discrete dual norm of ``s``;
* the equilibrated component flux is
  ``sigma_c = F_c(x) - sigma(r_alg) - sigma(R_c(x) - r_alg)``:
  ``storage + div sigma_c = source`` holds in every cell to round-off, and its
  three pieces are the discretisation flux, the linearisation flux and the
  algebraic flux;
* ``eta_disc`` measures what a conforming flux would change: the jump of the
  discrete flux within every cell (``h_K^2/12 (div F_K)^2 / |K|``, exact for
  piecewise-linear against two-point fluxes in 1D), the flux's change over
  the step (``|F^n - F^{n-1}|^2 / 3``: time lumped in, as the paper does) and
  the phase-transition term (the complementarity product at mid-step in the
  cells that change phase);
* the complementarity rows enter ``eta_lin`` (nonlinear minus linearised) and
  ``eta_alg`` (linearised residual) like a third component.

No proof that ``eta_disc + eta_lin + eta_alg`` bounds an error of the scheme
is claimed (docs/twophase.md §4).

Components are measured in pore volume per second: water divided by
``rho_w``, hydrogen by ``H P_ref``.  Every estimator is multiplied by
``sqrt(dt)`` (the ``L^2`` norm over the step).  :attr:`Estimate.total` is
``eta_disc + eta_lin + eta_alg``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

from ..errors import ParameterError

__all__ = ["WEIGHTS", "Estimate", "Estimator"]

#: How the components are weighed: ``volume`` (pore volume per second: water over
#: ``rho_w``, hydrogen over ``H P_ref``) or ``mass`` (kg/s as they come, as the
#: reference paper does: water then outweighs hydrogen by about 5e4).
WEIGHTS = ("volume", "mass")


@dataclass
class Estimate:
    """Estimators of one iterate of one time step (see the module docstring)."""

    disc: float
    lin: float
    alg: float
    space: float = 0.0
    time: float = 0.0
    transition: float = 0.0

    @property
    def total(self) -> float:
        """``eta_disc + eta_lin + eta_alg``."""
        return self.disc + self.lin + self.alg

    def as_dict(self) -> dict:
        """Return the estimators by name."""
        return {
            "disc": self.disc,
            "lin": self.lin,
            "alg": self.alg,
            "total": self.total,
            "space": self.space,
            "time": self.time,
            "transition": self.transition,
        }


class Estimator:
    """Evaluates :class:`Estimate` for a :class:`~fastmem.twophase.model.Problem`."""

    def __init__(self, problem, weights: str = "volume"):
        if weights not in WEIGHTS:
            raise ParameterError(f"weights must be one of {', '.join(WEIGHTS)}, got {weights!r}")
        self.weights = weights
        g = problem.grid
        if g.boundary_cells.size == 0:
            raise ParameterError(
                "the two-phase estimators need a Dirichlet face (the grid has none): give "
                "the grid boundary faces, or solve with strategy='exact' or 'inexact'"
            )
        self.problem = problem
        n = g.n
        left, right = g.faces[:, 0], g.faces[:, 1]
        w = g.geometry
        diag = np.bincount(left, w, n) + np.bincount(right, w, n)
        diag += np.bincount(g.boundary_cells, g.boundary_geometry, n)
        lap = sp.coo_matrix(
            (
                np.concatenate([diag, -w, -w]),
                (np.r_[np.arange(n), left, right], np.r_[np.arange(n), right, left]),
            ),
            shape=(n, n),
        ).tocsc()
        self._lu = splu(lap)
        ph = problem.physics
        p_ref, _ = problem.references()
        #: divisors taking water, hydrogen (kg/s) and the min rows to pore volume per second
        self.henry_ref = ph.henry_mass * p_ref
        if weights == "volume":
            self.scale = np.array([ph.rho_w, self.henry_ref])
            self.min_scale = np.array([1.0, self.henry_ref])  # (1 - S rows, Henry rows)
        else:  # "mass": kg/s as they come (the reference paper's measure)
            self.scale = np.array([1.0, 1.0])
            self.min_scale = np.array([1.0 / ph.rho_w, 1.0])
        h = g.volume ** (1.0 / g.dim)
        self._cell_weight = h**2 / 12.0 / g.volume

    # ------------------------------------------------------------------ building blocks
    def potential(self, s):
        """``L^{-1} s`` for cell sources ``s`` (N,) or (N, k)."""
        return self._lu.solve(np.asarray(s, dtype=float))

    def flux(self, s):
        """Interior and boundary face fluxes ``(F (F,), F_b (B,))`` with divergence ``s``."""
        g = self.problem.grid
        phi = self.potential(s)
        shape = (-1,) + (1,) * (phi.ndim - 1)
        fi = g.geometry.reshape(shape) * (phi[g.faces[:, 0]] - phi[g.faces[:, 1]])
        fb = g.boundary_geometry.reshape(shape) * phi[g.boundary_cells]
        return fi, fb

    def dual_norm2(self, s) -> float:
        """``s . L^{-1} s`` summed over the columns of ``s`` (N, k)."""
        s = np.asarray(s, dtype=float).reshape(self.problem.grid.n, -1)
        return float(np.sum(s * self.potential(s)))

    def face_norm2(self, fi, fb) -> float:
        """``sum_f F_f^2 / g_f`` over interior and boundary faces (columns summed)."""
        g = self.problem.grid
        fi = np.asarray(fi).reshape(g.faces.shape[0], -1)
        fb = np.asarray(fb).reshape(g.boundary_cells.size, -1)
        return float(
            np.sum(fi**2 / g.geometry[:, None]) + np.sum(fb**2 / g.boundary_geometry[:, None])
        )

    def min_rows_as_rate(self, rows, gas, dt):
        """Complementarity row values (N,) as pore volume per second."""
        pore = self.problem.grid.volume * self.problem.physics.porosity / dt
        if self.problem.complementarity == "fb":  # dimensionless, like 1 - S
            return pore * rows / self.min_scale[0]
        return pore * np.where(gas, rows / self.min_scale[1], rows / self.min_scale[0])

    # ------------------------------------------------------------------ the estimate
    def disc_terms(self, x, x_old, flux_old, dt):
        """``(space^2, time^2, transition^2)`` without the ``dt`` factor; fluxes at ``x``."""
        prob = self.problem
        fi, fb = prob.fluxes(x)
        fi = fi / self.scale
        fb = fb / self.scale
        div = prob.divergence(fi, fb)
        space = float(np.sum(self._cell_weight[:, None] * div**2))
        # flux mismatch: the two-point flux against the flux each side's own coefficients
        # give (upwinded mobilities and face averages against cell values)
        left, right, inner = prob.cell_side_fluxes(x)
        g = prob.grid
        space += (
            float(
                np.sum(
                    ((left / self.scale - fi) ** 2 + (right / self.scale - fi) ** 2)
                    / g.geometry[:, None]
                )
                + np.sum((inner / self.scale - fb) ** 2 / g.boundary_geometry[:, None])
            )
            / 3.0
        )
        time = 0.0
        if flux_old is not None:
            time = self.face_norm2(fi - flux_old[0], fb - flux_old[1]) / 3.0
        # phase transition: cells whose phase changes over the step, the complementarity
        # product of the mid-step state (both factors >= 0 at the two ends otherwise)
        mid = 0.5 * (x + x_old)
        one, two = prob.branches(mid)
        changed = prob.gas(x) != prob.gas(x_old)
        # the product of the two (dimensionless) arguments, in the min rows' units
        prod = (
            np.where(changed, np.sqrt(np.maximum(one, 0) * np.maximum(two, 0) / self.henry_ref), 0)
            / self.min_scale[0]
        )
        pore = prob.grid.volume * prob.physics.porosity / dt
        transition = self.dual_norm2(pore * prod)
        return space, time, transition, (fi, fb)

    def estimate(self, x, x_old, r_alg, gas, dt, t, flux_old=None) -> tuple:
        """Return ``(Estimate, scaled fluxes at x)`` for the iterate ``x``.

        ``r_alg`` (N, 3, kg/s and min-row units) is what the linear solver left
        of the Newton-min system, times the step length taken: the residual of
        ``x`` splits into it and the linearisation remainder ``R(x) - r_alg``.
        ``gas`` are the branches of the Newton-min system; ``flux_old`` the
        scaled fluxes at the start of the step (None: no time term).
        """
        prob = self.problem
        r_alg = np.asarray(r_alg, dtype=float).reshape(-1, 3)
        r_now = prob.residual(x, x_old, dt, t, gas)
        c_now = prob.complementarity_residual(x)
        alg_min = self.min_rows_as_rate(r_alg[:, 2], gas, dt)
        lin_min = self.min_rows_as_rate(c_now, prob.gas(x), dt) - alg_min
        alg2 = self.dual_norm2(np.column_stack([r_alg[:, :2] / self.scale, alg_min]))
        lin2 = self.dual_norm2(
            np.column_stack([(r_now[:, :2] - r_alg[:, :2]) / self.scale, lin_min])
        )
        space, time, transition, fluxes = self.disc_terms(x, x_old, flux_old, dt)
        est = Estimate(
            disc=float(np.sqrt(dt * (space + time + transition))),
            lin=float(np.sqrt(dt * lin2)),
            alg=float(np.sqrt(dt * alg2)),
            space=float(np.sqrt(dt * space)),
            time=float(np.sqrt(dt * time)),
            transition=float(np.sqrt(dt * transition)),
        )
        return est, fluxes

    def equilibrated(self, x, x_old, gas, dt, t):
        """Return the equilibrated component fluxes ``(sigma (F, 2), sigma_b (B, 2))``, kg/s.

        ``storage(x) - storage(x_old)) / dt + div sigma = Q`` in every cell.
        """
        prob = self.problem
        r_now = prob.residual(x, x_old, dt, t, gas)[:, :2]
        fi, fb = prob.fluxes(x)
        ci, cb = self.flux(r_now)
        return fi - ci, fb - cb
