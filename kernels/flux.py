"""Equilibrated flux reconstruction: RT1 mixed problems on vertex patches, in parallel.

For vertex a the patch problem (docs/method.md §4) in the dof basis of
:mod:`.rt1` is the symmetric saddle-point system

    [  M   -D^T ] [sigma]   [ -T_i ]
    [ -D    0   ] [  r  ] = [ -G_i ]

with M the RT1 mass on the patch, D the divergence-P1 coupling (three rows
per triangle), T_i = (tau_i^a, v) and G_i = (g_i^a, q); for an interior vertex
D has the constants in its left kernel (zero normal flux on the whole patch
boundary), the data are compatible and r is fixed only up to a constant.
Only sigma is needed, and it is computed from an equivalent smaller problem:

* Bubble elimination.  On each triangle the two interior (bubble) dofs have
  divergences spanning the mean-zero part of P1(K): two of the three
  divergence rows (those of lambda_1, lambda_2; their 2 x 2 bubble block B is
  invertible) give the bubbles as ``sigma_b = beta - K sigma_e`` with
  ``K = B^-1 D_e[1:]``, ``beta = B^-1 G[1:]``; what remains of the three rows
  is their sum, the flux balance ``(div sigma, 1)_K = (g, 1)_K``, whose row
  ``C_K`` involves edge dofs only.
* Reduced problem.  Substituting gives the SPD edge-dof problem
  ``min 1/2 s^T M' s - f^T s`` subject to ``C s = c`` (one row per triangle),
  with ``M' = M_ee - M_eb K - K^T M_be + K^T M_bb K`` assembled triangle by
  triangle.  It is solved by Cholesky of M' (2 dofs per free patch edge: 12 on
  an interior patch of a structured mesh) and of the nt x nt Schur complement
  ``C M'^-1 C^T``; for an interior patch the latter has the constants in its
  kernel and the compatible data are solved with ``S + alpha 1 1^T``.  The factors
  keep ``1 / L_jj`` on their diagonal, so the triangular solves multiply
  instead of divide, and the nt rows of ``L^-1 C^T`` are solved side by side
  (independent dependency chains overlap): 9-14 % less kernel time than
  dividing row by row, results within a few ulps of it.
* Contact load: ``lam_a psi_a`` (docs/method.md §4), or on the vertices
  flagged in ``redist`` the redistributed load of the same mass computed
  triangle by triangle from the load moments (fastmem.estimators.flux.contact_redistribution).
* Weighted norm (per-triangle tensions): membrane i minimises
  ``||mu_i^(-1/2) (tau_i^a + v)||`` over the patch, the norm that eta_F
  measures, so M' and the flux target of triangle K carry the factor
  ``1 / mu_i,K`` (docs/method.md §4).  Both membranes share the matrices --
  one factorisation, two right-hand sides -- whenever their weights are
  proportional on the patch: always for constant tensions (then the weights
  are 1 and the arithmetic is exactly the unweighted one), and on every patch
  inside one material.  Other patches factor M' and the Schur complement
  once per membrane.

This is exactly the same sigma as the full system (the same constraints and
the same quadratic functional); the full 24 + 18 system of an interior patch
became a 12 + 6 one.  The local matrices come from the Piola map
(:func:`.rt1.rt1_local_xy`: a few multiply-adds from fixed reference matrices,
no quadrature), and the dofs a patch adds to its triangles are turned into
canonical coefficients once per triangle at the end (not once per patch).

Factorisation reuse: by patch class.  The matrices depend only on the
geometry, but storing the per-triangle condensed quantities (M', K, C, about
50 doubles) for every triangle would take 3.4 GB at n = 2048 (8.4M
triangles).  Instead :func:`patch_classes` groups the patches whose
geometric part is the same bit for bit (the translated copies of a patch on
a mesh with dyadic coordinates: 14 classes cover all but 9 of the 1.05M
vertices of ``Mesh.square(1024)``); the first reconstruction factors one
patch per class into a small storage, and every member then computes only
its right-hand sides and triangular solves (about a quarter of the
arithmetic; :data:`LANES` members of one class side by side), with the same
bits as a patch computed in full.  Patches
without a class (unstructured meshes, per-triangle tensions) are computed in
full, as before.

Patch edges: an edge containing a carries two dofs (shared by its two patch
triangles, or free when it lies on the boundary of the domain); the edge
opposite a carries none (zero normal flux) unless a is a boundary vertex and
the edge lies on the boundary (free).

Threading: vertices are processed by colour classes of a proper colouring of
the vertex graph; no two vertices of one class share a triangle, so each
patch adds its sigma^a straight into the rows of its own triangles without
races, and the result does not depend on the number of threads.
"""

import functools

import numpy as np
from numba import types as _nt

from . import pool as _par
from ._jit import jit
from .rt1 import _flip_pattern, rt1_dofs_to_coefficients, rt1_local_xy
from .sparsity import BLOCK_THREADS

__all__ = [
    "classes_compiled",
    "color_vertices",
    "flux_estimators",
    "patch_classes",
    "precompile_grouping",
    "reconstruct_colored",
    "sweep_order",
]

#: floats per patch triangle in the class storage (:func:`_class_store`)
_CF = 48

#: class members solved side by side by :func:`_member_chunk` (:func:`_lanes_solve`)
LANES = 4


@jit
def color_vertices(n, indptr, indices):
    """Greedy proper colouring of the vertex graph (CSR adjacency, diagonal included).

    Returns
    -------
    colors : int64 (n,)
    n_colors : int
    order : int64 (n,)
        The vertices by colour, in vertex order within each (a counting sort:
        ``np.argsort(colors, kind="stable")``, which took 38 ms at 4.2M vertices).
    ptr : int64 (n_colors + 1,)
        Colour c is ``order[ptr[c]:ptr[c + 1]]``.
    """
    colors = np.full(n, -1, dtype=np.int64)
    n_colors = 0
    used = np.full(64, -1, dtype=np.int64)
    for a in range(n):
        for k in range(indptr[a], indptr[a + 1]):
            b = indices[k]
            if b != a and colors[b] >= 0 and colors[b] < 64:
                used[colors[b]] = a
        c = 0
        while c < 64 and used[c] == a:
            c += 1
        colors[a] = c
        if c + 1 > n_colors:
            n_colors = c + 1
    ptr = np.zeros(n_colors + 1, dtype=np.int64)
    for a in range(n):
        if colors[a] < 64:
            ptr[colors[a] + 1] += 1
    for c in range(n_colors):
        ptr[c + 1] += ptr[c]
    slot = ptr[:-1].copy()
    order = np.empty(n, dtype=np.int64)
    for a in range(n):
        c = colors[a]
        if c < 64:
            order[slot[c]] = a
            slot[c] += 1
    return colors, n_colors, order, ptr


@jit
def _vertex_colors(order, color_ptr):
    """Return the colour (int8) of each vertex from the colour classes ``order[color_ptr[c]:]``."""
    color = np.empty(order.shape[0], dtype=np.int8)
    for c in range(color_ptr.shape[0] - 1):
        for k in range(color_ptr[c], color_ptr[c + 1]):
            color[order[k]] = c
    return color


@jit
def _patch_spans(patch_ptr, patch_triangles, n_triangles):
    """Return the smallest and largest triangle of each vertex patch (n_triangles, -1: none)."""
    n = patch_ptr.shape[0] - 1
    first = np.empty(n, dtype=np.int64)
    last = np.empty(n, dtype=np.int64)
    for a in range(n):
        lo = n_triangles
        hi = -1
        for k in range(patch_ptr[a], patch_ptr[a + 1]):
            t = np.int64(patch_triangles[k])
            lo = min(lo, t)
            hi = max(hi, t)
        first[a] = lo
        last[a] = hi
    return first, last


@jit
def _by_first_triangle(first, n_triangles):
    """Return the vertices sorted by ``first`` (values 0..n_triangles), stably (counting sort)."""
    n = first.shape[0]
    start = np.zeros(n_triangles + 2, dtype=np.int32)
    for a in range(n):
        start[first[a] + 1] += 1
    for t in range(n_triangles + 1):
        start[t + 1] += start[t]
    by_tri = np.empty(n, dtype=np.int64)
    for a in range(n):
        t = first[a]
        by_tri[start[t]] = a
        start[t] += 1
    return by_tri


@jit
def sweep_order(order, color_ptr, patch_ptr, patch_triangles, n_triangles):
    """``order`` with the vertices of each colour sorted by the smallest triangle of their patch.

    Within a colour class the patches write disjoint rows, so their order does not
    change a bit of the result; sorted so, the patches of a colour sweep the
    triangle arrays (and the flux rows they write) from first to last.  A mesh
    made by refinement numbers its new triangles after the old ones, so a patch
    in vertex order jumps across them.  Within a colour no two patches share a
    triangle.  Two counting sorts (by that triangle, then stably by colour),
    O(N + M).
    """
    n = order.shape[0]
    color = _vertex_colors(order, color_ptr)
    first, _ = _patch_spans(patch_ptr, patch_triangles, n_triangles)
    by_tri = _by_first_triangle(first, n_triangles)
    slot = color_ptr[:-1].copy()
    out = np.empty_like(order)
    for k in range(n):
        a = by_tri[k]
        c = color[a]
        out[slot[c]] = a
        slot[c] += 1
    return out


@jit
def _cholesky(a, n):
    """In-place lower Cholesky factor of the leading n x n block of a (upper part untouched).

    The diagonal holds the reciprocals ``1 / L_jj`` (the triangular solves
    multiply by them instead of dividing: a division's latency sits on their
    dependency chains).  Returns False if a pivot is not positive (the block is
    not SPD).
    """
    for j in range(n):
        d = a[j, j]
        for k in range(j):
            d -= a[j, k] * a[j, k]
        if not d > 0.0:
            return False
        inv = 1.0 / np.sqrt(d)
        a[j, j] = inv
        for i in range(j + 1, n):
            s = a[i, j]
            for k in range(j):
                s -= a[i, k] * a[j, k]
            a[i, j] = s * inv
    return True


@jit
def _lower_solve2(lo, b, n):
    """In place ``b <- L^-1 b`` for the lower factor in ``lo`` and two columns of b."""
    for k in range(n):
        s0 = b[k, 0]
        s1 = b[k, 1]
        for m in range(k):
            s0 -= lo[k, m] * b[m, 0]
            s1 -= lo[k, m] * b[m, 1]
        b[k, 0] = s0 * lo[k, k]
        b[k, 1] = s1 * lo[k, k]


@jit
def _upper_solve2(lo, b, n):
    """In place ``b <- L^-T b`` for the lower factor in ``lo`` and two columns of b."""
    for k in range(n - 1, -1, -1):
        s0 = b[k, 0]
        s1 = b[k, 1]
        for m in range(k + 1, n):
            s0 -= lo[m, k] * b[m, 0]
            s1 -= lo[m, k] * b[m, 1]
        b[k, 0] = s0 * lo[k, k]
        b[k, 1] = s1 * lo[k, k]


@jit
def _forward_rows(lo, y, start, n, nrows):
    """In place ``y[p] <- L^-1 y[p]`` for the rows p < nrows of y; ``y[p, :start[p]] = 0``.

    The rows are independent: they advance together, one k at a time, so that
    their dependency chains overlap (each row's arithmetic is the same as
    solving it alone).
    """
    for k in range(n):
        dk = lo[k, k]  # 1 / L_kk
        for p in range(nrows):
            st = start[p]
            if st <= k:
                s = y[p, k]
                for m in range(st, k):
                    s -= lo[k, m] * y[p, m]
                y[p, k] = s * dk


@jit
def _lower_solve1(lo, b, n, c):
    """In place ``b[:, c] <- L^-1 b[:, c]`` for the lower factor in ``lo``."""
    for k in range(n):
        s0 = b[k, c]
        for m in range(k):
            s0 -= lo[k, m] * b[m, c]
        b[k, c] = s0 * lo[k, k]


@jit
def _upper_solve1(lo, b, n, c):
    """In place ``b[:, c] <- L^-T b[:, c]`` for the lower factor in ``lo``."""
    for k in range(n - 1, -1, -1):
        s0 = b[k, c]
        for m in range(k + 1, n):
            s0 -= lo[m, k] * b[m, c]
        b[k, c] = s0 * lo[k, k]


