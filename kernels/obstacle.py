r"""The obstacle-approximation terms on the red sub-triangles of the obstacle band.

For every band triangle K (docs/obstacle.md §5.2) and each of its ``P = 4^s``
pieces T (barycentric vertices ``ref[p]``), with the iterate ``u``, the
pressure ``ell`` (both P1 on K, given at K's vertices), the obstacle's values
``psi`` at the piece vertices, its envelope constants ``delta``, ``delta_p``
and the affine majorant ``U`` of the largest pressure (at the piece
vertices):

.. math::

    c^{disc}_K &= \sum_T \big[(\ell, (u - \Psi_T + \delta'_T)^+)_T\,[\text{line 1}]
                 + \overline{((U_T - \ell)^+, (\Psi_T + \delta_T - u)^+)_T}\big], \\
    c^{lin}_K &= \sum_T \overline{((U_T - \ell)^+, (u - \chi_h)^+)_T}\,[\text{two obstacles}],

where :math:`\overline{(y^+, z^+)_T}` is the exact ``(y, z^+)_T`` when
``y >= 0`` on T and :math:`(\max_T y)^+ (1, z^+)_T` otherwise (an upper
bound).  Every integral is the exact cut of :mod:`.cut`.

Threading: the band triangles in chunks; iteration ``b`` writes ``out[b]``
only.  Bitwise independent of the thread count.
"""

import numpy as np

from ._jit import jit
from .cut import _cut
from .pool import parallel_for

__all__ = ["band_terms"]


def band_terms(
    vertices, triangles, band, slots, ref, us, ell, psi, delta, delta_p, lam_up, first, other
):
    """``(c_disc, c_lin)`` of the band triangles (module docstring), float64 (B,) each.

    Parameters
    ----------
    vertices : float64 (N, 2)
    triangles : int64 (M, 3)
    band : int64 (B,)
        The band triangles.
    slots : int64 (B,)
        Where each band triangle's pieces start in the piece arrays, in units of P
        (the pieces of ``band[k]`` are rows ``slots[k] * P ... slots[k] * P + P - 1``).
    ref : float64 (P, 3, 3)
        Barycentric coordinates of the pieces' vertices (counter-clockwise).
    us, ell : float64 (N,)
        The iterate and the pressure at the vertices (mirrored for an upper obstacle).
    psi : float64 (S * P, 3)
        Obstacle values at the piece vertices (S >= B cached triangles).
    delta, delta_p : float64 (S * P,)
        Envelope constants of the pieces.
    lam_up : float64 (S * P, 3)
        The affine majorant of the largest pressure at the piece vertices.
    first : bool (B,)
        Whether line 1 is needed on the triangle.
    other : float64 (N,) or (0,)
        The other obstacle (mirrored), or empty without one.
    """
    b = band.shape[0]
    c_disc = np.zeros(b)
    c_lin = np.zeros(b)
    parallel_for(
        _band_range,
        b,
        vertices,
        triangles,
        band,
        slots,
        ref,
        us,
        ell,
        psi,
        delta,
        delta_p,
        lam_up,
        first,
        other,
        c_disc,
        c_lin,
        grain=256,
    )
    return c_disc, c_lin


@jit
def _weighted(y0, y1, y2, z0, z1, z2):
    """Upper bound of ``(y+, z+)_T / |T|`` (exact where ``y >= 0`` at the vertices)."""
    if y0 >= 0.0 and y1 >= 0.0 and y2 >= 0.0:
        _, m = _cut(z0, z1, z2, y0, y1, y2)
        return m
    ymax = max(y0, y1, y2)
    if ymax <= 0.0:
        return 0.0
    _, m = _cut(z0, z1, z2, 1.0, 1.0, 1.0)
    return ymax * m


@jit
def _band_range(
    lo,
    hi,
    vertices,
    triangles,
    band,
    slots,
    ref,
    us,
    ell,
    psi,
    delta,
    delta_p,
    lam_up,
    first,
    other,
    c_disc,
    c_lin,
):
    npc = ref.shape[0]
    two = other.shape[0] > 0
    for k in range(lo, hi):
        t = band[k]
        i0, i1, i2 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        x0, y0 = vertices[i0, 0], vertices[i0, 1]
        x1, y1 = vertices[i1, 0], vertices[i1, 1]
        x2, y2 = vertices[i2, 0], vertices[i2, 1]
        area = 0.5 * ((x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0))
        piece_area = area / npc
        u0, u1, u2 = us[i0], us[i1], us[i2]
        l0, l1, l2 = ell[i0], ell[i1], ell[i2]
        o0 = o1 = o2 = 0.0
        if two:
            o0, o1, o2 = other[i0], other[i1], other[i2]
        acc_d = 0.0
        acc_l = 0.0
        for p in range(npc):
            row = slots[k] * npc + p
            # the iterate, the pressure and the other obstacle at the piece's vertices
            ua = ref[p, 0, 0] * u0 + ref[p, 0, 1] * u1 + ref[p, 0, 2] * u2
            ub = ref[p, 1, 0] * u0 + ref[p, 1, 1] * u1 + ref[p, 1, 2] * u2
            uc = ref[p, 2, 0] * u0 + ref[p, 2, 1] * u1 + ref[p, 2, 2] * u2
            la = ref[p, 0, 0] * l0 + ref[p, 0, 1] * l1 + ref[p, 0, 2] * l2
            lb = ref[p, 1, 0] * l0 + ref[p, 1, 1] * l1 + ref[p, 1, 2] * l2
            lc = ref[p, 2, 0] * l0 + ref[p, 2, 1] * l1 + ref[p, 2, 2] * l2
            pa, pb, pc = psi[row, 0], psi[row, 1], psi[row, 2]
            dp = delta_p[row]
            dm = delta[row]
            if first[k]:
                _, m = _cut(ua - pa + dp, ub - pb + dp, uc - pc + dp, la, lb, lc)
                acc_d += m
            wa = lam_up[row, 0] - la
            wb = lam_up[row, 1] - lb
            wc = lam_up[row, 2] - lc
            acc_d += _weighted(wa, wb, wc, pa + dm - ua, pb + dm - ub, pc + dm - uc)
            if two:
                oa = ref[p, 0, 0] * o0 + ref[p, 0, 1] * o1 + ref[p, 0, 2] * o2
                ob = ref[p, 1, 0] * o0 + ref[p, 1, 1] * o1 + ref[p, 1, 2] * o2
                oc = ref[p, 2, 0] * o0 + ref[p, 2, 1] * o1 + ref[p, 2, 2] * o2
                acc_l += _weighted(wa, wb, wc, ua - oa, ub - ob, uc - oc)
        c_disc[k] = acc_d * piece_area
        c_lin[k] = acc_l * piece_area
