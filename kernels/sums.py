"""Sums over per-triangle estimator maps in fixed blocks, run in the kernel threads.

The totals of the error bound are sums of squares over every triangle.  Each
kernel sums fixed blocks of ``block`` consecutive entries, in order, and
writes one row of partial sums per block; the caller adds the rows.  The
blocks do not depend on the thread count, so neither does the result.  The
same pass checks the maps: an entry that is NaN, infinite or negative is
counted, and the caller says which map holds it.
"""

import math

from ._jit import jit

__all__ = ["BLOCK", "COMBINE_SUMS", "combine_blocks"]

#: Entries per block of partial sums.
BLOCK = 32768

#: Columns of the rows :func:`combine_blocks` writes.
COMBINE_SUMS = ("d1", "d2", "d2nc", "nc", "c", "bad")


@jit
def _bad(x):
    # neither NaN (every comparison false), nor negative, nor +inf
    return not (x >= 0.0 and x < math.inf)


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
        out[b, 0] = s1
        out[b, 1] = s2
        out[b, 2] = s2nc
        out[b, 3] = snc
        out[b, 4] = sc
        out[b, 5] = bad