def _reduced_solver(two):
    """Build the solver :func:`_reduced_solve` for two columns (``two``) or one.

    ``two`` is a constant of the compiled code: Numba drops the other branch
    before typing it, so each variant compiles only its own arithmetic (the
    constant-tension kernels use two columns, the weighted one both).
    """

    def _reduced_solve(mred, fred, cmat, crhs, smat, cstart, n_e, nt, interior, c0, c1, stage):
        """Factor and solve ``M' s + C^T m = f``, ``C s = c`` in place, for the columns c0..c1-1.

        ``stage`` 0: factor, then solve; 1: factor only; 2: solve only, with the
        factors already in place (a class member, :func:`_member_chunk`).  (One
        function, not two: each compiled callee costs first-run compilation.)

        Factoring: on entry ``mred`` holds the lower triangle of M' and ``cmat``
        the rows of C (row p zero before ``cstart[p]``); on exit ``mred`` holds
        the Cholesky factor of M', ``cmat`` the rows of ``Y^T = (L^-1 C^T)^T`` and
        ``smat`` the factor of the Schur complement ``Y^T Y`` (plus ``alpha 1
        1^T`` for an interior patch), with reciprocal diagonals
        (:func:`_cholesky`).  They depend on the geometry only: patches of one
        class share them (:func:`patch_classes`).

        Solving: on entry ``fred[:, c]`` holds the right-hand sides f and
        ``crhs[:, c]`` the data c (1 or 2 columns); on exit ``fred[:, c]`` holds s
        and ``crhs[:, c]`` the multipliers.  With two columns both right-hand
        sides share the factorisations.
        """
        if stage != 2:
            _cholesky(mred, n_e)
            _forward_rows(mred, cmat, cstart, n_e, nt)  # rows of Y^T = (L^-1 C^T)^T
            for p1 in range(nt):
                s1 = cstart[p1]
                for p2 in range(p1 + 1):
                    s = 0.0
                    for k in range(max(s1, cstart[p2]), n_e):
                        s += cmat[p1, k] * cmat[p2, k]
                    smat[p1, p2] = s
            if interior:
                # zero normal flux on the whole patch boundary: the flux balance rows
                # sum to zero, S has the constants in its kernel and the data are
                # compatible; any multiplier of the consistent system will do
                tr = 0.0
                for p in range(nt):
                    tr += smat[p, p]
                alpha = tr / nt
                for p1 in range(nt):
                    for p2 in range(p1 + 1):
                        smat[p1, p2] += alpha
            _cholesky(smat, nt)
        if stage == 1:
            return
        if two:
            _lower_solve2(mred, fred, n_e)  # t = L^-1 f
        else:
            _lower_solve1(mred, fred, n_e, c0)
        for p1 in range(nt):
            s1 = cstart[p1]
            if two:
                b0 = 0.0
                b1 = 0.0
                for k in range(s1, n_e):
                    b0 += cmat[p1, k] * fred[k, 0]
                    b1 += cmat[p1, k] * fred[k, 1]
                crhs[p1, 0] = b0 - crhs[p1, 0]
                crhs[p1, 1] = b1 - crhs[p1, 1]
            else:
                b0 = 0.0
                for k in range(s1, n_e):
                    b0 += cmat[p1, k] * fred[k, c0]
                crhs[p1, c0] = b0 - crhs[p1, c0]
        if two:
            _lower_solve2(smat, crhs, nt)  # mu = S^-1 (Y^T t - c)
            _upper_solve2(smat, crhs, nt)
        else:
            _lower_solve1(smat, crhs, nt, c0)
            _upper_solve1(smat, crhs, nt, c0)
        # --- sigma_e = L^-T (t - Y mu)
        for p in range(nt):
            if two:
                r0 = crhs[p, 0]
                r1 = crhs[p, 1]
                for k in range(cstart[p], n_e):
                    fred[k, 0] -= cmat[p, k] * r0
                    fred[k, 1] -= cmat[p, k] * r1
            else:
                r0 = crhs[p, c0]
                for k in range(cstart[p], n_e):
                    fred[k, c0] -= cmat[p, k] * r0
        if two:
            _upper_solve2(mred, fred, n_e)
        else:
            _upper_solve1(mred, fred, n_e, c0)

    _reduced_solve.__name__ = _reduced_solve.__qualname__ = "_reduced_solve" + ("2" if two else "1")
    return jit(_reduced_solve)


_reduced_solve2 = _reduced_solver(True)
_reduced_solve1 = _reduced_solver(False)


@jit
def _lanes_solve(lo, fred, cmat, crhs, smat, cstart, n_e, nt, acc):
    """Solve as :func:`_reduced_solve2` (stage 2) does, for the 2 LANES columns of LANES patches.

    The patches share the factors (one class, :func:`_member_chunk`); every
    column gets the operations, in the order, that :func:`_reduced_solve2`
    gives it, so each patch's sigma has the same bits as solved alone.  The
    columns run innermost (``acc``: 2 LANES accumulators), so that the
    compiler can apply each factor entry to all of them at once: 1.8-2.6 times
    faster than LANES two-column solves (measured in isolation, one thread,
    12 edge dofs and 6 triangles).
    """
    w = 2 * LANES
    for k in range(n_e):  # t = L^-1 f
        for c in range(w):
            acc[c] = fred[k, c]
        for m in range(k):
            v = lo[k, m]
            for c in range(w):
                acc[c] -= v * fred[m, c]
        d = lo[k, k]
        for c in range(w):
            fred[k, c] = acc[c] * d
    for p in range(nt):  # Y^T t - c
        for c in range(w):
            acc[c] = 0.0
        for k in range(cstart[p], n_e):
            v = cmat[p, k]
            for c in range(w):
                acc[c] += v * fred[k, c]
        for c in range(w):
            crhs[p, c] = acc[c] - crhs[p, c]
    for k in range(nt):  # mu = S^-1 (Y^T t - c)
        for c in range(w):
            acc[c] = crhs[k, c]
        for m in range(k):
            v = smat[k, m]
            for c in range(w):
                acc[c] -= v * crhs[m, c]
        d = smat[k, k]
        for c in range(w):
            crhs[k, c] = acc[c] * d
    for k in range(nt - 1, -1, -1):
        for c in range(w):
            acc[c] = crhs[k, c]
        for m in range(k + 1, nt):
            v = smat[m, k]
            for c in range(w):
                acc[c] -= v * crhs[m, c]
        d = smat[k, k]
        for c in range(w):
            crhs[k, c] = acc[c] * d
    for p in range(nt):  # t - Y mu
        for k in range(cstart[p], n_e):
            v = cmat[p, k]
            for c in range(w):
                fred[k, c] -= v * crhs[p, c]
    for k in range(n_e - 1, -1, -1):  # sigma_e = L^-T (t - Y mu)
        for c in range(w):
            acc[c] = fred[k, c]
        for m in range(k + 1, n_e):
            v = lo[m, k]
            for c in range(w):
                acc[c] -= v * fred[m, c]
        d = lo[k, k]
        for c in range(w):
            fred[k, c] = acc[c] * d


@jit
def _refine_balance(mred, fred, cmat, crhs, smat, cstart, n_e, nt, crow, emap, corig, c):
    """One step of iterative refinement of the flux balance ``C s = c`` for column c.

    After :func:`_reduced_solve` (whose factors it reuses), with ``crow`` the
    original entries of C (row p at the dofs ``emap[p]``) and ``corig`` the
    original data:  ``d = c - C s``, ``s += M'^-1 C^T S^-1 d`` (the KKT
    correction of the residual d).  With weights that differ by a factor
    1e6 on one patch M' is that much worse conditioned and the flux balance
    lost as many digits (1e-10 relative instead of 1e-15); one step restores
    round-off.  Done only on patches whose weights differ by more than 1e3
    (below, the loss stays under 1e-13: measured 2e-13 at 1e3).
    """
    for p in range(nt):
        d = corig[p, c]
        for r in range(6):
            pr = emap[p, r]
            if pr >= 0:
                d -= crow[p, r] * fred[pr, c]
        crhs[p, c] = d
    _lower_solve1(smat, crhs, nt, c)  # dm = S^-1 d (S as factored, with alpha 1 1^T)
    _upper_solve1(smat, crhs, nt, c)
    # ds = L^-T Y dm with Y = L^-1 C^T (rows of Y^T in cmat); column 2 of fred is scratch
    for k in range(n_e):
        fred[k, fred.shape[1] - 1] = 0.0
    for p in range(nt):
        dm = crhs[p, c]
        for k in range(cstart[p], n_e):
            fred[k, fred.shape[1] - 1] += cmat[p, k] * dm
    scratch = fred.shape[1] - 1
    _upper_solve1(mred, fred, n_e, scratch)
    for k in range(n_e):
        fred[k, c] += fred[k, scratch]


@jit
def _gradients(i, x0, y0, x1, y1, x2, y2, u1, u2, i0, i1, i2, inv2a):
    """Gradients of u1, u2 and psi of local vertex i on one triangle (1 / (2|K|) given)."""
    # grad u = sum_v u_v rot(edge opposite v) / (2|K|); grad psi_a likewise
    du1x = -(u1[i0] * (y2 - y1) + u1[i1] * (y0 - y2) + u1[i2] * (y1 - y0)) * inv2a
    du1y = (u1[i0] * (x2 - x1) + u1[i1] * (x0 - x2) + u1[i2] * (x1 - x0)) * inv2a
    du2x = -(u2[i0] * (y2 - y1) + u2[i1] * (y0 - y2) + u2[i2] * (y1 - y0)) * inv2a
    du2y = (u2[i0] * (x2 - x1) + u2[i1] * (x0 - x2) + u2[i2] * (x1 - x0)) * inv2a
    if i == 0:
        gax = -(y2 - y1) * inv2a
        gay = (x2 - x1) * inv2a
    elif i == 1:
        gax = -(y0 - y2) * inv2a
        gay = (x0 - x2) * inv2a
    else:
        gax = -(y1 - y0) * inv2a
        gay = (x1 - x0) * inv2a
    return du1x, du1y, du2x, du2y, gax, gay


@jit
def _patch_loads(
    i,
    t,
    area,
    m1,
    m2,
    du1x,
    du1y,
    du2x,
    du2y,
    gax,
    gay,
    f1c,
    f2c,
    load1,
    load2,
    chi_row,
    chi_mom,
    glued,
    r1a,
    r2a,
    lam_a,
    redist_a,
    gam,
    gloc,
    kapj,
):
    """Write the data ``(g_i^a, lambda_j)_K`` of one patch triangle, contact load included, to gloc.

    Triangle t, where the patch vertex has local index i; ``kapj`` is scratch.
    The general case: the patch kernel :func:`_reconstruct_chunk` calls it for
    every triangle, the class members' kernel only for a glued triangle or a
    redistributed vertex, and :func:`_plain_loads` otherwise (see there why).
    """
    # data (g, lambda_j)
    dot1 = m1 * (gax * du1x + gay * du1y) * area / 3.0
    dot2 = m2 * (gax * du2x + gay * du2y) * area / 3.0
    for j in range(3):
        mij = area / 12.0 * (2.0 if j == i else 1.0)  # int psi_a lambda_j
        if load1.shape[0] == 1:
            l1 = f1c * mij
        else:
            l1 = load1[t, i, j]
        if load2.shape[0] == 1:
            l2 = f2c * mij
        else:
            l2 = load2[t, i, j]
        if glued:
            # glued contact load on this triangle: (chi^a, lambda_j) moves
            # from membrane 2's data to membrane 1's (lam_a is 0 for a glued a)
            s_chi = chi_row[t]
            if s_chi >= 0:
                l1 += chi_mom[s_chi, i, j]
                l2 -= chi_mom[s_chi, i, j]
        gloc[j, 0] = l1 - dot1 - r1a * mij
        gloc[j, 1] = l2 - dot2 - r2a * mij
        # contact load (chi^a, lambda_j): lam_a psi_a, or the glued pressure (below)
        kapj[j] = (m1 * l2 - m2 * l1) / (m1 + m2) if redist_a else lam_a * mij
    if redist_a:
        # redistributed contact load (fastmem.estimators.flux.contact_redistribution): the
        # L2 projection onto P1(K) of psi_a (mu1 f2 - mu2 f1) / (mu1 + mu2),
        # negative vertex values cut to 0, plus gamma_a m_K psi_a
        ssum = kapj[0] + kapj[1] + kapj[2]
        scale = 12.0 / area
        n0 = max(scale * (kapj[0] - 0.25 * ssum), 0.0)
        n1 = max(scale * (kapj[1] - 0.25 * ssum), 0.0)
        n2 = max(scale * (kapj[2] - 0.25 * ssum), 0.0)
        nsum = n0 + n1 + n2
        # mass correction gamma_a m_K psi_a, m_K = mu1 mu2 / (mu1 + mu2)
        gk = gam * m1 * m2 / (m1 + m2) * area / 12.0
        kapj[0] = area / 12.0 * (n0 + nsum) + gk * (2.0 if i == 0 else 1.0)
        kapj[1] = area / 12.0 * (n1 + nsum) + gk * (2.0 if i == 1 else 1.0)
        kapj[2] = area / 12.0 * (n2 + nsum) + gk * (2.0 if i == 2 else 1.0)
    for j in range(3):
        gloc[j, 0] += kapj[j]
        gloc[j, 1] -= kapj[j]


