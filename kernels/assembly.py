"""P1 element kernels: local matrices as COO values and their gather into CSR.

Local matrices are computed per triangle in parallel into a preallocated
``(M, 3, 3)`` array (each triangle owns its slot, so no atomics).  The gather
into CSR runs in parallel over rows: row ``a`` is written only by the thread
that owns vertex ``a``, which visits the triangles of the patch of ``a``
(CSR ``patch_ptr``/``patch_triangles``/``patch_local``) and adds their row
``patch_local`` through the position map of :mod:`.sparsity`.  The result is
bitwise independent of the thread count.

Meshes of fewer than :data:`fastmem.kernels.topology.NUMPY_BELOW` triangles
assemble the stiffness and mass matrices with NumPy (:func:`stiffness_csr`,
:func:`mass_csr`) until the kernel is in the process
(:func:`fastmem.kernels.topology.numpy_path`): the same operations in the same
order, so the same bits, and no kernel compiled for a small first run.

Each kernel is a serial Numba loop over an index range (``_name_range(lo, hi,
...)``) run in chunks by Python threads (:mod:`._par`), not a ``prange``
loop: the same arithmetic, a fraction of the compile time.
"""

import numpy as np

from ._jit import jit
from .pool import parallel_for
from .topology import numpy_path

__all__ = [
    "area2_and_diameter2",
    "quadrature_points",
    "gather_csr",
    "mass_csr",
    "stiffness_csr",
    "gather_vector",
    "load_block",
    "mass_local",
    "stiffness_local",
]


def area2_and_diameter2(vertices, triangles):
    """Twice the signed area and the squared diameter (longest edge) of every triangle.

    One pass over the triangles, no temporaries (the NumPy expression allocated
    six (M, 3, 2) arrays: 4.2 s of the 9 s ``Mesh.square(2048)``).

    Returns
    -------
    area2 : float64 (M,)
        ``(p1 - p0) x (p2 - p0)``: positive for counter-clockwise triangles.
    h2 : float64 (M,)
        ``max_e |e|^2`` over the three edges.
    """
    m = triangles.shape[0]
    area2 = np.empty(m)
    h2 = np.empty(m)
    parallel_for(_area2_and_diameter2_range, m, vertices, triangles, area2, h2)
    return area2, h2


def quadrature_points(vertices, triangles, bary, parallel=True):
    """Physical quadrature points ``x[k, q] = sum_j bary[q, j] x_(triangles[k, j])``, and y.

    One pass over the triangles in parallel chunks, no temporaries (the NumPy
    gather ``vertices[triangles]`` and two products took 1.4 s of a 7 s
    manufactured-scene estimate at n = 1024, cProfile).  Returns two float64
    (M, nq) arrays.  ``parallel=False``: in the calling thread only (a caller
    whose other thread is busy, :func:`fastmem.fem.callables.integrals`).
    """
    m = triangles.shape[0]
    x = np.empty((m, bary.shape[0]))
    y = np.empty((m, bary.shape[0]))
    if parallel:
        parallel_for(_quadrature_points_range, m, vertices, triangles, bary, x, y)
    else:
        _quadrature_points_range(0, m, vertices, triangles, bary, x, y)
    return x, y


@jit
def _quadrature_points_range(lo, hi, vertices, triangles, bary, x, y):
    nq = bary.shape[0]
    for k in range(lo, hi):
        i0, i1, i2 = triangles[k, 0], triangles[k, 1], triangles[k, 2]
        x0, y0 = vertices[i0, 0], vertices[i0, 1]
        x1, y1 = vertices[i1, 0], vertices[i1, 1]
        x2, y2 = vertices[i2, 0], vertices[i2, 1]
        for q in range(nq):
            b0, b1, b2 = bary[q, 0], bary[q, 1], bary[q, 2]
            x[k, q] = b0 * x0 + b1 * x1 + b2 * x2
            y[k, q] = b0 * y0 + b1 * y1 + b2 * y2


@jit
def _area2_and_diameter2_range(lo, hi, vertices, triangles, area2, h2):
    for k in range(lo, hi):
        i0, i1, i2 = triangles[k, 0], triangles[k, 1], triangles[k, 2]
        x0, y0 = vertices[i0, 0], vertices[i0, 1]
        ax, ay = vertices[i1, 0] - x0, vertices[i1, 1] - y0
        bx, by = vertices[i2, 0] - x0, vertices[i2, 1] - y0
        area2[k] = ax * by - bx * ay
        cx, cy = bx - ax, by - ay
        h2[k] = max(ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy)


