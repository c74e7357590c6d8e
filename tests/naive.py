"""Slow, plain NumPy/SciPy references for the kernels and solvers (small meshes only).

Written independently of the package: local P1 quantities come from inverting
the 3x3 Vandermonde matrix of each triangle, sums are dense or LIL, and the
contact problem is solved on the full coupled 3N x 3N system.
"""

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


def _local_basis(p):
    """Coefficients (a, b, c) of phi_i = a + b x + c y on triangle with vertices p (3, 2)."""
    vand = np.column_stack([np.ones(3), p])
    return np.linalg.inv(vand)  # column i = coefficients of phi_i


def stiffness(vertices, triangles, coef=None):
    n = len(vertices)
    mat = sp.lil_matrix((n, n))
    for k, tri in enumerate(triangles):
        p = vertices[tri]
        coefs = _local_basis(p)
        grads = coefs[1:, :].T  # (3, 2)
        area = 0.5 * abs(np.linalg.det(np.column_stack([np.ones(3), p])))
        c = 1.0 if coef is None else coef[k]
        local = c * area * grads @ grads.T
        for i in range(3):
            for j in range(3):
                mat[tri[i], tri[j]] += local[i, j]
    return mat.tocsr()


def mass(vertices, triangles):
    """Consistent mass with the edge-midpoint rule (exact for quadratics)."""
    n = len(vertices)
    mat = sp.lil_matrix((n, n))
    for tri in triangles:
        p = vertices[tri]
        coefs = _local_basis(p)
        area = 0.5 * abs(np.linalg.det(np.column_stack([np.ones(3), p])))
        mids = 0.5 * (p[[0, 1, 2]] + p[[1, 2, 0]])
        phi = np.column_stack([np.ones(3), mids]) @ coefs  # (3 points, 3 functions)
        local = area / 3.0 * phi.T @ phi
        for i in range(3):
            for j in range(3):
                mat[tri[i], tri[j]] += local[i, j]
    return mat.tocsr()


def load(vertices, triangles, f, bary, weights):
    n = len(vertices)
    out = np.zeros(n)
    for tri in triangles:
        p = vertices[tri]
        area = 0.5 * abs(np.linalg.det(np.column_stack([np.ones(3), p])))
        x = bary @ p
        fv = np.array([f(np.array([xx]), np.array([yy]))[0] for xx, yy in x])
        for i in range(3):
            out[tri[i]] += area * np.sum(weights * fv * bary[:, i])
    return out


def contact_solve(vertices, triangles, mu1, mu2, f1, f2, g, c=1.0, max_iter=500):
    """Primal-dual active set on the full coupled system (u1, u2, lam), dense-ish.

    f1, f2 are load vectors (already integrated); g is a scalar boundary value.
    Returns u1, u2, lam and the number of iterations.
    """
    n = len(vertices)
    a = stiffness(vertices, triangles)
    area = np.zeros(n)
    for tri in triangles:
        p = vertices[tri]
        area[tri] += 0.5 * abs(np.linalg.det(np.column_stack([np.ones(3), p]))) / 3.0
    # boundary vertices: edges used by one triangle
    edges = {}
    for tri in triangles:
        for i in range(3):
            e = tuple(sorted((tri[i], tri[(i + 1) % 3])))
            edges[e] = edges.get(e, 0) + 1
    bnd = np.zeros(n, dtype=bool)
    for e, cnt in edges.items():
        if cnt == 1:
            bnd[list(e)] = True
    u1 = np.where(bnd, g, 0.0)
    u2 = np.zeros(n)
    lam = np.zeros(n)
    active = np.zeros(n, dtype=bool)
    for it in range(1, max_iter + 1):
        big = sp.lil_matrix((3 * n, 3 * n))
        b = np.zeros(3 * n)
        ad = a.toarray()
        for v in range(n):
            if bnd[v]:
                big[v, v] = 1.0
                b[v] = g
                big[n + v, n + v] = 1.0
                big[2 * n + v, 2 * n + v] = 1.0
                continue
            big[v, :n] = mu1 * ad[v]
            big[v, 2 * n + v] = -area[v]
            b[v] = f1[v]
            big[n + v, n : 2 * n] = mu2 * ad[v]
            big[n + v, 2 * n + v] = area[v]
            b[n + v] = f2[v]
            if active[v]:
                big[2 * n + v, v] = 1.0
                big[2 * n + v, n + v] = -1.0
            else:
                big[2 * n + v, 2 * n + v] = 1.0
        x = spla.spsolve(big.tocsc(), b)
        u1, u2, lam = x[:n], x[n : 2 * n], x[2 * n :]
        new_active = (~bnd) & (lam > c * (u1 - u2))
        if np.array_equal(new_active, active):
            return u1, u2, lam, it
        active = new_active
    raise RuntimeError("naive contact solve did not converge")
