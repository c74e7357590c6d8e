r"""Exact integrals of positive parts of P1 functions, triangle by triangle.

For a P1 function ``w`` with nodal values ``w_0, w_1, w_2`` on a triangle K the
set ``{w > 0} ∩ K`` is empty, K itself, a triangle (one positive vertex) or a
quadrilateral (two positive vertices), cut off by the zero line of ``w``.  The
zero line crosses edge ``(p, n)`` (``w_p > 0 >= w_n``) at

.. math::

    q = (1 - t)\,x_p + t\,x_n, \qquad
    t = \frac{w_p}{w_p - w_n}, \qquad 1 - t = \frac{-w_n}{w_p - w_n},

where the denominator is ``>= w_p > 0`` (no division by zero, no cancellation;
a zero vertex value gives ``t = 1``, i.e. the cut passes through the vertex).
Both ``t`` and ``1 - t`` are computed from their own formula, so all
sub-areas and weights are sums of products of non-negative numbers.  The
positive set is a union of (at most two) sub-triangles on which ``w⁺ = w`` is
linear and vanishes at the cut points; the product ``v w`` of two linear
functions is integrated exactly with the P1 mass formula

.. math::

    \int_T v\,w = \frac{|T|}{12}\Big(\sum_k v_k w_k + \sum_k v_k \sum_k w_k\Big)

(equivalent to the 3-point edge-midpoint rule).  With one positive vertex
``a`` (cut parameters ``t_b``, ``t_c`` on its two edges) the sub-triangle is
``(a, q_b, q_c)`` with area fraction ``t_b t_c``.  With two positive vertices
``b``, ``c`` and ``w_a <= 0`` the quadrilateral ``(b, c, q_c, q_b)`` is split
along ``b q_c`` into ``(b, c, q_c)`` (area fraction ``t_c``) and
``(b, q_c, q_b)`` (area fraction ``(1 - t_c) t_b``).

Values may range over many orders of magnitude (tested for 1e-12 ... 1e12);
only the ratios ``w_p / (w_p - w_n)`` enter the geometry, so scaling ``w`` by
a power of two leaves :func:`positive_area` bitwise unchanged.

Threading: every kernel runs over the triangles in chunks (serial Numba
loops in Python threads, :mod:`._par`); iteration ``t`` writes ``out[t]``
only, into an array allocated before the loop.  The result is bitwise
independent of the thread count.  Inputs are not modified.
"""

import numpy as np

from ._jit import jit
from .pool import parallel_for

__all__ = ["contact_terms", "nonconformity", "positive_area", "positive_product", "precompile"]


#: Smallest normal float64.  A cut with subnormal nodal values would divide by a
#: subnormal number, whose reciprocal overflows: the kernels' fastmath ``arcp``
#: (a / b as a * (1 / b)) then turns 0 / b into 0 * inf = NaN (found by
#: tests/package/test_hostile.py with g = 5e-324).
_TINY = 2.2250738585072014e-308
#: Exact rescaling of such values (powers of two): the cut's ratios are unchanged.
_UP = 2.0**600
_DOWN = 2.0**-600


@jit
def _cut(w0, w1, w2, v0, v1, v2):
    """:func:`_cut_normal`, with subnormal ``w`` rescaled exactly first (``w⁺`` is linear).

    One test per triangle; normal values take :func:`_cut_normal` unchanged.
    """
    a0, a1, a2 = abs(w0), abs(w1), abs(w2)
    # one branch: the comparisons combined without short-circuits
    tiny = ((a0 < _TINY) & (a0 > 0.0)) | ((a1 < _TINY) & (a1 > 0.0)) | ((a2 < _TINY) & (a2 > 0.0))
    if tiny:
        frac, moment = _cut_normal(w0 * _UP, w1 * _UP, w2 * _UP, v0, v1, v2)
        return frac, moment * _DOWN
    return _cut_normal(w0, w1, w2, v0, v1, v2)


