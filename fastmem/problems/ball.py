r"""The ball obstacle problem of PETSc ex9/ex34 (Bueler), docs/obstacle.md §8.1.

On :math:`\Omega = (-2, 2)^2` with :math:`f = 0`, :math:`\mu = 1` and the lower
obstacle (a hemisphere of radius one continued by its tangent cone)

.. math::

    \psi(r) = \sqrt{1 - r^2} \quad (r \le r_0), \qquad
    \psi(r) = \psi_0 + \psi_0' (r - r_0) \quad (r > r_0),

:math:`r_0 = 0.9`, :math:`\psi_0 = \sqrt{1 - r_0^2}`, :math:`\psi_0' = -r_0/\psi_0`,
the exact solution is

.. math::

    u = \psi \quad (r \le r_*), \qquad u = -A_* \ln r + B_* \quad (r > r_*),
    \qquad \lambda = \frac{2 - r^2}{(1 - r^2)^{3/2}}\, 1_{\{r < r_*\}},

with the constants :data:`RSTAR`, :data:`ASTAR`, :data:`BSTAR` of the issue (they are
PETSc's). The boundary data are :math:`g = u|_{\partial\Omega}` (:data:`ball_g`).

Contents:

- the constants, and :data:`ENERGY_SQ` :math:`= |||u|||^2` from its closed form
  (Catalan's constant :data:`CATALAN`);
- :data:`ball_obstacle`, an instance of :class:`BallObstacle`: the values of
  :math:`\psi`, its Laplacian, the pressure bound
  :math:`\Lambda_\psi = (-\Delta\psi)^+` and the guaranteed per-piece envelope
  constants of docs/obstacle.md §5.1-5.2 (:meth:`BallObstacle.envelope`);
- :func:`ball_solution`, :func:`ball_gradient`, :func:`ball_multiplier`;
- :func:`ball_energy_error`, :math:`|||u - u_h|||` of a P1 function, by the
  reduction to edge integrals ("way 1" of §8.1), exact up to round-off;
- the geometric helpers :func:`triangle_distance` (distance from a point to
  triangles) and :func:`enclosing_radius` (radius of the smallest enclosing disc),
  shared with :mod:`fastmem.problems.twosided`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import roots_legendre

from ..errors import DataError, MeshError
from ..estimators.obstacle import enclosing_radius
from .manufactured import _as_xy

__all__ = [
    "ASTAR",
    "BSTAR",
    "CATALAN",
    "CONTACT_AREA",
    "DOMAIN",
    "DPSI0",
    "ENERGY_SQ",
    "PSI0",
    "R0",
    "RSTAR",
    "BallObstacle",
    "ball_energy_error",
    "ball_g",
    "ball_gradient",
    "ball_multiplier",
    "ball_obstacle",
    "ball_solution",
    "enclosing_radius",
    "triangle_distance",
]

#: Radius where the hemisphere is continued by its tangent cone.
R0 = 0.9
#: Obstacle height at :data:`R0`, :math:`\sqrt{1 - r_0^2}`.
PSI0 = math.sqrt(1.0 - R0 * R0)
#: Radial slope of the obstacle at :data:`R0` (and beyond), :math:`-r_0/\psi_0`.
DPSI0 = -R0 / PSI0
#: Radius of the contact disc (the issue's / PETSc's value).
RSTAR = 0.697965148223374
#: Coefficient of the logarithm outside the contact disc, :math:`r_*^2/\sqrt{1 - r_*^2}`.
ASTAR = 0.680259411891719
#: Constant outside the contact disc, :math:`A_* \ln 2` (so that :math:`u = 0` at
#: :math:`r = 2`).
BSTAR = 0.471519893402112
#: Area of the contact set, the disc :math:`r \le r_*`.
CONTACT_AREA = math.pi * RSTAR * RSTAR
#: Catalan's constant :math:`G = \sum_{k \ge 0} (-1)^k / (2k + 1)^2`.
CATALAN = 0.915965594177219015054603514932384110774
#: The domain is ``(DOMAIN[0], DOMAIN[1])^2``.
DOMAIN = (-2.0, 2.0)
#: :math:`|||u|||^2 = \|\nabla u\|^2_\Omega` in closed form (docs/obstacle.md §8.1):
#: :math:`\pi(-r_*^2 - \ln(1 - r_*^2)) + A_*^2 (2\pi\ln(2/r_*) + 2\pi\ln 2 - 4G)`,
#: evaluated with the constants above, 3.948249232793283 (the exact root :math:`r_*`
#: gives 3.948249232793262, the value quoted in §8.1: 5e-15 relative apart).
ENERGY_SQ = math.pi * (-RSTAR * RSTAR - math.log1p(-RSTAR * RSTAR)) + ASTAR * ASTAR * (
    2.0 * math.pi * math.log(2.0 / RSTAR) + 2.0 * math.pi * math.log(2.0) - 4.0 * CATALAN
)

# Relative slack applied to radii and bounds so that round-off cannot push a
# guaranteed bound below the true value (the computed quantities are accurate to a
# few units in the last place; 1e-13 is far above that and far below any effect).
_SLACK = 1e-13

# Gauss-Legendre points per smooth piece of an edge: machine accuracy on the ball even
# for edges as long as the radius of the contact disc (10 points leave 1e-13 at n = 8).
_EDGE_POINTS = 16

# Number of edges / triangles processed at once: small enough that the temporaries stay in
# the caches (n = 1024: the energy error in 1.1-1.2 s against 1.7-2.7 s with 2^16, same bits).
_CHUNK = 1 << 13


# --------------------------------------------------------------------------- helpers


def _as_pieces(px, py) -> tuple[np.ndarray, np.ndarray]:
    """Return the vertex coordinates of pieces as float64 arrays of shape (P, 3)."""
    px = np.asarray(px, dtype=np.float64)
    py = np.asarray(py, dtype=np.float64)
    if px.ndim != 2 or px.shape[1] != 3 or px.shape != py.shape:
        raise DataError(
            f"px and py must both have shape (P, 3) (three vertices per piece), "
            f"got {px.shape} and {py.shape}"
        )
    if not (np.all(np.isfinite(px)) and np.all(np.isfinite(py))):
        raise DataError("px and py must be finite")
    return px, py


def triangle_distance(px, py, cx: float = 0.0, cy: float = 0.0) -> np.ndarray:
    """Return the Euclidean distance from the point ``(cx, cy)`` to each triangle.

    Parameters
    ----------
    px, py : ndarray of shape (P, 3)
        Vertex coordinates of ``P`` triangles (either orientation; degenerate
        triangles are treated as segments or points).
    cx, cy : float, default 0.0
        The point.

    Returns
    -------
    ndarray of shape (P,)
        The distance from the point to the closed triangle: 0 if the point lies in
        it, else the smallest distance to its three edges.

    Examples
    --------
    >>> import numpy as np
    >>> px = np.array([[1.0, 2.0, 1.0], [-1.0, 1.0, 0.0]])
    >>> py = np.array([[0.0, 0.0, 1.0], [-1.0, -1.0, 1.0]])
    >>> triangle_distance(px, py).tolist()
    [1.0, 0.0]
    """
    ax = np.asarray(px, dtype=np.float64) - cx
    ay = np.asarray(py, dtype=np.float64) - cy
    bx = np.roll(ax, -1, axis=1)
    by = np.roll(ay, -1, axis=1)
    dx = bx - ax
    dy = by - ay
    # inside test: the point (the origin after the shift) is on the same side of all
    # three edges (or on one of them)
    cross = ax * dy - ay * dx  # (a - 0) x (b - a): sign of the origin's side, negated
    inside = np.all(cross >= 0.0, axis=1) | np.all(cross <= 0.0, axis=1)
    # distance to the segments [a, b]: clamp the projection of the origin
    len2 = dx * dx + dy * dy
    safe = np.where(len2 > 0.0, len2, 1.0)
    t = np.clip(-(ax * dx + ay * dy) / safe, 0.0, 1.0)
    t = np.where(len2 > 0.0, t, 0.0)
    qx = ax + t * dx
    qy = ay + t * dy
    dist = np.sqrt(np.min(qx * qx + qy * qy, axis=1))
    return np.where(inside, 0.0, dist)


# --------------------------------------------------------------------------- the obstacle


class BallObstacle:
    r"""The lower obstacle of the ball problem with its guaranteed envelope constants.

    :math:`\psi(r) = \sqrt{1 - r^2}` for :math:`r \le r_0` and its tangent cone
    :math:`\psi_0 + \psi_0'(r - r_0)` beyond: :math:`C^1`, concave on
    :math:`\mathbb R^2`, in :math:`W^{2,\infty}`. Calling the object evaluates
    :math:`\psi`; :meth:`envelope` returns the per-piece constants of
    docs/obstacle.md §5.1-5.2 in the closed forms of §8.1.

    Examples
    --------
    >>> float(ball_obstacle(0.0, 0.0)), round(float(ball_obstacle(0.9, 0.0)), 12)
    (1.0, 0.435889894354)
    """

    def __repr__(self) -> str:
        return f"{type(self).__name__}(r0={R0!r})"

    def __call__(self, x, y) -> np.ndarray:
        r"""Return :math:`\psi(x, y)`.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one (or broadcastable) shape.

        Returns
        -------
        ndarray
            The obstacle at the points.
        """
        x, y = _as_xy(x, y)
        r2 = x * x + y * y
        r = np.sqrt(r2)
        inner = np.sqrt(np.maximum(1.0 - r2, 0.0))
        return np.where(r <= R0, inner, PSI0 + DPSI0 * (r - R0))

    def laplacian(self, x, y) -> np.ndarray:
        r"""Return :math:`\Delta\psi`: :math:`(r^2 - 2)(1 - r^2)^{-3/2}` inside :math:`r_0`.

        Outside :math:`r_0` it is :math:`\psi_0'/r`. At :math:`r = 0` both formulas
        are finite; the cone's value is never used there.

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one (or broadcastable) shape.

        Returns
        -------
        ndarray
            The Laplacian at the points (defined a.e.: the inner value on
            :math:`r = r_0`).
        """
        x, y = _as_xy(x, y)
        r2 = x * x + y * y
        r = np.sqrt(r2)
        inside = r <= R0
        s = np.where(inside, 1.0 - r2, 1.0)
        rr = np.where(inside, 1.0, r)
        return np.where(inside, (r2 - 2.0) / (s * np.sqrt(s)), DPSI0 / rr)

    def pressure_bound(self, x, y) -> np.ndarray:
        r"""Return :math:`\Lambda_\psi = (-\mu\Delta\psi - f)^+ = -\Delta\psi` (μ = 1, f = 0).

        Parameters
        ----------
        x, y : array_like
            Coordinates, of one (or broadcastable) shape.

        Returns
        -------
        ndarray
            :math:`(2 - r^2)(1 - r^2)^{-3/2}` for :math:`r \le r_0`,
            :math:`r_0 / (\psi_0 r)` beyond; positive.
        """
        return -self.laplacian(x, y)

    def envelope(self, px, py) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        r"""Return guaranteed envelope constants of :math:`\psi` on triangular pieces.

        With :math:`\underline r_T` the distance from the origin to the piece
        :math:`T` and :math:`\bar r_T` its largest vertex norm (docs/obstacle.md
        §8.1, "Closed forms for §5"):

        .. math::

            M^-_T &= \max\Big\{(1 - \min(\bar r_T, r_0)^2)^{-3/2}
                     \ [\underline r_T < r_0],\
                     \frac{r_0}{\psi_0 \max(\underline r_T, r_0)}\ [\bar r_T > r_0]\Big\}, \\
            M^+_T &= 0 \quad (\psi \text{ is concave}),

        and :math:`U_T = I_T\Lambda_\psi` on pieces with :math:`\bar r_T \le r_0`
        (:math:`\Lambda_\psi` is convex there), else the constant
        :math:`\sup_T\Lambda_\psi`. Radii are rounded outwards by a relative
        ``1e-13`` and the values of :math:`U_T` upwards, so that round-off cannot
        make a bound fall below the true value.

        Parameters
        ----------
        px, py : ndarray of shape (P, 3)
            Vertex coordinates of ``P`` triangles (pieces).

        Returns
        -------
        m_minus : ndarray of shape (P,)
            :math:`M^-_T \ge \sup_T \lambda_{\max}(-D^2\psi)^+`.
        m_plus : ndarray of shape (P,)
            :math:`M^+_T \ge \sup_T \lambda_{\max}(D^2\psi)^+`; zero.
        lam_upper : ndarray of shape (P, 3)
            Values at the three vertices of an affine :math:`U_T \ge \Lambda_\psi`
            on :math:`T`.

        Raises
        ------
        DataError
            If ``px`` and ``py`` do not have one shape ``(P, 3)`` or are not finite.

        Examples
        --------
        >>> import numpy as np
        >>> m_minus, m_plus, lam = ball_obstacle.envelope(
        ...     np.array([[0.0, 0.1, 0.0]]), np.array([[0.0, 0.0, 0.1]]))
        >>> round(float(m_minus[0]), 5), float(m_plus[0]), round(float(lam[0, 0]), 12)
        (1.01519, 0.0, 2.0)
        """
        px, py = _as_pieces(px, py)
        r_low = triangle_distance(px, py) * (1.0 - _SLACK)
        r_high = np.sqrt(np.max(px * px + py * py, axis=1)) * (1.0 + _SLACK)
        meets_inner = r_low < R0
        meets_outer = r_high > R0
        rho = np.minimum(r_high, R0)
        s = 1.0 - rho * rho
        inner_hess = np.where(meets_inner, 1.0 / (s * np.sqrt(s)), 0.0)
        inner_lam = np.where(meets_inner, (2.0 - rho * rho) / (s * np.sqrt(s)), 0.0)
        outer = np.where(meets_outer, R0 / (PSI0 * np.maximum(r_low, R0)), 0.0)
        m_minus = np.maximum(inner_hess, outer) * (1.0 + _SLACK)
        m_plus = np.zeros_like(m_minus)
        sup_lam = np.maximum(inner_lam, outer)
        interpolate = ~meets_outer
        lam = np.where(interpolate[:, None], self.pressure_bound(px, py), sup_lam[:, None]) * (
            1.0 + _SLACK
        )
        return m_minus, m_plus, lam


#: The ball obstacle :math:`\psi` (an instance of :class:`BallObstacle`).
ball_obstacle = BallObstacle()


# --------------------------------------------------------------------------- the solution


def ball_solution(x, y) -> np.ndarray:
    r"""Return the exact solution :math:`u` of the ball problem.

    :math:`u = \psi` for :math:`r \le r_*`, else :math:`-A_*\ln r + B_*`.

    Parameters
    ----------
    x, y : array_like
        Coordinates, of one (or broadcastable) shape.

    Returns
    -------
    ndarray
        :math:`u` at the points (zero, up to round-off, at :math:`r = 2`).

    Examples
    --------
    >>> abs(float(ball_solution(2.0, 0.0))) < 1e-15
    True
    """
    x, y = _as_xy(x, y)
    r2 = x * x + y * y
    inside = r2 <= RSTAR * RSTAR
    inner = np.sqrt(np.where(inside, 1.0 - r2, 1.0))
    outer = -0.5 * ASTAR * np.log(np.where(inside, 1.0, r2)) + BSTAR
    return np.where(inside, inner, outer)


#: The Dirichlet data :math:`g = u|_{\partial\Omega}`: the exact solution as a callable.
ball_g = ball_solution


def ball_gradient(x, y) -> tuple[np.ndarray, np.ndarray]:
    r"""Return the gradient of the exact solution.

    :math:`\nabla u = -\mathbf x/\sqrt{1 - r^2}` inside :math:`r_*`,
    :math:`-A_*\mathbf x/r^2` outside (continuous across :math:`r = r_*`).

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
    r2 = x * x + y * y
    inside = r2 <= RSTAR * RSTAR
    factor = np.where(
        inside,
        -1.0 / np.sqrt(np.where(inside, 1.0 - r2, 1.0)),
        -ASTAR / np.where(inside, 1.0, r2),
    )
    return factor * x, factor * y


