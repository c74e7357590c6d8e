"""Per-row measures of the Newton-min history in one pass over the interior vertices."""

from ._jit import jit

__all__ = ["row_measures"]


@jit
def row_measures(u1, u2, lam, interior, active, c):
    """``(n_changed, ||min(u1 - u2, lam)||^2)`` over the interior vertices.

    ``n_changed`` counts the vertices whose membership in the active-set rule
    ``lam_a > c (u1_a - u2_a)`` (:meth:`fastmem.Scene.active_rule`) differs from
    ``active`` (a mask over ``interior``).  One pass instead of six gathers of
    (N,) arrays: the history row of every estimator check pays O(N) once.
    """
    changed = 0
    total = 0.0
    for j in range(interior.size):
        a = interior[j]
        gap = u1[a] - u2[a]
        lj = lam[a]
        if (lj > c * gap) != active[j]:
            changed += 1
        m = gap if gap < lj else lj
        total += m * m
    return changed, total