def stiffness_local(vertices, triangles, coef):
    """Local P1 stiffness matrices ``coef_K |K| grad(phi_j) . grad(phi_i)``.

    Parameters
    ----------
    vertices : float64 (N, 2)
    triangles : int64 (M, 3), counter-clockwise
    coef : float64 (M,) or (1,)
        Per-triangle coefficient, or one value for all.

    Returns
    -------
    vals : float64 (M, 3, 3)

    Threading: parallel over triangles, each writes ``vals[t]`` only.
    """
    m = triangles.shape[0]
    vals = np.empty((m, 3, 3))
    parallel_for(_stiffness_local_range, m, vertices, triangles, coef, vals)
    return vals


@jit
def _stiffness_local_range(lo, hi, vertices, triangles, coef, vals):
    const = coef.shape[0] == 1
    for t in range(lo, hi):
        i0, i1, i2 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        x0, y0 = vertices[i0, 0], vertices[i0, 1]
        x1, y1 = vertices[i1, 0], vertices[i1, 1]
        x2, y2 = vertices[i2, 0], vertices[i2, 1]
        # edge vectors opposite each vertex; grad(phi_i) = rot(e_i) / (2|K|)
        ex0, ey0 = x2 - x1, y2 - y1
        ex1, ey1 = x0 - x2, y0 - y2
        ex2, ey2 = x1 - x0, y1 - y0
        area2 = ex2 * (-ey1) - (-ex1) * ey2  # (p1-p0) x (p2-p0)
        c = coef[0] if const else coef[t]
        s = c / (2.0 * area2)  # |K| / (2|K|)^2 = 1 / (2 * area2)
        # A_ij = |K| grad phi_i . grad phi_j = (e_i . e_j) / (4|K|)
        vals[t, 0, 0] = s * (ex0 * ex0 + ey0 * ey0)
        vals[t, 1, 1] = s * (ex1 * ex1 + ey1 * ey1)
        vals[t, 2, 2] = s * (ex2 * ex2 + ey2 * ey2)
        a01 = s * (ex0 * ex1 + ey0 * ey1)
        a02 = s * (ex0 * ex2 + ey0 * ey2)
        a12 = s * (ex1 * ex2 + ey1 * ey2)
        vals[t, 0, 1] = a01
        vals[t, 1, 0] = a01
        vals[t, 0, 2] = a02
        vals[t, 2, 0] = a02
        vals[t, 1, 2] = a12
        vals[t, 2, 1] = a12


def mass_local(areas, coef):
    """Local consistent P1 mass matrices ``coef_K |K| / 12 (1 + delta_ij)``, shape (M, 3, 3)."""
    m = areas.shape[0]
    vals = np.empty((m, 3, 3))
    parallel_for(_mass_local_range, m, areas, coef, vals)
    return vals


@jit
def _mass_local_range(lo, hi, areas, coef, vals):
    const = coef.shape[0] == 1
    for t in range(lo, hi):
        c = (coef[0] if const else coef[t]) * areas[t] / 12.0
        for i in range(3):
            for j in range(3):
                vals[t, i, j] = c
            vals[t, i, i] = 2.0 * c


def gather_csr(vals, indptr, offsets, patch_ptr, patch_triangles, patch_local):
    """Sum local matrices into the CSR data array of the vertex-graph pattern.

    Parameters
    ----------
    vals : float64 (M, 3, 3)
        Local matrices (COO values, entry ``(t, i, j)`` at row ``triangles[t, i]``,
        column ``triangles[t, j]``).
    indptr : int32 or int64 (N + 1,)
    offsets : uint16 (M, 3, 3)
        Position map from :func:`fastmem.kernels.sparsity.position_map`.
    patch_ptr, patch_triangles, patch_local : int64
        Vertex patches in CSR form.

    Returns
    -------
    data : float64 (nnz,)

    Threading: parallel over rows; row ``a`` is written only by its owner.
    """
    n = patch_ptr.shape[0] - 1
    data = np.zeros(indptr[n])
    parallel_for(
        _gather_csr_range, n, vals, indptr, offsets, patch_ptr, patch_triangles, patch_local, data
    )
    return data


@jit
def _gather_csr_range(lo, hi, vals, indptr, offsets, patch_ptr, patch_triangles, patch_local, data):
    for a in range(lo, hi):
        base = indptr[a]
        for p in range(patch_ptr[a], patch_ptr[a + 1]):
            t = patch_triangles[p]
            i = patch_local[p]
            for j in range(3):
                data[base + offsets[t, i, j]] += vals[t, i, j]


def gather_vector(local, patch_ptr, patch_triangles, patch_local):
    """Sum per-triangle local vectors (M, 3) into a nodal vector (N,).

    Threading: parallel over vertices; entry ``a`` is written only by its owner.
    """
    n = patch_ptr.shape[0] - 1
    out = np.zeros(n)
    parallel_for(_gather_vector_range, n, local, patch_ptr, patch_triangles, patch_local, out)
    return out