def ball_multiplier(x, y) -> np.ndarray:
    r"""Return the multiplier :math:`\lambda = -\Delta\psi\, 1_{\{r < r_*\}}`.

    Parameters
    ----------
    x, y : array_like
        Coordinates, of one (or broadcastable) shape.

    Returns
    -------
    ndarray
        :math:`(2 - r^2)(1 - r^2)^{-3/2}` on the contact disc, 0 elsewhere.

    Examples
    --------
    >>> float(ball_multiplier(0.0, 0.0)), float(ball_multiplier(1.0, 0.0))
    (2.0, 0.0)
    """
    x, y = _as_xy(x, y)
    r2 = x * x + y * y
    inside = r2 < RSTAR * RSTAR
    s = np.where(inside, 1.0 - r2, 1.0)
    return np.where(inside, (2.0 - r2) / (s * np.sqrt(s)), 0.0)


# --------------------------------------------------------------------------- energy error


def _mesh_arrays(mesh, u_h) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return ``vertices``, ``triangles`` and the checked nodal vector ``u_h``."""
    try:
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        triangles = np.asarray(mesh.triangles)
    except AttributeError:
        raise DataError(
            f"mesh must have 'vertices' and 'triangles' attributes, got {type(mesh).__name__}"
        ) from None
    u_h = np.asarray(u_h, dtype=np.float64)
    if u_h.shape != (vertices.shape[0],):
        raise DataError(
            f"u_h must have shape ({vertices.shape[0]},) (one value per vertex), got {u_h.shape}"
        )
    if not np.all(np.isfinite(u_h)):
        raise DataError("u_h contains NaN or infinite values")
    return vertices, triangles, u_h


def _check_ball_domain(vertices: np.ndarray, triangles: np.ndarray) -> None:
    """Raise :class:`MeshError` unless the mesh covers the square ``DOMAIN^2``."""
    lo, hi = DOMAIN
    p = vertices[triangles]
    e1 = p[:, 1] - p[:, 0]
    e2 = p[:, 2] - p[:, 0]
    area = 0.5 * math.fsum(np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]))
    box = (vertices[:, 0].min(), vertices[:, 0].max(), vertices[:, 1].min(), vertices[:, 1].max())
    if not (
        np.allclose(box, (lo, hi, lo, hi), rtol=0.0, atol=1e-12)
        and abs(area - (hi - lo) ** 2) <= 1e-12 * (hi - lo) ** 2
    ):
        raise MeshError(
            f"the ball energy error needs a mesh of the whole square ({lo}, {hi})^2 "
            f"(|||u|||^2 is known in closed form there); got bounding box {box} and area {area}"
        )


def _edge_means(a: np.ndarray, b: np.ndarray, n_points: int = _EDGE_POINTS) -> np.ndarray:
    r"""Return the mean of :math:`u` over the segments ``[a, b]``, exact up to round-off.

    A segment is split where it crosses the circle :math:`r = r_*` (the roots of
    :math:`|a + t(b - a)|^2 = r_*^2` in :math:`(0, 1)`); :math:`u` is analytic on
    each of the (at most three) pieces, integrated by ``n_points``-point
    Gauss-Legendre. Only the few segments that cross the circle are split.
    """
    d = b - a
    qa = np.einsum("ij,ij->i", d, d)
    qb = np.einsum("ij,ij->i", a, d)
    qc = np.einsum("ij,ij->i", a, a) - RSTAR * RSTAR
    disc = qb * qb - qa * qc
    real = (disc > 0.0) & (qa > 0.0)
    root = np.sqrt(np.where(real, disc, 0.0))
    # stable roots: q = -(qb + sign(qb) root), t1 = q / qa, t2 = qc / q
    q = -(qb + np.copysign(root, qb))
    t1 = np.where(real, q / np.where(qa > 0.0, qa, 1.0), 0.0)
    t2 = np.where(real & (q != 0.0), qc / np.where(q != 0.0, q, 1.0), 0.0)
    t1 = np.clip(t1, 0.0, 1.0)
    t2 = np.clip(t2, 0.0, 1.0)
    cut = real & (((t1 > 0.0) & (t1 < 1.0)) | ((t2 > 0.0) & (t2 < 1.0)))
    nodes, weights = roots_legendre(n_points)
    t = 0.5 * (nodes + 1.0)
    # segments inside or outside the circle: one piece, [0, 1]
    x = a[:, 0, None] + t * d[:, 0, None]
    y = a[:, 1, None] + t * d[:, 1, None]
    means = 0.5 * (ball_solution(x, y) @ weights)
    if np.any(cut):
        idx = np.flatnonzero(cut)
        breaks = np.sort(
            np.column_stack([np.zeros(idx.size), t1[idx], t2[idx], np.ones(idx.size)]),
            axis=1,
        )
        lo = breaks[:, :-1, None]  # (c, 3, 1)
        half = 0.5 * (breaks[:, 1:, None] - lo)
        tc = lo + half * (nodes + 1.0)  # (c, 3, n)
        x = a[idx, 0, None, None] + tc * d[idx, 0, None, None]
        y = a[idx, 1, None, None] + tc * d[idx, 1, None, None]
        means[idx] = np.einsum("cpq,q,cp->c", ball_solution(x, y), weights, half[:, :, 0])
    return means


def _triangle_edge_means(mesh, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Return the mean of :math:`u` over the local edges of every triangle, shape (M, 3).

    Uses the mesh's unique edges when it has them (``edges``, ``triangle_edges``),
    else the three local edges of every triangle.
    """
    edges = getattr(mesh, "edges", None)
    tri_edges = getattr(mesh, "triangle_edges", None)
    if edges is not None and tri_edges is not None:
        edges = np.asarray(edges)
        a_all, b_all = vertices[edges[:, 0]], vertices[edges[:, 1]]
        tri_edges = np.asarray(tri_edges)
    else:
        p = vertices[triangles]
        # local edge i joins local vertices i+1 and i+2
        a_all = p[:, [1, 2, 0]].reshape(-1, 2)
        b_all = p[:, [2, 0, 1]].reshape(-1, 2)
        tri_edges = np.arange(3 * triangles.shape[0]).reshape(-1, 3)
    means = np.empty(a_all.shape[0])
    for start in range(0, a_all.shape[0], _CHUNK):
        stop = start + _CHUNK
        means[start:stop] = _edge_means(a_all[start:stop], b_all[start:stop])
    return means[tri_edges]


