"""Per-vertex passes of Newton-min: the history row's measures, the decoupled step's triple."""

from ._jit import jit, jit_divide

__all__ = ["boundary_triple_range", "decoupled_triple_range", "row_measures"]


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


@jit_divide
def decoupled_triple_range(
    lo, hi, interior, active, s, s_full, w_i, indptr, indices, data, rhs_w, kappa, b_int,
    mu1, mu2, u1, u2, lam,
):  # fmt: skip
    """Compute the decoupled step's triple at the interior vertices ``interior[lo:hi]``.

    ``u1 = (s + mu2 w) / (mu1 + mu2)``, ``u2 = (s - mu1 w) / (mu1 + mu2)`` and, on
    the active set, ``lam = ((A_II w)_r - rhs_w,r) / (kappa B_r)`` (0 elsewhere),
    each row's product summed in the order of the stored entries: the operations of
    :meth:`fastmem.solver.linear.DecoupledStep.triple`, so the same bits.  ``s``
    holds all vertices (``s_full``) or the interior ones.
    """
    m = mu1 + mu2
    for r in range(lo, hi):
        i = interior[r]
        w = w_i[r]
        sv = s[i] if s_full else s[r]
        u1[i] = (sv + mu2 * w) / m
        u2[i] = (sv - mu1 * w) / m
        if active[r]:
            acc = 0.0
            for k in range(indptr[r], indptr[r + 1]):
                acc += data[k] * w_i[indices[k]]
            lam[i] = (acc - rhs_w[r]) / (kappa * b_int[r])
        else:
            lam[i] = 0.0


@jit
def boundary_triple_range(lo, hi, boundary, g, u1, u2, lam):
    """``u1 = g``, ``u2 = lam = 0`` at the boundary vertices ``boundary[lo:hi]``."""
    for q in range(lo, hi):
        i = boundary[q]
        u1[i] = g[i]
        u2[i] = 0.0
        lam[i] = 0.0