@jit
def _cut_normal(w0, w1, w2, v0, v1, v2):
    """Area fraction of ``{w > 0}`` in K and ``(v, w⁺)_K / |K|`` for nodal P1 ``w``, ``v``.

    Returns
    -------
    frac : float
        ``|{w > 0} ∩ K| / |K|`` in [0, 1].
    moment : float
        ``(v, w⁺)_K / |K|``.
    """
    n_pos = 0
    if w0 > 0.0:
        n_pos += 1
    if w1 > 0.0:
        n_pos += 1
    if w2 > 0.0:
        n_pos += 1
    if n_pos == 0:  # all values <= 0 (also w == 0 on K)
        return 0.0, 0.0
    if n_pos == 3:  # whole triangle, w⁺ = w
        return 1.0, (w0 * v0 + w1 * v1 + w2 * v2 + (w0 + w1 + w2) * (v0 + v1 + v2)) / 12.0
    # Rotate so that vertex a is the odd one out: the positive vertex when
    # n_pos == 1, the non-positive one when n_pos == 2.
    odd_sign = n_pos == 1
    if (w0 > 0.0) == odd_sign:
        wa, wb, wc, va, vb, vc = w0, w1, w2, v0, v1, v2
    elif (w1 > 0.0) == odd_sign:
        wa, wb, wc, va, vb, vc = w1, w2, w0, v1, v2, v0
    else:
        wa, wb, wc, va, vb, vc = w2, w0, w1, v2, v0, v1
    if n_pos == 1:
        # wa > 0 >= wb, wc; q_x = (1 - t_x) a + t_x x on edge (a, x).
        db = wa - wb  # >= wa > 0
        dc = wa - wc
        tb = min(wa / db, 1.0)
        sb = min(-wb / db, 1.0)  # 1 - tb
        tc = min(wa / dc, 1.0)
        sc = min(-wc / dc, 1.0)
        vqb = sb * va + tb * vb
        vqc = sc * va + tc * vc
        frac = tb * tc
        # triangle (a, q_b, q_c), w = (wa, 0, 0): |T|/12 * wa (2 va + vqb + vqc)
        return frac, frac * wa * (2.0 * va + vqb + vqc) / 12.0
    # n_pos == 2: wb, wc > 0 >= wa; q_x = (1 - t_x) x + t_x a on edge (x, a).
    db = wb - wa  # >= wb > 0
    dc = wc - wa
    tb = min(wb / db, 1.0)
    sb = min(-wa / db, 1.0)  # 1 - tb
    tc = min(wc / dc, 1.0)
    sc = min(-wa / dc, 1.0)
    vqb = sb * vb + tb * va
    vqc = sc * vc + tc * va
    f1 = tc  # triangle (b, c, q_c), w = (wb, wc, 0)
    f2 = sc * tb  # triangle (b, q_c, q_b), w = (wb, 0, 0)
    m1 = wb * vb + wc * vc + (wb + wc) * (vb + vc + vqc)
    m2 = wb * (2.0 * vb + vqc + vqb)
    return f1 + f2, (f1 * m1 + f2 * m2) / 12.0


def positive_area(vertices, triangles, w):
    """Area of ``{w > 0} ∩ K`` for every triangle K, for a nodal P1 function ``w``.

    Parameters
    ----------
    vertices : float64 (N, 2)
    triangles : int64 (M, 3), counter-clockwise
    w : float64 (N,)
        Nodal values, finite.

    Returns
    -------
    area : float64 (M,)
        ``0`` where ``w <= 0`` on K, ``|K|`` where ``w > 0`` at all three vertices.

    Threading: parallel over triangles, iteration ``t`` writes ``area[t]`` only.
    """
    m = triangles.shape[0]
    out = np.empty(m)
    parallel_for(_positive_area_range, m, vertices, triangles, w, out)
    return out


@jit
def _positive_area_range(lo, hi, vertices, triangles, w, out):
    for t in range(lo, hi):
        i0, i1, i2 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        x0, y0 = vertices[i0, 0], vertices[i0, 1]
        x1, y1 = vertices[i1, 0], vertices[i1, 1]
        x2, y2 = vertices[i2, 0], vertices[i2, 1]
        area = 0.5 * ((x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0))
        frac, _ = _cut(w[i0], w[i1], w[i2], 0.0, 0.0, 0.0)
        out[t] = frac * area


def positive_product(vertices, triangles, w, v):
    """``(v, w⁺)_K`` for every triangle K, for nodal P1 functions ``v`` and ``w``.

    ``w⁺ = max(w, 0)`` pointwise (not a P1 function): the integral is taken
    exactly over the sub-triangles of ``{w > 0} ∩ K``.

    Parameters
    ----------
    vertices : float64 (N, 2)
    triangles : int64 (M, 3), counter-clockwise
    w, v : float64 (N,)
        Nodal values, finite.

    Returns
    -------
    product : float64 (M,)
        Non-negative wherever ``v >= 0`` at the vertices of K.

    Threading: parallel over triangles, iteration ``t`` writes ``product[t]`` only.
    """
    m = triangles.shape[0]
    out = np.empty(m)
    parallel_for(_positive_product_range, m, vertices, triangles, w, v, out)
    return out


@jit
def _positive_product_range(lo, hi, vertices, triangles, w, v, out):
    for t in range(lo, hi):
        i0, i1, i2 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        x0, y0 = vertices[i0, 0], vertices[i0, 1]
        x1, y1 = vertices[i1, 0], vertices[i1, 1]
        x2, y2 = vertices[i2, 0], vertices[i2, 1]
        area = 0.5 * ((x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0))
        _, moment = _cut(w[i0], w[i1], w[i2], v[i0], v[i1], v[i2])
        out[t] = moment * area