def ball_energy_error(mesh, u_h) -> float:
    r"""Return the energy error :math:`|||u - u_h|||` of a P1 function on the ball problem.

    Uses the reduction to one-dimensional integrals of docs/obstacle.md §8.1
    ("way 1"):

    .. math::

        |||u - u_h|||^2 = |||u|||^2 + \sum_K \Big(|K|\,|\nabla u_h|_K|^2
            - 2\,\nabla u_h|_K \cdot \int_K \nabla u\Big),
        \qquad \int_K \nabla u = \sum_{E \subset \partial K} n_{K,E} \int_E u\,ds
        = -2|K| \sum_i \bar u_{E_i} \nabla\varphi_i ,

    with :math:`|||u|||^2` = :data:`ENERGY_SQ`, :math:`\bar u_{E_i}` the mean of
    :math:`u` over the edge opposite vertex :math:`i` and :math:`\varphi_i` the hat
    functions. Each edge is split where it crosses :math:`r = r_*` (the kink of
    :math:`\nabla u`) and integrated by 16-point Gauss-Legendre per piece, so the
    result is exact up to round-off; the per-triangle terms are summed with
    :func:`math.fsum`. The subtraction loses about
    :math:`\log_{10}(|||u|||^2 / |||u - u_h|||^2)` digits (about 5 at
    :math:`n = 1024`).

    With the rounded constants the two branches of :math:`u` differ by 3e-15 on
    :math:`r = r_*`; through the divergence theorem this changes the squared
    error by about 1e-14 (a 2D quadrature agrees to 1e-13 relative at
    :math:`n = 8, 16`).

    Parameters
    ----------
    mesh : fastmem.mesh.mesh.Mesh
        A mesh of the whole square :math:`(-2, 2)^2` (anything with ``vertices``
        (N, 2) and ``triangles`` (M, 3)), e.g.
        ``Mesh.rectangle(n, n, (-2, 2, -2, 2), diagonal="symmetric")``.
    u_h : ndarray of shape (N,)
        Nodal values of the P1 function (any values; they need not match
        :data:`ball_g` on the boundary).

    Returns
    -------
    float
        :math:`|||u - u_h|||`.

    Raises
    ------
    DataError
        If ``u_h`` has the wrong shape or non-finite values.
    MeshError
        If the mesh does not cover :math:`(-2, 2)^2` (bounding box and total area).

    Examples
    --------
    >>> from fastmem.mesh.mesh import Mesh
    >>> mesh = Mesh.rectangle(32, 32, (-2.0, 2.0, -2.0, 2.0), diagonal="symmetric")
    >>> u_h = ball_solution(mesh.vertices[:, 0], mesh.vertices[:, 1])
    >>> round(ball_energy_error(mesh, u_h), 4)
    0.1353
    """
    vertices, triangles, u_h = _mesh_arrays(mesh, u_h)
    _check_ball_domain(vertices, triangles)
    means = _triangle_edge_means(mesh, vertices, triangles)
    terms = np.empty(triangles.shape[0])
    for start in range(0, triangles.shape[0], _CHUNK):
        tri = triangles[start : start + _CHUNK]
        grads, area = _hat_gradients(vertices[tri])
        gh = np.einsum("mi,mij->mj", u_h[tri], grads)  # grad u_h per triangle
        g_dot = np.einsum("mj,mij->mi", gh, grads)  # grad u_h . grad phi_i
        m_i = means[start : start + _CHUNK]
        terms[start : start + _CHUNK] = area * (
            np.einsum("mj,mj->m", gh, gh) + 4.0 * np.einsum("mi,mi->m", m_i, g_dot)
        )
    err2 = ENERGY_SQ + math.fsum(terms)
    return math.sqrt(max(err2, 0.0))


