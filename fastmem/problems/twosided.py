r"""A manufactured two-sided obstacle problem with a known solution, docs/obstacle.md §8.3.

On :math:`\Omega = (-1, 1)^2` with the bubble :math:`b = (1 - x^2)(1 - y^2)`,
parameters :math:`s_0 \ne 0`, :math:`\alpha > 0`, :math:`\kappa \ge 0`,
:math:`r_c > 0`, :math:`m > r_c` with :math:`m + r_c < 1`, and :math:`\mu > 0`:

.. math::

    u &= s_0\, x\, b(x, y), \qquad p_\mp = (x \pm m)^2 + y^2 - r_c^2
    \quad (\text{discs } \mathcal D_\mp = \{p_\mp \le 0\} \text{ centred at } (\mp m, 0)), \\
    \psi &= u - \alpha\,(p_-^+)^2, \qquad \chi = u + \alpha\,(p_+^+)^2, \\
    \lambda^+ &= \kappa\,(-p_-)^+, \qquad \lambda^- = \kappa\,(-p_+)^+, \qquad
    \lambda = \lambda^+ - \lambda^-, \\
    f &= -\mu\Delta u - \lambda^+ + \lambda^-, \qquad
    \Delta u = 2 s_0\, x\,(x^2 + 3y^2 - 4), \qquad g = 0 .

The membrane lies on the lower obstacle on :math:`\mathcal D_-`, under the upper
one on :math:`\mathcal D_+`, and is free elsewhere. The problem is invariant under
the lower/upper symmetry of docs/obstacle.md §7 combined with :math:`x \mapsto -x`:
:math:`\psi(-x, y) = -\chi(x, y)`, :math:`f(-x, y) = -f(x, y)`.

The pressure bounds of the Lewy-Stampacchia assumption (LS) are

.. math::

    \Lambda_\psi = \begin{cases} \kappa(-p_-) & \text{on } \mathcal D_-,\\
    Q = \mu\alpha(16p_- + 8r_c^2) & \text{off } \mathcal D_- \cup \mathcal D_+,\\
    (Q + \kappa p_+)^+ & \text{on } \mathcal D_+, \end{cases}
    \qquad \Lambda_\chi(x, y) = \Lambda_\psi(-x, y),

and :class:`TwoSidedObstacle` provides guaranteed per-piece envelope constants of
both obstacles (docs/obstacle.md §5.1-5.3): Hessian bounds from interval enclosures
of the Hessian entries, and affine majorants of :math:`\Lambda`. The energy error
of a P1 function is exact up to round-off (:meth:`TwoSided.energy_error`: the
gradient of :math:`u` has degree 4, the squared error degree 8).
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import DataError, ParameterError
from ..fem.quadrature import triangle_rule
from .ball import (
    _SLACK,
    _as_pieces,
    _as_xy,
    _hat_gradients,
    _mesh_arrays,
    enclosing_radius,
    triangle_distance,
)
from .manufactured import _check_real

__all__ = ["DOMAIN", "ERROR_DEGREE", "TwoSided", "TwoSidedObstacle"]

#: The domain is ``(DOMAIN[0], DOMAIN[1])^2``.
DOMAIN = (-1.0, 1.0)

#: Degree of the triangle rule of :meth:`TwoSided.energy_error` (exact: the
#: integrand has degree 8).
ERROR_DEGREE = 8

# A piece counts as inside a contact disc only when all its vertices have
# p <= -_P_TOL: round-off in p (a few 1e-16) must not move a vertex that lies on or
# just outside the circle inside (Lambda_psi jumps up across the circle of D_-).
_P_TOL = 1e-12

# Triangles processed at once by the error integral: small enough that the (chunk, points)
# arrays stay in the caches (n = 1024: 0.54-0.63 s against 0.83-1.32 s with 2^15, same bits).
_CHUNK = 1 << 13


# --------------------------------------------------------------------------- interval helpers


def _square_range(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the range of ``t**2`` for ``t`` in ``[lo, hi]``."""
    lo2, hi2 = lo * lo, hi * hi
    low = np.where((lo <= 0.0) & (hi >= 0.0), 0.0, np.minimum(lo2, hi2))
    return low, np.maximum(lo2, hi2)


