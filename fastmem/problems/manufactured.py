r"""Manufactured solutions of the two-membrane contact problem (docs/method.md §7).

On :math:`\Omega = (-1, 1)^2` let :math:`b(x, y) = (1 - x^2)(1 - y^2)` and
take parameters :math:`\mu_1, \mu_2 > 0`, :math:`g > 0`, :math:`\beta > 0`,
:math:`s_0` and :math:`\kappa \ge 0`. Then

.. math::

    q &= g - \beta b, \qquad w = \frac{(q^+)^2}{g}, \qquad s = \mu_1 g + s_0 b, \\
    u_1 &= \frac{s + \mu_2 w}{\mu_1 + \mu_2}, \qquad
    u_2 = \frac{s - \mu_1 w}{\mu_1 + \mu_2}, \\
    \lambda &= \kappa\, (-q)^+ \quad \text{(or } \lambda = \kappa\, 1_{\{q < 0\}}
    \text{ for the discontinuous variant)}, \\
    f_1 &= -\mu_1 \Delta u_1 - \lambda, \qquad f_2 = -\mu_2 \Delta u_2 + \lambda,

solve the problem of docs/method.md §1: the gap is :math:`u_1 - u_2 = w \ge 0`,
:math:`w = 0` on the contact set :math:`\{q \le 0\} = \{b \ge g/\beta\}`
where :math:`\lambda` may be positive, :math:`w = g` and :math:`b = 0` on
:math:`\partial\Omega`, so that :math:`u_1 = g` and :math:`u_2 = 0` there.
The closed forms used for the derivatives are

.. math::

    \nabla b &= \bigl(-2x(1 - y^2),\; -2y(1 - x^2)\bigr), \qquad
    \Delta b = -2(1 - y^2) - 2(1 - x^2), \\
    \nabla w &= -\frac{2\beta}{g}\, q^+ \nabla b, \qquad
    \Delta w = \frac{2}{g}\bigl(\beta^2 |\nabla b|^2 - \beta q \Delta b\bigr)
    \text{ on } \{q > 0\}, \quad 0 \text{ elsewhere}, \\
    \nabla u_{1,2} &= \frac{s_0 \nabla b \pm \mu_{2,1} \nabla w}{\mu_1 + \mu_2}, \qquad
    \Delta u_{1,2} = \frac{s_0 \Delta b \pm \mu_{2,1} \Delta w}{\mu_1 + \mu_2}.

:math:`w` is :math:`C^1` but not :math:`C^2`: :math:`\Delta w`, hence
:math:`f_1, f_2`, jump across the free boundary :math:`\{q = 0\}`. The
defaults :math:`g = 0.1, \beta = 0.25, s_0 = 1, \kappa = 1` give the contact
set :math:`\{b \ge 0.4\}`; :math:`\kappa = 0` is the degenerate case
:math:`\lambda \equiv 0` on a contact set of positive measure. (Note that this
:math:`\kappa` is a parameter of the manufactured :math:`\lambda`, unrelated to
the :math:`\kappa = 1/\mu_1 + 1/\mu_2` of the decoupled solver in docs/method.md §3.3.)

Errors of discrete solutions are measured in the energy norm
:math:`|||v|||^2 = \mu_1 \|\nabla v_1\|^2 + \mu_2 \|\nabla v_2\|^2` with a
triangle quadrature of degree at least 6 (:func:`energy_error`). The exact
gradients are polynomials of degree 7 in :math:`x, y` on each side of the free
boundary (:math:`b` has degree 4, :math:`w` degree 8), so the squared error
integrand has degree 14: the integral is exact, up to round-off, only with a
rule of degree at least 14 and on triangles the free boundary does not cross.
The default degree 7 makes the quadrature error negligible next to the
:math:`O(h)` P1 error; report the degree used (``quadrature_degree``).
"""

from __future__ import annotations

import logging
import math
import numbers
from collections.abc import Callable, Sequence

import numpy as np

from ..errors import DataError, MeshError, ParameterError
from ..fem.quadrature import quadrature_points, triangle_rule
from ..fem.scene import Scene

__all__ = [
    "DEFAULT_ERROR_DEGREE",
    "MIN_ERROR_DEGREE",
    "Manufactured",
    "energy_error",
    "energy_error_parts",
]