def _hat_gradients(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the hat-function gradients (m, 3, 2) and the areas (m,) of triangles ``p``."""
    e = p[:, [2, 0, 1]] - p[:, [1, 2, 0]]  # edge opposite vertex i, from i+1 to i+2
    det = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 2, 0] - p[:, 0, 0]) * (
        p[:, 1, 1] - p[:, 0, 1]
    )
    if np.any(det == 0.0):
        raise MeshError("degenerate triangles (zero area)")
    grads = np.stack([-e[..., 1], e[..., 0]], axis=-1) / det[:, None, None]
    return grads, 0.5 * np.abs(det)


def _energy_error_2d(mesh, u_h, n_angle: int = 24, n_radius: int = 24) -> float:
    r"""Return :math:`|||u - u_h|||` by direct 2D quadrature ("way 2" of §8.1); slow.

    A reference for tests, independent of :data:`ENERGY_SQ` and of the edge
    integrals: every triangle is integrated in polar coordinates about the origin.
    The angle range is split at the vertex angles and at the angles where the
    edges cross :math:`r = r_*`; on each angular interval the ray meets the
    triangle in :math:`[r_{lo}(\theta), r_{hi}(\theta)]` (from its three
    half-planes), a smooth function of :math:`\theta`, which is split at
    :math:`r_*`. Gauss-Legendre in both variables.

    Parameters
    ----------
    mesh : fastmem.mesh.mesh.Mesh
        Any mesh (not necessarily of the whole square).
    u_h : ndarray of shape (N,)
        Nodal values of the P1 function.
    n_angle, n_radius : int, default 24
        Gauss-Legendre points per angular interval and per radial piece.

    Returns
    -------
    float
        :math:`\|\nabla(u - u_h)\|` over the mesh.
    """
    vertices, triangles, u_h = _mesh_arrays(mesh, u_h)
    nodes_a, weights_a = roots_legendre(n_angle)
    nodes_r, weights_r = roots_legendre(n_radius)
    total = []
    for start in range(0, triangles.shape[0], 256):
        tri = triangles[start : start + 256]
        p = vertices[tri]  # (m, 3, 2)
        grads, _ = _hat_gradients(p)
        gh = np.einsum("mi,mij->mj", u_h[tri], grads)
        m = p.shape[0]
        # breakpoints: vertex angles (vertices away from the origin) and crossings
        norms = np.hypot(p[..., 0], p[..., 1])
        vert_ang = np.where(norms > 0.0, np.arctan2(p[..., 1], p[..., 0]), np.nan)
        a = p[:, [1, 2, 0]]
        d = p[:, [2, 0, 1]] - a
        qa = np.einsum("mij,mij->mi", d, d)
        qb = np.einsum("mij,mij->mi", a, d)
        qc = np.einsum("mij,mij->mi", a, a) - RSTAR * RSTAR
        disc = qb * qb - qa * qc
        root = np.sqrt(np.maximum(disc, 0.0))
        cross_ang = []
        for sign in (-1.0, 1.0):
            t = (-qb + sign * root) / qa
            ok = (disc > 0.0) & (t > 0.0) & (t < 1.0)
            cx = a[..., 0] + t * d[..., 0]
            cy = a[..., 1] + t * d[..., 1]
            cross_ang.append(np.where(ok, np.arctan2(cy, cx), np.nan))
        ang = np.concatenate([vert_ang] + cross_ang, axis=1) % (2.0 * np.pi)  # (m, 9)
        ang = np.sort(np.where(np.isnan(ang), np.inf, ang), axis=1)
        first = ang[:, :1] + 2.0 * np.pi
        ang = np.where(np.isinf(ang), first, ang)
        bps = np.concatenate([ang, first], axis=1)  # (m, 10)
        lo = bps[:, :-1, None]
        half = 0.5 * (bps[:, 1:, None] - lo)
        theta = lo + half * (nodes_a + 1.0)  # (m, 9, na)
        wtheta = half * weights_a  # (m, 9, na)
        cth, sth = np.cos(theta), np.sin(theta)
        # half-planes of the triangle: n_i . x <= n_i . a_i with outward normals n_i
        orient = np.sign(
            (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
            - (p[:, 2, 0] - p[:, 0, 0]) * (p[:, 1, 1] - p[:, 0, 1])
        )
        nx = d[..., 1] * orient[:, None]
        ny = -d[..., 0] * orient[:, None]
        c = nx * a[..., 0] + ny * a[..., 1]  # (m, 3)
        nd = nx[:, None, None, :] * cth[..., None] + ny[:, None, None, :] * sth[..., None]
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = c[:, None, None, :] / nd
        r_lo = np.max(np.where(nd < 0.0, ratio, 0.0), axis=-1)
        r_lo = np.maximum(r_lo, 0.0)
        r_hi = np.min(np.where(nd > 0.0, ratio, np.inf), axis=-1)
        r_hi = np.where(np.isfinite(r_hi), r_hi, r_lo)
        r_hi = np.maximum(r_hi, r_lo)
        # both sides of r_*: [r_lo, min(r_hi, r*)] and [max(r_lo, r*), r_hi]
        pieces = [
            (r_lo, np.maximum(np.minimum(r_hi, RSTAR), r_lo)),
            (np.minimum(np.maximum(r_lo, RSTAR), r_hi), r_hi),
        ]
        acc = np.zeros(m)
        for r0, r1 in pieces:
            rh = 0.5 * (r1 - r0)
            r = r0[..., None] + rh[..., None] * (nodes_r + 1.0)  # (m, 9, na, nr)
            x = r * cth[..., None]
            y = r * sth[..., None]
            gx, gy = ball_gradient(x, y)
            ex = gx - gh[:, 0, None, None, None]
            ey = gy - gh[:, 1, None, None, None]
            f = (ex * ex + ey * ey) * r
            acc += np.einsum("mpar,r,mpa,mpa->m", f, weights_r, rh, wtheta)
        total.append(acc)
    return math.sqrt(math.fsum(np.concatenate(total)))