def contact_terms(vertices, triangles, gap, lam_hat, mu2):
    r"""``eta_nc`` and ``eta_C`` of every triangle in one pass (the adaptive checks' hot loop).

    ``eta_nc[K] = (mu2_K |grad gap|_K^2 |{gap < 0} ∩ K|)^{1/2}`` (the gradient of
    the P1 gap is constant on K) and ``eta_C[K] = (lam_hat, gap⁺)_K`` exactly,
    as :func:`positive_area` and :func:`positive_product` compute them; fused so
    the checks make one sweep instead of five NumPy passes over (M, 3, 2)
    arrays (0.13 s -> 0.03 s per check at n = 1024).

    Parameters
    ----------
    vertices : float64 (N, 2)
    triangles : int64 (M, 3), counter-clockwise
    gap, lam_hat : float64 (N,)
        ``u1 - u2`` and ``max(lam, 0)`` at the vertices.
    mu2 : float64 (M,) or (1,)
        Per-triangle tension of membrane 2, or one value for all.

    Returns
    -------
    eta_nc, eta_c : float64 (M,)
    """
    m = triangles.shape[0]
    eta_nc = np.empty(m)
    eta_c = np.empty(m)
    parallel_for(_contact_terms_range, m, vertices, triangles, gap, lam_hat, mu2, eta_nc, eta_c)
    return eta_nc, eta_c


@jit
def nonconformity(x0, y0, x1, y1, x2, y2, g0, g1, g2, mu):
    r"""``(eta_nc, |K|)`` of one triangle from its vertices, gap values and tension ``mu``.

    ``eta_nc = (mu |grad gap|^2 |{gap < 0} ∩ K|)^{1/2}`` as in :func:`contact_terms`.
    Exactly 0 where ``gap >= 0`` on K (then ``delta = (-gap)^+`` vanishes on K),
    without forming the gradient: the value the formula gives whenever it is finite,
    at a quarter of the cost (most triangles of a check).  Scalars in and out (no
    array arguments, so no reference counting when a caller does not inline it):
    :func:`contact_terms` and the checks' one-pass sums
    (:func:`fastmem.kernels.sums.global_blocks`) compute it with the same operations.
    """
    ax, ay = x1 - x0, y1 - y0
    bx, by = x2 - x0, y2 - y0
    det = ax * by - ay * bx
    area = 0.5 * det
    frac, _ = _cut(-g0, -g1, -g2, 0.0, 0.0, 0.0)
    if frac == 0.0:  # gap >= 0 on K (most triangles): delta = 0 on K, no gradient needed
        return 0.0, area
    d1, d2 = g1 - g0, g2 - g0
    gx = (by * d1 - ay * d2) / det
    gy = (ax * d2 - bx * d1) / det
    return np.sqrt(mu * (gx * gx + gy * gy) * frac * area), area


@jit
def _contact_terms_range(lo, hi, vertices, triangles, gap, lam_hat, mu2, eta_nc, eta_c):
    m = triangles.shape[0]
    per_triangle = mu2.shape[0] == m and m > 1
    for t in range(lo, hi):
        i0, i1, i2 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        g0, g1, g2 = gap[i0], gap[i1], gap[i2]
        mu = mu2[t] if per_triangle else mu2[0]
        eta_nc[t], area = nonconformity(
            vertices[i0, 0], vertices[i0, 1], vertices[i1, 0], vertices[i1, 1],
            vertices[i2, 0], vertices[i2, 1], g0, g1, g2, mu,
        )  # fmt: skip
        _, moment = _cut(g0, g1, g2, lam_hat[i0], lam_hat[i1], lam_hat[i2])
        eta_c[t] = moment * area


def precompile() -> None:
    """Compile (or load from Numba's cache) :func:`contact_terms`' kernel, computing nothing.

    With the types :func:`fastmem.estimators.terms.local_terms` passes (read-only
    mesh arrays, a writable gap and ``lam_hat``, one tension): the compile helper
    of ``fastmem run`` (:mod:`fastmem.cli.warmup`) calls it while it waits for the
    patch kernel's largest callee from the caller, so that the caller loads this
    kernel (2 s to compile on the benchmark VM) from the cache instead.
    """
    vertices = np.zeros((3, 2))
    triangles = np.array([[0, 1, 2]], dtype=np.int64)
    vertices.setflags(write=False)
    triangles.setflags(write=False)
    z = np.zeros(3)
    _contact_terms_range(0, 0, vertices, triangles, z, z, np.ones(1), np.empty(1), np.empty(1))