@jit
def _plain_loads(
    i, t, area, m1, m2, du1x, du1y, du2x, du2y, gax, gay, f1c, f2c, load1, load2, r1a, r2a, lam_a
):
    """:func:`_patch_loads` without a glued or redistributed contact load: the six values of gloc.

    Returned as ``(g_00, g_01, g_10, g_11, g_20, g_21)`` (row j, membrane c)
    with the same operations as :func:`_patch_loads`, so the same bits.  Why
    a second function: a call that LLVM does not inline costs the call of an
    array-taking function, which increments and decrements the reference count
    of each array argument (atomic operations) and passes every array as a
    dozen words; :func:`_patch_loads`, with its rare branches, was not
    inlined, and it took 40 % of the class members' kernel (1.27 s of one
    thread at n = 1024).  This small function is inlined, and the kernel
    took 0.74-0.85 s.
    """
    dot1 = m1 * (gax * du1x + gay * du1y) * area / 3.0
    dot2 = m2 * (gax * du2x + gay * du2y) * area / 3.0
    w0 = area / 12.0 * (2.0 if i == 0 else 1.0)  # int psi_a lambda_j
    w1 = area / 12.0 * (2.0 if i == 1 else 1.0)
    w2 = area / 12.0 * (2.0 if i == 2 else 1.0)
    if load1.shape[0] == 1:
        a0 = f1c * w0
        a1 = f1c * w1
        a2 = f1c * w2
    else:
        a0 = load1[t, i, 0]
        a1 = load1[t, i, 1]
        a2 = load1[t, i, 2]
    if load2.shape[0] == 1:
        b0 = f2c * w0
        b1 = f2c * w1
        b2 = f2c * w2
    else:
        b0 = load2[t, i, 0]
        b1 = load2[t, i, 1]
        b2 = load2[t, i, 2]
    k0 = lam_a * w0  # the contact load lam_a psi_a
    k1 = lam_a * w1
    k2 = lam_a * w2
    return (
        a0 - dot1 - r1a * w0 + k0,
        b0 - dot2 - r2a * w0 - k0,
        a1 - dot1 - r1a * w1 + k1,
        b1 - dot2 - r2a * w1 - k1,
        a2 - dot1 - r1a * w2 + k2,
        b2 - dot2 - r2a * w2 - k2,
    )


def _patch_kernel(weighted):
    """Build the patch kernel :func:`_reconstruct_chunk`, for constant tensions or weighted.

    ``weighted`` (per-triangle tensions) is a constant of the compiled code:
    Numba drops the branches of the other case before typing them, so the
    constant-tension kernel that every first run compiles carries none of the
    weights, second factorisations and refinement steps, and a scene with
    per-triangle tensions compiles its own kernel when it first needs it.  For
    constant tensions the weights are exactly 1, so both kernels give the same
    bits there.
    """

    def _reconstruct_chunk(
        order,
        k0,
        k1,
        vertices,
        triangles,
        diameters,
        tri_edges,
        edge_tris,
        boundary,
        patch_ptr,
        patch_triangles,
        patch_local,
        u1,
        u2,
        lam,
        rho1,
        rho2,
        mu1,
        mu2,
        f1c,
        f2c,
        load1,
        load2,
        redist,
        gamma,
        chi_row,
        chi_mom,
        max_nt,
        out,
        ring,
        slots,
        cls,
    ):
        """Patch problems of the vertices ``order[k0:k1]`` (one colour class or part of one).

        For each vertex a: solve its patch problem and add the local dof values to
        ``out`` (2, M, 8): row t of triangle t (``slots`` 1), or with ``slots`` 3 row
        ``3 (t % ring) + i`` (i the local index of a in t: one row per patch of t, in
        the ring of triangle rows of :func:`flux_norms_banded`).  One workspace for the
        chunk (sized for ``max_nt`` triangles); no allocation and no array views inside
        the patch loop.  (One function rather than a loop calling a patch solver: Numba re-optimises
        every callee inside each caller, and this level cost 1.3 s of first-run
        compilation.)

        Reduced formulation (module docstring): per triangle the bubbles are
        eliminated through two of the three divergence equations, leaving an SPD
        problem on the patch edge dofs with one flux-balance constraint per
        triangle.

        Weights (docs/method.md §4, per-triangle tensions): membrane i minimises
        ``sum_K w_iK ||tau + v||_K^2`` with ``w_iK = mu_i,K0 / mu_i,K`` (K0 the
        first patch triangle; a constant factor does not change the minimiser),
        so M' and the right-hand side of triangle K are scaled by w_iK.  When
        ``w_1K = w_2K`` on the whole patch (always for constant tensions, where
        both are 1 and the arithmetic is the unweighted one) the membranes share
        M', its factor and the Schur complement; otherwise membrane 2 gets its own
        (``mred2``, ``cmat2``, ``smat2``).

        Patch classes (:func:`patch_classes`, constant tensions only): vertices
        with ``cls[a] >= 0`` are skipped here, :func:`_member_chunk` solves them
        from the class storage that :func:`_class_fill` wrote; ``cls`` of shape
        (1,): no classes.  (Separate kernels: this one, which every first run
        compiles, stays as it was; the others compile only for meshes with
        classes.  A store mode in this kernel cost 1-1.5 s more first-run
        compilation.)
        """
        if weighted:
            classes = False
        else:
            classes = cls.shape[0] > 1
        wnt = max_nt  # workspace sizes: triangles of the largest patch
        wne = 6 * max_nt  # and a bound on its edge dofs (3 edges per triangle)
        edge_ids = np.empty(3 * wnt, dtype=np.int64)
        emap = np.empty((wnt, 6), dtype=np.int64)
        cstart = np.empty(wnt, dtype=np.int64)
        kmat = np.empty((wnt, 2, 6))
        beta = np.empty((wnt, 2, 2))
        mred = np.empty((wne, wne))
        fred = np.empty((wne, 3))  # two right-hand sides and a scratch column
        cmat = np.empty((wnt, wne))
        crhs = np.empty((wnt, 2))
        smat = np.empty((wnt, wnt))
        if weighted:
            # second factorisation, only for patches whose weights are not proportional
            mred2 = np.empty((wne, wne))
            cmat2 = np.empty((wnt, wne))
            smat2 = np.empty((wnt, wnt))
            crow = np.empty((wnt, 6))  # original rows of C, for the refinement step
            corig = np.empty((wnt, 2))
        mass = np.empty((8, 8))
        div = np.empty((3, 8))
        tau = np.empty((3, 2, 8))
        gloc = np.empty((3, 2))
        kapj = np.empty(3)
        glued = chi_row.shape[0] == triangles.shape[0]
        for k in range(k0, k1):
            a = order[k]
            pstart = patch_ptr[a]
            nt = patch_ptr[a + 1] - pstart
            interior = not boundary[a]
            if classes and cls[a] >= 0:
                continue  # a class member: _member_chunk
            if weighted:
                # --- weights 1 / mu_i,K relative to the first patch triangle; shared factorisation?
                shared = True
                t0 = patch_triangles[pstart]
                mu1_0 = mu1[0] if mu1.shape[0] == 1 else mu1[t0]
                mu2_0 = mu2[0] if mu2.shape[0] == 1 else mu2[t0]
                lo1 = hi1 = lo2 = hi2 = 1.0
                for p in range(nt):
                    t = patch_triangles[pstart + p]
                    w1 = mu1_0 / (mu1[0] if mu1.shape[0] == 1 else mu1[t])
                    w2 = mu2_0 / (mu2[0] if mu2.shape[0] == 1 else mu2[t])
                    lo1 = min(lo1, w1)
                    hi1 = max(hi1, w1)
                    lo2 = min(lo2, w2)
                    hi2 = max(hi2, w2)
                    if abs(w1 - w2) > 1e-13 * max(w1, w2):
                        shared = False
                # contrast of the weights on the patch: beyond 1e3 one step of iterative
                # refinement keeps the flux balance at round-off (_refine_balance)
                refine = hi1 > 1e3 * lo1 or hi2 > 1e3 * lo2
            # --- patch edges with dofs
            ne = 0
            for p in range(nt):
                t = patch_triangles[pstart + p]
                i = patch_local[pstart + p]
                for k in range(3):
                    e = tri_edges[t, k]
                    on_bnd = edge_tris[e, 1] < 0
                    if k == i and not (on_bnd and not interior):
                        emap[p, 2 * k] = -1  # zero normal flux on this patch-boundary edge
                        emap[p, 2 * k + 1] = -1
                        continue
                    s = -1
                    for q in range(ne):
                        if edge_ids[q] == e:
                            s = q
                            break
                    if s < 0:
                        edge_ids[ne] = e
                        s = ne
                        ne += 1
                    emap[p, 2 * k] = 2 * s
                    emap[p, 2 * k + 1] = 2 * s + 1
            n_e = 2 * ne
            for r in range(n_e):
                fred[r, 0] = 0.0
                fred[r, 1] = 0.0
                for s in range(r + 1):
                    mred[r, s] = 0.0
            if weighted:
                if not shared:
                    for r in range(n_e):
                        for s in range(r + 1):
                            mred2[r, s] = 0.0
            for p in range(nt):
                for r in range(n_e):
                    cmat[p, r] = 0.0
            r1a = 0.0 if not interior else rho1[a]
            r2a = 0.0 if not interior else rho2[a]
            lam_a = 0.0 if not interior else lam[a]
            redist_a = interior and redist.shape[0] > 1 and redist[a]
            gam = gamma[a] if redist_a else 0.0
            # --- per triangle: local matrices, bubble elimination, scatter
            for p in range(nt):
                t = patch_triangles[pstart + p]
                i = patch_local[pstart + p]
                i0 = triangles[t, 0]
                i1 = triangles[t, 1]
                i2 = triangles[t, 2]
                x0 = vertices[i0, 0]
                y0 = vertices[i0, 1]
                x1 = vertices[i1, 0]
                y1 = vertices[i1, 1]
                x2 = vertices[i2, 0]
                y2 = vertices[i2, 1]
                area = rt1_local_xy(
                    x0, y0, x1, y1, x2, y2, i0, i1, i2, diameters[t], mass, div, tau
                )
                du1x, du1y, du2x, du2y, gax, gay = _gradients(
                    i, x0, y0, x1, y1, x2, y2, u1, u2, i0, i1, i2, 0.5 / area
                )
                if weighted:
                    m1 = mu1[0] if mu1.shape[0] == 1 else mu1[t]
                    m2 = mu2[0] if mu2.shape[0] == 1 else mu2[t]
                    # weights of the patch norm: w_i = mu_i,K0 / mu_i,K
                    w1 = mu1_0 / m1
                    w2 = w1 if shared else mu2_0 / m2
                else:
                    m1 = mu1[0]
                    m2 = mu2[0]
                # data (g, lambda_j) with the contact load (the class members' code); here
                # out of line, unlike _member_chunk: the factorisations dominate this kernel
                # (inlining _plain_loads saved 9 % of an estimate without classes at n = 1024)
                # and every first run compiles it (the inlined copy cost 0.8 s of the cold
                # `fastmem run`, 7.6 -> 8.4 s)
                _patch_loads(
                    i, t, area, m1, m2, du1x, du1y, du2x, du2y, gax, gay, f1c, f2c, load1,
                    load2, chi_row, chi_mom, glued, r1a, r2a, lam_a, redist_a, gam, gloc, kapj,
                )  # fmt: skip
                # bubbles from divergence rows 1, 2:  sigma_b = beta - K sigma_e
                b00 = div[1, 6]
                b01 = div[1, 7]
                b10 = div[2, 6]
                b11 = div[2, 7]
                idet = 1.0 / (b00 * b11 - b01 * b10)
                c00 = b11 * idet
                c01 = -b01 * idet
                c10 = -b10 * idet
                c11 = b00 * idet
                for r in range(6):
                    kmat[p, 0, r] = c00 * div[1, r] + c01 * div[2, r]
                    kmat[p, 1, r] = c10 * div[1, r] + c11 * div[2, r]
                for c in range(2):
                    beta[p, 0, c] = c00 * gloc[1, c] + c01 * gloc[2, c]
                    beta[p, 1, c] = c10 * gloc[1, c] + c11 * gloc[2, c]
                # flux target -(tau, v) of the bubbles (tau = mu psi_a grad u)
                tb10 = -m1 * (du1x * tau[i, 0, 6] + du1y * tau[i, 1, 6])
                tb11 = -m1 * (du1x * tau[i, 0, 7] + du1y * tau[i, 1, 7])
                tb20 = -m2 * (du2x * tau[i, 0, 6] + du2y * tau[i, 1, 6])
                tb21 = -m2 * (du2x * tau[i, 0, 7] + du2y * tau[i, 1, 7])
                # flux balance row: sum of the three divergence rows (bubbles eliminated)
                sb0 = div[0, 6] + div[1, 6] + div[2, 6]
                sb1 = div[0, 7] + div[1, 7] + div[2, 7]
                st = n_e
                for r in range(6):
                    pr = emap[p, r]
                    if pr < 0:
                        continue
                    if pr < st:
                        st = pr
                    k0 = kmat[p, 0, r]
                    k1 = kmat[p, 1, r]
                    cmat[p, pr] = div[0, r] + div[1, r] + div[2, r] - sb0 * k0 - sb1 * k1
                    if weighted:
                        crow[p, r] = cmat[p, pr]
                    # A = M_eb - K^T M_bb (row r)
                    a0 = mass[r, 6] - (k0 * mass[6, 6] + k1 * mass[7, 6])
                    a1 = mass[r, 7] - (k0 * mass[6, 7] + k1 * mass[7, 7])
                    te1 = -m1 * (du1x * tau[i, 0, r] + du1y * tau[i, 1, r])
                    te2 = -m2 * (du2x * tau[i, 0, r] + du2y * tau[i, 1, r])
                    fe1 = te1 - k0 * tb10 - k1 * tb11 - a0 * beta[p, 0, 0] - a1 * beta[p, 1, 0]
                    fe2 = te2 - k0 * tb20 - k1 * tb21 - a0 * beta[p, 0, 1] - a1 * beta[p, 1, 1]
                    if weighted:
                        fred[pr, 0] += w1 * fe1
                        fred[pr, 1] += w2 * fe2
                    else:  # the weights are 1
                        fred[pr, 0] += fe1
                        fred[pr, 1] += fe2
                    # reduced mass M' = M_ee - M_eb K - K^T M_be + K^T M_bb K
                    #                = M_ee - A K - K^T M_be
                    for s in range(6):
                        ps = emap[p, s]
                        if ps >= 0 and ps <= pr:
                            mm = (
                                mass[r, s]
                                - (a0 * kmat[p, 0, s] + a1 * kmat[p, 1, s])
                                - (mass[s, 6] * k0 + mass[s, 7] * k1)
                            )
                            if weighted:
                                mred[pr, ps] += w1 * mm
                                if not shared:
                                    mred2[pr, ps] += w2 * mm
                            else:
                                mred[pr, ps] += mm
                cstart[p] = st
                for c in range(2):
                    crhs[p, c] = (
                        gloc[0, c]
                        + gloc[1, c]
                        + gloc[2, c]
                        - sb0 * beta[p, 0, c]
                        - sb1 * beta[p, 1, c]
                    )
            # --- M' sigma + C^T mu = f, C sigma = c: Cholesky of M', then of the Schur complement
            # (the column counts and the stage are runtime values, never literals: a
            # literal argument compiles another specialisation of the solver)
            if weighted:
                if refine:
                    for p in range(nt):
                        corig[p, 0] = crhs[p, 0]
                        corig[p, 1] = crhs[p, 1]
                if shared:  # one factorisation for both membranes
                    for c0 in range(0, 2, 2):
                        _reduced_solve2(
                            mred,
                            fred,
                            cmat,
                            crhs,
                            smat,
                            cstart,
                            n_e,
                            nt,
                            interior,
                            c0,
                            c0 + 2,
                            0 * c0,
                        )
                        if refine:
                            for c in range(c0, c0 + 2):
                                _refine_balance(
                                    mred,
                                    fred,
                                    cmat,
                                    crhs,
                                    smat,
                                    cstart,
                                    n_e,
                                    nt,
                                    crow,
                                    emap,
                                    corig,
                                    c,
                                )
                else:  # one per membrane
                    for p in range(nt):
                        for r in range(cstart[p], n_e):
                            cmat2[p, r] = cmat[p, r]
                    for c0 in range(2):
                        mr = mred if c0 == 0 else mred2
                        cm = cmat if c0 == 0 else cmat2
                        sm = smat if c0 == 0 else smat2
                        _reduced_solve1(
                            mr, fred, cm, crhs, sm, cstart, n_e, nt, interior, c0, c0 + 1, 0 * c0
                        )
                        if refine:
                            _refine_balance(
                                mr, fred, cm, crhs, sm, cstart, n_e, nt, crow, emap, corig, c0
                            )
            else:
                for c0 in range(0, 2, 2):
                    _reduced_solve2(
                        mred, fred, cmat, crhs, smat, cstart, n_e, nt, interior, c0, c0 + 2, 0 * c0
                    )
            for p in range(nt):
                t = patch_triangles[pstart + p]
                row = t if slots == 1 else 3 * (t % ring) + patch_local[pstart + p]
                for c in range(2):
                    z0 = beta[p, 0, c]
                    z1 = beta[p, 1, c]
                    for j in range(6):
                        pj = emap[p, j]
                        if pj >= 0:
                            sj = fred[pj, c]
                            z0 -= kmat[p, 0, j] * sj
                            z1 -= kmat[p, 1, j] * sj
                            out[c, row, j] += sj
                    out[c, row, 6] += z0
                    out[c, row, 7] += z1

    name = "_reconstruct_chunk_weighted" if weighted else "_reconstruct_chunk"
    _reconstruct_chunk.__name__ = _reconstruct_chunk.__qualname__ = name
    return jit(_reconstruct_chunk)


