r"""The liquid–gas model with gas appearance: data, grid, discrete equations, Jacobian.

The discrete equations are finite volumes with two-point fluxes on a *cell
graph*: cells with volumes, and faces joining two cells (or a cell and a
Dirichlet boundary) with a geometric factor ``g = area / distance``.  The 1D
column of the benchmark (cell-centred, ``g = 1/dx``) and the 2D vertex-centred
scheme on a triangular mesh (dual cells, ``g`` from the P1 stiffness) are both
such graphs (:class:`Grid`, docs/twophase.md §2).  Unknowns per cell
``X = (S, P, chi)``: liquid saturation, liquid pressure, dissolved hydrogen
molar fraction (docs/twophase.md).  Per cell ``i``, backward Euler
from ``X°``:

.. math::

    R_{w,i} &= |V_i|\varphi\rho_w \frac{S_i - S_i^\circ}{\Delta t}
             + \sum_{f \ni i} \pm F_{w,f} - Q_{w,i}, \\
    R_{h,i} &= |V_i|\varphi\frac{m_h(X_i) - m_h(X_i^\circ)}{\Delta t}
             + \sum_{f \ni i} \pm F_{h,f} - Q_{h,i}, \\
    C_i &= \min\{1 - S_i,\ H(P_i + P_c(S_i)) - \beta_l\chi_i\},

with the hydrogen mass per pore volume :math:`m_h = \beta_l\chi S + \beta_g P_g (1 - S)`,
:math:`P_g = P + P_c(S)`, and the face fluxes from the first cell ``l`` to the
second ``r`` (kg/s per unit depth or cross-section)

.. math::

    F_w = \rho_w q_l - J,\qquad F_h = \beta_l\bar\chi q_l + \beta_g \bar P_g q_g + J,\\
    q_l = -K g\,\lambda_l (P_r - P_l),\quad q_g = -K g\,\lambda_g (P_{g,r} - P_{g,l}),\quad
    J = -\varphi M_h \bar S\Big(\frac{\rho_w}{M_w} + \frac{\beta_l\bar\chi}{M_h}\Big) D g
        (\chi_r - \chi_l),

mobilities :math:`\lambda_\alpha = k_{r\alpha}/\mu_\alpha` upwinded by the sign of
the phase's potential difference, arithmetic face averages
:math:`\bar S, \bar\chi, \bar P_g` (the reference paper's choices).

The Jacobian is exact to round-off: the derivatives of every face flux with
respect to its six inputs, and of every storage term with respect to its
three, are taken by the complex step on whole arrays (nine vectorised
evaluations), then scattered into a CSR matrix whose pattern is built once.
Newton-min takes, per cell, the row of the smaller argument of the min.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import ParameterError
from ..mesh.mesh import Mesh
from .laws import VanGenuchten

__all__ = ["COMPLEMENTARITY", "R_GAS", "YEAR", "Grid", "Physics", "Problem", "mesh_grid"]

#: The complementarity functions: Newton-min, or Newton on Fischer-Burmeister.
COMPLEMENTARITY = ("min", "fb")

#: Seconds per year (365.25 days).
YEAR = 365.25 * 86400.0
#: Gas constant (J mol^-1 K^-1).
R_GAS = 8.314462618
#: Complex-step size (any tiny value is exact for analytic laws).
_H = 1e-30

_POSITIVE = (
    "porosity",
    "permeability",
    "mu_l",
    "mu_g",
    "rho_w",
    "molar_w",
    "molar_h",
    "diffusion",
    "henry",
    "temperature",
    "pr",
)


@dataclass(frozen=True)
class Physics:
    """Material and fluid data of the model, SI units (``temperature`` in kelvin).

    The defaults are the Couplex-Gas / MoMaS hydrogen benchmark with the MoMaS
    viscosities (docs/twophase.md); ``henry`` is ``H~`` in mol Pa^-1 m^-3.
    """

    porosity: float = 0.15
    permeability: float = 5e-20
    mu_l: float = 1e-3
    mu_g: float = 9e-6
    rho_w: float = 1e3
    molar_w: float = 1e-2
    molar_h: float = 2e-3
    diffusion: float = 3e-9
    henry: float = 7.65e-6
    temperature: float = 303.0
    pr: float = 2e6
    n: float = 1.49
    slr: float = 0.4
    sgr: float = 0.0

    def __post_init__(self):
        for name in _POSITIVE:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ParameterError(f"Physics.{name} must be a number, got {value!r}")
            if not (math.isfinite(value) and value > 0):
                raise ParameterError(f"Physics.{name} must be positive and finite, got {value!r}")
        if not self.porosity <= 1:
            raise ParameterError(f"Physics.porosity must be in (0, 1], got {self.porosity!r}")
        if not (isinstance(self.n, (int, float)) and self.n > 1):
            raise ParameterError(f"Physics.n must exceed 1 (m = 1 - 1/n > 0), got {self.n!r}")
        if not (0 <= self.slr < 1 and 0 <= self.sgr < 1 and self.slr + self.sgr < 1):
            raise ParameterError(
                "Physics residual saturations must satisfy 0 <= slr, 0 <= sgr, slr + sgr < 1; "
                f"got slr={self.slr!r}, sgr={self.sgr!r}"
            )

    @property
    def beta_l(self) -> float:
        """``rho_w M_h / M_w``: dissolved hydrogen mass per unit volume and molar fraction."""
        return self.rho_w * self.molar_h / self.molar_w

    @property
    def beta_g(self) -> float:
        """``M_h / (R T)``: gas density per unit pressure (ideal gas)."""
        return self.molar_h / (R_GAS * self.temperature)

    @property
    def henry_mass(self) -> float:
        """``H = H~ M_h`` (kg m^-3 Pa^-1)."""
        return self.henry * self.molar_h

    def laws(self) -> VanGenuchten:
        """Return the van Genuchten–Mualem laws of these data."""
        return VanGenuchten(self.pr, self.n, self.slr, self.sgr)


class Grid:
    """Cells joined by two-point faces; Dirichlet faces at the boundary.

    Parameters
    ----------
    volume : (N,) array
        Cell volumes (m per unit cross-section in 1D, m^2 per unit depth in 2D).
    centres : (N, d) array
        A point per cell (for profiles and fronts).
    faces : (F, 2) int array
        The two cells of every interior face.
    geometry : (F,) array
        ``area / distance`` of every interior face (positive).
    boundary_cells : (B,) int array
        The cell of every Dirichlet face.
    boundary_geometry : (B,) array
        ``area / distance`` from the cell's point to the boundary.
    """

    def __init__(self, volume, centres, faces, geometry, boundary_cells, boundary_geometry):
        self.volume = np.ascontiguousarray(volume, dtype=float)
        n = self.volume.size
        self.centres = np.asarray(centres, dtype=float).reshape(n, -1)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 2)
        self.geometry = np.ascontiguousarray(geometry, dtype=float)
        self.boundary_cells = np.ascontiguousarray(boundary_cells, dtype=np.int64)
        self.boundary_geometry = np.ascontiguousarray(boundary_geometry, dtype=float)
        if n < 2 or not (np.isfinite(self.volume).all() and (self.volume > 0).all()):
            raise ParameterError("Grid.volume must hold at least 2 positive finite volumes")
        if self.geometry.shape != (self.faces.shape[0],) or not (self.geometry > 0).all():
            raise ParameterError("Grid.geometry must hold one positive value per face")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= n):
            raise ParameterError(f"Grid.faces must name cells 0..{n - 1}")
        if self.boundary_geometry.shape != self.boundary_cells.shape:
            raise ParameterError("Grid.boundary_geometry must hold one value per boundary face")
        if self.boundary_cells.size:
            if self.boundary_cells.min() < 0 or self.boundary_cells.max() >= n:
                bad = self.boundary_cells[(self.boundary_cells < 0) | (self.boundary_cells >= n)]
                raise ParameterError(
                    f"Grid.boundary_cells must name cells 0..{n - 1}, got {int(bad[0])}"
                )
            if not (
                np.isfinite(self.boundary_geometry).all() and (self.boundary_geometry > 0).all()
            ):
                i = int(np.flatnonzero(~(self.boundary_geometry > 0))[0])
                value = float(self.boundary_geometry[i])
                raise ParameterError(
                    f"Grid.boundary_geometry must be positive, got {value!r} on boundary face {i}"
                )

    @property
    def n(self) -> int:
        """Number of cells."""
        return self.volume.size

    @property
    def dim(self) -> int:
        """Dimension of the cell points."""
        return self.centres.shape[1]

    @classmethod
    def column(cls, length: float, n_cells: int, *, left_dirichlet=False, right_dirichlet=True):
        """Equal cells on ``[0, length]``, cell-centred, Dirichlet faces at the chosen ends."""
        if isinstance(n_cells, bool) or not (
            isinstance(n_cells, (int, np.integer)) and n_cells >= 2
        ):
            raise ParameterError(f"n_cells must be an integer >= 2, got {n_cells!r}")
        if not (isinstance(length, (int, float)) and math.isfinite(length) and length > 0):
            raise ParameterError(f"length must be positive and finite, got {length!r}")
        dx = float(length) / int(n_cells)
        cells = np.arange(n_cells)
        faces = np.stack([cells[:-1], cells[1:]], axis=1)
        bcells = [c for c, on in ((0, left_dirichlet), (n_cells - 1, right_dirichlet)) if on]
        grid = cls(
            np.full(n_cells, dx),
            (cells + 0.5) * dx,
            faces,
            np.full(n_cells - 1, 1.0 / dx),
            bcells,
            np.full(len(bcells), 2.0 / dx),
        )
        grid.dx = dx
        return grid


def mesh_grid(mesh: Mesh, dirichlet):
    """Build the vertex-centred grid of a triangular mesh and its Dirichlet faces.

    The cells are the dual cells of the free vertices (volume: the lumped P1
    mass ``|omega_a|/3``).  Two vertices joined by an edge share a face whose
    ``area/distance`` is minus the P1 stiffness entry of the edge, the
    cotangent weight; it is the two-point flux of the dual cells on a
    Delaunay mesh (docs/twophase.md §2).  Edges with a zero weight (the
    hypotenuses of right triangles) carry no flux and are dropped; a negative
    weight (an obtuse pair: not Delaunay) is refused.

    Parameters
    ----------
    mesh : fastmem.Mesh
    dirichlet : (N,) bool array
        The vertices whose states are given; edges from a free vertex to one
        of them become the Dirichlet faces.

    Returns
    -------
    grid : Grid
    free : (n,) int array
        The mesh vertex of every cell.
    boundary_vertices : (B,) int array
        The Dirichlet vertex of every boundary face.
    """
    if not isinstance(mesh, Mesh):
        raise ParameterError(f"mesh must be a fastmem.Mesh, got {type(mesh).__name__}")
    fixed = np.asarray(dirichlet, dtype=bool)
    if fixed.shape != (mesh.n_vertices,):
        raise ParameterError(
            f"dirichlet must be a bool mask of the {mesh.n_vertices} vertices, got shape "
            f"{fixed.shape}"
        )
    tri = mesh.triangles
    grads = mesh.gradients
    areas = mesh.areas
    pairs = ((0, 1), (1, 2), (2, 0))
    i = np.concatenate([tri[:, a] for a, _ in pairs])
    j = np.concatenate([tri[:, b] for _, b in pairs])
    w = np.concatenate([-areas * np.einsum("td,td->t", grads[:, a], grads[:, b]) for a, b in pairs])
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    key = lo.astype(np.int64) * mesh.n_vertices + hi
    uniq, inverse = np.unique(key, return_inverse=True)
    weight = np.bincount(inverse, w, uniq.size)
    lo, hi = uniq // mesh.n_vertices, uniq % mesh.n_vertices
    scale = np.abs(weight).max()
    if (weight < -1e-12 * scale).any():
        e = int(np.argmin(weight))
        raise ParameterError(
            f"the mesh is not Delaunay: edge ({lo[e]}, {hi[e]}) has the negative two-point "
            f"weight {weight[e]:.3g}; the vertex-centred scheme needs a Delaunay mesh"
        )
    keep = weight > 1e-12 * scale
    lo, hi, weight = lo[keep], hi[keep], weight[keep]
    free = np.flatnonzero(~fixed)
    index = np.full(mesh.n_vertices, -1, dtype=np.int64)
    index[free] = np.arange(free.size)
    inner = ~fixed[lo] & ~fixed[hi]
    edge_b = fixed[lo] ^ fixed[hi]
    cell_b = np.where(fixed[lo[edge_b]], hi[edge_b], lo[edge_b])
    vert_b = np.where(fixed[lo[edge_b]], lo[edge_b], hi[edge_b])
    grid = Grid(
        mesh.lumped_mass[free],
        mesh.vertices[free],
        np.stack([index[lo[inner]], index[hi[inner]]], axis=1),
        weight[inner],
        index[cell_b],
        weight[edge_b],
    )
    return grid, free, vert_b


class Problem:
    """The liquid–gas problem on a grid: physics, sources, Dirichlet and initial states.

    Parameters
    ----------
    grid : Grid
    physics : Physics
    boundary : (3,) or (B, 3) array
        ``(S, P, chi)`` on the Dirichlet faces.
    initial : (3,) or (N, 3) array
        ``(S, P, chi)`` at ``t = 0``.
    hydrogen, water : (N,) arrays or float, optional
        Injection rates per cell, kg/s (per unit cross-section or depth).
    stop_injection : float, optional
        Time (s) after which nothing more is injected.
    monitor : int, optional
        The cell whose values a run records per step (default: the largest
        hydrogen source).
    complementarity : {"min", "fb"}
        The third equation of a cell: ``min{a, b}`` (Newton-min) or the
        Fischer-Burmeister function ``a + b - sqrt(a^2 + b^2)`` of ``a = 1 - S``
        and ``b = (H P_g - beta_l chi) / (H P_ref)`` (made dimensionless so
        that the two arguments weigh alike).
    """

    def __init__(
        self,
        grid: Grid,
        physics: Physics | None = None,
        *,
        boundary=(1.0, 1e6, 0.0),
        initial=(1.0, 1e6, 0.0),
        hydrogen=0.0,
        water=0.0,
        stop_injection: float | None = None,
        monitor: int | None = None,
        complementarity: str = "min",
    ):
        if complementarity not in COMPLEMENTARITY:
            raise ParameterError(
                f"complementarity must be one of {', '.join(COMPLEMENTARITY)}, got "
                f"{complementarity!r}"
            )
        #: "min" (Newton-min) or "fb" (Newton on the Fischer-Burmeister function)
        self.complementarity = complementarity
        if grid.boundary_cells.size == 0:
            raise ParameterError(
                "the grid has no Dirichlet face: water is incompressible, so with no-flow "
                "boundaries only the pressure is undetermined; give the grid a Dirichlet face "
                "(Grid.column(..., right_dirichlet=True), or dirichlet= in mesh_grid)"
            )
        self.grid = grid
        self.physics = Physics() if physics is None else physics
        self.laws = self.physics.laws()
        n = grid.n
        self.boundary = np.broadcast_to(
            np.asarray(boundary, dtype=float), (grid.boundary_cells.size, 3)
        ).copy()
        self.initial = np.broadcast_to(np.asarray(initial, dtype=float), (n, 3)).copy()
        self.check_state(self.initial, "initial")
        if self.boundary.size:
            self.check_state(self.boundary, "boundary")
        self.hydrogen = np.broadcast_to(np.asarray(hydrogen, dtype=float), (n,)).copy()
        self.water = np.broadcast_to(np.asarray(water, dtype=float), (n,)).copy()
        for name, q in (("hydrogen", self.hydrogen), ("water", self.water)):
            if not np.isfinite(q).all():
                raise ParameterError(f"Problem.{name} injection rates must be finite")
        if stop_injection is not None and not (
            isinstance(stop_injection, (int, float)) and stop_injection > 0
        ):
            raise ParameterError(
                f"stop_injection must be a positive time in s, got {stop_injection!r}"
            )
        self.stop_injection = stop_injection
        #: the cell whose values a run records per step (default: the largest hydrogen source)
        self.monitor = int(np.argmax(self.hydrogen)) if monitor is None else int(monitor)
        #: the scene's name and sizes (archives); the mesh of a vertex-centred grid, the
        #: mesh vertex of every cell and of every Dirichlet face (exports)
        self.scene: dict = {}
        self.mesh = None
        self.cell_vertex = None
        self.boundary_vertex = None
        if not 0 <= self.monitor < n:
            raise ParameterError(f"monitor must be a cell index in 0..{n - 1}, got {monitor!r}")
        self._build_pattern()

    # ------------------------------------------------------------------ checks
    def check_state(self, x, name="state"):
        """Refuse a state with S outside [S_lr, 1], P <= 0 or chi < 0, naming the first cell."""
        ph = self.physics
        x = np.asarray(x)
        tests = (
            (~np.isfinite(x).all(axis=1), "is not finite"),
            ((x[:, 0] < ph.slr) | (x[:, 0] > 1.0), f"has S outside [S_lr, 1] = [{ph.slr}, 1]"),
            (x[:, 1] <= 0.0, "has a nonpositive pressure P (Pa)"),
            (x[:, 2] < 0.0, "has a negative dissolved fraction chi"),
        )
        for bad, what in tests:
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                raise ParameterError(
                    f"{name} state {what}: cell {i} has (S, P, chi) = "
                    f"({x[i, 0]!r}, {x[i, 1]!r}, {x[i, 2]!r})"
                )

    def sources(self, t: float):
        """Return ``(Q_w, Q_h)`` (N,) each at time ``t`` (the end of a step)."""
        if self.stop_injection is not None and t > self.stop_injection * (1 + 1e-12):
            z = np.zeros_like(self.hydrogen)
            return z, z
        return self.water, self.hydrogen

    # ------------------------------------------------------------------ the equations
    def pressure_gas(self, s, p):
        """``P_g = P + P_c(S)``."""
        return p + self.laws.capillary(s)

    def mass_h(self, s, p, chi):
        """Hydrogen mass per pore volume ``beta_l chi S + beta_g P_g (1 - S)``."""
        ph = self.physics
        return ph.beta_l * chi * s + ph.beta_g * self.pressure_gas(s, p) * (1.0 - s)

    def storage(self, x):
        """Component masses per cell, shape (N, 2): water and hydrogen (kg)."""
        ph = self.physics
        pore = self.grid.volume * ph.porosity
        out = np.empty((x.shape[0], 2), dtype=np.result_type(x, float))
        out[:, 0] = pore * ph.rho_w * x[:, 0]
        out[:, 1] = pore * self.mass_h(x[:, 0], x[:, 1], x[:, 2])
        return out

    def face_fluxes(self, xl, xr, geometry, coefficients=None, laws_lr=None):
        """``(F_w, F_h)`` from states ``xl`` to ``xr`` (F, 3) across faces of ``geometry``.

        With ``coefficients`` (F, 3), every coefficient of the fluxes (the
        mobilities, ``S``, ``chi`` and ``P_g`` in the face terms) is taken from
        that state instead of upwinding and face averages, the differences
        still from ``xl`` and ``xr``: the flux a cell's own values give
        (the estimators' flux mismatch).  ``laws_lr``, the six arrays
        ``(P_c, k_rl, k_rg)`` of the left and the right states
        (``pcl, pcr, kll, klr, kgl, kgr``), spare evaluating the laws per face.
        """
        ph, laws = self.physics, self.laws
        sl, pl, cl = xl[:, 0], xl[:, 1], xl[:, 2]
        sr, pr_, cr = xr[:, 0], xr[:, 1], xr[:, 2]
        if laws_lr is None:
            laws_lr = (
                laws.capillary(sl),
                laws.capillary(sr),
                laws.k_liquid(sl),
                laws.k_liquid(sr),
                laws.k_gas(sl),
                laws.k_gas(sr),
            )
        pcl, pcr, kll, klr, kgl, kgr = laws_lr
        pgl = pl + pcl
        pgr = pr_ + pcr
        dp = pr_ - pl
        dpg = pgr - pgl
        if coefficients is None:
            kl = np.where(np.real(dp) <= 0.0, kll, klr)
            kg = np.where(np.real(dpg) <= 0.0, kgl, kgr)
            s_f = 0.5 * (sl + sr)
            c_f = 0.5 * (cl + cr)
            pg_f = 0.5 * (pgl + pgr)
        else:
            s_f, c_f = coefficients[:, 0], coefficients[:, 2]
            kl, kg = laws.k_liquid(s_f), laws.k_gas(s_f)
            pg_f = coefficients[:, 1] + laws.capillary(s_f)
        ql = -ph.permeability * geometry * kl / ph.mu_l * dp
        qg = -ph.permeability * geometry * kg / ph.mu_g * dpg
        j = (
            -ph.porosity
            * ph.molar_h
            * s_f
            * (ph.rho_w / ph.molar_w + ph.beta_l * c_f / ph.molar_h)
            * ph.diffusion
            * geometry
            * (cr - cl)
        )
        fw = ph.rho_w * ql - j
        fh = ph.beta_l * c_f * ql + ph.beta_g * pg_f * qg + j
        return fw, fh

    def cell_side_fluxes(self, x):
        """Interior face fluxes with each side's own coefficients: ``(F_l, F_r)`` (F, 2) each."""
        g = self.grid
        xl, xr = x[g.faces[:, 0]], x[g.faces[:, 1]]
        left = np.stack(self.face_fluxes(xl, xr, g.geometry, xl), axis=1)
        right = np.stack(self.face_fluxes(xl, xr, g.geometry, xr), axis=1)
        xb = x[g.boundary_cells]
        inner = np.stack(
            self.face_fluxes(xb, self.boundary.astype(xb.dtype), g.boundary_geometry, xb), axis=1
        )
        return left, right, inner

    def cell_laws(self, s, derivatives=False):
        """``(P_c, k_rl, k_rg)`` of the saturations ``s`` (N,), with their S-derivatives.

        Returns three arrays, or with ``derivatives`` three ``(value,
        derivative)`` pairs (complex step: exact to round-off).
        """
        laws = (self.laws.capillary, self.laws.k_liquid, self.laws.k_gas)
        if not derivatives:
            return tuple(law(s) for law in laws)
        z = np.asarray(s, dtype=float) + 1j * _H
        return tuple((np.real(v), np.imag(v) / _H) for v in (law(z) for law in laws))

    def _boundary_laws(self):
        if not hasattr(self, "_bl"):
            self._bl = self.cell_laws(self.boundary[:, 0])
        return self._bl

    def fluxes(self, x):
        """Interior and boundary face fluxes: ``(F (F, 2), F_b (B, 2))``, kg/s, l → r / out."""
        g = self.grid
        left, right, bc = g.faces[:, 0], g.faces[:, 1], g.boundary_cells
        if np.iscomplexobj(x):
            lr = blr = None
        else:
            pc, kl, kg = self.cell_laws(x[:, 0])
            lr = (pc[left], pc[right], kl[left], kl[right], kg[left], kg[right])
            bpc, bkl, bkg = self._boundary_laws()
            blr = (pc[bc], bpc, kl[bc], bkl, kg[bc], bkg)
        fi = np.stack(self.face_fluxes(x[left], x[right], g.geometry, laws_lr=lr), axis=1)
        xb = x[bc]
        fb = np.stack(
            self.face_fluxes(xb, self.boundary.astype(xb.dtype), g.boundary_geometry, laws_lr=blr),
            axis=1,
        )
        return fi, fb

    def divergence(self, fi, fb):
        """Net outflow per cell (N, 2) of interior and boundary face fluxes."""
        g = self.grid
        out = np.zeros((g.n, 2), dtype=np.result_type(fi, fb))
        for c in range(2):  # the two components, each a vectorised scatter
            out[:, c] = (
                np.bincount(g.faces[:, 0], np.real(fi[:, c]), g.n)
                - np.bincount(g.faces[:, 1], np.real(fi[:, c]), g.n)
                + np.bincount(g.boundary_cells, np.real(fb[:, c]), g.n)
            )
            if np.iscomplexobj(out):
                out[:, c] += 1j * (
                    np.bincount(g.faces[:, 0], np.imag(fi[:, c]), g.n)
                    - np.bincount(g.faces[:, 1], np.imag(fi[:, c]), g.n)
                    + np.bincount(g.boundary_cells, np.imag(fb[:, c]), g.n)
                )
        return out

    def conservation(self, x, x_old, dt, t):
        """Return the two conservation residuals (N, 2), kg/s."""
        qw, qh = self.sources(t)
        out = (self.storage(x) - self.storage(x_old)) / dt + self.divergence(*self.fluxes(x))
        out[:, 0] -= qw
        out[:, 1] -= qh
        return out

    def branches(self, x):
        """Return the arguments of the min: ``1 - S`` and ``H P_g - beta_l chi`` (N,) each."""
        ph = self.physics
        return 1.0 - x[:, 0], ph.henry_mass * self.pressure_gas(x[:, 0], x[:, 1]) - (
            ph.beta_l * x[:, 2]
        )

    def gas(self, x):
        """Cells where Newton-min picks the Henry branch (``H P_g - beta_l chi < 1 - S``)."""
        one, two = self.branches(x)
        return two < one

    def residual(self, x, x_old, dt, t, gas=None):
        """All residuals (N, 3); ``gas`` (bool (N,)) picks the min's branch per cell."""
        out = np.empty((x.shape[0], 3), dtype=np.result_type(x, float))
        out[:, :2] = self.conservation(x, x_old, dt, t)
        one, two = self.branches(x)
        if self.complementarity == "fb":
            out[:, 2] = self.fischer_burmeister(one, two)
            return out
        if gas is None:
            gas = np.real(two) < np.real(one)
        out[:, 2] = np.where(gas, two, one)
        return out

    def fischer_burmeister(self, one, two):
        """Return ``a + b - sqrt(a^2 + b^2)`` with ``a = 1 - S``, ``b = two / (H P_ref)``."""
        b = two / (self.physics.henry_mass * self.references()[0])
        return one + b - np.sqrt(one * one + b * b)

    def complementarity_residual(self, x):
        """Return the nonlinear third equation at ``x``: the min or Fischer-Burmeister (N,)."""
        one, two = self.branches(x)
        if self.complementarity == "fb":
            return self.fischer_burmeister(one, two)
        return np.minimum(one, two)

    # ------------------------------------------------------------------ Jacobian
    def _build_pattern(self):
        """Rows/columns of every Jacobian entry and the CSR order they sum into."""
        g = self.grid
        n = g.n
        left, right = g.faces[:, 0], g.faces[:, 1]
        a = np.arange(2)[:, None]  # conservation rows
        b = np.arange(3)[None, :]  # unknowns
        rows, cols = [], []
        # face blocks: (l,l) (l,r) (r,l) (r,r), each (F, 2, 3)
        for ri, ci in ((left, left), (left, right), (right, left), (right, right)):
            rows.append((3 * ri[:, None, None] + a[None]).repeat(3, axis=2).ravel())
            cols.append((3 * ci[:, None, None] + b[None]).repeat(2, axis=1).ravel())
        bc = g.boundary_cells
        rows.append((3 * bc[:, None, None] + a[None]).repeat(3, axis=2).ravel())
        cols.append((3 * bc[:, None, None] + b[None]).repeat(2, axis=1).ravel())
        cells = np.arange(n)
        rows.append((3 * cells[:, None, None] + a[None]).repeat(3, axis=2).ravel())
        cols.append((3 * cells[:, None, None] + b[None]).repeat(2, axis=1).ravel())
        # complementarity rows: one row of 3 per cell
        rows.append(np.repeat(3 * cells + 2, 3))
        cols.append((3 * cells[:, None] + np.arange(3)[None]).ravel())
        rows = np.concatenate(rows)
        cols = np.concatenate(cols)
        key = rows * (3 * n) + cols
        uniq, inverse = np.unique(key, return_inverse=True)
        self._slot = inverse
        self._indices = (uniq % (3 * n)).astype(np.int32)
        self._indptr = np.searchsorted(uniq // (3 * n), np.arange(3 * n + 1)).astype(np.int32)
        self._nnz = uniq.size

    def _complex_derivatives(self, fun, args, count):
        """Return the derivatives of ``fun(*args)`` w.r.t. the 3 unknowns of each argument."""
        out = []
        for which in count:
            cols = []
            for k in range(3):
                z = [np.asarray(v, dtype=complex) for v in args]
                z[which] = z[which].copy()
                step = _H * np.maximum(np.abs(np.real(z[which][:, k])), 1.0)
                z[which][:, k] += 1j * step
                cols.append([np.imag(v) / step for v in fun(*z)])
            out.append(cols)  # out[which][k][component] -> (M,)
        return out

    def jacobian(self, x, gas, dt):
        """Return the Newton-min Jacobian (3N x 3N CSR), exact to round-off (complex step)."""
        g = self.grid
        left, right, bc = g.faces[:, 0], g.faces[:, 1], g.boundary_cells
        (pc, dpc), (kl, dkl), (kg, dkg) = self.cell_laws(x[:, 0], derivatives=True)
        bpc, bkl, bkg = self._boundary_laws()
        # every face flux against each of its inputs by the complex step, the laws
        # entering through their cell values and derivatives (chain rule)
        sides = (
            (x[left], x[right], g.geometry, (left, right)),
            (x[bc], self.boundary, g.boundary_geometry, (bc, None)),
        )
        blocks = []
        for xa, xb_, geo, (ia, ib) in sides:
            if ib is None:
                base = [pc[ia], bpc, kl[ia], bkl, kg[ia], bkg]
                which_sides = (0,)
                cells = (ia,)
            else:
                base = [pc[ia], pc[ib], kl[ia], kl[ib], kg[ia], kg[ib]]
                which_sides = (0, 1)
                cells = (ia, ib)
            out = []
            for which in which_sides:
                cols = []
                for k in range(3):
                    z = [np.asarray(xa, dtype=complex), np.asarray(xb_, dtype=complex)]
                    step = _H * np.maximum(np.abs(z[which][:, k].real), 1.0)
                    z[which] = z[which].copy()
                    z[which][:, k] += 1j * step
                    lw = [np.asarray(v, dtype=complex) for v in base]
                    if k == 0:
                        c = cells[which]
                        for law, deriv in enumerate((dpc, dkl, dkg)):
                            lw[2 * law + which] = lw[2 * law + which] + 1j * step * deriv[c]
                    fw, fh = self.face_fluxes(z[0], z[1], geo, laws_lr=lw)
                    cols.append(np.stack([np.imag(fw) / step, np.imag(fh) / step], axis=1))
                out.append(np.stack(cols, axis=2))  # (F, 2, 3)
            blocks.append(out)
        (dl, dr), (dbb,) = blocks

        def store(a):
            st = self.storage(a)
            return st[:, 0] / dt, st[:, 1] / dt

        ds = self._complex_derivatives(store, (x,), (0,))
        dss = np.stack([np.stack(ds[0][k], axis=1) for k in range(3)], axis=2)
        # complementarity rows
        ph = self.physics
        crow = np.zeros((g.n, 3))
        if self.complementarity == "fb":
            one, two = self.branches(x)
            scale = ph.henry_mass * self.references()[0]
            b = two / scale
            r = np.hypot(one, b)
            zero = r == 0.0  # the kink: the generalised derivative (1 - 1/sqrt 2) (1, 1)
            da = np.where(zero, 1 - 0.5**0.5, 1 - one / np.where(zero, 1.0, r))
            db = np.where(zero, 1 - 0.5**0.5, 1 - b / np.where(zero, 1.0, r))
            crow[:, 0] = -da + db * ph.henry_mass * dpc / scale
            crow[:, 1] = db * ph.henry_mass / scale
            crow[:, 2] = -db * ph.beta_l / scale
        else:
            crow[:, 0] = np.where(gas, ph.henry_mass * dpc, -1.0)
            crow[:, 1] = np.where(gas, ph.henry_mass, 0.0)
            crow[:, 2] = np.where(gas, -ph.beta_l, 0.0)
        vals = np.concatenate(
            [
                dl.ravel(),
                dr.ravel(),
                -dl.ravel(),
                -dr.ravel(),
                dbb.ravel(),
                dss.ravel(),
                crow.ravel(),
            ]
        )
        data = np.bincount(self._slot, vals, self._nnz)
        n3 = 3 * g.n
        return sp.csr_matrix((data, self._indices, self._indptr), shape=(n3, n3))

    # ------------------------------------------------------------------ scales
    def references(self):
        """``(P_ref, chi_ref)``: the largest boundary or initial pressure and its Henry fraction."""
        ph = self.physics
        p = np.concatenate([self.initial[:, 1], self.boundary[:, 1]])
        p_ref = float(np.max(np.abs(p)))
        return p_ref, ph.henry_mass * p_ref / ph.beta_l

    def units(self) -> np.ndarray:
        """Scales of the unknowns ``(1, P_ref, chi_ref)``."""
        p_ref, chi_ref = self.references()
        return np.array([1.0, p_ref, chi_ref])

    def row_scales(self, dt, gas):
        """Per-cell scales of the three residual rows (N, 3): storage of a unit change."""
        ph = self.physics
        p_ref, chi_ref = self.references()
        pore = self.grid.volume * ph.porosity / dt
        out = np.empty((self.grid.n, 3))
        out[:, 0] = pore * ph.rho_w
        out[:, 1] = pore * ph.beta_l * chi_ref
        out[:, 2] = (
            1.0 if self.complementarity == "fb" else np.where(gas, ph.henry_mass * p_ref, 1.0)
        )
        return out

    def admissible(self, x):
        """``x`` projected on ``S in [S_lr + 1e-9, 1]``, ``chi >= 0`` (a copy)."""
        x = np.array(x, dtype=float)
        np.clip(x[:, 0], self.physics.slr + 1e-9, 1.0, out=x[:, 0])
        np.maximum(x[:, 2], 0.0, out=x[:, 2])
        return x

    def hydrogen_in_place(self, x) -> float:
        """Hydrogen in the domain (kg per unit cross-section or depth)."""
        return float(np.sum(self.storage(x)[:, 1]))

    def outflow(self, x):
        """``(water, hydrogen)`` through the Dirichlet faces, kg/s, positive outwards."""
        _, fb = self.fluxes(x)
        return float(np.sum(fb[:, 0])), float(np.sum(fb[:, 1]))
