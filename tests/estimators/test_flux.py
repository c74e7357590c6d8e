"""Equilibrated flux reconstruction (MATH.md section 4): package kernel vs naive reference.

The reference ``naive_flux`` solves every patch problem with 8 free canonical
coefficients per triangle, explicit normal-flux constraints and a dense KKT
system; the package (``fastmem.estimators.flux``) must agree with it to round-off, and
both must be H(div)-conforming and equilibrated.
"""

import functools

import naive_flux
import numpy as np
import pytest
from meshes import circle_mesh, perturbed_square

import fastmem as fm
import fastmem.estimators.flux as flux
from fastmem.fem.quadrature import triangle_rule
from fastmem.fem.residual import residuals

# ----------------------------------------------------------------------------- data


def _circle():
    return circle_mesh(2)


MESH_BUILDERS = {
    "square4": lambda: fm.Mesh.square(4),
    "square8": lambda: fm.Mesh.square(8),
    "square5-right": lambda: fm.Mesh.square(5, diagonal="right"),
    "perturbed": lambda: perturbed_square(6, 0.3),
    "lshape": lambda: fm.Mesh.lshape(4),
    "circle": _circle,
}
MESHES = list(MESH_BUILDERS)


def f1_callable(x, y):
    return -1.0 - x * y + 0.3 * np.sin(3.0 * x)


def f2_callable(x, y):
    return 1.0 + 0.5 * np.cos(2.0 * y) * x


@functools.cache
def get_mesh(name):
    return MESH_BUILDERS[name]()


def _perturb(mesh, u1, u2, lam, seed=7, amount=0.05):
    """Add noise at interior vertices: R != 0, lam of both signs, gap of both signs."""
    rng = np.random.default_rng(seed)
    inner = mesh.interior_vertices
    u1, u2, lam = u1.copy(), u2.copy(), lam.copy()
    u1[inner] += amount * rng.standard_normal(inner.size)
    u2[inner] += amount * rng.standard_normal(inner.size)
    lam[inner] += 0.5 * rng.standard_normal(inner.size)
    return u1, u2, lam


def _mu_per_triangle(mesh, base, amp, seed):
    """Piecewise-constant tension with values in base * [1 - amp, 1 + amp]."""
    rng = np.random.default_rng(seed)
    return base * (1.0 + amp * rng.uniform(-1.0, 1.0, mesh.n_triangles))


def _nodal(func):
    """Mark a load given as per-vertex (P1) values of ``func``."""
    return ("nodal", func)


DATASETS = {
    # name: (mu, f, perturb); mu may be a callable(mesh) giving per-triangle values
    "default": ((1.0, 1.0), (-1.0, 1.0), False),
    "mu1-10": ((1.0, 10.0), (-1.0, 1.0), False),
    "callable": ((1.0, 10.0), (f1_callable, f2_callable), False),
    "perturbed": ((1.0, 1.0), (-1.0, 1.0), True),
    "perturbed-callable": ((3.0, 0.5), (f1_callable, f2_callable), True),
    # beyond the constant-mu scope: P1 (per-vertex) loads and per-triangle tensions
    "nodal-f": ((1.0, 2.0), (_nodal(f1_callable), _nodal(f2_callable)), False),
    "perturbed-mu-per-triangle": (
        lambda mesh: (_mu_per_triangle(mesh, 1.0, 0.5, 1), _mu_per_triangle(mesh, 4.0, 0.5, 2)),
        (-1.0, _nodal(f2_callable)),
        True,
    ),
}
DATA = list(DATASETS)


def _load(f, mesh):
    if isinstance(f, tuple) and f[0] == "nodal":
        return f[1](*mesh.vertices.T)
    return f


@functools.cache
def case(mesh_name, data_name):
    """(scene, u1, u2, lam, r1, r2, (ref1, ref2), patches) for one mesh and data set."""
    mesh = get_mesh(mesh_name)
    mu, f, perturb = DATASETS[data_name]
    mu = mu(mesh) if callable(mu) else mu
    scene = fm.Scene(mesh, mu=mu, f=tuple(_load(fi, mesh) for fi in f), g=0.1)
    sol = fm.solve(scene, method="exact")
    assert sol.converged
    u1, u2, lam = sol.u1, sol.u2, sol.lam
    if perturb:
        u1, u2, lam = _perturb(mesh, u1, u2, lam)
    r1, r2 = residuals(scene, u1, u2, lam)
    c1, c2, patches = naive_flux.naive_reconstruct(scene, u1, u2, lam, r1, r2, return_patches=True)
    return scene, u1, u2, lam, r1, r2, (c1, c2), patches


