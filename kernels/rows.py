"""Per-vertex passes of Newton-min: the history row's measures, the decoupled step's triple."""

from ._jit import jit, jit_divide

__all__ = [
    "active_rule_range",
    "active_weight_range",
    "boundary_triple_range",
    "decoupled_rhs_range",
    "decoupled_triple_range",
    "gap_start_range",
    "lambda_parts_range",
    "row_measures",
    "spread_range",
    "warm_active_range",
]


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


@jit
def gap_start_range(lo, hi, interior, active, rhs_w, u1, u2, rhs, w0):
    """Write the gap CG's right-hand side and start at the interior vertices ``interior[lo:hi]``.

    ``rhs = where(active, 0, rhs_w)`` and ``w0 = where(active, 0, (u1 - u2)[interior])``
    (:meth:`fastmem.solver.steps.DecoupledCG.start`): the same values, in one pass
    instead of a gather, a subtraction and two selections.
    """
    for r in range(lo, hi):
        if active[r]:
            rhs[r] = 0.0
            w0[r] = 0.0
        else:
            rhs[r] = rhs_w[r]
            i = interior[r]
            w0[r] = u1[i] - u2[i]


@jit_divide
def active_weight_range(lo, hi, interior, d, d1, d2, lumped, out):
    """``out = (d / d1 + d / d2) * lumped`` at the interior vertices ``interior[lo:hi]``.

    The operations of :attr:`fastmem.fem.scene.Scene.active_weight` on the
    diagonals of ``A``, ``mu1 A`` and ``mu2 A``, in its order: the same bits.
    """
    for r in range(lo, hi):
        i = interior[r]
        a = d[i]
        kappa = a / d1[i]
        kappa += a / d2[i]
        out[r] = kappa * lumped[i]


@jit
def active_rule_range(lo, hi, interior, c, u1, u2, lam, out):
    """``out = lam > c (u1 - u2)`` at the interior vertices ``interior[lo:hi]``.

    :meth:`fastmem.fem.scene.Scene.active_rule`'s operations, the same bits.
    """
    for r in range(lo, hi):
        i = interior[r]
        out[r] = lam[i] > c * (u1[i] - u2[i])


@jit
def warm_active_range(lo, hi, interior, weight, u1, u2, lam, out):
    """``out = weight lam > u1 - u2`` at the interior vertices ``interior[lo:hi]``.

    :func:`fastmem.solver.nested.warm_active_set`'s operations (``weight`` over the
    interior vertices), the same bits.
    """
    for r in range(lo, hi):
        i = interior[r]
        out[r] = weight[r] * lam[i] > (u1[i] - u2[i])


@jit_divide
def decoupled_rhs_range(
    lo, hi, interior, indptr, indices, data, g, f1, f2, mu1, mu2, rhs_w, rhs_s
):  # fmt: skip
    """Write the decoupled step's right-hand sides at the interior vertices ``interior[lo:hi]``.

    With ``lift = A g`` (row i of the stiffness matrix summed in the order of its
    stored entries, as scipy sums ``A @ g``): ``rhs_w = (f1 / mu1 - f2 / mu2) - lift``
    and ``rhs_s = (f1 + f2) - mu1 lift`` at each interior vertex, the operations of
    :class:`fastmem.solver.linear.DecoupledStep` in its order: the same bits.
    """
    for r in range(lo, hi):
        i = interior[r]
        lift = 0.0
        for k in range(indptr[i], indptr[i + 1]):
            lift += data[k] * g[indices[k]]
        rhs_w[r] = (f1[i] / mu1 - f2[i] / mu2) - lift
        rhs_s[r] = (f1[i] + f2[i]) - mu1 * lift


@jit
def spread_range(lo, hi, index, values, out):
    """``out[index[r]] = values[r]`` for ``r`` in ``lo .. hi-1`` (distinct indices)."""
    for r in range(lo, hi):
        out[index[r]] = values[r]


@jit
def lambda_parts_range(lo, hi, lam, boundary, lam_hat, lam_minus):
    """``lam_hat = max(lam, 0)`` and ``lam_minus = lam_hat - lam``, 0 on the boundary.

    Vertices ``lo .. hi-1``; NumPy's ``maximum`` (the first argument where it is
    greater or NaN, else the second: ``maximum(-0.0, 0.0) = 0.0``) and subtraction,
    the same bits as :func:`fastmem.estimators.terms._lambda_parts`' NumPy path.
    """
    for i in range(lo, hi):
        v = 0.0 if boundary[i] else lam[i]
        h = v if (v > 0.0 or v != v) else 0.0
        lam_hat[i] = h
        lam_minus[i] = h - v
