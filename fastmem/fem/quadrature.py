r"""Quadrature rules on triangles, in barycentric coordinates.

A rule is a pair ``(bary, weights)``: ``bary`` of shape ``(nq, 3)`` holds the
barycentric coordinates of the points and ``weights`` of shape ``(nq,)`` sums
to one, so that on any triangle :math:`K`

.. math::

    \int_K f \,\mathrm{d}x \approx |K| \sum_{q} w_q f(x_q),
    \qquad x_q = \sum_{k=0}^{2} \mathrm{bary}_{q,k}\, a_k ,

with :math:`a_k` the vertices of :math:`K`. The rule returned by
:func:`triangle_rule` for ``degree`` integrates every polynomial of total
degree at most ``degree`` exactly (up to round-off):

- degrees 0 and 1: the centroid (1 point, exact to degree 1);
- degree 2: the symmetric interior rule with points (2/3, 1/6, 1/6) and
  permutations, weights 1/3 (3 points, exact to degree 2);
- degrees 3, 4 and 5: Radon's rule (7 points, exact to degree 5);
- degrees 6 to 30: a conical product (collapsed square) Gauss rule with n²
  points, exact to degree 2n - 1,

with ``n = ceil((degree + 1) / 2)`` for the conical product rule. That rule
maps the unit square to the reference triangle by :math:`x = s`,
:math:`y = t(1 - s)` (Jacobian :math:`1 - s`); it uses ``n`` Gauss–Jacobi
nodes for the weight :math:`(1 - s)` in ``s`` and ``n`` Gauss–Legendre nodes
in ``t``. All its points are strictly inside the triangle and all its weights
are positive.

Radon's rule has the centroid with weight :math:`9/40` and the points
:math:`(a, a, 1 - 2a)` and permutations for
:math:`a_{1,2} = (6 \mp \sqrt{15})/21` with weights
:math:`(155 \mp \sqrt{15})/1200`.

Rules are cached; the returned arrays are read-only and shared between calls.
"""

from __future__ import annotations

import functools
import logging
import math
import numbers

import numpy as np
from scipy.special import roots_jacobi, roots_legendre

from ..errors import DataError, ParameterError
from ..kernels import assembly as _ka

__all__ = ["MAX_DEGREE", "quadrature_points", "triangle_rule"]

logger = logging.getLogger(__name__)

#: Largest polynomial degree :func:`triangle_rule` accepts.
MAX_DEGREE = 30


def _check_degree(degree) -> int:
    """Return ``degree`` as a Python int, or raise :class:`ParameterError`."""
    if isinstance(degree, (bool, np.bool_)) or not isinstance(degree, numbers.Integral):
        raise ParameterError(
            f"degree must be a non-negative integer, got {degree!r} of type {type(degree).__name__}"
        )
    degree = int(degree)
    if degree < 0:
        raise ParameterError(f"degree must be a non-negative integer, got {degree}")
    if degree > MAX_DEGREE:
        raise ParameterError(
            f"degree must be at most {MAX_DEGREE}, got {degree} "
            "(higher degrees are not supported by fastmem's triangle rules)"
        )
    return degree


def _checked_array(value, name: str, kinds: str, what: str) -> np.ndarray:
    """Return ``np.asarray(value)`` if its dtype kind is in ``kinds``, else raise DataError."""
    try:
        arr = np.asarray(value)
    except Exception as exc:
        raise DataError(f"{name} cannot be converted to an array: {exc}") from exc
    if arr.dtype.kind not in kinds:
        raise DataError(f"{name} must {what}, got dtype {arr.dtype}")
    return arr


def _real_array(value, name: str) -> np.ndarray:
    """Return ``value`` as a float64 array, or raise :class:`DataError` naming ``name``."""
    return np.asarray(_checked_array(value, name, "iuf", "be real numbers"), dtype=np.float64)


def _orbit3(a: float) -> np.ndarray:
    """Return the three barycentric points ``(a, a, 1-2a)`` and its permutations."""
    c = 1.0 - 2.0 * a
    return np.array([[c, a, a], [a, c, a], [a, a, c]])


def _centroid_rule() -> tuple[np.ndarray, np.ndarray]:
    return np.full((1, 3), 1.0 / 3.0), np.ones(1)


def _three_point_rule() -> tuple[np.ndarray, np.ndarray]:
    return _orbit3(1.0 / 6.0), np.full(3, 1.0 / 3.0)


def _radon_rule() -> tuple[np.ndarray, np.ndarray]:
    r15 = math.sqrt(15.0)
    a1 = (6.0 - r15) / 21.0
    a2 = (6.0 + r15) / 21.0
    w1 = (155.0 - r15) / 1200.0
    w2 = (155.0 + r15) / 1200.0
    bary = np.vstack([np.full((1, 3), 1.0 / 3.0), _orbit3(a1), _orbit3(a2)])
    weights = np.concatenate([[9.0 / 40.0], np.full(3, w1), np.full(3, w2)])
    return bary, weights