logger = logging.getLogger(__name__)

#: Smallest quadrature degree accepted for error integrals (docs/method.md §7).
MIN_ERROR_DEGREE = 6

#: Default quadrature degree for error integrals.
DEFAULT_ERROR_DEGREE = 7

# Number of triangles processed at once by the error integrals: the (chunk, points)
# arrays stay in the caches (0.8 MB at the 13 points of degree 7); 2^16 made every NumPy
# operation stream through memory (n = 1024: 1.84-2.46 s against 0.83-0.90 s, same bits).
_CHUNK = 1 << 13

GradientFunction = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


# --------------------------------------------------------------------------- validation


def _check_real(
    name: str, value, *, positive: bool = False, nonnegative: bool = False, nonzero: bool = False
) -> float:
    """Return ``value`` as a finite float, or raise :class:`ParameterError` naming ``name``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ParameterError(f"{name} must be a finite real number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ParameterError(f"{name} must be finite, got {value!r}")
    if positive and not value > 0.0:
        raise ParameterError(f"{name} must be positive, got {value!r}")
    if nonnegative and not value >= 0.0:
        raise ParameterError(f"{name} must be non-negative, got {value!r}")
    if nonzero and value == 0.0:
        raise ParameterError(f"{name} must be non-zero, got {value!r}")
    return value


def _check_mu(mu) -> tuple[float, float]:
    """Return ``mu`` as a pair of positive finite floats, or raise :class:`ParameterError`."""
    if isinstance(mu, (str, bytes)) or not isinstance(mu, (Sequence, np.ndarray)):
        raise ParameterError(f"mu must be a pair (mu1, mu2) of positive numbers, got {mu!r}")
    mu = tuple(mu)
    if len(mu) != 2:
        raise ParameterError(
            f"mu must be a pair (mu1, mu2) of positive numbers, got {len(mu)} values: {mu!r}"
        )
    return (
        _check_real("mu1", mu[0], positive=True),
        _check_real("mu2", mu[1], positive=True),
    )


def _as_xy(x, y) -> tuple[np.ndarray, np.ndarray]:
    """Return ``x, y`` as float64 arrays of a common (broadcast) shape."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.shape != y.shape:
        try:
            x, y = np.broadcast_arrays(x, y)
        except ValueError:
            raise DataError(
                f"x and y must have the same shape, got {x.shape} and {y.shape}"
            ) from None
    return x, y


def _mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    """Return the ``vertices`` and ``triangles`` arrays of a mesh-like object."""
    try:
        return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles)
    except AttributeError:
        raise DataError(
            f"mesh must have 'vertices' and 'triangles' attributes, got {type(mesh).__name__}"
        ) from None


# --------------------------------------------------------------------------- bubble b


def _bubble(x, y):
    return (1.0 - x * x) * (1.0 - y * y)


def _grad_bubble(x, y):
    return -2.0 * x * (1.0 - y * y), -2.0 * y * (1.0 - x * x)


def _lap_bubble(x, y):
    return -2.0 * (1.0 - y * y) - 2.0 * (1.0 - x * x)


# --------------------------------------------------------------------------- error integrals


def _p1_geometry(vertices: np.ndarray, triangles: np.ndarray):
    """Return edge vectors, determinants and areas of the triangles."""
    p0 = vertices[triangles[:, 0]]
    e1 = vertices[triangles[:, 1]] - p0
    e2 = vertices[triangles[:, 2]] - p0
    det = e1[:, 0] * e2[:, 1] - e2[:, 0] * e1[:, 1]
    if np.any(det == 0.0) or not np.all(np.isfinite(det)):
        bad = np.flatnonzero((det == 0.0) | ~np.isfinite(det))
        raise MeshError(f"degenerate triangles (zero area): indices {bad[:10].tolist()}")
    return e1, e2, det, 0.5 * np.abs(det)


