"""Sums over per-triangle estimator maps in fixed blocks, run in the kernel threads.

The totals of the error bound are sums of squares over every triangle.  Each
kernel sums fixed blocks of ``block`` consecutive entries, in order, and
writes one row of partial sums per block; the caller adds the rows.  The
blocks do not depend on the thread count, so neither does the result.  The
same pass checks the maps: an entry that is NaN, infinite or negative is
counted, and the caller says which map holds it.  :func:`global_blocks` sums the
squared norms of the global terms triangle by triangle in the same way.
"""

import math

from ._jit import jit
from .cut import nonconformity

__all__ = [
    "BLOCK",
    "COMBINE_SUMS",
    "GLOBAL_SUMS",
    "combine_blocks",
    "global_blocks",
    "lumped_blocks",
    "vertex_values",
]

#: Entries per block of partial sums.
BLOCK = 32768

#: Columns of the rows :func:`combine_blocks` writes.
COMBINE_SUMS = ("d1", "d2", "d2nc", "nc", "c", "bad")


@jit
def _bad(x):
    # neither NaN (every comparison false), nor negative, nor +inf
    return not (x >= 0.0 and x < math.inf)


@jit
def _store(out, row, s0, s1, s2, s3, s4, s5):
    """Write six values of one block (sums, or five sums and the count of bad entries)."""
    out[row, 0] = s0
    out[row, 1] = s1
    out[row, 2] = s2
    out[row, 3] = s3
    out[row, 4] = s4
    out[row, 5] = s5


@jit
def combine_blocks(lo, hi, block, osc1, osc2, nc, eta_c, f1, f2, out):
    """Partial sums of blocks ``lo <= b < hi`` of the six maps of the bound.

    Row ``b`` of ``out``: the sums over the block of ``d1^2``, ``d2^2``,
    ``(d2 + nc)^2``, ``nc^2``, ``eta_c`` and the number of entries of any map
    that are not finite and non-negative, with ``d1 = osc1 + f1`` and
    ``d2 = osc2 + f2`` (:func:`fastmem.estimators.terms.combine`).
    """
    m = osc1.shape[0]
    for b in range(lo, hi):
        s1 = 0.0
        s2 = 0.0
        s2nc = 0.0
        snc = 0.0
        sc = 0.0
        bad = 0
        end = min((b + 1) * block, m)
        for k in range(b * block, end):
            o1 = osc1[k]
            o2 = osc2[k]
            n = nc[k]
            c = eta_c[k]
            a1 = f1[k]
            a2 = f2[k]
            if _bad(o1) or _bad(o2) or _bad(n) or _bad(c) or _bad(a1) or _bad(a2):
                bad += 1
            d1 = o1 + a1
            d2 = o2 + a2
            e = d2 + n
            s1 += d1 * d1
            s2 += d2 * d2
            s2nc += e * e
            snc += n * n
            sc += c
        _store(out, b, s1, s2, s2nc, snc, sc, bad)


#: Columns of the rows :func:`global_blocks` writes.
GLOBAL_SUMS = ("glob1", "glob2", "rho1", "rho2", "lam_minus", "nc", "bad")


@jit
def _finite(x):
    return abs(x) < math.inf  # False for NaN and +-inf


@jit
def vertex_values(lo, hi, u1, u2, lam, r1, r2, b, boundary, rho1, rho2, lam_minus, gap, flags):
    """Write the vertex values :func:`global_blocks` sums, for vertices ``lo <= v < hi``.

    ``rho_i = r_i / b`` and ``lam^- = max(lam, 0) - lam`` at interior vertices, 0
    on the boundary; ``gap = u1 - u2`` everywhere; ``flags[v] = 1`` when one of
    ``u1, u2, lam, r1, r2`` is not finite at ``v``.  Once per vertex instead of
    once per triangle corner (six divisions and fifteen tests per triangle): the
    sums took 42 ms instead of 63 ms at n = 1024 (two threads), with the same bits.
    """
    for v in range(lo, hi):
        ok = _finite(u1[v]) and _finite(u2[v]) and _finite(lam[v])
        flags[v] = 0 if ok and _finite(r1[v]) and _finite(r2[v]) else 1
        gap[v] = u1[v] - u2[v]
        if boundary[v]:
            rho1[v] = 0.0
            rho2[v] = 0.0
            lam_minus[v] = 0.0
        else:
            rho1[v] = r1[v] / b[v]
            rho2[v] = r2[v] / b[v]
            lam_minus[v] = max(lam[v], 0.0) - lam[v]