def _product_range(alo, ahi, blo, bhi) -> tuple[np.ndarray, np.ndarray]:
    """Return the range of ``a * b`` for ``a`` in ``[alo, ahi]``, ``b`` in ``[blo, bhi]``."""
    c = np.stack([alo * blo, alo * bhi, ahi * blo, ahi * bhi])
    return c.min(axis=0), c.max(axis=0)


def _cubic_range(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the range of ``t - t**3`` for ``t`` in ``[lo, hi]`` (critical points ±1/√3)."""
    crit = 1.0 / math.sqrt(3.0)
    cand = [lo, hi]
    for c in (-crit, crit):
        cand.append(np.where((lo <= c) & (c <= hi), c, lo))
    t = np.stack(cand)
    v = t - t * t * t
    return v.min(axis=0), v.max(axis=0)


def _lam_max_sup(a_hi, c_hi, b_abs) -> np.ndarray:
    r"""Return :math:`\sup \lambda_{\max}` of symmetric 2x2 matrices with entries in a box.

    :math:`\lambda_{\max}\begin{pmatrix} a & b\\ b & c\end{pmatrix} = \frac{a + c}{2}
    + \sqrt{(\frac{a - c}{2})^2 + b^2}` is non-decreasing in :math:`a`, in :math:`c`
    and in :math:`|b|`, so its supremum over the box is its value at
    ``(a_hi, c_hi, b_abs)`` (sharper than Gershgorin's
    :math:`\max(a_{hi}, c_{hi}) + |b|`, and equally guaranteed).
    """
    half = 0.5 * (a_hi - c_hi)
    return 0.5 * (a_hi + c_hi) + np.sqrt(half * half + b_abs * b_abs)


# --------------------------------------------------------------------------- obstacles


class TwoSidedObstacle:
    r"""One obstacle of :class:`TwoSided`: :math:`\psi` (``side="lower"``) or :math:`\chi`.

    Calling the object evaluates the obstacle; :meth:`laplacian` and
    :meth:`pressure_bound` give :math:`\Delta\psi` and :math:`\Lambda_\psi`
    (resp. for :math:`\chi`), and :meth:`envelope` the guaranteed per-piece
    constants of docs/obstacle.md §5.1-5.2. Obtain instances as
    :attr:`TwoSided.lower` and :attr:`TwoSided.upper`.

    Parameters
    ----------
    problem : TwoSided
        The problem whose obstacle this is.
    side : {"lower", "upper"}
        Which obstacle.
    """

    def __init__(self, problem: TwoSided, side: str):
        if side not in ("lower", "upper"):
            raise ParameterError(f"side must be 'lower' or 'upper', got {side!r}")
        self._problem = problem
        self._side = side

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self._problem!r}, side={self._side!r})"

    @property
    def side(self) -> str:
        r"""``"lower"`` (:math:`\psi`) or ``"upper"`` (:math:`\chi`)."""
        return self._side

    def __call__(self, x, y) -> np.ndarray:
        r"""Return :math:`\psi = u - \alpha (p_-^+)^2` or :math:`\chi = u + \alpha (p_+^+)^2`.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one (or broadcastable) shape.

        Returns
        -------
        ndarray
            The obstacle at the points.
        """
        pr = self._problem
        x, y = _as_xy(x, y)
        if self._side == "lower":
            pp = np.maximum(pr._p_minus(x, y), 0.0)
            return pr.solution(x, y) - pr.alpha * pp * pp
        pp = np.maximum(pr._p_plus(x, y), 0.0)
        return pr.solution(x, y) + pr.alpha * pp * pp

    def laplacian(self, x, y) -> np.ndarray:
        r"""Return the Laplacian of the obstacle (defined a.e.).

        :math:`\Delta\psi = \Delta u - \alpha(16p_- + 8r_c^2)` off
        :math:`\mathcal D_-` and :math:`\Delta u` on it; :math:`\Delta\chi = \Delta u
        + \alpha(16p_+ + 8r_c^2)` off :math:`\mathcal D_+` and :math:`\Delta u` on it.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one (or broadcastable) shape.

        Returns
        -------
        ndarray
            The Laplacian at the points.
        """
        pr = self._problem
        x, y = _as_xy(x, y)
        if self._side == "lower":
            p = pr._p_minus(x, y)
            return pr.laplacian(x, y) - np.where(
                p > 0.0, pr.alpha * (16.0 * p + 8.0 * pr.rc**2), 0.0
            )
        p = pr._p_plus(x, y)
        return pr.laplacian(x, y) + np.where(p > 0.0, pr.alpha * (16.0 * p + 8.0 * pr.rc**2), 0.0)

    def pressure_bound(self, x, y) -> np.ndarray:
        r"""Return :math:`\Lambda_\psi = (-\mu\Delta\psi - f)^+` or :math:`\Lambda_\chi = (f + \mu\Delta\chi)^+`.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one (or broadcastable) shape.

        Returns
        -------
        ndarray
            The pressure bound of (LS) at the points, non-negative.
        """  # noqa: E501
        pr = self._problem
        x, y = _as_xy(x, y)
        if self._side == "lower":
            return np.maximum(-pr.mu * self.laplacian(x, y) - pr.load(x, y), 0.0)
        return np.maximum(pr.load(x, y) + pr.mu * self.laplacian(x, y), 0.0)

    def envelope(self, px, py) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r"""Return guaranteed envelope constants of the obstacle on triangular pieces.

        For the lower obstacle :math:`\psi` (the upper one follows from
        :math:`\chi(x, y) = -\psi(-x, y)`, which exchanges :math:`M^-` and
        :math:`M^+`, and :math:`\Lambda_\chi(x, y) = \Lambda_\psi(-x, y)`):

        - :math:`M^\pm_T`: the entries of :math:`D^2\psi = D^2u - \alpha D^2((p_-^+)^2)`
          are enclosed in intervals on the piece (the polynomial entries of
          :math:`D^2u` exactly on its bounding box;
          :math:`D^2(p^2) = 8(\mathbf x - \mathbf c)(\mathbf x - \mathbf c)^\top
          + 4pI` on :math:`p > 0`, with the range of :math:`p` on the piece itself,
          and 0 where the piece meets the disc), and :math:`\lambda_{\max}` is
          bounded on that box of symmetric matrices (exactly, see
          :func:`_lam_max_sup`);
        - :math:`U_T` (docs/obstacle.md §8.3): on pieces inside
          :math:`\mathcal D_-`, :math:`I_T\Lambda_\psi + \kappa r_T^2`
          (:math:`\Lambda_\psi = \kappa(-p_-)` is concave with Hessian
          :math:`-2\kappa I`); on pieces inside :math:`\mathcal D_+`,
          :math:`I_T\Lambda_\psi` (the positive part of a convex quadratic); on
          other pieces that do not meet the open disc :math:`\mathcal D_-`,
          :math:`I_T Q` (:math:`\Lambda_\psi \le Q` there and :math:`Q` is convex);
          on pieces crossing :math:`\partial\mathcal D_-` (where
          :math:`\Lambda_\psi` jumps) the constant
          :math:`\max(\kappa(r_c^2 - \underline d^2), \sup_T Q)`, with
          :math:`\underline d` the distance from the disc's centre to the piece.

        All bounds are rounded up by a relative ``1e-13`` (plus as much absolute)
        against round-off.

        Parameters
        ----------
        px, py : ndarray of shape (P, 3)
            Vertex coordinates of ``P`` triangles (pieces).

        Returns
        -------
        m_minus : ndarray of shape (P,)
            :math:`M^-_T \ge \sup_T \lambda_{\max}(-D^2 v)^+` for the obstacle
            :math:`v` (:math:`\psi` or :math:`\chi`).
        m_plus : ndarray of shape (P,)
            :math:`M^+_T \ge \sup_T \lambda_{\max}(D^2 v)^+`.
        lam_upper : ndarray of shape (P, 3)
            Values at the three vertices of an affine :math:`U_T \ge \Lambda_v` on
            :math:`T`.

        Raises
        ------
        DataError
            If ``px`` and ``py`` do not have one shape ``(P, 3)`` or are not finite.
        """
        px, py = _as_pieces(px, py)
        if self._side == "lower":
            return self._problem._lower_envelope(px, py)
        m_minus, m_plus, lam = self._problem._lower_envelope(-px, py)
        return m_plus, m_minus, lam


# --------------------------------------------------------------------------- the problem


class TwoSided:
    r"""The manufactured two-sided obstacle problem of docs/obstacle.md §8.3.

    See the module docstring for the formulas. All field methods are vectorised:
    ``x`` and ``y`` are arrays of one (or broadcastable) shape and the results
    have that shape.

    Parameters
    ----------
    s0 : float, default 1.0
        Amplitude of the solution, non-zero (``s0 > 0`` makes the lower obstacle
        convex on its contact disc, ``s0 < 0`` concave).
    alpha : float, default 1.0
        How fast the obstacles leave the solution, positive.
    kappa : float, default 10.0
        Pressure amplitude, non-negative (0: contact without pressure).
    m : float, default 0.5
        Offset of the disc centres ``(-m, 0)`` (lower contact) and ``(m, 0)``
        (upper contact); ``m > rc`` (disjoint discs) and ``m + rc < 1`` (discs
        strictly inside the domain).
    rc : float, default 0.3
        Radius of the contact discs, positive.
    mu : float, default 1.0
        Tension, positive.

    Attributes
    ----------
    lower, upper : TwoSidedObstacle
        The obstacles :math:`\psi` and :math:`\chi`.

    Raises
    ------
    ParameterError
        If a parameter is out of range; the message names it and its value.

    Examples
    --------
    >>> p = TwoSided()
    >>> round(float(p.load(-0.5, 0.0)), 12), round(float(p.multiplier(-0.5, 0.0)), 12)
    (-4.65, 0.9)
    >>> float(p.lower(-0.5, 0.0)) == float(p.solution(-0.5, 0.0))
    True
    """

    def __init__(
        self,
        s0: float = 1.0,
        alpha: float = 1.0,
        kappa: float = 10.0,
        m: float = 0.5,
        rc: float = 0.3,
        mu: float = 1.0,
    ):
        self._s0 = _check_real("s0", s0, nonzero=True)
        self._alpha = _check_real("alpha", alpha, positive=True)
        self._kappa = _check_real("kappa", kappa, nonnegative=True)
        self._rc = _check_real("rc", rc, positive=True)
        self._m = _check_real("m", m)
        self._mu = _check_real("mu", mu, positive=True)
        if not self._m > self._rc:
            raise ParameterError(
                f"m must exceed rc so that the contact discs are disjoint, got m={self._m!r}, "
                f"rc={self._rc!r}"
            )
        if not self._m + self._rc < DOMAIN[1]:
            raise ParameterError(
                f"m + rc must be below 1 so that the contact discs lie inside the domain, "
                f"got m={self._m!r}, rc={self._rc!r}"
            )
        self.lower = TwoSidedObstacle(self, "lower")
        self.upper = TwoSidedObstacle(self, "upper")

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(s0={self._s0!r}, alpha={self._alpha!r}, "
            f"kappa={self._kappa!r}, m={self._m!r}, rc={self._rc!r}, mu={self._mu!r})"
        )

    # ------------------------------------------------------------------ parameters

    @property
    def s0(self) -> float:
        """Amplitude of the solution."""
        return self._s0

    @property
    def alpha(self) -> float:
        """Rate at which the obstacles leave the solution."""
        return self._alpha

    @property
    def kappa(self) -> float:
        """Pressure amplitude."""
        return self._kappa

    @property
    def m(self) -> float:
        """Offset of the disc centres ``(-m, 0)`` and ``(m, 0)``."""
        return self._m

    @property
    def rc(self) -> float:
        """Radius of the contact discs."""
        return self._rc

    @property
    def mu(self) -> float:
        """Tension."""
        return self._mu

    @property
    def domain(self) -> tuple[float, float]:
        """The domain is ``(domain[0], domain[1])^2``."""
        return DOMAIN

    @property
    def g(self) -> float:
        """Dirichlet data (zero)."""
        return 0.0

    def to_dict(self) -> dict:
        """Return the parameters as a plain dict.

        Returns
        -------
        dict
            Keys ``s0, alpha, kappa, m, rc, mu``.
        """
        return {
            "s0": self._s0,
            "alpha": self._alpha,
            "kappa": self._kappa,
            "m": self._m,
            "rc": self._rc,
            "mu": self._mu,
        }

    # ------------------------------------------------------------------ fields

    def _p_minus(self, x, y):
        """``p_- = (x + m)^2 + y^2 - rc^2`` (disc D_- centred at (-m, 0))."""
        dx = x + self._m
        return dx * dx + y * y - self._rc * self._rc

    def _p_plus(self, x, y):
        """``p_+ = (x - m)^2 + y^2 - rc^2`` (disc D_+ centred at (m, 0))."""
        dx = x - self._m
        return dx * dx + y * y - self._rc * self._rc

    def solution(self, x, y) -> np.ndarray:
        """Return the exact solution ``u = s0 x (1 - x^2)(1 - y^2)``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one (or broadcastable) shape.

        Returns
        -------
        ndarray
            ``u`` at the points.
        """
        x, y = _as_xy(x, y)
        return self._s0 * x * (1.0 - x * x) * (1.0 - y * y)

    def gradient(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Return the gradient of ``u``: ``s0 ((1 - 3x^2)(1 - y^2), -2xy(1 - x^2))``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one (or broadcastable) shape.

        Returns
        -------
        dx, dy : ndarray
            The partial derivatives at the points.
        """
        x, y = _as_xy(x, y)
        return (
            self._s0 * (1.0 - 3.0 * x * x) * (1.0 - y * y),
            -2.0 * self._s0 * x * y * (1.0 - x * x),
        )

    def laplacian(self, x, y) -> np.ndarray:
        """Return ``lap u = 2 s0 x (x^2 + 3 y^2 - 4)``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one (or broadcastable) shape.

        Returns
        -------
        ndarray
            The Laplacian of the solution at the points.
        """
        x, y = _as_xy(x, y)
        return 2.0 * self._s0 * x * (x * x + 3.0 * y * y - 4.0)

    def multiplier_plus(self, x, y) -> np.ndarray:
        """Return the lower contact pressure ``lambda^+ = kappa (-p_-)^+``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one (or broadcastable) shape.

        Returns
        -------
        ndarray
            ``lambda^+`` at the points, non-negative, zero off the disc ``D_-``.
        """
        x, y = _as_xy(x, y)
        return self._kappa * np.maximum(-self._p_minus(x, y), 0.0)

    def multiplier_minus(self, x, y) -> np.ndarray:
        """Return the upper contact pressure ``lambda^- = kappa (-p_+)^+``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one (or broadcastable) shape.

        Returns
        -------
        ndarray
            ``lambda^-`` at the points, non-negative, zero off the disc ``D_+``.
        """
        x, y = _as_xy(x, y)
        return self._kappa * np.maximum(-self._p_plus(x, y), 0.0)

    def multiplier(self, x, y) -> np.ndarray:
        """Return the multiplier ``lambda = lambda^+ - lambda^-``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one (or broadcastable) shape.

        Returns
        -------
        ndarray
            ``lambda`` at the points.
        """
        return self.multiplier_plus(x, y) - self.multiplier_minus(x, y)

    def load(self, x, y) -> np.ndarray:
        """Return the load ``f = -mu lap u - lambda^+ + lambda^-``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one (or broadcastable) shape.

        Returns
        -------
        ndarray
            ``f`` at the points (continuous, with kinks on the two circles).
        """
        return -self._mu * self.laplacian(x, y) - self.multiplier(x, y)

    # ------------------------------------------------------------------ envelopes

    def _hessian_u_box(self, xl, xh, yl, yh):
        """Interval enclosures of the entries of ``D^2 u`` on the boxes ``[xl, xh] x [yl, yh]``.

        ``D^2 u = s0 [[-6x(1 - y^2), -2y(1 - 3x^2)], [., -2(x - x^3)]]``; each entry is
        a product of functions of ``x`` and of ``y`` (or of ``x`` alone), so the
        ranges below are exact on the box.
        """
        y2l, y2h = _square_range(yl, yh)
        x2l, x2h = _square_range(xl, xh)
        a_lo, a_hi = _product_range(xl, xh, 1.0 - y2h, 1.0 - y2l)
        b_lo, b_hi = _product_range(yl, yh, 1.0 - 3.0 * x2h, 1.0 - 3.0 * x2l)
        c_lo, c_hi = _cubic_range(xl, xh)
        entries = []
        for lo, hi, factor in ((a_lo, a_hi, -6.0), (b_lo, b_hi, -2.0), (c_lo, c_hi, -2.0)):
            f = factor * self._s0
            entries.append((np.minimum(f * lo, f * hi), np.maximum(f * lo, f * hi)))
        return entries

    def _hessian_bump_box(self, px, py, cx, xl, xh, yl, yh):
        r"""Interval enclosures of the entries of :math:`D^2((p^+)^2)` on the pieces.

        For the disc of radius ``rc`` centred at ``(cx, 0)``: on :math:`p > 0` the
        Hessian is :math:`8(\mathbf x - \mathbf c)(\mathbf x - \mathbf c)^\top + 4pI`,
        elsewhere 0. The range of :math:`p` on a piece is
        :math:`[\underline d^2 - r_c^2, \max_{\text{vertices}} p]` (``p`` is convex).
        """
        rc2 = self._rc * self._rc
        dist = triangle_distance(px, py, cx, 0.0)
        p_lo = dist * dist - rc2
        dxv = px - cx
        p_hi = np.max(dxv * dxv + py * py, axis=1) - rc2
        dx2l, dx2h = _square_range(xl - cx, xh - cx)
        dy2l, dy2h = _square_range(yl, yh)
        pp_lo = np.maximum(p_lo, 0.0)
        pp_hi = np.maximum(p_hi, 0.0)
        k11 = [8.0 * dx2l + 4.0 * pp_lo, 8.0 * dx2h + 4.0 * pp_hi]
        k22 = [8.0 * dy2l + 4.0 * pp_lo, 8.0 * dy2h + 4.0 * pp_hi]
        k12 = list(_product_range(xl - cx, xh - cx, yl, yh))
        k12 = [8.0 * k12[0], 8.0 * k12[1]]
        meets = p_lo < 0.0  # the piece meets the open disc, where the Hessian is 0
        inside = p_hi <= 0.0  # the piece lies in the closed disc
        out = []
        for lo, hi in (k11, k12, k22):
            lo = np.where(meets, np.minimum(lo, 0.0), lo)
            hi = np.where(meets, np.maximum(hi, 0.0), hi)
            out.append((np.where(inside, 0.0, lo), np.where(inside, 0.0, hi)))
        return out

    def _lower_envelope(self, px, py):
        """:meth:`TwoSidedObstacle.envelope` of the lower obstacle (checked arrays)."""
        alpha, kappa, mu, rc2 = self._alpha, self._kappa, self._mu, self._rc * self._rc
        xl, xh = px.min(axis=1), px.max(axis=1)
        yl, yh = py.min(axis=1), py.max(axis=1)
        hu = self._hessian_u_box(xl, xh, yl, yh)
        hk = self._hessian_bump_box(px, py, -self._m, xl, xh, yl, yh)
        # D^2 psi = D^2 u - alpha D^2((p_-^+)^2): [lo_u - alpha hi_k, hi_u - alpha lo_k]
        (a_lo, a_hi), (b_lo, b_hi), (c_lo, c_hi) = (
            (u_lo - alpha * k_hi, u_hi - alpha * k_lo)
            for (u_lo, u_hi), (k_lo, k_hi) in zip(hu, hk, strict=True)
        )
        b_abs = np.maximum(np.abs(b_lo), np.abs(b_hi))
        scale = np.abs(a_lo) + np.abs(a_hi) + np.abs(c_lo) + np.abs(c_hi) + b_abs
        m_plus = np.maximum(_lam_max_sup(a_hi, c_hi, b_abs), 0.0)
        m_minus = np.maximum(_lam_max_sup(-a_lo, -c_lo, b_abs), 0.0)
        m_plus = m_plus * (1.0 + _SLACK) + _SLACK * scale
        m_minus = m_minus * (1.0 + _SLACK) + _SLACK * scale

        # U_T, the affine majorant of Lambda_psi
        pm = self._p_minus(px, py)  # (P, 3)
        pp = self._p_plus(px, py)
        q = mu * alpha * (16.0 * pm + 8.0 * rc2)  # Q at the vertices
        dist = triangle_distance(px, py, -self._m, 0.0)
        in_minus = np.max(pm, axis=1) <= -_P_TOL
        off_minus = dist * dist >= rc2
        in_plus = np.max(pp, axis=1) <= 0.0
        r_t = enclosing_radius(px, py)
        lam_in_minus = kappa * (-pm) + (kappa * r_t * r_t)[:, None]
        lam_off = np.where(in_plus[:, None], np.maximum(q + kappa * pp, 0.0), q)
        sup_cross = np.maximum(kappa * (rc2 - dist * dist), np.max(q, axis=1))
        lam = np.where(
            in_minus[:, None],
            lam_in_minus,
            np.where(off_minus[:, None], lam_off, sup_cross[:, None]),
        )
        lam = lam * (1.0 + _SLACK) + _SLACK * (kappa + mu * alpha)
        return m_minus, m_plus, lam

    # ------------------------------------------------------------------ errors

    def energy_error(self, mesh, u_h) -> float:
        r"""Return the energy error :math:`|||u - u_h||| = \mu^{1/2}\|\nabla(u - u_h)\|`.

        :math:`\nabla u` is a polynomial of degree 4, so the integrand has degree 8
        on every triangle and the triangle rule of degree :data:`ERROR_DEGREE` = 8
        integrates it exactly (up to round-off); the per-triangle integrals are
        summed with :func:`math.fsum`.

        Parameters
        ----------
        mesh : fastmem.mesh.mesh.Mesh
            A mesh (anything with ``vertices`` (N, 2) and ``triangles`` (M, 3)),
            normally of :math:`(-1, 1)^2`; the error is integrated over it.
        u_h : ndarray of shape (N,)
            Nodal values of the P1 function.

        Returns
        -------
        float
            The energy error.

        Raises
        ------
        DataError
            If ``u_h`` has the wrong shape or non-finite values.
        MeshError
            If a triangle is degenerate.

        Examples
        --------
        >>> from fastmem.mesh.mesh import Mesh
        >>> p = TwoSided()
        >>> mesh = Mesh.square(16)
        >>> e = p.energy_error(mesh, p.solution(mesh.vertices[:, 0], mesh.vertices[:, 1]))
        >>> round(e, 4)
        0.2211
        """
        vertices, triangles, u_h = _mesh_arrays(mesh, u_h)
        if triangles.ndim != 2 or triangles.shape[1] != 3:
            raise DataError(f"triangles must have shape (M, 3), got {triangles.shape}")
        bary, weights = triangle_rule(ERROR_DEGREE)
        parts = np.empty(triangles.shape[0])
        for start in range(0, triangles.shape[0], _CHUNK):
            tri = triangles[start : start + _CHUNK]
            p = vertices[tri]  # (m, 3, 2)
            grads, area = _hat_gradients(p)
            gh = np.einsum("mi,mij->mj", u_h[tri], grads)
            x = p[:, :, 0] @ bary.T  # (m, nq)
            y = p[:, :, 1] @ bary.T
            gx, gy = self.gradient(x, y)
            ex = gx - gh[:, 0, None]
            ey = gy - gh[:, 1, None]
            parts[start : start + _CHUNK] = area * ((ex * ex + ey * ey) @ weights)
        return math.sqrt(self._mu * math.fsum(parts))
