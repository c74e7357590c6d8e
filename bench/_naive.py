"""The naive baseline: the active-set loop a Python user would write with scipy.

Coupled system in all three unknowns ``(u1, u2, lam)`` (3N x 3N, one row
block per unknown), assembled with :func:`scipy.sparse.bmat` and solved with
:func:`scipy.sparse.linalg.spsolve` at every step (docs/method.md §2 and 3.1)::

    interior a:   mu1 (A u1)_a - B_a lam_a = F1_a
                  mu2 (A u2)_a + B_a lam_a = F2_a
                  u1_a - u2_a = 0   if a is active,   lam_a = 0   otherwise
    boundary a:   u1_a = g_a,  u2_a = 0,  lam_a = 0

The active set of the next step is ``{a interior : lam_a > c (u1_a - u2_a)}``
(primal-dual active set = Newton-min); the loop starts from zero (empty
active set) and stops when the active set repeats the previous one.  Nothing
is reused between steps: the user rebuilds the block matrix and calls the
direct solver again.  It only reads the stiffness matrix, lumped mass and
load vectors from the scene, so that both codes solve the same discrete problem.
"""

import time

import numpy as np


def naive_active_set(scene, max_steps=500):
    """Solve the discrete contact problem the naive way; return a dict with the triple and stats."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    mesh = scene.mesh
    n = mesh.n_vertices
    bnd = mesh.boundary_vertex_mask
    inner = ~bnd
    c = scene.active_c
    b = mesh.lumped_mass
    f1, f2 = scene.loads
    g = scene.boundary_values
    # Dirichlet rows: keep the interior rows of mu_i A, put identity rows on the boundary
    keep = sp.diags(inner.astype(float))
    ident_b = sp.diags(bnd.astype(float))
    k1 = (keep @ scene.weighted_stiffness(1) + ident_b).tocsr()
    k2 = (keep @ scene.weighted_stiffness(2) + ident_b).tocsr()
    b_in = sp.diags(np.where(inner, b, 0.0))
    rhs = np.concatenate([np.where(inner, f1, g), np.where(inner, f2, 0.0), np.zeros(n)])

    active = np.zeros(n, dtype=bool)
    seen = {active.tobytes()}
    steps = []
    converged = cycled = False
    u1 = u2 = lam = None
    for _ in range(max_steps):
        t0 = time.perf_counter()
        on = sp.diags(active.astype(float))
        off = sp.diags((~active).astype(float))
        system = sp.bmat([[k1, None, -b_in], [None, k2, b_in], [on, -on, off]], format="csc")
        t1 = time.perf_counter()
        x = spsolve(system, rhs)
        t2 = time.perf_counter()
        u1, u2, lam = x[:n], x[n : 2 * n], x[2 * n :]
        new_active = inner & (lam > c * (u1 - u2))
        steps.append({"n_active": int(active.sum()), "build_s": t1 - t0, "spsolve_s": t2 - t1})
        if np.array_equal(new_active, active):
            converged = True
            break
        key = new_active.tobytes()
        if key in seen:  # an earlier active set again: the loop would cycle forever
            cycled = True
            break
        seen.add(key)
        active = new_active
    gap = (u1 - u2)[inner]
    return {
        "u1": u1,
        "u2": u2,
        "lam": lam,
        "active": active,
        "steps": len(steps),
        "converged": converged,
        "cycled": cycled,
        "build_s": float(sum(s["build_s"] for s in steps)),
        "spsolve_s": float(sum(s["spsolve_s"] for s in steps)),
        "unknowns": 3 * n,
        "complementarity": float(np.abs(np.minimum(gap, lam[inner])).max()),
    }