@jit
def _gather_vector_range(lo, hi, local, patch_ptr, patch_triangles, patch_local, out):
    for a in range(lo, hi):
        s = 0.0
        for p in range(patch_ptr[a], patch_ptr[a + 1]):
            s += local[patch_triangles[p], patch_local[p]]
        out[a] = s


@jit
def load_block(fv, w, bary, outer, areas, start, local, mom, norm):
    """Integrals of one block of callable values: load vector parts, moments, oscillation.

    ``fv[k, q]``: the values at the ``nq`` points of the rule (``bary`` (nq, 3),
    weights ``w`` summing to one) of triangle ``start + k``.  Writes row ``start + k``
    of ``local`` (M, 3), ``(f, lambda_j)_K``, and, when ``norm`` is not empty, of
    ``mom`` (M, 3, 3), ``int_K f lambda_i lambda_j`` (``outer[q, 3 i + j] = bary[q, i]
    bary[q, j]``), and ``norm`` (M,), ``||f - Pi_K f||_K``.  The L2(K) projection onto P1
    has the coefficients ``12 a_j - 3 sum(a)`` of the means ``a_j = (f, lambda_j)_K / |K|``
    (the inverse of the P1 mass matrix); the squares of ``f - Pi_K f`` are summed at the
    points in units of ``max_q |f|`` on K (no cancellation, no overflow near the float
    range).  One pass over the block in cache: the NumPy expressions of the same sums
    took 6x longer (a block of 2^13 triangles, 7 points).
    """
    nq = fv.shape[1]
    want_all = norm.shape[0] > 0
    fw = np.empty(nq)
    acc = np.empty(9)
    for k in range(fv.shape[0]):
        t = start + k
        a = areas[t]
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        for q in range(nq):
            v = fv[k, q] * w[q]
            fw[q] = v
            s0 += v * bary[q, 0]
            s1 += v * bary[q, 1]
            s2 += v * bary[q, 2]
        local[t, 0] = s0 * a
        local[t, 1] = s1 * a
        local[t, 2] = s2 * a
        if not want_all:
            continue
        for r in range(9):
            acc[r] = 0.0
        for q in range(nq):
            v = fw[q]
            for r in range(9):
                acc[r] += v * outer[q, r]
        for i in range(3):
            for j in range(3):
                mom[t, i, j] = acc[3 * i + j] * a
        scale = 0.0
        for q in range(nq):
            x = abs(fv[k, q])
            if x > scale:
                scale = x
        if scale == 0.0:
            scale = 1.0
        a0 = s0 / scale
        a1 = s1 / scale
        a2 = s2 / scale
        tot = a0 + a1 + a2
        c0 = 12.0 * a0 - 3.0 * tot
        c1 = 12.0 * a1 - 3.0 * tot
        c2 = 12.0 * a2 - 3.0 * tot
        ss = 0.0
        for q in range(nq):
            d = fv[k, q] / scale - (c0 * bary[q, 0] + c1 * bary[q, 1] + c2 * bary[q, 2])
            ss += d * d * w[q]
        norm[t] = scale * np.sqrt(ss * a)


def stiffness_csr(
    vertices, triangles, coef, indptr, offsets, patch_ptr, patch_triangles, patch_local
):
    """P1 stiffness straight into CSR data: the local kernel fused with the row gather.

    Row ``a`` visits the triangles of its patch and adds row ``i`` (the local
    index of ``a``) of each local matrix, recomputed on the fly; nothing of
    size (M, 3, 3) is stored.  Same arithmetic as :func:`stiffness_local`.

    Threading: parallel over rows; row ``a`` is written only by its owner.
    Small meshes: :func:`_csr_numpy`, the same bits.
    """
    n = patch_ptr.shape[0] - 1
    if numpy_path(triangles.shape[0], _stiffness_csr_range):
        return _csr_numpy(
            _stiffness_rows(vertices, triangles, coef),
            indptr,
            offsets,
            patch_ptr,
            patch_triangles,
            patch_local,
        )
    data = np.zeros(indptr[n])
    parallel_for(
        _stiffness_csr_range,
        n,
        vertices,
        triangles,
        coef,
        indptr,
        offsets,
        patch_ptr,
        patch_triangles,
        patch_local,
        data,
    )
    return data