@jit
def global_blocks(
    lo, hi, block, triangles, areas, rho1, rho2, lam_minus, gap, flags, vertices, mu2, out
):
    """Partial sums of the squared L2 norms of the global terms, over blocks of triangles.

    Row ``t`` of ``out`` for the triangles of blocks ``lo <= t < hi``: the sums of
    ``v^T M_K v = |K| / 12 (sum_i v_i^2 + (sum_i v_i)^2)`` (the consistent P1 mass
    matrix of triangle K) for ``v`` = ``rho1 + lam^-``, ``rho2 - lam^-``, ``rho1``,
    ``rho2``, ``lam^-`` at its three vertices, from the vertex values of
    :func:`vertex_values` (0 on the boundary, so boundary vertices add nothing:
    :func:`fastmem.estimators.terms.global_terms`); then the sum of ``eta_nc^2``
    (:func:`fastmem.kernels.cut.nonconformity` of the gap ``u1 - u2``, tension
    ``mu2[k]`` per triangle or ``mu2[0]``), only when ``vertices`` is not empty
    (else 0); then the number of triangle corners whose vertex is flagged (a value
    of ``u1, u2, lam, r1, r2`` that is not finite), plus the ``eta_nc`` that are not
    finite and non-negative.  The ``eta_nc`` squares are added in triangle order,
    as :func:`combine_blocks` adds those of the map.
    """
    m = triangles.shape[0]
    with_nc = vertices.shape[0] > 0
    per_triangle = mu2.shape[0] == m and m > 1
    for t in range(lo, hi):
        a0 = a1 = a2 = a3 = a4 = 0.0
        snc = 0.0
        bad = 0
        for k in range(t * block, min((t + 1) * block, m)):
            s1 = s2 = sl = 0.0  # sums over the vertices of rho1, rho2, lam^-
            q0 = q1 = q2 = q3 = q4 = 0.0  # and of the squares of the five fields
            for c in range(3):
                v = triangles[k, c]
                bad += flags[v]
                x1 = rho1[v]
                x2 = rho2[v]
                lm = lam_minus[v]
                s1 += x1
                s2 += x2
                sl += lm
                g1 = x1 + lm
                g2 = x2 - lm
                q0 += g1 * g1
                q1 += g2 * g2
                q2 += x1 * x1
                q3 += x2 * x2
                q4 += lm * lm
            w = areas[k] / 12.0
            g1 = s1 + sl
            g2 = s2 - sl
            a0 += w * (q0 + g1 * g1)
            a1 += w * (q1 + g2 * g2)
            a2 += w * (q2 + s1 * s1)
            a3 += w * (q3 + s2 * s2)
            a4 += w * (q4 + sl * sl)
            if with_nc:
                i0, i1, i2 = triangles[k, 0], triangles[k, 1], triangles[k, 2]
                g0, g1, g2 = gap[i0], gap[i1], gap[i2]
                if g0 >= 0.0 and g1 >= 0.0 and g2 >= 0.0:
                    continue  # eta_nc = 0 exactly (nonconformity's first exit), snc += 0
                nc, _ = nonconformity(
                    vertices[i0, 0], vertices[i0, 1], vertices[i1, 0], vertices[i1, 1],
                    vertices[i2, 0], vertices[i2, 1], g0, g1, g2,
                    mu2[k] if per_triangle else mu2[0],
                )  # fmt: skip
                if _bad(nc):
                    bad += 1
                snc += nc * nc
        _store(out, t, a0, a1, a2, a3, a4, snc)
        out[t, 6] = bad


@jit
def lumped_blocks(lo, hi, block, triangles, areas, r, b, boundary, out):
    """Partial sums of ``||rho||^2`` with ``rho = r / b`` at interior vertices, 0 on the boundary.

    Row ``t`` of ``out`` (two columns) for the triangles of blocks ``lo <= t < hi``:
    the sum of ``|K| / 12 (sum_i rho_i^2 + (sum_i rho_i)^2)`` and the number of
    vertex values of ``r`` met that are not finite.  The same operations as the
    ``rho1`` column of :func:`global_blocks`, for one vector instead of five.
    """
    m = triangles.shape[0]
    for t in range(lo, hi):
        a = 0.0
        bad = 0
        for k in range(t * block, min((t + 1) * block, m)):
            s = 0.0
            q = 0.0
            for c in range(3):
                v = triangles[k, c]
                if not _finite(r[v]):
                    bad += 1
                if boundary[v]:
                    continue
                x = r[v] / b[v]
                s += x
                q += x * x
            w = areas[k] / 12.0
            a += w * (q + s * s)
        out[t, 0] = a
        out[t, 1] = bad