def _p1_gradients(e1, e2, det, triangles, values) -> tuple[np.ndarray, np.ndarray]:
    """Return the constant gradient of the P1 interpolant of nodal ``values`` per triangle.

    With ``J = [e1 e2]`` the Jacobian of the affine map from the reference
    triangle, ``grad u = J^{-T} (u1 - u0, u2 - u0)``; valid for either orientation.
    """
    v = values[triangles]
    d1 = v[:, 1] - v[:, 0]
    d2 = v[:, 2] - v[:, 0]
    gx = (e2[:, 1] * d1 - e1[:, 1] * d2) / det
    gy = (e1[:, 0] * d2 - e2[:, 0] * d1) / det
    return gx, gy


def _check_nodal(name: str, values, n: int) -> np.ndarray:
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (n,):
        raise DataError(f"{name} must have shape ({n},) (one value per vertex), got {values.shape}")
    if not np.all(np.isfinite(values)):
        raise DataError(f"{name} contains NaN or infinite values")
    return values


def energy_error_parts(
    vertices: np.ndarray,
    triangles: np.ndarray,
    mu: tuple[float, float],
    grad_exact: tuple[GradientFunction, GradientFunction],
    u1h: np.ndarray,
    u2h: np.ndarray,
    degree: int = DEFAULT_ERROR_DEGREE,
) -> tuple[float, float]:
    r"""Return the per-membrane energy errors of P1 nodal fields against exact gradients.

    .. math::

        e_i = \mu_i^{1/2} \|\nabla u_i - \nabla u_{ih}\|_{\Omega}, \qquad i = 1, 2,

    with :math:`\nabla u_{ih}` constant on each triangle and the integrals
    computed by :func:`~fastmem.fem.quadrature.triangle_rule` of ``degree``.

    Parameters
    ----------
    vertices : ndarray of shape (N, 2)
        Vertex coordinates.
    triangles : ndarray of shape (M, 3)
        Vertex indices of each triangle (either orientation).
    mu : tuple of float
        The tension coefficients ``(mu1, mu2)``, positive.
    grad_exact : tuple of callable
        ``(grad_u1, grad_u2)``; each maps arrays ``x, y`` of shape ``(m, nq)``
        to a pair ``(dx, dy)`` of arrays broadcastable to that shape.
    u1h, u2h : ndarray of shape (N,)
        Nodal values of the discrete membranes.
    degree : int, default 7
        Quadrature degree, at least 6.

    Returns
    -------
    e1, e2 : float
        The two weighted errors; the energy error is ``hypot(e1, e2)``.

    Raises
    ------
    ParameterError
        If ``degree`` is not an integer in ``[6, 30]`` or ``mu`` is invalid.
    DataError
        If arrays have wrong shapes or nodal values are not finite.
    MeshError
        If a triangle is degenerate.
    """
    bary, weights = triangle_rule(degree)
    if degree < MIN_ERROR_DEGREE:
        raise ParameterError(
            f"degree must be at least {MIN_ERROR_DEGREE} for error integrals, got {degree}"
        )
    mu = _check_mu(mu)
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = np.asarray(triangles)
    if vertices.ndim != 2 or vertices.shape[1] != 2:
        raise DataError(f"vertices must have shape (N, 2), got {vertices.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise DataError(f"triangles must have shape (M, 3), got {triangles.shape}")
    n = vertices.shape[0]
    nodal = (_check_nodal("u1h", u1h, n), _check_nodal("u2h", u2h, n))
    if len(grad_exact) != 2:
        raise DataError(f"grad_exact must be a pair of callables, got {len(grad_exact)} items")

    squares = [0.0, 0.0]
    for start in range(0, triangles.shape[0], _CHUNK):
        tri = triangles[start : start + _CHUNK]
        e1, e2, det, area = _p1_geometry(vertices, tri)
        x, y = quadrature_points(vertices, tri, bary)
        for i in range(2):
            ghx, ghy = _p1_gradients(e1, e2, det, tri, nodal[i])
            gx, gy = grad_exact[i](x, y)
            gx = np.broadcast_to(np.asarray(gx, dtype=np.float64), x.shape)
            gy = np.broadcast_to(np.asarray(gy, dtype=np.float64), x.shape)
            integrand = (gx - ghx[:, None]) ** 2 + (gy - ghy[:, None]) ** 2
            squares[i] += float(area @ (integrand @ weights))
    parts = (math.sqrt(mu[0] * squares[0]), math.sqrt(mu[1] * squares[1]))
    logger.debug("energy error parts %s (quadrature degree %d)", parts, degree)
    return parts


def energy_error(
    vertices: np.ndarray,
    triangles: np.ndarray,
    mu: tuple[float, float],
    grad_exact: tuple[GradientFunction, GradientFunction],
    u1h: np.ndarray,
    u2h: np.ndarray,
    degree: int = DEFAULT_ERROR_DEGREE,
) -> float:
    r"""Return the energy error of P1 nodal fields against exact gradients.

    .. math::

        |||u - u_h||| = \bigl(\mu_1 \|\nabla(u_1 - u_{1h})\|^2
                        + \mu_2 \|\nabla(u_2 - u_{2h})\|^2\bigr)^{1/2}.

    Parameters
    ----------
    vertices : ndarray of shape (N, 2)
        Vertex coordinates.
    triangles : ndarray of shape (M, 3)
        Vertex indices of each triangle (either orientation).
    mu : tuple of float
        The tension coefficients ``(mu1, mu2)``, positive.
    grad_exact : tuple of callable
        ``(grad_u1, grad_u2)``, see :func:`energy_error_parts`.
    u1h, u2h : ndarray of shape (N,)
        Nodal values of the discrete membranes.
    degree : int, default 7
        Quadrature degree, at least 6.

    Returns
    -------
    float
        The energy error.

    Raises
    ------
    ParameterError, DataError, MeshError
        As :func:`energy_error_parts`.

    Examples
    --------
    A linear function is reproduced exactly by its P1 interpolant:

    >>> import numpy as np
    >>> v = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    >>> t = np.array([[0, 1, 2], [1, 3, 2]])
    >>> grad = lambda x, y: (2.0, -1.0)
    >>> u = 2.0 * v[:, 0] - v[:, 1]
    >>> energy_error(v, t, (1.0, 1.0), (grad, grad), u, u) < 1e-14
    True
    """
    e1, e2 = energy_error_parts(vertices, triangles, mu, grad_exact, u1h, u2h, degree)
    return math.hypot(e1, e2)


# --------------------------------------------------------------------------- the class


class Manufactured:
    r"""A manufactured exact solution ``(u1, u2, lam)`` of the two-membrane problem.

    See the module docstring for the formulas. All field methods are
    vectorised: ``x`` and ``y`` are arrays of one (or broadcastable) shape and
    the results have that shape.

    Parameters
    ----------
    mu : tuple of float, default (1.0, 1.0)
        Tension coefficients ``(mu1, mu2)``, positive and finite.
    g : float, default 0.1
        Boundary value of the upper membrane, positive.
    beta : float, default 0.25
        Depth of the obstacle term, positive; the contact set is
        ``{b >= g / beta}`` (empty when ``beta < g``).
    s0 : float, default 1.0
        Amplitude of the contact-free part ``s = mu1 g + s0 b``.
    kappa : float, default 1.0
        Amplitude of the multiplier, non-negative (``0`` gives ``lam = 0``).
    discontinuous : bool, default False
        Use ``lam = kappa 1_{q<0}`` instead of ``lam = kappa (-q)^+``.

    Attributes
    ----------
    quadrature_degree : int
        Quadrature degree of the latest :meth:`energy_error` (or
        :meth:`energy_error_parts`) call; 7 before any call.

    Raises
    ------
    ParameterError
        If a parameter is out of range; the message names it and its value.

    Examples
    --------
    >>> m = Manufactured()
    >>> float(m.u1(1.0, 0.3)), float(m.u2(-1.0, 0.5))
    (0.1, 0.0)
    >>> bool(m.contact_indicator(0.0, 0.0)), float(m.contact_threshold)
    (True, 0.4)
    """

    def __init__(
        self,
        mu: tuple[float, float] = (1.0, 1.0),
        g: float = 0.1,
        beta: float = 0.25,
        s0: float = 1.0,
        kappa: float = 1.0,
        discontinuous: bool = False,
    ):
        self._mu = _check_mu(mu)
        self._g = _check_real("g", g, positive=True)
        self._beta = _check_real("beta", beta, positive=True)
        self._s0 = _check_real("s0", s0)
        self._kappa = _check_real("kappa", kappa, nonnegative=True)
        if not isinstance(discontinuous, (bool, np.bool_)):
            raise ParameterError(f"discontinuous must be a bool, got {discontinuous!r}")
        self._discontinuous = bool(discontinuous)
        self.quadrature_degree = DEFAULT_ERROR_DEGREE

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(mu={self._mu!r}, g={self._g!r}, beta={self._beta!r}, "
            f"s0={self._s0!r}, kappa={self._kappa!r}, discontinuous={self._discontinuous!r})"
        )

    # ------------------------------------------------------------------ parameters

    @property
    def mu(self) -> tuple[float, float]:
        """Tension coefficients ``(mu1, mu2)``."""
        return self._mu

    @property
    def mu1(self) -> float:
        """Tension coefficient of the upper membrane."""
        return self._mu[0]

    @property
    def mu2(self) -> float:
        """Tension coefficient of the lower membrane."""
        return self._mu[1]

    @property
    def g(self) -> float:
        """Boundary value of the upper membrane."""
        return self._g

    @property
    def beta(self) -> float:
        """Obstacle depth parameter."""
        return self._beta

    @property
    def s0(self) -> float:
        """Amplitude of the contact-free part ``s``."""
        return self._s0

    @property
    def kappa(self) -> float:
        """Amplitude of the multiplier."""
        return self._kappa

    @property
    def discontinuous(self) -> bool:
        """Whether ``lam`` is the discontinuous variant ``kappa 1_{q<0}``."""
        return self._discontinuous

    @property
    def contact_threshold(self) -> float:
        """The contact set is ``{b >= contact_threshold}`` with ``contact_threshold = g/beta``."""
        return self._g / self._beta

    def to_dict(self) -> dict:
        """Return the parameters as a plain dict (for reports and archives).

        Returns
        -------
        dict
            Keys ``mu, g, beta, s0, kappa, discontinuous``.
        """
        return {
            "mu": list(self._mu),
            "g": self._g,
            "beta": self._beta,
            "s0": self._s0,
            "kappa": self._kappa,
            "discontinuous": self._discontinuous,
        }

    # ------------------------------------------------------------------ fields

    def q(self, x, y) -> np.ndarray:
        """Return ``q = g - beta b``; contact where ``q <= 0``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one shape.

        Returns
        -------
        ndarray
            ``q`` at the points.
        """
        x, y = _as_xy(x, y)
        return self._g - self._beta * _bubble(x, y)

    def gap(self, x, y) -> np.ndarray:
        """Return the gap ``w = u1 - u2 = (q^+)^2 / g``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one shape.

        Returns
        -------
        ndarray
            ``w`` at the points.
        """
        qp = np.maximum(self.q(x, y), 0.0)
        # qp * (qp / g) rather than qp**2 / g: exactly g where b = 0 (on the boundary).
        return qp * (qp / self._g)

    def _s(self, x, y):
        return self._mu[0] * self._g + self._s0 * _bubble(x, y)

    def u1(self, x, y) -> np.ndarray:
        """Return the upper membrane ``u1 = (s + mu2 w) / (mu1 + mu2)``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one shape.

        Returns
        -------
        ndarray
            ``u1`` at the points.
        """
        x, y = _as_xy(x, y)
        mu1, mu2 = self._mu
        return (self._s(x, y) + mu2 * self.gap(x, y)) / (mu1 + mu2)

    def u2(self, x, y) -> np.ndarray:
        """Return the lower membrane ``u2 = (s - mu1 w) / (mu1 + mu2)``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one shape.

        Returns
        -------
        ndarray
            ``u2`` at the points.
        """
        x, y = _as_xy(x, y)
        mu1, mu2 = self._mu
        return (self._s(x, y) - mu1 * self.gap(x, y)) / (mu1 + mu2)

    def lam(self, x, y) -> np.ndarray:
        """Return the contact pressure ``kappa (-q)^+`` (or ``kappa 1_{q<0}``).

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one shape.

        Returns
        -------
        ndarray
            ``lam`` at the points, non-negative.
        """
        q = self.q(x, y)
        if self._discontinuous:
            return np.where(q < 0.0, self._kappa, 0.0)
        return self._kappa * np.maximum(-q, 0.0)

    def contact_indicator(self, x, y) -> np.ndarray:
        """Return whether the points lie in the contact set ``{q <= 0}``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one shape.

        Returns
        -------
        ndarray of bool
            ``True`` where ``q <= 0``.
        """
        return self.q(x, y) <= 0.0

    def _grad_gap(self, x, y):
        qp = np.maximum(self.q(x, y), 0.0)
        bx, by = _grad_bubble(x, y)
        c = -2.0 * self._beta / self._g * qp
        return c * bx, c * by

    def _load_parts(self, x, y):
        """``lap b``, ``lap w`` and ``lam`` at the points, sharing ``q`` and ``lap b``.

        ``lap w = (2 / g) (beta^2 |grad b|^2 - beta q lap b)`` where ``q > 0``, else 0
        (``w = (q^+)^2 / g``); ``lam`` as :meth:`lam`.  ``q`` and ``lap b`` are
        computed once for both terms: the loads are evaluated at every quadrature
        point of the finest mesh (7 per triangle).
        """
        q = self.q(x, y)
        lap_b = _lap_bubble(x, y)
        bx, by = _grad_bubble(x, y)
        lap = (2.0 / self._g) * (self._beta**2 * (bx * bx + by * by) - self._beta * q * lap_b)
        lap_w = np.where(q > 0.0, lap, 0.0)
        if self._discontinuous:
            lam = np.where(q < 0.0, self._kappa, 0.0)
        else:
            lam = self._kappa * np.maximum(-q, 0.0)
        return lap_b, lap_w, lam

    def grad_u1(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Return the gradient of ``u1``, ``(s0 grad b + mu2 grad w) / (mu1 + mu2)``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one shape.

        Returns
        -------
        dx, dy : ndarray
            The partial derivatives at the points.
        """
        x, y = _as_xy(x, y)
        mu1, mu2 = self._mu
        bx, by = _grad_bubble(x, y)
        wx, wy = self._grad_gap(x, y)
        return (self._s0 * bx + mu2 * wx) / (mu1 + mu2), (self._s0 * by + mu2 * wy) / (mu1 + mu2)

    def grad_u2(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Return the gradient of ``u2``, ``(s0 grad b - mu1 grad w) / (mu1 + mu2)``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one shape.

        Returns
        -------
        dx, dy : ndarray
            The partial derivatives at the points.
        """
        x, y = _as_xy(x, y)
        mu1, mu2 = self._mu
        bx, by = _grad_bubble(x, y)
        wx, wy = self._grad_gap(x, y)
        return (self._s0 * bx - mu1 * wx) / (mu1 + mu2), (self._s0 * by - mu1 * wy) / (mu1 + mu2)

    def f1(self, x, y) -> np.ndarray:
        """Return the load of the upper membrane, ``f1 = -mu1 lap u1 - lam``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one shape.

        Returns
        -------
        ndarray
            ``f1`` at the points (discontinuous across ``q = 0``).
        """
        x, y = _as_xy(x, y)
        mu1, mu2 = self._mu
        lap_b, lap_w, lam = self._load_parts(x, y)
        lap_u1 = (self._s0 * lap_b + mu2 * lap_w) / (mu1 + mu2)
        return -mu1 * lap_u1 - lam

    def f2(self, x, y) -> np.ndarray:
        """Return the load of the lower membrane, ``f2 = -mu2 lap u2 + lam``.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one shape.

        Returns
        -------
        ndarray
            ``f2`` at the points (discontinuous across ``q = 0``).
        """
        x, y = _as_xy(x, y)
        mu1, mu2 = self._mu
        lap_b, lap_w, lam = self._load_parts(x, y)
        lap_u2 = (self._s0 * lap_b - mu1 * lap_w) / (mu1 + mu2)
        return -mu2 * lap_u2 + lam

    # ------------------------------------------------------------------ meshes

    def scene(self, mesh, **options):
        """Return the :class:`fastmem.fem.scene.Scene` of this problem on ``mesh``.

        Parameters
        ----------
        mesh : fastmem.mesh.mesh.Mesh
            A mesh of ``(-1, 1)^2``.
        **options
            Passed on to :class:`~fastmem.fem.scene.Scene`; ``parallel_callables``
            defaults to True (the loads are vectorised NumPy code without state).

        Returns
        -------
        fastmem.fem.scene.Scene
            ``Scene(mesh, mu=(mu1, mu2), f=(self.f1, self.f2), g=self.g, **options)``.
        """
        options.setdefault("parallel_callables", True)
        return Scene(mesh, mu=self._mu, f=(self.f1, self.f2), g=self._g, **options)

    def interpolate(self, mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the nodal interpolants of ``u1``, ``u2`` and ``lam`` on ``mesh``.

        On boundary vertices ``u1`` is set to exactly ``g``, ``u2`` and ``lam``
        to exactly ``0`` (the formulas give these values up to round-off), so
        the triple is admissible for the discrete problem of docs/method.md §2.

        Parameters
        ----------
        mesh : fastmem.mesh.mesh.Mesh
            A mesh of ``(-1, 1)^2``, with ``vertices`` of shape (N, 2) and the
            boolean ``boundary_vertex_mask`` of shape (N,).

        Returns
        -------
        u1h, u2h, lamh : ndarray of shape (N,)
            Nodal values.

        Raises
        ------
        MeshError
            If a vertex lies outside ``[-1, 1]^2`` or a boundary vertex is not on
            its boundary (the manufactured solution lives on ``(-1, 1)^2``).
        """
        vertices, _ = _mesh_arrays(mesh)
        boundary = np.asarray(mesh.boundary_vertex_mask, dtype=bool)
        if boundary.shape != (vertices.shape[0],):
            raise DataError(
                f"mesh.boundary_vertex_mask must have shape ({vertices.shape[0]},), "
                f"got {boundary.shape}"
            )
        x, y = vertices[:, 0], vertices[:, 1]
        radius = np.maximum(np.abs(x), np.abs(y))
        tol = 1e-12
        if np.any(radius > 1.0 + tol):
            raise MeshError("manufactured solutions need a mesh of (-1, 1)^2; vertices lie outside")
        if np.any(np.abs(radius[boundary] - 1.0) > tol):
            raise MeshError(
                "manufactured solutions need a mesh of (-1, 1)^2; boundary vertices lie "
                "off its boundary"
            )
        u1h = self.u1(x, y)
        u2h = self.u2(x, y)
        lamh = self.lam(x, y)
        u1h[boundary] = self._g
        u2h[boundary] = 0.0
        lamh[boundary] = 0.0
        return u1h, u2h, lamh

    def energy_error_parts(
        self, mesh, u1h, u2h, degree: int = DEFAULT_ERROR_DEGREE
    ) -> tuple[float, float]:
        """Return ``(mu1^(1/2) ||grad(u1 - u1h)||, mu2^(1/2) ||grad(u2 - u2h)||)``.

        Parameters
        ----------
        mesh : fastmem.mesh.mesh.Mesh
            The mesh of the P1 fields.
        u1h, u2h : ndarray of shape (N,)
            Nodal values of the discrete membranes.
        degree : int, default 7
            Quadrature degree, at least 6; stored in :attr:`quadrature_degree`.

        Returns
        -------
        e1, e2 : float
            The weighted errors of the two membranes.
        """
        vertices, triangles = _mesh_arrays(mesh)
        parts = energy_error_parts(
            vertices, triangles, self._mu, (self.grad_u1, self.grad_u2), u1h, u2h, degree
        )
        self.quadrature_degree = int(degree)
        return parts

    def energy_error(self, mesh, u1h, u2h, degree: int = DEFAULT_ERROR_DEGREE) -> float:
        """Return the energy error ``|||u - u_h|||`` of P1 fields on ``mesh``.

        Parameters
        ----------
        mesh : fastmem.mesh.mesh.Mesh
            The mesh of the P1 fields.
        u1h, u2h : ndarray of shape (N,)
            Nodal values of the discrete membranes.
        degree : int, default 7
            Quadrature degree, at least 6; stored in :attr:`quadrature_degree`.

        Returns
        -------
        float
            ``sqrt(mu1 ||grad(u1 - u1h)||^2 + mu2 ||grad(u2 - u2h)||^2)``.

        Raises
        ------
        ParameterError
            If ``degree`` is below 6, above 30 or not an integer.
        """
        return math.hypot(*self.energy_error_parts(mesh, u1h, u2h, degree))