@functools.cache
def package(mesh_name, data_name):
    """The package's fluxes with the contact load lam_a psi_a of MATH.md section 4.

    (The default redistributes the contact load between membranes of unequal
    tension on closed-contact patches; tests/test_weighted_flux.py covers it.)
    """
    scene, u1, u2, lam, r1, r2, _, _ = case(mesh_name, data_name)
    return flux.reconstruct(scene, u1, u2, lam, r1, r2, redistribute=False)


ALL_CASES = [(m, d) for m in MESHES for d in DATA]


def _rel(a, b):
    return np.abs(a - b).max() / max(np.abs(b).max(), 1e-300)


# ------------------------------------------------------------------------- helpers


def _edge_points(mesh, ts=(0.0, 0.5, 1.0)):
    """Interior edges: points along them, both neighbours, unit normals."""
    inner = np.flatnonzero(mesh.edge_triangles[:, 1] >= 0)
    p0 = mesh.vertices[mesh.edges[inner, 0]]
    p1 = mesh.vertices[mesh.edges[inner, 1]]
    tvec = p1 - p0
    normal = np.stack([tvec[:, 1], -tvec[:, 0]], axis=1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    pts = np.concatenate([p0 + t * tvec for t in ts])
    k = len(ts)
    return (
        pts,
        np.tile(mesh.edge_triangles[inner, 0], k),
        np.tile(mesh.edge_triangles[inner, 1], k),
        np.tile(normal, (k, 1)),
    )


def _normal_jump(evaluate, mesh):
    """max |sigma_L.n - sigma_R.n| over interior-edge points, and max |sigma| there."""
    pts, tl, tr, n = _edge_points(mesh)
    sl = evaluate(tl, pts[:, 0], pts[:, 1])
    sr = evaluate(tr, pts[:, 0], pts[:, 1])
    jump = np.abs(((sl - sr) * n).sum(axis=1)).max()
    scale = max(np.abs(sl).max(), np.abs(sr).max())
    return jump, scale


def _quad_points(mesh, bary):
    corners = mesh.vertices[mesh.triangles]  # (M, 3, 2)
    return np.einsum("qk,mkc->mqc", bary, corners)  # (M, Q, 2)


def _equilibration_defect(scene, lam, r, i, divergence):
    """Per triangle and q in P1(K): int_K (Pi f +- lam_h - rho - div sigma) q, and the scale.

    ``divergence(tri, x, y)`` evaluates div sigma_ih.  Returns (max defect, max term).
    """
    mesh = scene.mesh
    m = mesh.n_triangles
    f = scene.f1 if i == 0 else scene.f2
    sgn = 1.0 if i == 0 else -1.0
    bary, w = naive_flux.QUAD_BARY, naive_flux.QUAD_W  # degree 8, ample for P1 x P1
    area = mesh.areas
    pts = _quad_points(mesh, bary)
    tri = np.repeat(np.arange(m), len(w))
    div = divergence(tri, pts[..., 0].ravel(), pts[..., 1].ravel()).reshape(m, -1)
    lam_h = lam[mesh.triangles] @ bary.T  # (M, Q)
    rho = (r / mesh.lumped_mass)[mesh.triangles] @ bary.T
    terms = [(area[:, None] * (w * v)) @ bary for v in (sgn * lam_h, -rho, -div)]  # each (M, 3)
    if callable(f):
        bq, wq = triangle_rule(scene.load_degree)
        pf = _quad_points(mesh, bq)
        fv = f(pf[..., 0], pf[..., 1])
        terms.append((area[:, None] * (wq * fv)) @ bq)
    elif np.ndim(f) == 0:
        terms.append(np.outer(area, np.full(3, float(f) / 3.0)))
    else:  # P1 data: Pi_K f = f
        fq = np.asarray(f)[mesh.triangles] @ bary.T
        terms.append((area[:, None] * (w * fq)) @ bary)
    total = sum(terms)
    scale = max(np.abs(t).max() for t in terms)
    return np.abs(total).max(), scale


def _naive_eval(mesh, coef):
    return lambda tri, x, y: naive_flux.evaluate(mesh, coef, tri, x, y)


def _naive_div(mesh, coef):
    return lambda tri, x, y: naive_flux.divergence(mesh, coef, tri, x, y)


# ----------------------------------------------------------------- reference alone


@pytest.mark.parametrize("mesh_name", MESHES)
def test_reference_reproduces_linear_flux(mesh_name):
    """f = 0, lam = 0, linear u: A u = 0 at interior vertices, so sigma = -mu grad u exactly."""
    mesh = get_mesh(mesh_name)
    x, y = mesh.vertices.T
    scene = fm.Scene(mesh, mu=(2.0, 0.5), f=(0.0, 0.0), g=0.1)
    u1 = 0.3 + 0.2 * x - 0.1 * y
    u2 = -0.1 + 0.5 * x + 0.7 * y
    lam = np.zeros_like(x)
    c1, c2 = naive_flux.naive_reconstruct(scene, u1, u2, lam)
    for coef, mu, grad in ((c1, 2.0, (0.2, -0.1)), (c2, 0.5, (0.5, 0.7))):
        expect = np.zeros_like(coef)
        expect[:, 0] = -mu * grad[0]
        expect[:, 3] = -mu * grad[1]
        assert np.abs(coef - expect).max() <= 1e-12 * mu * np.abs(grad).max()


@pytest.mark.parametrize("mesh_name", MESHES)
@pytest.mark.parametrize("data_name", ["default", "perturbed-callable"])
def test_reference_patch_zero_flux(mesh_name, data_name):
    """Each patch solution sigma_i^a has zero normal flux on its zero-flux edges.

    Also checks the set of zero-flux edges: all of the patch boundary for an
    interior vertex; the patch boundary minus the domain boundary otherwise.
    """
    scene, *_, patches = case(mesh_name, data_name)
    mesh = scene.mesh
    bnd_edges = {tuple(e) for e in mesh.edges[mesh.boundary_edges].tolist()}
    worst = 0.0
    for a, _i, tris, coef, zero_edges in patches:
        # the patch boundary (edges with one patch triangle)
        count = {}
        for k in tris:
            t = mesh.triangles[k]
            for j in range(3):
                e = tuple(sorted((int(t[(j + 1) % 3]), int(t[(j + 2) % 3]))))
                count[e] = count.get(e, 0) + 1
        patch_bnd = {e for e, c in count.items() if c == 1}
        if mesh.boundary_vertex_mask[a]:
            assert set(zero_edges) == patch_bnd - bnd_edges
        else:
            assert set(zero_edges) == patch_bnd
        local = np.zeros((mesh.n_triangles, 8))
        local[tris] = coef
        scale = np.abs(coef).max()
        for e in zero_edges:
            (k,) = [k for k in tris if set(e) <= set(mesh.triangles[k].tolist())]
            p0, p1 = mesh.vertices[e[0]], mesh.vertices[e[1]]
            tvec = p1 - p0
            n = np.array([tvec[1], -tvec[0]]) / np.linalg.norm(tvec)
            pts = np.array([p0 + t * tvec for t in (0.0, 0.3, 0.5, 1.0)])
            s = naive_flux.evaluate(mesh, local, np.full(4, k), pts[:, 0], pts[:, 1])
            worst = max(worst, np.abs(s @ n).max() / scale)
        # the patch solution is normal-continuous inside the patch
        pts, tl, tr, n = _edge_points(mesh)
        inside = np.isin(tl, tris) & np.isin(tr, tris)
        if inside.any():
            sl = naive_flux.evaluate(mesh, local, tl[inside], pts[inside, 0], pts[inside, 1])
            sr = naive_flux.evaluate(mesh, local, tr[inside], pts[inside, 0], pts[inside, 1])
            worst = max(worst, np.abs(((sl - sr) * n[inside]).sum(axis=1)).max() / scale)
    assert worst <= 1e-11


def _p2_curls(p, grads, bary):
    """curl of the 6 P2 Lagrange functions (vertices 0..2, then edges opposite 0..2) at bary."""
    out = []
    for i in range(3):  # lambda_i (2 lambda_i - 1)
        out.append((4.0 * bary[:, i] - 1.0)[:, None] * grads[i][None, :])
    for i in range(3):  # 4 lambda_j lambda_k on the edge opposite i
        j, k = (i + 1) % 3, (i + 2) % 3
        out.append(4.0 * (bary[:, j, None] * grads[k] + bary[:, k, None] * grads[j]))
    g = np.stack(out, axis=1)  # (P, 6, 2) gradients
    return np.stack([g[..., 1], -g[..., 0]], axis=2)  # curl = (d/dy, -d/dx)


@pytest.mark.parametrize("mesh_name", MESHES)
@pytest.mark.parametrize("data_name", ["perturbed-callable", "perturbed-mu-per-triangle"])
def test_reference_patch_optimality(mesh_name, data_name):
    """mu_i^-1 (sigma_i^a + tau_i^a) is L2-orthogonal to the divergence-free fields of V^a.

    (The optimality condition of the mu-weighted patch problem; for constant mu
    the weight is a scalar.)

    Those are the curls of continuous P2 functions vanishing on the zero-flux part
    of the patch boundary (nodes: a, midpoints of patch-interior edges and, for a
    boundary vertex, midpoints of its domain-boundary edges).  With the constraint
    div sigma = Pi_Q g and sigma in V^a this characterises the minimiser.
    """
    scene, u1, u2, lam, r1, r2, _, patches = case(mesh_name, data_name)
    mesh = scene.mesh
    bary, w = naive_flux.QUAD_BARY, naive_flux.QUAD_W
    worst = 0.0
    for a, i, tris, coef, zero_edges in patches:
        u, mu = (u1, scene.mu1) if i == 0 else (u2, scene.mu2)
        zero = {frozenset(e) for e in zero_edges}
        nodes = {}  # P2 node (vertex a or an edge) -> accumulated (s + tau, curl phi)
        norm2 = 0.0
        for j, k in enumerate(tris):
            t = mesh.triangles[k]
            p = mesh.vertices[t]
            grads = mesh.gradients[k]
            la = int(np.flatnonzero(t == a)[0])
            pts = bary @ p
            s = naive_flux.evaluate(mesh, _one(mesh, k, coef[j]), np.full(len(w), k), *pts.T)
            mu_k = mu if np.ndim(mu) == 0 else mu[k]
            v = (s + mu_k * bary[:, la, None] * (grads.T @ u[t])[None, :]) / mu_k
            norm2 += mesh.areas[k] * (w * (v**2).sum(axis=1)).sum()
            curls = _p2_curls(p, grads, bary)
            ints = mesh.areas[k] * np.einsum("p,pc,pnc->n", w, v, curls)
            nodes[("v", a)] = nodes.get(("v", a), 0.0) + ints[la]
            for e_loc in range(3):
                edge = frozenset((int(t[(e_loc + 1) % 3]), int(t[(e_loc + 2) % 3])))
                if a in edge and edge not in zero:
                    nodes[edge] = nodes.get(edge, 0.0) + ints[3 + e_loc]
        scale = np.sqrt(norm2) + 1e-300  # ||curl phi||_K = O(1)
        worst = max(worst, max(abs(x) for x in nodes.values()) / scale)
    assert worst <= 1e-12


def _one(mesh, k, c):
    out = np.zeros((mesh.n_triangles, 8))
    out[k] = c
    return out


@pytest.mark.parametrize(("mesh_name", "data_name"), ALL_CASES)
def test_reference_conforming_and_equilibrated(mesh_name, data_name):
    scene, u1, u2, lam, r1, r2, ref, _ = case(mesh_name, data_name)
    mesh = scene.mesh
    for i, (coef, r) in enumerate(zip(ref, (r1, r2), strict=False)):
        jump, scale = _normal_jump(_naive_eval(mesh, coef), mesh)
        assert jump <= 1e-11 * scale
        defect, size = _equilibration_defect(scene, lam, r, i, _naive_div(mesh, coef))
        assert defect <= 1e-12 * size


def test_perturbed_triples_are_inexact():
    """The perturbed data sets really have R != 0, lam of both signs and an infeasible gap."""
    scene, u1, u2, lam, r1, r2, _, _ = case("square8", "perturbed")
    inner = scene.mesh.interior_vertices
    assert (lam[inner] < 0).any()
    assert (lam[inner] > 0).any()
    assert (u1 - u2)[inner].min() < 0
    assert np.abs(r1).max() > 1e-3
    assert np.abs(r2).max() > 1e-3


# ------------------------------------------------------------- package vs reference


@pytest.mark.parametrize(("mesh_name", "data_name"), ALL_CASES)
def test_package_matches_reference(mesh_name, data_name):
    *_, ref, _ = case(mesh_name, data_name)
    fl = package(mesh_name, data_name)
    mesh = get_mesh(mesh_name)
    assert fl.coef.shape == (2, mesh.n_triangles, 8)
    for i in range(2):
        assert np.abs(fl.coef[i] - ref[i]).max() <= 1e-10 * np.abs(ref[i]).max()


def _check_conforming_and_equilibrated(scene, fl, lam, r1, r2):
    """Normal jumps <= 1e-11 and equilibration defects <= 1e-12 of their scales."""
    for i, r in enumerate((r1, r2)):
        jump, scale = _normal_jump(lambda t, x, y, i=i: fl.evaluate(i, t, x, y), scene.mesh)
        assert jump <= 1e-11 * scale
        defect, size = _equilibration_defect(
            scene, lam, r, i, lambda t, x, y, i=i: fl.divergence(i, t, x, y)
        )
        assert defect <= 1e-12 * size


@pytest.mark.parametrize(("mesh_name", "data_name"), ALL_CASES)
def test_package_conforming_and_equilibrated(mesh_name, data_name):
    scene, u1, u2, lam, r1, r2, _, _ = case(mesh_name, data_name)
    _check_conforming_and_equilibrated(scene, package(mesh_name, data_name), lam, r1, r2)


@pytest.mark.parametrize("mesh_name", ["perturbed", "circle"])
def test_package_evaluate_and_divergence(mesh_name, rng):
    """Fluxes.evaluate / divergence agree with the canonical formulas at random points."""
    scene, *_, ref, _ = case(mesh_name, "perturbed-callable")
    fl = package(mesh_name, "perturbed-callable")
    mesh = scene.mesh
    tri = rng.integers(0, mesh.n_triangles, size=200)
    bary = rng.dirichlet(np.ones(3), size=200)
    pts = np.einsum("pk,pkc->pc", bary, mesh.vertices[mesh.triangles[tri]])
    for i in range(2):
        s = fl.evaluate(i, tri, pts[:, 0], pts[:, 1])
        d = fl.divergence(i, tri, pts[:, 0], pts[:, 1])
        assert s.shape == (200, 2)
        assert d.shape == (200,)
        s_ref = naive_flux.evaluate(mesh, fl.coef[i], tri, pts[:, 0], pts[:, 1])
        d_ref = naive_flux.divergence(mesh, fl.coef[i], tri, pts[:, 0], pts[:, 1])
        assert _rel(s, s_ref) <= 1e-13
        assert _rel(d, d_ref) <= 1e-13
        # and against the reference reconstruction itself
        assert _rel(s, naive_flux.evaluate(mesh, ref[i], tri, pts[:, 0], pts[:, 1])) <= 1e-10


@pytest.mark.parametrize("load_degree", [2, 8])
def test_package_matches_reference_other_load_degree(load_degree):
    """Callable loads use the scene's load rule in both the load vector and the patch data."""
    mesh = get_mesh("perturbed")
    scene = fm.Scene(
        mesh, mu=(2.0, 1.0), f=(f1_callable, f2_callable), g=0.1, load_degree=load_degree
    )
    sol = fm.solve(scene, method="exact")
    u1, u2, lam = _perturb(mesh, sol.u1, sol.u2, sol.lam, seed=11)
    r1, r2 = residuals(scene, u1, u2, lam)
    ref = naive_flux.naive_reconstruct(scene, u1, u2, lam, r1, r2)
    fl = flux.reconstruct(scene, u1, u2, lam, r1, r2, redistribute=False)
    for i in range(2):
        assert np.abs(fl.coef[i] - ref[i]).max() <= 1e-10 * np.abs(ref[i]).max()
        defect, size = _equilibration_defect(
            scene, lam, (r1, r2)[i], i, lambda t, x, y, i=i: fl.divergence(i, t, x, y)
        )
        assert defect <= 1e-12 * size


@pytest.mark.parametrize("mesh_name", ["square4", "circle"])
def test_package_default_residuals(mesh_name):
    """r1 = r2 = None computes the residuals with fastmem.fem.residual.residuals."""
    scene, u1, u2, lam, r1, r2, _, _ = case(mesh_name, "perturbed")
    a = flux.reconstruct(scene, u1, u2, lam, redistribute=False)
    b = package(mesh_name, "perturbed")
    assert np.abs(a.coef - b.coef).max() <= 1e-13 * np.abs(b.coef).max()


# ---------------------------------------------------------------------- exactness


def _flux_estimator(mesh, coef, mu, u, evaluate):
    """Per triangle ||mu^1/2 grad u + mu^-1/2 sigma||_K (degree-8 quadrature)."""
    bary, w = naive_flux.QUAD_BARY, naive_flux.QUAD_W
    m = mesh.n_triangles
    pts = _quad_points(mesh, bary)
    tri = np.repeat(np.arange(m), len(w))
    s = evaluate(tri, pts[..., 0].ravel(), pts[..., 1].ravel()).reshape(m, len(w), 2)
    grad = np.einsum("mkc,mk->mc", mesh.gradients, u[mesh.triangles])
    v = np.sqrt(mu) * grad[:, None, :] + s / np.sqrt(mu)
    return np.sqrt(mesh.areas * ((v**2).sum(axis=2) @ w)), np.sqrt(mu) * np.abs(grad).max()


@pytest.mark.parametrize("mesh_name", MESHES)
def test_exact_for_linear_fields(mesh_name):
    """f = 0, lam = 0, linear u1, u2 (R = 0 up to round-off): sigma_ih = -mu_i grad u_ih."""
    mesh = get_mesh(mesh_name)
    x, y = mesh.vertices.T
    mu = (2.0, 0.5)
    scene = fm.Scene(mesh, mu=mu, f=(0.0, 0.0), g=0.1)
    u = (0.3 + 0.2 * x - 0.1 * y, -0.1 + 0.5 * x + 0.7 * y)
    lam = np.zeros_like(x)
    r1, r2 = residuals(scene, *u, lam)
    assert max(np.abs(r1).max(), np.abs(r2).max()) <= 1e-13
    fl = flux.reconstruct(scene, *u, lam)
    for i in range(2):
        eta, scale = _flux_estimator(
            mesh, fl.coef[i], mu[i], u[i], lambda t, xx, yy, i=i: fl.evaluate(i, t, xx, yy)
        )
        assert eta.max() <= 1e-12 * scale


@pytest.mark.parametrize("mesh_name", ["square4", "perturbed", "circle"])
def test_exact_without_load_or_contact(mesh_name):
    """f = 0, constant g: the discrete solution is u1 = g, u2 = 0, lam = 0 and sigma_h = 0."""
    mesh = get_mesh(mesh_name)
    scene = fm.Scene(mesh, mu=(1.0, 3.0), f=(0.0, 0.0), g=0.25)
    sol = fm.solve(scene, method="exact")
    assert np.allclose(sol.u1, 0.25, rtol=0, atol=1e-14)
    assert np.abs(sol.u2).max() <= 1e-14
    assert np.abs(sol.lam).max() == 0.0
    fl = flux.reconstruct(scene, sol.u1, sol.u2, sol.lam, sol.r1, sol.r2)
    assert np.abs(fl.coef).max() <= 1e-13
    for i, u in enumerate((sol.u1, sol.u2)):
        eta, _ = _flux_estimator(
            mesh,
            fl.coef[i],
            scene.mu1 if i == 0 else scene.mu2,
            u,
            lambda t, xx, yy, i=i: fl.evaluate(i, t, xx, yy),
        )
        assert eta.max() <= 1e-13