_reconstruct_chunk = _patch_kernel(False)
_reconstruct_chunk_weighted = _patch_kernel(True)


@jit
def _class_fill(
    reps,
    vertices,
    triangles,
    diameters,
    tri_edges,
    edge_tris,
    boundary,
    patch_ptr,
    patch_triangles,
    patch_local,
    max_nt,
    cint,
    cflt,
    coff,
    c0,
    c1,
):
    """Factor the patch problems of the class representatives ``reps[c0:c1]``; store them.

    The geometric part of :func:`_reconstruct_chunk` for constant tensions
    (edge dofs, local matrices, bubble elimination, M', C, both factors), with
    the same operations in the same order, written to class c's storage by
    :func:`_class_store`; :func:`_member_chunk` adds the right-hand sides.
    (Its own kernel, compiled only for meshes with classes: see
    :func:`_reconstruct_chunk`.)
    """
    wnt = max_nt
    wne = 6 * max_nt
    edge_ids = np.empty(3 * wnt, dtype=np.int64)
    emap = np.empty((wnt, 6), dtype=np.int64)
    cstart = np.empty(wnt, dtype=np.int64)
    kmat = np.empty((wnt, 2, 6))
    arow = np.empty((wnt, 2, 6))  # rows r of A = M_eb - K^T M_bb
    binv = np.empty((wnt, 6))  # B^-1 (4), the flux balance row's bubble part (2)
    tloc = np.empty((wnt, 2, 8))  # tau of the patch vertex (its local index i)
    areas = np.empty(wnt)
    mred = np.empty((wne, wne))
    fred = np.empty((wne, 3))  # unused (factor only)
    cmat = np.empty((wnt, wne))
    crhs = np.empty((wnt, 2))
    smat = np.empty((wnt, wnt))
    mass = np.empty((8, 8))
    div = np.empty((3, 8))
    tau = np.empty((3, 2, 8))
    # columns 0..2, stage 1 (factor only), as runtime values: literal arguments would
    # compile another specialisation of _reduced_solve2 than the patch kernel's
    cols = np.empty(3, dtype=np.int64)
    cols[0] = 0
    cols[1] = 2
    cols[2] = 1
    for c in range(c0, c1):
        a = reps[c]
        pstart = patch_ptr[a]
        nt = patch_ptr[a + 1] - pstart
        interior = not boundary[a]
        # --- patch edges with dofs (as in _reconstruct_chunk)
        ne = 0
        for p in range(nt):
            t = patch_triangles[pstart + p]
            i = patch_local[pstart + p]
            for k in range(3):
                e = tri_edges[t, k]
                on_bnd = edge_tris[e, 1] < 0
                if k == i and not (on_bnd and not interior):
                    emap[p, 2 * k] = -1
                    emap[p, 2 * k + 1] = -1
                    continue
                s = -1
                for q in range(ne):
                    if edge_ids[q] == e:
                        s = q
                        break
                if s < 0:
                    edge_ids[ne] = e
                    s = ne
                    ne += 1
                emap[p, 2 * k] = 2 * s
                emap[p, 2 * k + 1] = 2 * s + 1
        n_e = 2 * ne
        for r in range(n_e):
            for s in range(r + 1):
                mred[r, s] = 0.0
        for p in range(nt):
            for r in range(n_e):
                cmat[p, r] = 0.0
        for p in range(nt):
            t = patch_triangles[pstart + p]
            i = patch_local[pstart + p]
            i0 = triangles[t, 0]
            i1 = triangles[t, 1]
            i2 = triangles[t, 2]
            areas[p] = rt1_local_xy(
                vertices[i0, 0],
                vertices[i0, 1],
                vertices[i1, 0],
                vertices[i1, 1],
                vertices[i2, 0],
                vertices[i2, 1],
                i0,
                i1,
                i2,
                diameters[t],
                mass,
                div,
                tau,
            )
            # bubbles from divergence rows 1, 2:  sigma_b = beta - K sigma_e
            b00 = div[1, 6]
            b01 = div[1, 7]
            b10 = div[2, 6]
            b11 = div[2, 7]
            idet = 1.0 / (b00 * b11 - b01 * b10)
            c00 = b11 * idet
            c01 = -b01 * idet
            c10 = -b10 * idet
            c11 = b00 * idet
            binv[p, 0] = c00
            binv[p, 1] = c01
            binv[p, 2] = c10
            binv[p, 3] = c11
            for r in range(6):
                kmat[p, 0, r] = c00 * div[1, r] + c01 * div[2, r]
                kmat[p, 1, r] = c10 * div[1, r] + c11 * div[2, r]
            sb0 = div[0, 6] + div[1, 6] + div[2, 6]
            sb1 = div[0, 7] + div[1, 7] + div[2, 7]
            binv[p, 4] = sb0
            binv[p, 5] = sb1
            for r in range(8):
                tloc[p, 0, r] = tau[i, 0, r]
                tloc[p, 1, r] = tau[i, 1, r]
            st = n_e
            for r in range(6):
                pr = emap[p, r]
                if pr < 0:
                    continue
                if pr < st:
                    st = pr
                k0 = kmat[p, 0, r]
                k1 = kmat[p, 1, r]
                cmat[p, pr] = div[0, r] + div[1, r] + div[2, r] - sb0 * k0 - sb1 * k1
                a0 = mass[r, 6] - (k0 * mass[6, 6] + k1 * mass[7, 6])
                a1 = mass[r, 7] - (k0 * mass[6, 7] + k1 * mass[7, 7])
                arow[p, 0, r] = a0
                arow[p, 1, r] = a1
                for s in range(6):
                    ps = emap[p, s]
                    if ps >= 0 and ps <= pr:
                        mm = (
                            mass[r, s]
                            - (a0 * kmat[p, 0, s] + a1 * kmat[p, 1, s])
                            - (mass[s, 6] * k0 + mass[s, 7] * k1)
                        )
                        mred[pr, ps] += 1.0 * mm  # the weight mu_K0 / mu_K = 1
            cstart[p] = st
        _reduced_solve2(
            mred, fred, cmat, crhs, smat, cstart, n_e, nt, interior, cols[0], cols[1], cols[2]
        )
        _class_store(
            c,
            nt,
            n_e,
            max_nt,
            cstart,
            emap,
            kmat,
            arow,
            tloc,
            binv,
            areas,
            mred,
            cmat,
            smat,
            cint,
            cflt,
            coff,
        )