def _conical_rule(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Collapsed-square Gauss rule with ``n`` points per direction (exact to ``2n - 1``)."""
    # Gauss-Jacobi for the weight (1 - xi) on [-1, 1]; s = (1 + xi) / 2 in [0, 1].
    xi, wj = roots_jacobi(n, 1.0, 0.0)
    # Gauss-Legendre on [-1, 1]; t = (1 + eta) / 2 in [0, 1].
    eta, wl = roots_legendre(n)
    s = 0.5 * (1.0 + xi)
    t = 0.5 * (1.0 + eta)
    # int_T f = int_0^1 int_0^1 f(s, t (1 - s)) (1 - s) ds dt
    #         = (1/8) sum_jk wj_j wl_k f(s_j, t_k (1 - s_j));  |T| = 1/2.
    x = np.repeat(s, n)
    y = np.outer(1.0 - s, t).ravel()
    weights = np.outer(wj, wl).ravel() / 4.0
    bary = np.column_stack([1.0 - x - y, x, y])
    return bary, weights


@functools.lru_cache(maxsize=MAX_DEGREE + 1)
def _cached_rule(degree: int) -> tuple[np.ndarray, np.ndarray]:
    if degree <= 1:
        bary, weights = _centroid_rule()
    elif degree == 2:
        bary, weights = _three_point_rule()
    elif degree <= 5:
        bary, weights = _radon_rule()
    else:
        bary, weights = _conical_rule(math.ceil((degree + 1) / 2))
    bary = np.ascontiguousarray(bary, dtype=np.float64)
    weights = np.ascontiguousarray(weights, dtype=np.float64)
    bary.flags.writeable = False
    weights.flags.writeable = False
    logger.debug("built triangle rule of degree %d with %d points", degree, weights.size)
    return bary, weights


def triangle_rule(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Return a triangle quadrature rule exact for polynomials of total degree ``degree``.

    Parameters
    ----------
    degree : int
        Polynomial degree to integrate exactly, ``0 <= degree <= 30``.

    Returns
    -------
    bary : ndarray of shape (nq, 3)
        Barycentric coordinates of the quadrature points (all non-negative, each
        row sums to one). Read-only.
    weights : ndarray of shape (nq,)
        Positive weights summing to one, so that
        ``integral over K of f ~= |K| * sum(weights * f(x_q))``. Read-only.

    Raises
    ------
    ParameterError
        If ``degree`` is not an integer, is negative or exceeds 30.

    Notes
    -----
    Degrees 0 and 1 give the centroid rule, degree 2 the symmetric 3-point
    rule, degrees 3 to 5 Radon's 7-point rule and higher degrees a conical
    product of Gauss–Jacobi and Gauss–Legendre rules with
    ``n = ceil((degree + 1) / 2)`` points per direction (exact to ``2n - 1``).
    The rules are cached; do not try to modify the returned arrays.

    Examples
    --------
    >>> bary, weights = triangle_rule(2)
    >>> bary.shape, weights.shape
    ((3, 3), (3,))
    >>> float(weights.sum())
    1.0
    """
    return _cached_rule(_check_degree(degree))


def quadrature_points(
    vertices: np.ndarray, triangles: np.ndarray, bary: np.ndarray, parallel: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Map barycentric quadrature points to the physical points of every triangle.

    Parameters
    ----------
    vertices : ndarray of shape (N, 2)
        Vertex coordinates.
    triangles : ndarray of shape (M, 3)
        Vertex indices of each triangle.
    bary : ndarray of shape (nq, 3)
        Barycentric coordinates of the quadrature points, as returned by
        :func:`triangle_rule`.
    parallel : bool
        Use the worker threads (default); ``False``: the calling thread only.

    Returns
    -------
    x, y : ndarray of shape (M, nq)
        Coordinates of the quadrature points, ``x[m, q] = sum_k bary[q, k] *
        vertices[triangles[m, k], 0]`` and likewise for ``y``.

    Raises
    ------
    DataError
        If the arrays have the wrong shapes or dtypes (real ``vertices`` and
        ``bary``, integer ``triangles``), or an index is out of range.

    Examples
    --------
    >>> import numpy as np
    >>> v = np.array([[0.0, 0.0], [3.0, 0.0], [0.0, 3.0]])
    >>> x, y = quadrature_points(v, np.array([[0, 1, 2]]), np.full((1, 3), 1.0 / 3.0))
    >>> float(x[0, 0]), float(y[0, 0])
    (1.0, 1.0)
    """
    vertices = _real_array(vertices, "vertices")
    bary = _real_array(bary, "bary")
    triangles = _checked_array(triangles, "triangles", "iu", "have an integer dtype")
    if vertices.ndim != 2 or vertices.shape[1] != 2:
        raise DataError(f"vertices must have shape (N, 2), got {vertices.shape}")
    if triangles.ndim != 2 or triangles.shape[1] != 3:
        raise DataError(f"triangles must have shape (M, 3), got {triangles.shape}")
    if bary.ndim != 2 or bary.shape[1] != 3:
        raise DataError(f"bary must have shape (nq, 3), got {bary.shape}")
    if triangles.size and (triangles.min() < 0 or triangles.max() >= vertices.shape[0]):
        raise DataError(
            f"triangles reference vertices outside [0, {vertices.shape[0] - 1}] "
            f"(indices {int(triangles.min())} .. {int(triangles.max())})"
        )
    # one parallel pass (fastmem.kernels.assembly.quadrature_points), on the dtypes
    # the solver's arrays have: one compiled specialisation
    return _ka.quadrature_points(
        np.ascontiguousarray(vertices, dtype=np.float64),
        np.ascontiguousarray(triangles, dtype=np.int64),
        np.ascontiguousarray(bary, dtype=np.float64),
        parallel=bool(parallel),
    )