@jit
def _stiffness_csr_range(
    lo,
    hi,
    vertices,
    triangles,
    coef,
    indptr,
    offsets,
    patch_ptr,
    patch_triangles,
    patch_local,
    data,
):
    const = coef.shape[0] == 1
    for a in range(lo, hi):
        base = indptr[a]
        for p in range(patch_ptr[a], patch_ptr[a + 1]):
            t = patch_triangles[p]
            i = patch_local[p]
            i0, i1, i2 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
            x0, y0 = vertices[i0, 0], vertices[i0, 1]
            x1, y1 = vertices[i1, 0], vertices[i1, 1]
            x2, y2 = vertices[i2, 0], vertices[i2, 1]
            ex0, ey0 = x2 - x1, y2 - y1
            ex1, ey1 = x0 - x2, y0 - y2
            ex2, ey2 = x1 - x0, y1 - y0
            area2 = ex2 * (-ey1) - (-ex1) * ey2
            c = coef[0] if const else coef[t]
            s = c / (2.0 * area2)
            if i == 0:
                exi, eyi = ex0, ey0
            elif i == 1:
                exi, eyi = ex1, ey1
            else:
                exi, eyi = ex2, ey2
            data[base + offsets[t, i, 0]] += s * (exi * ex0 + eyi * ey0)
            data[base + offsets[t, i, 1]] += s * (exi * ex1 + eyi * ey1)
            data[base + offsets[t, i, 2]] += s * (exi * ex2 + eyi * ey2)


def mass_csr(areas, coef, indptr, offsets, patch_ptr, patch_triangles, patch_local):
    """Consistent P1 mass straight into CSR data (fused kernel and gather, as stiffness_csr)."""
    n = patch_ptr.shape[0] - 1
    if numpy_path(areas.shape[0], _mass_csr_range):
        return _csr_numpy(
            _mass_rows(areas, coef), indptr, offsets, patch_ptr, patch_triangles, patch_local
        )
    data = np.zeros(indptr[n])
    parallel_for(
        _mass_csr_range,
        n,
        areas,
        coef,
        indptr,
        offsets,
        patch_ptr,
        patch_triangles,
        patch_local,
        data,
    )
    return data


@jit
def _mass_csr_range(
    lo, hi, areas, coef, indptr, offsets, patch_ptr, patch_triangles, patch_local, data
):
    const = coef.shape[0] == 1
    for a in range(lo, hi):
        base = indptr[a]
        for p in range(patch_ptr[a], patch_ptr[a + 1]):
            t = patch_triangles[p]
            i = patch_local[p]
            c = (coef[0] if const else coef[t]) * areas[t] / 12.0
            for j in range(3):
                data[base + offsets[t, i, j]] += 2.0 * c if j == i else c


def _stiffness_rows(vertices, triangles, coef):
    """Local stiffness matrices (M, 3, 3), with :func:`_stiffness_csr_range`'s operations."""
    x = vertices[triangles, 0]
    y = vertices[triangles, 1]
    ex = x[:, [2, 0, 1]] - x[:, [1, 2, 0]]  # edge i opposite vertex i: e0 = x2 - x1, ...
    ey = y[:, [2, 0, 1]] - y[:, [1, 2, 0]]
    area2 = ex[:, 2] * (-ey[:, 1]) - (-ex[:, 1]) * ey[:, 2]
    c = coef[0] if coef.shape[0] == 1 else coef
    s = c / (2.0 * area2)
    return s[:, None, None] * (ex[:, :, None] * ex[:, None, :] + ey[:, :, None] * ey[:, None, :])


def _mass_rows(areas, coef):
    """Local mass matrices (M, 3, 3), with :func:`_mass_csr_range`'s operations."""
    # (the kernel's "/ 12.0" compiles to a product with the reciprocal: fastmath "arcp")
    c = (coef[0] if coef.shape[0] == 1 else coef) * areas * (1.0 / 12.0)
    local = np.repeat(c, 9).reshape(-1, 3, 3)
    local[:, [0, 1, 2], [0, 1, 2]] = 2.0 * c[:, None]
    return local


def _csr_numpy(local, indptr, offsets, patch_ptr, patch_triangles, patch_local):
    """Sum the local matrices' rows into CSR data as the fused kernels do.

    Row ``a`` adds row ``patch_local[p]`` of triangle ``patch_triangles[p]`` for
    ``p`` in its patch, in that order: ``np.bincount`` sums in the order of its
    input, so every entry is the same sum, term for term, as the kernel's.
    """
    n = patch_ptr.shape[0] - 1
    owner = np.repeat(np.arange(n, dtype=np.int64), np.diff(patch_ptr))
    t = patch_triangles.astype(np.int64)
    i = patch_local.astype(np.int64)
    positions = indptr[owner].astype(np.int64)[:, None] + offsets[t, i, :]
    return np.bincount(positions.ravel(), weights=local[t, i, :].ravel(), minlength=int(indptr[n]))