@jit
def _member_chunk(
    order,
    k0,
    k1,
    vertices,
    triangles,
    diameters,
    tri_edges,
    edge_tris,
    boundary,
    patch_ptr,
    patch_triangles,
    patch_local,
    u1,
    u2,
    lam,
    rho1,
    rho2,
    mu1,
    mu2,
    f1c,
    f2c,
    load1,
    load2,
    redist,
    gamma,
    chi_row,
    chi_mom,
    max_nt,
    out,
    ring,
    slots,
    cls,
    cint,
    cflt,
    coff,
):
    """Solve the patch problems of the class members among ``order[k0:k1]`` from their storage.

    Arguments as :func:`_reconstruct_chunk` (constant tensions).  For a vertex
    of class c the edge dofs, the bubble elimination (K, A, B^-1, the balance
    row's bubble part), tau of the patch vertex and the factors of M' and of
    the Schur complement come from the storage that :func:`_class_store`
    wrote for c's representative; the right-hand sides and the solves are
    computed here with the same operations as in the patch kernel, so every
    member's sigma^a has the bits it would have there.  :data:`LANES` members
    of one class that follow each other in ``order`` (on a structured mesh
    runs of about a hundred) are solved side by side (:func:`_lanes_solve`):
    the kernel took 0.55-0.64 s instead of 0.83-1.06 s at n = 1024 (one
    thread, the same arguments, same bits).
    """
    wnt = max_nt
    wne = 6 * max_nt
    emap = np.empty((wnt, 6), dtype=np.int64)
    cstart = np.empty(wnt, dtype=np.int64)
    kmat = np.empty((wnt, 2, 6))
    beta = np.empty((LANES, wnt, 2, 2))
    mred = np.empty((wne, wne))
    fred = np.empty((wne, 2 * LANES))  # columns 2 l, 2 l + 1: the two membranes of lane l
    cmat = np.empty((wnt, wne))
    crhs = np.empty((wnt, 2 * LANES))
    smat = np.empty((wnt, wnt))
    acc = np.empty(2 * LANES)
    gloc = np.empty((3, 2))
    kapj = np.empty(3)
    glued = chi_row.shape[0] == triangles.shape[0]
    m1 = mu1[0]
    m2 = mu2[0]
    # the two columns as runtime values: literal arguments would compile another
    # specialisation of _reduced_solve2 than the patch kernel's
    cols = np.empty(3, dtype=np.int64)
    cols[0] = 0
    cols[1] = 2
    cols[2] = 2  # solve only
    k = k0
    while k < k1:
        a = order[k]
        cid = cls[a]
        if cid < 0:
            k += 1
            continue
        # LANES members of one class in a row share the factors: solved side by side
        nl = LANES if k + LANES <= k1 else 1
        for q in range(1, nl):
            if cls[order[k + q]] != cid:
                nl = 1
                break
        nt = patch_ptr[a + 1] - patch_ptr[a]
        interior = not boundary[a]
        n_e = cint[cid, 1]
        for p in range(nt):
            for r in range(6):
                emap[p, r] = cint[cid, 2 + max_nt + 6 * p + r]
        for r in range(n_e):
            for c in range(2 * nl):
                fred[r, c] = 0.0
        for ln in range(nl):  # the right-hand sides of lane ln: columns col, col + 1
            a = order[k + ln]
            col = 2 * ln
            pstart = patch_ptr[a]
            r1a = 0.0 if not interior else rho1[a]
            r2a = 0.0 if not interior else rho2[a]
            lam_a = 0.0 if not interior else lam[a]
            redist_a = interior and redist.shape[0] > 1 and redist[a]
            gam = gamma[a] if redist_a else 0.0
            for p in range(nt):
                t = patch_triangles[pstart + p]
                i = patch_local[pstart + p]
                i0 = triangles[t, 0]
                i1 = triangles[t, 1]
                i2 = triangles[t, 2]
                o = coff[cid] + _CF * p  # K (12), A (12), tau (16), B^-1 (4), balance (2), area
                area = cflt[o + 46]
                du1x, du1y, du2x, du2y, gax, gay = _gradients(
                    i,
                    vertices[i0, 0],
                    vertices[i0, 1],
                    vertices[i1, 0],
                    vertices[i1, 1],
                    vertices[i2, 0],
                    vertices[i2, 1],
                    u1,
                    u2,
                    i0,
                    i1,
                    i2,
                    0.5 / area,
                )
                if redist_a or (glued and chi_row[t] >= 0):
                    _patch_loads(
                        i, t, area, m1, m2, du1x, du1y, du2x, du2y, gax, gay, f1c, f2c, load1,
                        load2, chi_row, chi_mom, glued, r1a, r2a, lam_a, redist_a, gam, gloc,
                        kapj,
                    )  # fmt: skip
                else:  # inlined (_plain_loads says why)
                    g00, g01, g10, g11, g20, g21 = _plain_loads(
                        i, t, area, m1, m2, du1x, du1y, du2x, du2y, gax, gay, f1c, f2c,
                        load1, load2, r1a, r2a, lam_a,
                    )  # fmt: skip
                    gloc[0, 0] = g00
                    gloc[0, 1] = g01
                    gloc[1, 0] = g10
                    gloc[1, 1] = g11
                    gloc[2, 0] = g20
                    gloc[2, 1] = g21
                c00 = cflt[o + 40]
                c01 = cflt[o + 41]
                c10 = cflt[o + 42]
                c11 = cflt[o + 43]
                sb0 = cflt[o + 44]
                sb1 = cflt[o + 45]
                for c in range(2):
                    beta[ln, p, 0, c] = c00 * gloc[1, c] + c01 * gloc[2, c]
                    beta[ln, p, 1, c] = c10 * gloc[1, c] + c11 * gloc[2, c]
                tb10 = -m1 * (du1x * cflt[o + 30] + du1y * cflt[o + 38])
                tb11 = -m1 * (du1x * cflt[o + 31] + du1y * cflt[o + 39])
                tb20 = -m2 * (du2x * cflt[o + 30] + du2y * cflt[o + 38])
                tb21 = -m2 * (du2x * cflt[o + 31] + du2y * cflt[o + 39])
                b00 = beta[ln, p, 0, 0]
                b10 = beta[ln, p, 1, 0]
                b01 = beta[ln, p, 0, 1]
                b11 = beta[ln, p, 1, 1]
                st = n_e
                for r in range(6):
                    k0r = cflt[o + r]
                    k1r = cflt[o + 6 + r]
                    kmat[p, 0, r] = k0r
                    kmat[p, 1, r] = k1r
                    pr = emap[p, r]
                    if pr < 0:
                        continue
                    if pr < st:
                        st = pr
                    a0 = cflt[o + 12 + r]
                    a1 = cflt[o + 18 + r]
                    te1 = -m1 * (du1x * cflt[o + 24 + r] + du1y * cflt[o + 32 + r])
                    te2 = -m2 * (du2x * cflt[o + 24 + r] + du2y * cflt[o + 32 + r])
                    fe1 = te1 - k0r * tb10 - k1r * tb11 - a0 * b00 - a1 * b10
                    fe2 = te2 - k0r * tb20 - k1r * tb21 - a0 * b01 - a1 * b11
                    fred[pr, col] += fe1  # the weights are mu_K0 / mu_K = 1
                    fred[pr, col + 1] += fe2
                cstart[p] = st
                for c in range(2):
                    crhs[p, col + c] = (
                        gloc[0, c]
                        + gloc[1, c]
                        + gloc[2, c]
                        - sb0 * beta[ln, p, 0, c]
                        - sb1 * beta[ln, p, 1, c]
                    )
        o = coff[cid] + _CF * nt  # the factors: M' (n_e x n_e), Y^T (nt x n_e), S (nt x nt)
        for r in range(n_e):
            for s in range(r + 1):
                mred[r, s] = cflt[o + r * n_e + s]
        o += n_e * n_e
        for p in range(nt):
            for r in range(cstart[p], n_e):
                cmat[p, r] = cflt[o + p * n_e + r]
        o += nt * n_e
        for p in range(nt):
            for q in range(p + 1):
                smat[p, q] = cflt[o + p * nt + q]
        if nl == LANES:
            _lanes_solve(mred, fred, cmat, crhs, smat, cstart, n_e, nt, acc)
        else:
            _reduced_solve2(
                mred, fred, cmat, crhs, smat, cstart, n_e, nt, interior, cols[0], cols[1], cols[2]
            )
        for ln in range(nl):
            pstart = patch_ptr[order[k + ln]]
            col = 2 * ln
            for p in range(nt):
                t = patch_triangles[pstart + p]
                row = t if slots == 1 else 3 * (t % ring) + patch_local[pstart + p]
                for c in range(2):
                    z0 = beta[ln, p, 0, c]
                    z1 = beta[ln, p, 1, c]
                    for j in range(6):
                        pj = emap[p, j]
                        if pj >= 0:
                            sj = fred[pj, col + c]
                            z0 -= kmat[p, 0, j] * sj
                            z1 -= kmat[p, 1, j] * sj
                            out[c, row, j] += sj
                    out[c, row, 6] += z0
                    out[c, row, 7] += z1
        k += nl


@jit
def _class_store(
    cid,
    nt,
    n_e,
    max_nt,
    cstart,
    emap,
    kmat,
    arow,
    tloc,
    binv,
    areas,
    mred,
    cmat,
    smat,
    cint,
    cflt,
    coff,
):
    """Write the geometric part of a factored patch problem into class ``cid``'s storage.

    Layout (read back by :func:`_reconstruct_chunk`): ``cint[cid]`` = nt, n_e,
    ``cstart[:max_nt]``, ``emap`` (max_nt x 6); ``cflt[coff[cid]:]`` = per
    triangle :data:`_CF` values (K (12), A (12), tau of the patch vertex (16),
    B^-1 (4), the balance row's bubble part (2), the area), then the factor of
    M' (n_e x n_e), the rows of Y^T (nt x n_e), the factor of S (nt x nt).
    """
    cint[cid, 0] = nt
    cint[cid, 1] = n_e
    for p in range(nt):
        cint[cid, 2 + p] = cstart[p]
        for r in range(6):
            cint[cid, 2 + max_nt + 6 * p + r] = emap[p, r]
    o0 = coff[cid]
    for p in range(nt):
        o = o0 + _CF * p
        for r in range(6):
            cflt[o + r] = kmat[p, 0, r]
            cflt[o + 6 + r] = kmat[p, 1, r]
            cflt[o + 12 + r] = arow[p, 0, r]
            cflt[o + 18 + r] = arow[p, 1, r]
            cflt[o + 40 + r] = binv[p, r]
        for r in range(8):
            cflt[o + 24 + r] = tloc[p, 0, r]
            cflt[o + 32 + r] = tloc[p, 1, r]
        cflt[o + 46] = areas[p]
    o = o0 + _CF * nt
    for r in range(n_e):
        for s in range(r + 1):
            cflt[o + r * n_e + s] = mred[r, s]
    o += n_e * n_e
    for p in range(nt):
        for r in range(cstart[p], n_e):
            cflt[o + p * n_e + r] = cmat[p, r]
    o += nt * n_e
    for p in range(nt):
        for q in range(p + 1):
            cflt[o + p * nt + q] = smat[p, q]


@jit
def _coefficients_chunk(vertices, triangles, diameters, out, t0, t1):
    """Local dof values -> canonical RT1 coefficients, in place, for triangles t0..t1-1."""
    m = triangles.shape[0]
    rows = out.reshape((2 * m, 8))
    for t in range(t0, t1):
        i0, i1, i2 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        x0, y0 = vertices[i0, 0], vertices[i0, 1]
        x1, y1 = vertices[i1, 0], vertices[i1, 1]
        x2, y2 = vertices[i2, 0], vertices[i2, 1]
        h = diameters[t]
        rt1_dofs_to_coefficients(x0, y0, x1, y1, x2, y2, i0, i1, i2, h, rows, t)
        rt1_dofs_to_coefficients(x0, y0, x1, y1, x2, y2, i0, i1, i2, h, rows, m + t)


@jit
def _patch_key(a, geo, edge_ids, key):
    """Write what the geometric part of vertex a's patch problem depends on into ``key``.

    Returns ``(length, n_e)``.  The key: the number of triangles, the interior
    flag, and per patch triangle (in patch order) the local index of a, the
    edge orientation pattern, the Jacobian ``(x1 - x0, y1 - y0, x2 - x0, y2 -
    y0)`` and the diameter exactly as :func:`.rt1.rt1_local_xy` computes
    them, and the patch edge slot of each local edge (-1: no dofs).  Two
    patches with equal keys (bit for bit) have the same local matrices, edge
    dofs and factors.  ``geo``: the mesh arrays (vertices, triangles,
    diameters, triangle edges, edge triangles, boundary mask, patch_ptr,
    patch_triangles, patch_local).
    """
    vertices, triangles, diameters, tri_edges, edge_tris, boundary = geo[:6]
    patch_ptr, patch_triangles, patch_local = geo[6:]
    pstart = patch_ptr[a]
    nt = patch_ptr[a + 1] - pstart
    interior = not boundary[a]
    key[0] = nt
    key[1] = 1.0 if interior else 0.0
    ne = 0
    q = 2
    for p in range(nt):
        t = patch_triangles[pstart + p]
        i = patch_local[pstart + p]
        i0 = triangles[t, 0]
        i1 = triangles[t, 1]
        i2 = triangles[t, 2]
        key[q] = i
        key[q + 1] = _flip_pattern(i0, i1, i2)
        key[q + 2] = vertices[i1, 0] - vertices[i0, 0]
        key[q + 3] = vertices[i1, 1] - vertices[i0, 1]
        key[q + 4] = vertices[i2, 0] - vertices[i0, 0]
        key[q + 5] = vertices[i2, 1] - vertices[i0, 1]
        key[q + 6] = diameters[t]
        for k in range(3):
            e = tri_edges[t, k]
            on_bnd = edge_tris[e, 1] < 0
            slot = -1
            if not (k == i and not (on_bnd and not interior)):
                for r in range(ne):
                    if edge_ids[r] == e:
                        slot = r
                        break
                if slot < 0:
                    edge_ids[ne] = e
                    slot = ne
                    ne += 1
            key[q + 7 + k] = slot
        q += 10
    return q, 2 * ne


