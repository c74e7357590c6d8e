r"""An exact solution with a checkerboard cross point: Kellogg's singular function.

On :math:`\Omega = (-1, 1)^2` with the tension :math:`a = R` in the first and
third quadrants and :math:`a = 1` in the second and fourth, the function

.. math::

    u = r^\gamma m(\theta), \qquad
    m(\theta) = \begin{cases}
    \cos((\pi/2 - \sigma)\gamma)\,\cos((\theta - \pi/2 + \rho)\gamma), & 0 \le \theta < \pi/2,\\
    \cos(\rho\gamma)\,\cos((\theta - \pi + \sigma)\gamma), & \pi/2 \le \theta < \pi,\\
    \cos(\sigma\gamma)\,\cos((\theta - \pi - \rho)\gamma), & \pi \le \theta < 3\pi/2,\\
    \cos((\pi/2 - \rho)\gamma)\,\cos((\theta - 3\pi/2 - \sigma)\gamma), & 3\pi/2 \le \theta < 2\pi
    \end{cases}

solves :math:`-\nabla\cdot(a\nabla u) = 0` (Kellogg 1975; the standard test of
adaptive methods for jumping coefficients): it is continuous, and so is the
normal flux :math:`a\,\partial_\theta u / r` across the four half-axes.  For a
contrast R the exponent is :math:`\gamma = (4/\pi)\arctan(R^{-1/2})` (0.1 for
R = 161.45, 0.040 for 1e3, 0.0013 for 1e6): the energy of :math:`u` in the
disc of radius h is proportional to :math:`h^{2\gamma}/(2\gamma)`, so the P1
error decays like :math:`h^\gamma` and no reference solution a few
refinements finer resolves it.  This is the singularity at the cross points of
a checkerboard of tensions (docs/heterogeneous.md §7), here with its exact
value.  With :math:`\rho = \pi/4`, :math:`\sigma` follows from
:math:`1/R = -\tan(\rho\gamma)\cot(\sigma\gamma)`.

As a contact scene (:meth:`Kellogg.scene`): membrane 1 has the tension
``a`` per triangle, ``f1 = 0`` and ``u1 = shift + u`` on the boundary;
membrane 2 has tension 1, ``f2 = 0`` and ``u2 = 0``.  With the default
``shift = 2`` (> max |u| = 2^(γ/2)) the membranes never touch, ``u2 = 0``
and ``lam = 0`` exactly, and the error is membrane 1's.

The energy error is exact up to 1-D quadrature on the boundary (no quadrature
near the singular point): since :math:`\nabla\cdot(a\nabla u) = 0` in each
quadrant and the normal flux is continuous, :math:`\int_\Omega a\nabla u\cdot
\nabla v = \int_{\partial\Omega} a\,\partial_n u\, v` for every
:math:`v \in H^1`, so

.. math:: |||u - u_h|||^2 = \int_{\partial\Omega} a\,\partial_n u\,(u - 2u_h)
          + u_h^T A_a u_h

(:meth:`Kellogg.energy_error`; :math:`A_a` the stiffness matrix with the
tension per triangle).  The boundary data are the nodal interpolant of
``shift + u``, which is not linear on boundary edges: the bound of
docs/method.md §5 is then guaranteed only up to that interpolation error
(smooth there, :math:`O(h^2)` against the :math:`O(h^\gamma)` error at the
cross point).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import ParameterError
from ..fem.assembly import assemble_stiffness
from ..fem.scene import Scene

__all__ = ["Kellogg"]

_QUADRANT_EDGES = (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi)


class Kellogg:
    """Kellogg's exact solution for a cross point of contrast R (module docstring).

    Parameters
    ----------
    contrast : float, default 161.4476387975881
        R > 1, the tension of the first and third quadrants (1 in the others).
        The default gives the classical exponent gamma = 0.1.
    shift : float, default 2.0
        Boundary value offset of membrane 1, > 2^(gamma/2) so that the
        membranes never touch.

    Examples
    --------
    >>> k = Kellogg()
    >>> round(k.gamma, 6)
    0.1
    >>> round(k.sigma, 6)
    -14.922565
    """

    def __init__(self, contrast: float = 161.4476387975881, shift: float = 2.0):
        contrast = float(contrast)
        if not (np.isfinite(contrast) and contrast > 1.0):
            raise ParameterError(f"contrast must be a finite number > 1, got {contrast!r}")
        self.contrast = contrast
        self.gamma = 4.0 / math.pi * math.atan(contrast**-0.5)
        self.rho = 0.25 * math.pi
        # 1/R = -tan(rho gamma) cot(sigma gamma), sigma gamma in (-pi/2, 0)
        self.sigma = math.atan(-contrast * math.tan(self.rho * self.gamma)) / self.gamma
        shift = float(shift)
        if not (np.isfinite(shift) and shift > 2.0 ** (0.5 * self.gamma)):
            raise ParameterError(
                f"shift must be > 2^(gamma/2) = {2.0 ** (0.5 * self.gamma):.6g} so that the "
                f"membranes never touch, got {shift!r}"
            )
        self.shift = shift

    def __repr__(self) -> str:
        return f"Kellogg(contrast={self.contrast!r}, shift={self.shift!r})"

    def _pieces(self):
        g, s, r = self.gamma, self.sigma, self.rho
        # (amplitude, phase): m = amp * cos((theta - phase) * gamma) on each quadrant
        return (
            (math.cos((0.5 * math.pi - s) * g), 0.5 * math.pi - r),
            (math.cos(r * g), math.pi - s),
            (math.cos(s * g), math.pi + r),
            (math.cos((0.5 * math.pi - r) * g), 1.5 * math.pi + s),
        )

    def _quadrant(self, theta):
        return np.minimum((theta // (0.5 * math.pi)).astype(np.int64), 3)

    def angular(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """``m(theta)`` and ``m'(theta)`` for ``theta`` in [0, 2 pi)."""
        theta = np.asarray(theta, dtype=np.float64)
        q = self._quadrant(theta)
        amp = np.array([p[0] for p in self._pieces()])[q]
        phase = np.array([p[1] for p in self._pieces()])[q]
        arg = (theta - phase) * self.gamma
        return amp * np.cos(arg), -self.gamma * amp * np.sin(arg)

    def tension(self, x, y) -> np.ndarray:
        """``a(x, y)``: R where x y > 0 (first and third quadrants), 1 elsewhere."""
        return np.where(np.asarray(x) * np.asarray(y) > 0.0, self.contrast, 1.0)

    def _polar(self, x, y):
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        return np.hypot(x, y), np.mod(np.arctan2(y, x), 2.0 * math.pi)

    def u(self, x, y) -> np.ndarray:
        """The singular function ``r^gamma m(theta)`` (without the shift)."""
        r, t = self._polar(x, y)
        return r**self.gamma * self.angular(t)[0]

    def grad(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Its gradient (singular like ``r^(gamma - 1)`` at the origin)."""
        r, t = self._polar(x, y)
        m, dm = self.angular(t)
        rg = r ** (self.gamma - 1.0)
        ur, ut = self.gamma * rg * m, rg * dm  # d/dr and (1/r) d/dtheta
        c, s = np.cos(t), np.sin(t)
        return ur * c - ut * s, ur * s + ut * c

    def mu(self, mesh) -> np.ndarray:
        """Per-triangle tension of membrane 1 on ``mesh`` (by centroid)."""
        cen = mesh.vertices[mesh.triangles].mean(axis=1)
        return self.tension(cen[:, 0], cen[:, 1])

    def scene(self, mesh, **options):
        """The contact scene (module docstring) on a mesh of (-1, 1)^2 with the axes as edges."""
        return Scene(mesh, mu=(self.mu(mesh), 1.0), f=(0.0, 0.0), g=self.boundary_value, **options)

    def boundary_value(self, x, y) -> np.ndarray:
        """``shift + u``: membrane 1's boundary value (a callable, so refined meshes get it)."""
        return self.shift + self.u(x, y)

    def energy_error(self, mesh, u1h, u2h=None, points: int = 8) -> float:
        r"""Exact energy error :math:`|||u - u_h|||` of a triple on ``mesh`` (module docstring).

        ``points`` Gauss points per boundary edge for :math:`\int_{\partial\Omega}
        a\,\partial_n u\,(u - 2u_h)` (u is analytic on the boundary).  ``u2h``,
        if given, adds :math:`\|\nabla u_{2h}\|^2` (the exact u2 is 0).
        """
        u1h = np.asarray(u1h, dtype=np.float64) - self.shift
        e = mesh.edges[mesh.boundary_edges]
        p0, p1 = mesh.vertices[e[:, 0]], mesh.vertices[e[:, 1]]
        s, w = np.polynomial.legendre.leggauss(points)
        s, w = 0.5 * (s + 1.0), 0.5 * w
        xy = p0[:, None, :] + s[None, :, None] * (p1 - p0)[:, None, :]
        length = np.linalg.norm(p1 - p0, axis=1)
        tangent = (p1 - p0) / length[:, None]
        normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
        # outward: the square's normal points away from the origin
        mid = 0.5 * (p0 + p1)
        normal *= np.sign((normal * mid).sum(axis=1))[:, None]
        x, y = xy[..., 0], xy[..., 1]
        gx, gy = self.grad(x, y)
        # a on the boundary side of the edge: its midpoint's quadrant, nudged inside
        inside = mid - 1e-9 * normal
        a = self.tension(inside[:, 0], inside[:, 1])[:, None]
        flux = a * (gx * normal[:, None, 0] + gy * normal[:, None, 1])
        uh = u1h[e[:, 0], None] * (1.0 - s) + u1h[e[:, 1], None] * s
        bnd = float((((flux * (self.u(x, y) - 2.0 * uh)) @ w) * length).sum())
        stiff = assemble_stiffness(mesh, self.mu(mesh))
        err2 = bnd + float(u1h @ (stiff @ u1h))
        if u2h is not None:
            u2h = np.asarray(u2h, dtype=np.float64)
            err2 += float(u2h @ (assemble_stiffness(mesh, 1.0) @ u2h))
        return math.sqrt(max(err2, 0.0))