@jit
def _patch_hash_range(geo, max_nt, stride, hashes, n_e, a0, a1):
    """64-bit hashes of the patch keys (:func:`_patch_key`) of vertices ``stride * k``, and n_e.

    For k = a0..a1-1, written to ``hashes[k]``, ``n_e[k]`` (stride 1: every vertex).

    The sum of the key's words, each mixed with its position (independent
    per word, no dependency chain): a filter only, equal keys are checked
    word by word afterwards (:func:`_verify_range`).
    """
    key = np.empty(2 + 10 * max_nt)
    bits = key.view(np.uint64)
    edge_ids = np.empty(3 * max_nt, dtype=np.int64)
    for k in range(a0, a1):
        length, ne = _patch_key(stride * k, geo, edge_ids, key)
        h = np.uint64(0)
        c = np.uint64(0)
        for j in range(length):
            # each word with its position through the splitmix64 finaliser, then summed
            # (independent per word); a plain weighted sum collided on dyadic keys,
            # whose words differ only in their exponent bits
            c += np.uint64(0x9E3779B97F4A7C15)
            x = bits[j] + c
            x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            h += x ^ (x >> np.uint64(31))
        hashes[k] = h
        n_e[k] = ne


@jit
def _slot(table_hash, table_rep, h):
    """Return the slot of hash ``h`` in an open-addressing table.

    Its entry, or the empty slot where it goes (``table_rep < 0``: empty; the
    size is a power of two).  Shared by every hash table of the patch classes.
    """
    mask = table_rep.shape[0] - 1
    s = np.int64(h & np.uint64(mask))
    while table_rep[s] >= 0 and table_hash[s] != h:
        s = (s + 1) & mask
    return s


@jit
def _doubled(table_hash, table_rep):
    """Return the table twice as large, its entries inserted again (in slot order)."""
    size = 2 * table_rep.shape[0]
    new_hash = np.zeros(size, dtype=np.uint64)
    new_rep = np.full(size, -1, dtype=np.int64)
    for j in range(table_rep.shape[0]):
        if table_rep[j] >= 0:
            s = _slot(new_hash, new_rep, table_hash[j])
            new_rep[s] = table_rep[j]
            new_hash[s] = table_hash[j]
    return new_hash, new_rep


@jit
def _group_hashes(hashes, rep):
    """``rep[a]``: the first vertex with the hash of a; returns the number of distinct hashes.

    Open addressing in a table that doubles when half full (a structured mesh
    has a few dozen distinct patches: the table stays in cache).  Serial, O(N).
    """
    table_hash = np.zeros(1024, dtype=np.uint64)
    table_rep = np.full(1024, -1, dtype=np.int64)
    used = 0
    for a in range(hashes.shape[0]):
        if 2 * used >= table_rep.shape[0]:
            table_hash, table_rep = _doubled(table_hash, table_rep)
        h = hashes[a]
        s = _slot(table_hash, table_rep, h)
        if table_rep[s] < 0:
            table_rep[s] = a
            table_hash[s] = h
            used += 1
        rep[a] = table_rep[s]
    return used


@jit
def _chunk_firsts(lo, hi, hashes, n_chunks, firsts, n_first):
    """Chunks ``lo <= k < hi`` of ``hashes``: the first vertex of each hash met in the chunk.

    Chunk k holds ``N k / K <= a < N (k + 1) / K``; its first vertices, in
    increasing order, go to ``firsts[N k / K:]`` and their number to ``n_first[k]``.
    Open addressing as in :func:`_group_hashes`, one table per chunk.
    """
    n = hashes.shape[0]
    for k in range(lo, hi):
        a0 = n * k // n_chunks
        a1 = n * (k + 1) // n_chunks
        table_hash = np.zeros(1024, dtype=np.uint64)
        table_rep = np.full(1024, -1, dtype=np.int64)
        used = 0
        for a in range(a0, a1):
            if 2 * used >= table_rep.shape[0]:
                table_hash, table_rep = _doubled(table_hash, table_rep)
            h = hashes[a]
            s = _slot(table_hash, table_rep, h)
            if table_rep[s] < 0:
                table_rep[s] = a
                table_hash[s] = h
                firsts[a0 + used] = a
                used += 1
        n_first[k] = used


@jit
def _merge_firsts(hashes, firsts, n_chunks, n_first):
    """Return the table of :func:`_group_hashes` from the chunks' first vertices, in order.

    Returns ``(table_hash, table_rep, used)``: a hash's first vertex in the whole
    array is its first in the first chunk that has it.
    """
    n = hashes.shape[0]
    total = 0
    for k in range(n_chunks):
        total += n_first[k]
    size = 1024
    while size < 2 * total + 2:
        size *= 2
    table_hash = np.zeros(size, dtype=np.uint64)
    table_rep = np.full(size, -1, dtype=np.int64)
    used = 0
    for k in range(n_chunks):
        a0 = n * k // n_chunks
        for j in range(a0, a0 + n_first[k]):
            a = firsts[j]
            h = hashes[a]
            s = _slot(table_hash, table_rep, h)
            if table_rep[s] < 0:
                table_rep[s] = a
                table_hash[s] = h
                used += 1
    return table_hash, table_rep, used


@jit
def _lookup_range(lo, hi, hashes, table_hash, table_rep, rep):
    """``rep[a]`` for ``lo <= a < hi``: the first vertex of a's hash, from the merged table."""
    for a in range(lo, hi):
        rep[a] = table_rep[_slot(table_hash, table_rep, hashes[a])]


def _group_hashes_threaded(hashes, rep, threads, grain=None):
    """Return :func:`_group_hashes` (the same ``rep`` and count), in the kernel threads.

    From :data:`~fastmem.kernels.sparsity.BLOCK_THREADS` threads on (below, the
    serial kernel, and nothing more to compile): each chunk finds the first vertex
    of each of its hashes, one thread merges them in chunk order (a few dozen per
    chunk on a structured mesh), and the chunks look their vertices up.
    """
    n = hashes.shape[0]
    chunks = _par.ranges(n, threads, TRIANGLE_GRAIN if grain is None else grain)
    if threads < BLOCK_THREADS or len(chunks) == 1:
        return _group_hashes(hashes, rep)
    n_chunks = len(chunks)
    firsts = np.empty(n, dtype=np.int64)
    n_first = np.empty(n_chunks, dtype=np.int64)
    _par.run_ranges(
        lambda lo, hi: _chunk_firsts(lo, hi, hashes, n_chunks, firsts, n_first),
        [(k, k + 1) for k in range(n_chunks)],
    )
    table_hash, table_rep, used = _merge_firsts(hashes, firsts, n_chunks, n_first)
    _par.run_ranges(
        lambda lo, hi: _lookup_range(lo, hi, hashes, table_hash, table_rep, rep), chunks
    )
    return used


def precompile_grouping() -> None:
    """Compile (or load) the threaded grouping of the patch hashes, with BLOCK_THREADS or more.

    :func:`fastmem.warm_up`'s meshes are too small for its chunks: here eight
    hashes in four chunks.  Nothing to compile with fewer threads.
    """
    if _par.n_threads() >= BLOCK_THREADS:
        hashes = np.array([5, 7, 5, 9, 7, 7, 11, 5], dtype=np.uint64)
        _group_hashes_threaded(hashes, np.empty(8, dtype=np.int64), BLOCK_THREADS, grain=1)


@jit
def _class_keys(geo, max_nt, reps, keys, lengths):
    """Write the keys of the class representatives ``reps`` (one row each)."""
    edge_ids = np.empty(3 * max_nt, dtype=np.int64)
    for c in range(reps.shape[0]):
        lengths[c], _ = _patch_key(reps[c], geo, edge_ids, keys[c])


@jit
def _verify_range(geo, max_nt, rep, ids, keys, lengths, cls, a0, a1):
    """Set ``cls[a]``: the class of its representative if their keys agree bitwise, else -1."""
    key = np.empty(2 + 10 * max_nt)
    kb = key.view(np.uint64)
    edge_ids = np.empty(3 * max_nt, dtype=np.int64)
    for a in range(a0, a1):
        c = ids[rep[a]]
        cls[a] = -1
        if c < 0:
            continue
        la, _ = _patch_key(a, geo, edge_ids, key)
        if la != lengths[c]:
            continue
        rb = keys[c].view(np.uint64)
        same = True
        for j in range(la):
            if kb[j] != rb[j]:
                same = False
                break
        if same:
            cls[a] = c


#: a class is stored when it has at least this many patches (its representative is
#: solved once more, to fill the storage: below, reuse would not pay)
CLASS_MIN_PATCHES = 4
#: at most this many floats of class storage (8 bytes each)
CLASS_MAX_FLOATS = 8_000_000
#: the sample of vertices that decides whether to search (every (N / CLASS_SAMPLE)-th) ...
CLASS_SAMPLE = 4096
#: ... and the fraction of it whose patch must recur in the sample (a square: 99.5 %;
#: an adapted L-shape mesh of 215k vertices: 97 %, and 715 classes cover 99.5 % of it;
#: a mesh with coordinates that are not dyadic: none recur)
CLASS_MIN_COVERAGE = 0.8


def patch_classes(geo, max_nt, n_threads):
    """Group the vertex patches whose patch problems share their geometric part.

    Two patches are in one class when their keys (:func:`_patch_key`) agree bit
    for bit: then their local matrices, edge dofs and both factorisations are
    the same, and only the right-hand sides differ.  On a mesh whose vertex
    coordinates are dyadic (``Mesh.square(2^k)``, its bisections) the
    translated copies of a patch have exactly equal keys; elsewhere the keys
    differ in the last bits and there are no classes.  A strided sample decides
    first whether classes would cover enough of the mesh
    (:data:`CLASS_MIN_COVERAGE`).  Then hashes in parallel, one
    serial O(N) pass of open addressing, the classes of at least
    :data:`CLASS_MIN_PATCHES` patches, largest first, within
    :data:`CLASS_MAX_FLOATS` of storage, then a parallel check of each key
    against its representative's, word by word (a hash collision leaves the
    patch unclassed).

    ``geo``: the mesh arrays of :func:`_patch_key`; ``max_nt``: the most
    triangles in a patch.  Returns None when no class qualifies, else ``(cls, reps, cint, cflt,
    coff)``: ``cls`` int32 (N,) the class of each vertex or -1, ``reps`` the
    representatives, and the empty storage that :func:`reconstruct_colored`
    fills on its first use (``cint[:, 0] = 0`` until then).
    """
    patch_ptr = geo[6]
    n = patch_ptr.shape[0] - 1
    args = (geo, int(max_nt))
    threads = max(1, int(n_threads))
    # a strided sample first: where its repeated patches cover less than
    # CLASS_MIN_COVERAGE, the search would cost about what the classes save
    stride = max(1, n // CLASS_SAMPLE)
    m = (n + stride - 1) // stride
    hashes = np.empty(m, dtype=np.uint64)
    n_e = np.empty(m, dtype=np.int32)
    _patch_hash_range(*args, stride, hashes, n_e, 0, m)
    rep = np.empty(m, dtype=np.int64)
    _group_hashes(hashes, rep)
    counts = np.bincount(rep, minlength=m)
    if np.count_nonzero(counts[rep] >= 2) < CLASS_MIN_COVERAGE * m:
        return None
    hashes = np.empty(n, dtype=np.uint64)
    n_e = np.empty(n, dtype=np.int32)
    chunks = _par.ranges(n, threads, TRIANGLE_GRAIN)
    _par.run_ranges(functools.partial(_patch_hash_range, *args, 1, hashes, n_e), chunks)
    rep = np.empty(n, dtype=np.int64)
    distinct = _group_hashes_threaded(hashes, rep, threads)
    hashes = None
    if 2 * distinct > n:  # mostly patches of their own (coordinates not dyadic): no classes
        return None
    counts = np.bincount(rep, minlength=n)
    reps = np.flatnonzero(counts >= CLASS_MIN_PATCHES)
    if reps.size == 0:
        return None
    reps = reps[np.argsort(-counts[reps], kind="stable")]
    del counts
    nt = patch_ptr[reps + 1] - patch_ptr[reps]
    ne = n_e[reps].astype(np.int64)
    size = _CF * nt + ne * ne + nt * ne + nt * nt
    keep = np.cumsum(size) <= CLASS_MAX_FLOATS
    reps, size = reps[keep], size[keep]
    if reps.size == 0:
        return None
    coff = np.zeros(reps.size, dtype=np.int64)
    np.cumsum(size[:-1], out=coff[1:])
    ids = np.full(n, -1, dtype=np.int32)
    ids[reps] = np.arange(reps.size, dtype=np.int32)
    keys = np.empty((reps.size, 2 + 10 * int(max_nt)))
    lengths = np.empty(reps.size, dtype=np.int64)
    _class_keys(*args, reps, keys, lengths)
    cls = np.empty(n, dtype=np.int32)
    _par.run_ranges(functools.partial(_verify_range, *args, rep, ids, keys, lengths, cls), chunks)
    cint = np.zeros((reps.size, 2 + 7 * int(max_nt)), dtype=np.int64)
    cflt = np.empty(int(size.sum()))
    return cls, reps, cint, cflt, coff


def classes_compiled() -> bool:
    """Tell whether the patch classes' kernels are compiled (or loaded) in this process.

    Then classes cost no compilation: :func:`fastmem.estimators.flux.patch_classes`
    uses them on smaller meshes too.
    """
    kernels = (_patch_hash_range, _group_hashes, _class_keys, _verify_range, _class_fill)
    return all(k.signatures for k in (*kernels, _member_chunk))


#: fewest patches (triangles) per thread: below, a colour class (the final pass)
#: runs in the calling thread (a thread hand-off costs about 20 us)
PATCH_GRAIN = 256
#: pieces per thread of a colour class, handed out dynamically (:func:`._par.run_pieces`);
#: 1: one fixed chunk per thread
PATCH_PIECES = 16
TRIANGLE_GRAIN = 4096
#: pieces per thread of a band's completed triangles (:func:`flux_norms_banded`), handed
#: out dynamically: in one chunk per thread, the slowest of 16 chunks made the pass
#: take twice its share (``bench.critical_path``, n = 2048, 16 threads)
FINISH_PIECES = 4


#: Called, when set, before the patch kernel first runs (then cleared by its
#: owner): :func:`fastmem.warm_up` sets it to wait for a helper process that is
#: compiling the patch kernel into Numba's cache at the same time.
compile_gate = None


def _readonly(a):
    a.setflags(write=False)
    return a


def _writable(a):
    """Return ``a``, or a copy when it is read-only.

    Numba compiles one specialisation per read-only flag, and the solver's own
    vectors are writable (the solution arrays of a Result are not; without this,
    a reconstruction from them would compile the kernel anew).
    """
    return a if a.flags.writeable else a.copy()


def precompile(part: str) -> None:
    """Compile (or load from Numba's cache) one group of this module's kernels.

    ``part``: ``"patches"`` (the patch kernel and its callees, the bulk of the
    compile time, constant tensions), ``"weighted"`` (the patch kernel for
    per-triangle tensions), ``"solvers"`` (the largest callee of the first),
    ``"coefficients"`` (the coefficient pass and the vertex colouring),
    ``"estimators"`` or ``"callees"`` (the first large callee the patch kernel's
    typing meets, :func:`fastmem.kernels.rt1.rt1_local_xy`, compiled for the
    argument types the patch kernel passes, :func:`_callee_signatures`).  The kernels are
    called on empty ranges with arrays of exactly the types
    :func:`fastmem.estimators.flux.reconstruct` and :func:`fastmem.estimators.bound.flux_terms` pass
    (read-only mesh arrays, 32-bit topology), so the code compiled here is the
    code a solve uses (tests/test_coldstart.py checks that no second
    specialisation appears).  Nothing is computed.
    """
    f8 = np.float64
    vertices = _readonly(np.zeros((3, 2)))
    triangles = _readonly(np.array([[0, 1, 2]], dtype=np.int64))
    diameters = _readonly(np.ones(1))
    coef = np.zeros((2, 1, 8))
    if part in ("patches", "weighted"):
        kernel = _reconstruct_chunk_weighted if part == "weighted" else _reconstruct_chunk
        kernel(
            np.zeros(1, dtype=np.int64),
            0,
            0,
            vertices,
            triangles,
            diameters,
            _readonly(np.zeros((1, 3), dtype=np.int32)),
            _readonly(np.zeros((3, 2), dtype=np.int32)),
            _readonly(np.zeros(3, dtype=np.bool_)),
            _readonly(np.zeros(4, dtype=np.int64)),
            _readonly(np.zeros(3, dtype=np.int32)),
            _readonly(np.zeros(3, dtype=np.int8)),
            *(np.zeros(3, dtype=f8) for _ in range(5)),
            np.ones(1),
            np.ones(1),
            0.0,
            0.0,
            np.zeros((1, 3, 3)),
            np.zeros((1, 3, 3)),
            np.zeros(1, dtype=np.bool_),
            np.zeros(1),
            np.full(1, -1, dtype=np.int32),
            np.zeros((1, 3, 3)),
            1,
            coef,
            0,
            1,
            np.full(1, -1, dtype=np.int32),
        )
    elif part == "callees":
        for dispatcher, signature in _callee_signatures():
            dispatcher.compile(signature)
    elif part == "solvers":
        a = np.zeros((0, 3))
        cstart = np.zeros(0, dtype=np.int64)
        _reduced_solve2(a, a, a, a, a, cstart, 0, 0, False, 0, 2, 0)  # nothing to solve
    elif part == "coefficients":
        _coefficients_chunk(vertices, triangles, diameters, coef, 0, 0)
        # and the vertex colouring (writable int32 CSR arrays, as csr_structure gives)
        color_vertices(0, np.zeros(1, dtype=np.int32), np.zeros(0, dtype=np.int32))
    elif part == "estimators":
        rule = _readonly(np.zeros((1, 3))), _readonly(np.zeros(1))
        u = np.zeros(3)
        _estimators_chunk(
            vertices,
            triangles,
            diameters,
            coef,
            u,
            u,
            np.ones(1),
            np.ones(1),
            *rule,
            np.zeros((2, 1)),
            0,
            0,
        )
    else:
        raise ValueError(
            "part must be 'patches', 'weighted', 'solvers', 'callees', 'coefficients' or "
            "'estimators', "
            f"got {part!r}"
        )


def _callee_signatures():
    """Callees of the patch kernel for part ``"callees"``, with the argument types it passes.

    Written out, because they take scalars and work arrays of the patch kernel (no
    call from Python could type them the same way without computing);
    tests/cli/test_coldstart.py checks that the patch kernel compiles no other
    specialisation of them.
    """
    f8, i8 = _nt.float64, _nt.int64
    a2, a3 = _nt.Array(f8, 2, "C"), _nt.Array(f8, 3, "C")
    return [(rt1_local_xy, (f8,) * 6 + (i8,) * 3 + (f8, a2, a2, a3))]


def _patch_runner(order, inputs, chi_row, chi_mom, classes):
    """Prepare the patch kernels (arguments of :func:`reconstruct_colored`); return ``run, args``.

    ``inputs``: the positional arguments of :func:`reconstruct_colored` after its
    colouring (``vertices`` ... ``n_threads``).

    ``run(out, ring, slots, lo, hi)`` solves the patches of the vertices
    ``order[lo:hi]`` (all of one colour) in parallel and adds their local dof
    values into ``out`` (rows as the patch kernel's ``ring`` and ``slots`` say).
    The class storage is filled here on its first use.  ``args``: the kernels' arguments
    before ``out`` (the arrays made writable once, for the caller's kernels too).
    """
    (
        vertices, triangles, diameters, tri_edges, edge_tris, boundary, patch_ptr,
        patch_triangles, patch_local, u1, u2, lam, rho1, rho2, mu1, mu2, f1c, f2c, load1,
        load2, redist, gamma, max_nt, threads,
    ) = inputs  # fmt: skip
    threads = max(1, int(threads))
    global compile_gate
    if compile_gate is not None:
        gate, compile_gate = compile_gate, None
        gate()
    if chi_row is None or chi_mom is None:
        chi_row = np.full(1, -1, dtype=np.int32)
        chi_mom = np.zeros((1, 3, 3))
    chi_row = np.ascontiguousarray(chi_row, dtype=np.int32)
    chi_mom = np.ascontiguousarray(chi_mom, dtype=np.float64)
    u1, u2, lam, rho1, rho2, mu1, mu2, load1, load2, redist, gamma, chi_row, chi_mom = (
        _writable(a)
        for a in (u1, u2, lam, rho1, rho2, mu1, mu2, load1, load2, redist, gamma, chi_row, chi_mom)
    )
    args = (
        vertices, triangles, diameters, tri_edges, edge_tris, boundary, patch_ptr,
        patch_triangles, patch_local, u1, u2, lam, rho1, rho2, mu1, mu2, float(f1c),
        float(f2c), load1, load2, redist, gamma, chi_row, chi_mom, int(max_nt),
    )  # fmt: skip
    if classes is not None and mu1.shape[0] == 1 and mu2.shape[0] == 1:
        cls, reps, cint, cflt, coff = classes
        if cint[0, 0] == 0:  # fill the storage: the representatives' factors

            def fill(k0, k1):
                _class_fill(reps, *args[:9], int(max_nt), cint, cflt, coff, k0, k1)

            _par.run_ranges(fill, _par.ranges(reps.shape[0], threads, 8))
    else:
        cls = np.full(1, -1, dtype=np.int32)
        cint = np.zeros((1, 1), dtype=np.int64)
        cflt = np.zeros(1)
        coff = np.zeros(1, dtype=np.int64)

    members = cls.shape[0] > 1

    weighted = mu1.shape[0] != 1 or mu2.shape[0] != 1
    kernel = _reconstruct_chunk_weighted if weighted else _reconstruct_chunk

    def run(out, ring, slots, lo, hi):
        def patches(k0, k1):
            kernel(order, k0, k1, *args, out, ring, slots, cls)
            if members:
                _member_chunk(order, k0, k1, *args, out, ring, slots, cls, cint, cflt, coff)

        if PATCH_PIECES > 1 and threads > 1:
            chunks = _par.ranges(hi - lo, PATCH_PIECES * threads, PATCH_GRAIN)
            _par.run_pieces(patches, [(lo + a, lo + b) for a, b in chunks], threads)
        else:
            chunks = _par.ranges(hi - lo, threads, PATCH_GRAIN)
            _par.run_ranges(patches, [(lo + a, lo + b) for a, b in chunks])

    return run, args


def reconstruct_colored(
    order,
    color_ptr,
    vertices,
    triangles,
    diameters,
    tri_edges,
    edge_tris,
    boundary,
    patch_ptr,
    patch_triangles,
    patch_local,
    u1,
    u2,
    lam,
    rho1,
    rho2,
    mu1,
    mu2,
    f1c,
    f2c,
    load1,
    load2,
    redist,
    gamma,
    max_nt,
    n_threads,
    chi_row=None,
    chi_mom=None,
    classes=None,
):
    """Equilibrated fluxes of both membranes, canonical RT1 coefficients (2, M, 8).

    Parameters
    ----------
    order, color_ptr : int64
        Vertices sorted by colour; class c is ``order[color_ptr[c]:color_ptr[c+1]]``.
    vertices, triangles, diameters, tri_edges, edge_tris, boundary :
        Mesh arrays (boundary: bool mask of boundary vertices).
    patch_ptr, patch_triangles, patch_local : int64
        Vertex patches (CSR).
    u1, u2, lam : float64 (N,)
        Nodal values of the triple.
    rho1, rho2 : float64 (N,)
        Nodal ``R_i,a / B_a`` (zero on the boundary).
    mu1, mu2 : float64 (1,) or (M,)
        Tensions.
    f1c, f2c : float
        Constant loads, used when ``load1``/``load2`` has shape (1, 3, 3).
    load1, load2 : float64 (M, 3, 3) or (1, 3, 3)
        Load moments ``int_K f lambda_i lambda_j`` for non-constant data.
    redist : bool (N,) or (1,)
        Vertices whose contact load is redistributed (shape (1,): none): on
        triangle K the load of patch a is then ``psi_a (mu_1 f_2 - mu_2 f_1) /
        (mu_1 + mu_2) + gamma_a psi_a`` instead of ``lam_a psi_a``
        (:func:`fastmem.estimators.flux.contact_redistribution`).
    gamma : float64 (N,) or (1,)
        The mass corrections gamma_a.
    max_nt : int
        Largest number of triangles in a patch (sizes the workspaces).
    n_threads : int
        Threads; each colour class is cut into at most this many chunks, each
        with its own workspace.
    chi_row, chi_mom : int32 (M,) and float64 (S, 3, 3), optional
        Glued contact load (:func:`fastmem.estimators.flux.glued_contact_load`): on
        triangle t with ``s = chi_row[t] >= 0`` the load moments of membrane 1
        gain ``chi_mom[s]`` and those of membrane 2 lose it (row i: the vertex
        of local index i; zero rows for vertices that are not glued).  Only the
        S triangles in contact are stored, not full (M, 3, 3) load copies.
    classes : tuple, optional
        The patch classes of the mesh (:func:`patch_classes`), used with
        constant tensions only.  Their storage is filled on first use (one
        patch problem per class, in parallel) and reused by every later call
        with the same tuple.

    Threading: one colour class at a time, its vertices cut into chunks run by
    :mod:`._par` (serial Numba kernels without the GIL, so no parallel
    compilation); a patch writes only the rows of its own triangles, which no
    other vertex of the class touches, so the result is bit-identical for any
    number of threads.  The patches accumulate local dof values (the sum of
    the sigma^a); one final pass over the triangles turns them into canonical
    coefficients.
    """
    m = triangles.shape[0]
    out = np.zeros((2, m, 8))
    threads = max(1, int(n_threads))
    inputs = (
        vertices, triangles, diameters, tri_edges, edge_tris, boundary, patch_ptr,
        patch_triangles, patch_local, u1, u2, lam, rho1, rho2, mu1, mu2, f1c, f2c, load1,
        load2, redist, gamma, max_nt, threads,
    )  # fmt: skip
    run, _ = _patch_runner(order, inputs, chi_row, chi_mom, classes)
    for c in range(color_ptr.shape[0] - 1):
        run(out, 0, 1, int(color_ptr[c]), int(color_ptr[c + 1]))

    def coefficients(t0, t1):
        _coefficients_chunk(vertices, triangles, diameters, out, t0, t1)

    _par.run_ranges(coefficients, _par.ranges(m, threads, TRIANGLE_GRAIN))
    return out


@jit
def _triangle_norms(
    vertices, triangles, diameters, coef, k, u1, u2, mu1, mu2, bary, weights, out, t
):
    """``out[:, t]``: the flux estimators of triangle t, its coefficients in ``coef[:, k]``."""
    i0, i1, i2 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
    x0, y0 = vertices[i0, 0], vertices[i0, 1]
    x1, y1 = vertices[i1, 0], vertices[i1, 1]
    x2, y2 = vertices[i2, 0], vertices[i2, 1]
    area2 = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    xc = (x0 + x1 + x2) / 3.0
    yc = (y0 + y1 + y2) / 3.0
    h = diameters[t]
    # grad(phi_v) = rot(edge opposite v) / (2|K|)
    g0x, g0y = -(y2 - y1) / area2, (x2 - x1) / area2
    g1x, g1y = -(y0 - y2) / area2, (x0 - x2) / area2
    g2x, g2y = -(y1 - y0) / area2, (x1 - x0) / area2
    for i in range(2):
        u = u1 if i == 0 else u2
        mu_arr = mu1 if i == 0 else mu2
        mu = mu_arr[0] if mu_arr.shape[0] == 1 else mu_arr[t]
        smu = np.sqrt(mu)
        gx = u[i0] * g0x + u[i1] * g1x + u[i2] * g2x
        gy = u[i0] * g0y + u[i1] * g1y + u[i2] * g2y
        c = coef[i, k]
        acc = 0.0
        for q in range(weights.shape[0]):
            xq = bary[q, 0] * x0 + bary[q, 1] * x1 + bary[q, 2] * x2
            yq = bary[q, 0] * y0 + bary[q, 1] * y1 + bary[q, 2] * y2
            xi = (xq - xc) / h
            eta = (yq - yc) / h
            quad = c[6] * xi + c[7] * eta
            sx = c[0] + c[1] * xi + c[2] * eta + xi * quad
            sy = c[3] + c[4] * xi + c[5] * eta + eta * quad
            dx = smu * gx + sx / smu
            dy = smu * gy + sy / smu
            acc += weights[q] * (dx * dx + dy * dy)
        out[i, t] = np.sqrt(0.5 * abs(area2) * acc)


@jit
def _estimators_chunk(
    vertices, triangles, diameters, coef, u1, u2, mu1, mu2, bary, weights, out, t0, t1
):
    """Rows t0..t1-1 of :func:`flux_estimators` (written into ``out``)."""
    for t in range(t0, t1):
        _triangle_norms(
            vertices, triangles, diameters, coef, t, u1, u2, mu1, mu2, bary, weights, out, t
        )


def flux_estimators(vertices, triangles, diameters, coef, u1, u2, mu1, mu2, bary, weights):
    """Per-triangle ``|| mu_i^(1/2) grad u_ih + mu_i^(-1/2) sigma_ih ||_K``, shape (2, M).

    ``coef`` (2, M, 8) holds the canonical RT1 coefficients (see :mod:`.rt1`);
    the rule must be exact for degree 4 (the integrand's degree).

    Threading: the triangles in chunks (:mod:`._par`), each writes its own column.
    """
    m = triangles.shape[0]
    out = np.empty((2, m))
    coef, u1, u2, mu1, mu2 = (_writable(a) for a in (coef, u1, u2, mu1, mu2))

    def rows(t0, t1):
        _estimators_chunk(
            vertices, triangles, diameters, coef, u1, u2, mu1, mu2, bary, weights, out, t0, t1
        )

    _par.run_ranges(rows, _par.ranges(m, _par.n_threads(), TRIANGLE_GRAIN))
    return out


# --- the flux estimators in bands of triangles: O(band) flux storage -------------------

#: triangles per band of :func:`flux_norms_banded` (at least; see the next constant).
#: Default scene, n = 1024, two threads, the ring reused, medians of 5: 0.54 s per
#: evaluation with 2^14 against 0.66 s with 2^16 (a ring of 26 MB, beyond the caches)
#: and 0.64 s with 2^13 (twice the hand-offs to the threads)
BAND_TRIANGLES = 1 << 14
#: ... and at least this many per thread, so that each (band, colour) segment keeps
#: every thread busy for a while between hand-offs
BAND_TRIANGLES_PER_THREAD = 8192


@jit
def band_plan(order, color_ptr, patch_ptr, patch_triangles, n_triangles, band):
    """Plan :func:`flux_norms_banded`: bands of ``band`` triangles, each a sweep by colour.

    Vertex a belongs to band ``first(a) // band``, ``first(a)`` the smallest triangle of its
    patch; the patches run band after band, colour by colour within a band (by their
    smallest triangle within a colour).  Triangle t is complete when the band of its
    last vertex is done: after band b every triangle below ``lows[b + 1]`` is.

    Returns ``(seq, seg, lows, ring)``: the vertices in that order, the start of each
    (band, colour) segment of ``seq`` (``seg[b * C + c]``, C colours, B bands), the
    bounds ``lows`` (B + 1) of the triangles completed by each band, and the ring: the
    length of the longest interval of triangle numbers alive at once (written and not
    yet finished), so that ``t % ring`` names distinct rows for them.  Also ``color``
    (int8, per vertex).  O(N + M).
    """
    n = order.shape[0]
    n_colors = color_ptr.shape[0] - 1
    n_bands = max(1, (n_triangles + band - 1) // band)
    color = _vertex_colors(order, color_ptr)
    first, last = _patch_spans(patch_ptr, patch_triangles, n_triangles)
    top = np.full(n_bands, -1, dtype=np.int64)  # the largest triangle a band's patches write
    for a in range(n):
        b = min(first[a] // band, n_bands - 1)
        top[b] = max(top[b], last[a])
    # counting sort by the smallest triangle, then stably by (band, colour)
    by_tri = _by_first_triangle(first, n_triangles)
    seg = np.zeros(n_bands * n_colors + 1, dtype=np.int64)
    for a in range(n):
        seg[min(first[a] // band, n_bands - 1) * n_colors + color[a] + 1] += 1
    for k in range(n_bands * n_colors):
        seg[k + 1] += seg[k]
    slot = seg[:-1].copy()
    seq = np.empty(n, dtype=np.int64)
    for k in range(n):
        a = by_tri[k]
        key = min(first[a] // band, n_bands - 1) * n_colors + color[a]
        seq[slot[key]] = a
        slot[key] += 1
    # lows[b + 1]: the smallest triangle whose last vertex is in a later band than b
    least = np.full(n_bands + 1, n_triangles, dtype=np.int64)
    done = np.zeros(n_triangles, dtype=np.int32)
    for a in range(n):
        b = min(first[a] // band, n_bands - 1)
        for k in range(patch_ptr[a], patch_ptr[a + 1]):
            t = patch_triangles[k]
            done[t] = max(done[t], b)
    for t in range(n_triangles):
        least[done[t]] = min(least[done[t]], t)
    lows = np.empty(n_bands + 1, dtype=np.int64)
    lows[n_bands] = n_triangles
    for b in range(n_bands - 1, -1, -1):  # the smallest triangle completed in band b or later
        lows[b] = min(lows[b + 1], least[b])
    ring = 1
    reach = -1
    for b in range(n_bands):
        reach = max(reach, top[b])
        ring = max(ring, reach + 1 - lows[b])
    return seq, seg, lows, ring, color


@jit
def _band_finish(
    vertices, triangles, diameters, color, win, ring, u1, u2, mu1, mu2, bary, weights, out, t0, t1
):
    """Triangles t0..t1-1 (complete): their flux estimators into ``out``, their rows zeroed.

    The three rows of t in the ring (one per patch, :func:`flux_norms_banded`) are
    summed in the order of their vertices' colours, the order in which
    :func:`reconstruct_colored` adds the patches into one row, so the local dof
    values have the same bits; then the same coefficient map and norms as
    :func:`_coefficients_chunk` and :func:`_estimators_chunk`.
    """
    v = np.empty((2, 8))
    for t in range(t0, t1):
        i0, i1, i2 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        c0, c1, c2 = color[i0], color[i1], color[i2]
        # the local indices by colour: l0 first, l2 last
        if c0 < c1:
            l0, l1 = 0, 1
            lc0, lc1 = c0, c1
        else:
            l0, l1 = 1, 0
            lc0, lc1 = c1, c0
        if c2 < lc0:
            l0, l1, l2 = 2, l0, l1
        elif c2 < lc1:
            l1, l2 = 2, l1
        else:
            l2 = 2
        r = 3 * (t % ring)
        for c in range(2):
            for j in range(8):
                v[c, j] = (win[c, r + l0, j] + win[c, r + l1, j]) + win[c, r + l2, j]
                win[c, r, j] = 0.0
                win[c, r + 1, j] = 0.0
                win[c, r + 2, j] = 0.0
        x0, y0 = vertices[i0, 0], vertices[i0, 1]
        x1, y1 = vertices[i1, 0], vertices[i1, 1]
        x2, y2 = vertices[i2, 0], vertices[i2, 1]
        h = diameters[t]
        rt1_dofs_to_coefficients(x0, y0, x1, y1, x2, y2, i0, i1, i2, h, v, 0)
        rt1_dofs_to_coefficients(x0, y0, x1, y1, x2, y2, i0, i1, i2, h, v, 1)
        _triangle_norms(
            vertices, triangles, diameters, v.reshape((2, 1, 8)), 0, u1, u2, mu1, mu2, bary,
            weights, out, t,
        )  # fmt: skip


def flux_norms_banded(
    plan, bary, weights, *inputs, chi_row=None, chi_mom=None, classes=None, window=None
):
    """Return the flux estimators of :func:`reconstruct_colored`'s fluxes, not storing them.

    ``inputs``: the arguments of :func:`reconstruct_colored` after its colouring
    (``vertices`` ... ``n_threads``), and its keywords; ``bary``, ``weights``: the rule
    of :func:`flux_estimators`.  Returns ``(norms, window)``: ``norms`` (2, M) as
    :func:`flux_estimators` gives them for ``reconstruct_colored(...)`` with the same
    arguments, bit for bit, and the ring of rows to pass again as ``window`` (all zero
    again on return).

    ``plan``: :func:`band_plan` of the colouring.  The patches run band after band
    (colour by colour within a band, threads as in :func:`reconstruct_colored`); each
    writes its own row of each of its triangles in a ring of ``3 ring`` rows (the patch
    kernels' ``slots`` 3).  When a band is done, its completed triangles are summed
    (:func:`_band_finish`, in parallel, :data:`FINISH_PIECES` pieces per thread), their
    norms written and their rows cleared.
    The ring holds 48 doubles per live triangle, against 16 per triangle of the
    mesh for the stored fluxes; a mesh whose patches span far apart triangle numbers
    gives a ring as large as the mesh (the caller then stores the fluxes instead).
    """
    seq, seg, lows, ring, color = plan
    vertices, triangles, diameters = inputs[:3]
    m = triangles.shape[0]
    threads = max(1, int(inputs[-1]))
    n_bands = lows.shape[0] - 1
    n_colors = (seg.shape[0] - 1) // n_bands
    if window is None or window.shape != (2, 3 * ring, 8):
        window = np.zeros((2, 3 * ring, 8))
    run, args = _patch_runner(seq, inputs, chi_row, chi_mom, classes)
    u1, u2, mu1, mu2 = args[9], args[10], args[14], args[15]  # (made writable there)
    # first touched here by the pool's threads, not inside the bands: the piece that first
    # wrote each new (huge) page of it took 9 ms against 0.5 ms (n = 2048, 16 threads)
    norms = _par.zeros((2, m), np.float64)
    finish = functools.partial(
        _band_finish, vertices, triangles, diameters, color, window, int(ring), u1, u2, mu1,
        mu2, bary, weights, norms,
    )  # fmt: skip
    for b in range(n_bands):
        for c in range(n_colors):
            lo, hi = int(seg[b * n_colors + c]), int(seg[b * n_colors + c + 1])
            if hi > lo:
                run(window, int(ring), 3, lo, hi)
        t0, t1 = int(lows[b]), int(lows[b + 1])
        pieces = _par.ranges(t1 - t0, FINISH_PIECES * threads, TRIANGLE_GRAIN)
        _par.run_pieces(finish, [(t0 + a, t0 + c) for a, c in pieces], threads)
    return norms, window
