"""Tests of fastmem/mesh/refine.py and kernels/nvb.py: NVB with closure, transfer, Dörfler marking.

The kernels are checked against a plain Python reference written here: it
bisects the marked triangles, then bisects every triangle with a hanging
vertex (the midpoint of one of its edges is a vertex of the mesh) until there
is none, a different algorithm from the edge closure of the kernels, with the
same (unique) result: the coarsest conforming NVB refinement.
"""

import math

import numba
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from meshes import perturbed_square
from numpy.testing import assert_allclose, assert_array_equal

import fastmem as fm
from fastmem.errors import DataError, InputTypeError, ParameterError
from fastmem.mesh.refine import dorfler_mark, refine_marked

FEW = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# --------------------------------------------------------------------------- references
def _mid(p, q):
    return (0.5 * (p[0] + q[0]), 0.5 * (p[1] + q[1]))


def _bisect(t):
    """Children of (newest, a, b): the midpoint of (a, b) becomes their newest vertex."""
    p0, p1, p2 = t
    m = _mid(p1, p2)
    return [(m, p0, p1), (m, p2, p0)]


def ref_refine(tris, marked):
    """Reference NVB: bisect the marked triangles, then every triangle with a hanging vertex."""
    marked = set(int(k) for k in marked)
    out = []
    for k, t in enumerate(tris):
        out.extend(_bisect(t) if k in marked else [t])
    while True:
        verts = {p for t in out for p in t}
        hanging = {
            k
            for k, t in enumerate(out)
            if any(_mid(t[j], t[(j + 1) % 3]) in verts for j in range(3))
        }
        if not hanging:
            return out
        new = []
        for k, t in enumerate(out):
            new.extend(_bisect(t) if k in hanging else [t])
        out = new


def ref_longest(mesh):
    """Longest edge of each triangle, ties to the lexicographically smallest vertex pair."""
    v, ref = mesh.vertices, []
    for tri in mesh.triangles.tolist():
        best = None
        for i in range(3):
            a, b = tri[(i + 1) % 3], tri[(i + 2) % 3]
            length2 = (v[b, 0] - v[a, 0]) ** 2 + (v[b, 1] - v[a, 1]) ** 2
            key = (-length2, min(a, b), max(a, b))
            if best is None or key < best[0]:
                best = (key, i)
        ref.append(best[1])
    return np.array(ref)


def labelled(mesh, ref):
    """Triangles as coordinate tuples, newest vertex first (refinement edge opposite)."""
    v = [tuple(p) for p in mesh.vertices.tolist()]
    return [
        tuple(v[tri[(r + j) % 3]] for j in range(3))
        for tri, r in zip(mesh.triangles.tolist(), ref, strict=True)
    ]


def dorfler_reference(eta2, theta):
    """Minimal count by a full sort (largest first)."""
    total = eta2.sum()
    csum = np.cumsum(np.sort(eta2)[::-1])
    return int(np.searchsorted(csum, theta * total)) + 1, csum


# --------------------------------------------------------------------------- meshes
def diagonal_square(n, seed):
    """Square (0, 1)^2 with n x n cells, each cut by a random diagonal."""
    rng = np.random.default_rng(seed)
    xs = np.linspace(0.0, 1.0, n + 1)
    X, Y = np.meshgrid(xs, xs)
    vertices = np.stack([X.ravel(), Y.ravel()], axis=1)
    i, j = np.meshgrid(np.arange(n), np.arange(n))
    a = (j * (n + 1) + i).ravel()
    b, c, d = a + 1, a + n + 2, a + n + 1
    slash = rng.random(a.size) < 0.5
    t1 = np.where(slash[:, None], np.stack([a, b, c], 1), np.stack([a, b, d], 1))
    t2 = np.where(slash[:, None], np.stack([a, c, d], 1), np.stack([b, c, d], 1))
    return fm.Mesh(vertices, np.vstack([t1, t2]))


def make_mesh(kind, n, seed):
    if kind == "diagonals":
        return diagonal_square(n, seed)
    if kind == "perturbed":
        return perturbed_square(n, 0.3, seed=seed)
    return fm.Mesh.lshape(2 * max(n // 2, 1))


MESHES = st.tuples(
    st.sampled_from(["diagonals", "perturbed", "lshape"]),
    st.integers(2, 5),
    st.integers(0, 2**31 - 1),
)


# --------------------------------------------------------------------------- checks
def min_angle_of(p):
    """Smallest angle of the triangles with corners p (k, 3, 2)."""
    out = np.inf
    for i in range(3):
        u = p[:, (i + 1) % 3] - p[:, i]
        w = p[:, (i + 2) % 3] - p[:, i]
        cross = np.abs(u[:, 0] * w[:, 1] - u[:, 1] * w[:, 0])
        out = min(out, float(np.arctan2(cross, (u * w).sum(axis=1)).min()))
    return out


def min_angle(mesh):
    return min_angle_of(mesh.vertices[mesh.triangles])


def signed_area2(mesh):
    p = mesh.vertices[mesh.triangles]
    d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    return d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]


def boundary_length(mesh):
    e = mesh.edges[mesh.boundary_edges]
    return float(np.linalg.norm(mesh.vertices[e[:, 1]] - mesh.vertices[e[:, 0]], axis=1).sum())


def assert_conforming(mesh, initial):
    """Interior edges shared by two triangles, no hanging vertex, boundary on the initial one."""
    counts = np.bincount(mesh.triangle_edges.ravel(), minlength=mesh.n_edges)
    assert set(np.unique(counts)) <= {1, 2}
    # no vertex at the midpoint of an edge (bisection puts every hanging vertex there)
    verts = {tuple(p) for p in mesh.vertices.tolist()}
    mids = 0.5 * (mesh.vertices[mesh.edges[:, 0]] + mesh.vertices[mesh.edges[:, 1]])
    assert not any(tuple(p) in verts for p in mids.tolist())
    # a hanging vertex would add the inner edges to the boundary
    assert_allclose(boundary_length(mesh), boundary_length(initial), rtol=1e-12)
    # every boundary edge lies on a boundary edge of the initial mesh
    e0 = initial.vertices[initial.edges[initial.boundary_edges]]  # (B0, 2, 2)
    e = mesh.edges[mesh.boundary_edges]
    q = 0.5 * (mesh.vertices[e[:, 0]] + mesh.vertices[e[:, 1]])
    a, d = e0[None, :, 0], e0[None, :, 1] - e0[None, :, 0]
    s = np.clip(((q[:, None] - a) * d).sum(-1) / (d * d).sum(-1), 0, 1)
    dist = np.linalg.norm(a + s[..., None] * d - q[:, None], axis=-1).min(axis=1)
    assert dist.max() < 1e-12


def nvb_class_bound(mesh, ref, generations=5):
    """Smallest angle among the first NVB generations of every initial triangle.

    NVB creates at most four similarity classes per initial triangle, all
    present in the first generations: a lower bound for every descendant.
    """
    bound = np.inf
    for t in labelled(mesh, ref):
        gen = [t]
        for _ in range(generations):
            gen = [c for x in gen for c in _bisect(x)]
            bound = min(bound, min_angle_of(np.array(gen)))
    return bound


# --------------------------------------------------------------------------- NVB vs reference
def refine_rounds(mesh, ref, rng, rounds, fraction, kernel_ref=None):
    """Kernel and reference side by side; yields (kernel mesh, reference list) each round.

    ``ref`` labels the initial triangles for the reference; the kernel gets
    ``kernel_ref`` in the first round (None: its default) and its stored
    labels afterwards.
    """
    tris = labelled(mesh, ref)
    cur, label = mesh, ref
    for _ in range(rounds):
        index = {t: k for k, t in enumerate(tris)}
        marked = np.flatnonzero(rng.random(cur.n_triangles) < fraction)
        before = labelled(cur, label)
        tris = ref_refine(tris, [index[before[k]] for k in marked])
        cur, _ = refine_marked(cur, marked, refinement_edge=kernel_ref)
        kernel_ref, label = None, np.zeros(cur.n_triangles, dtype=int)
        yield cur, tris


@FEW
@given(MESHES, st.integers(0, 2**31 - 1), st.booleans())
def test_matches_python_reference(spec, seed, explicit_labels):
    mesh = make_mesh(*spec)
    rng = np.random.default_rng(seed)
    if explicit_labels:
        ref = rng.integers(0, 3, mesh.n_triangles)
        kernel_ref = ref
    else:
        ref, kernel_ref = ref_longest(mesh), None
    for fine, tris in refine_rounds(mesh, ref, rng, 3, 0.2, kernel_ref):
        got = labelled(fine, np.zeros(fine.n_triangles, dtype=int))
        assert len(got) == len(tris)
        assert set(got) == set(tris)  # same triangles, same newest vertex, same orientation


def test_reference_sees_closure():
    """A case where the closure propagates: the reference and the kernel agree on it."""
    mesh = diagonal_square(4, 7)
    ref = np.full(mesh.n_triangles, 1)  # mostly incompatible labels: long closure chains
    rng = np.random.default_rng(20261121)
    for fine, tris in refine_rounds(mesh, ref, rng, 2, 0.05, kernel_ref=ref):
        assert set(labelled(fine, np.zeros(fine.n_triangles, dtype=int))) == set(tris)
    # one mark: the closure bisects up to several edges
    sizes = [refine_marked(mesh, [k], refinement_edge=ref)[1].n_new_vertices for k in range(32)]
    k = int(np.argmax(sizes))
    assert sizes[k] >= 3
    fine, _ = refine_marked(mesh, [k], refinement_edge=ref)
    expected = ref_refine(labelled(mesh, ref), [k])
    assert set(labelled(fine, np.zeros(fine.n_triangles, dtype=int))) == set(expected)


# --------------------------------------------------------------------------- properties
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(MESHES, st.integers(0, 2**31 - 1), st.floats(0.05, 0.5), st.booleans())
def test_successive_refinements_keep_a_valid_nvb_mesh(spec, seed, fraction, default_labels):
    mesh = make_mesh(*spec)
    rng = np.random.default_rng(seed)
    ref = ref_longest(mesh) if default_labels else rng.integers(0, 3, mesh.n_triangles)
    bound = nvb_class_bound(mesh, ref)
    alpha0 = min_angle(mesh)
    area0 = mesh.areas.sum()
    cur, kernel_ref = mesh, None if default_labels else ref
    for _ in range(8):
        if cur.n_triangles > 5000:
            break
        marked = rng.random(cur.n_triangles) < fraction
        fine, transfer = refine_marked(cur, marked, refinement_edge=kernel_ref)
        kernel_ref = None
        assert_conforming(fine, mesh)
        assert (signed_area2(fine) > 0).all()  # counter-clockwise
        assert_allclose(fine.areas.sum(), area0, rtol=1e-12)
        n_children = transfer.n_children
        assert (n_children[marked] >= 2).all()  # every marked triangle refined
        assert set(np.unique(n_children)) <= {1, 2, 3, 4}
        # old vertices keep their indices; each bisected triangle's children have a new
        # vertex as newest vertex
        assert_array_equal(fine.vertices[: cur.n_vertices], cur.vertices)
        split = n_children[transfer.parent_triangle] > 1
        assert (fine.triangles[split, 0] >= cur.n_vertices).all()
        cur = fine
    angle = min_angle(cur)
    assert angle >= bound * (1 - 1e-9)  # the similarity classes of NVB
    if default_labels:  # longest edges first: the minimum angle at most halves
        assert angle >= 0.5 * alpha0 * (1 - 1e-9)


_TOPOLOGY = ("edges", "triangle_edges", "edge_triangles", "boundary_edges", "boundary_vertex_mask")


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(MESHES, st.integers(0, 2**31 - 1), st.sampled_from([0.01, 0.1, 0.3, 1.0]))
def test_derived_topology_equals_the_topology_from_scratch(spec, seed, fraction):
    """validate=False derives the edges from the parent's: the same arrays, same dtypes."""
    from fastmem.kernels.topology import edge_topology

    cur = make_mesh(*spec)
    rng = np.random.default_rng(seed)
    for _ in range(5):
        if cur.n_triangles > 5000:
            break
        marked = rng.random(cur.n_triangles) < fraction
        fast, _ = refine_marked(cur, marked, validate=False)
        full, _ = refine_marked(cur, marked, validate=True)
        edges, tri_edges, et, counts, forward = edge_topology(fast.triangles, fast.n_vertices)
        for name, want in (("edges", edges), ("triangle_edges", tri_edges), ("edge_triangles", et)):
            got = getattr(fast, name)
            assert got.dtype == want.dtype, name
            assert_array_equal(got, want, err_msg=name)
        for name in _TOPOLOGY:
            assert getattr(fast, name).dtype == getattr(full, name).dtype, name
            assert_array_equal(getattr(fast, name), getattr(full, name), err_msg=name)
        # patches (counting sort) and lumped mass (kernel): the NumPy definitions, bit for bit
        order = np.argsort(fast.triangles.ravel(), kind="stable")
        assert_array_equal(fast.patch_triangles, order // 3)
        assert_array_equal(fast.patch_local, order % 3)
        assert_array_equal(np.diff(fast.patch_ptr), np.bincount(fast.triangles.ravel()))
        lumped = np.bincount(
            fast.triangles.ravel(),
            weights=np.repeat(fast.areas / 3.0, 3),
            minlength=fast.n_vertices,
        )
        assert_array_equal(fast.lumped_mass, lumped)
        cur = fast


def test_refine_all_twice_on_compatible_mesh_halves_every_edge():
    """Marking all twice on a mesh of compatible pairs gives the red refinement's vertices."""
    mesh = fm.Mesh.square(4, diagonal="right")  # hypotenuses shared: compatible
    fine, _ = refine_marked(mesh, np.ones(mesh.n_triangles, dtype=bool))
    assert fine.n_triangles == 2 * mesh.n_triangles
    fine, _ = refine_marked(fine, np.ones(fine.n_triangles, dtype=bool))
    red = mesh.refine()  # same vertices, same triangle sizes (another pattern)
    assert fine.n_triangles == red.n_triangles
    assert {tuple(p) for p in fine.vertices.tolist()} == {tuple(p) for p in red.vertices.tolist()}
    assert_allclose(fine.areas, mesh.areas[0] / 4, rtol=1e-14)


def test_longest_edge_ties_do_not_depend_on_vertex_order():
    # lengths^2 4, 5, 5: two longest edges; the tie goes to the lower global edge (0, 2)
    v = np.array([[0.0, 0.0], [2.0, 0.0], [1.0, 2.0], [1.0, -1.0]])
    for tri in ([0, 1, 2], [1, 2, 0], [2, 0, 1]):
        mesh = fm.Mesh(v, [tri, [0, 3, 1]])
        fine, transfer = refine_marked(mesh, [0])
        first = transfer.parent_edges[0].tolist()
        assert first == [0, 2]
        assert transfer.n_new_vertices == 1


def test_stored_labels_survive_a_rebuild_with_refinement_edge_0(rng):
    mesh = perturbed_square(4, 0.3)
    fine, _ = refine_marked(mesh, rng.random(mesh.n_triangles) < 0.3)
    marked = rng.random(fine.n_triangles) < 0.3
    a, _ = refine_marked(fine, marked)
    rebuilt = fm.Mesh(fine.vertices, fine.triangles)
    b, _ = refine_marked(rebuilt, marked, refinement_edge=0)
    assert_array_equal(a.triangles, b.triangles)
    assert_array_equal(a.vertices, b.vertices)


@pytest.mark.parametrize("validate", [True, False])
def test_serial_and_parallel_agree(rng, monkeypatch, validate):
    """One thread against every thread in chunks of a few triangles / edges: same arrays.

    (validate=False derives the edges from the parent's in chunks as well.)
    """
    from fastmem.kernels import pool, topology

    mesh = perturbed_square(16, 0.3)
    marked = rng.random(mesh.n_triangles) < 0.3
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        a, ta = refine_marked(mesh, marked, validate=validate)
    finally:
        numba.set_num_threads(threads)
    monkeypatch.setattr(pool, "GRAIN", 7)  # chunks of the pool's parallel loops
    monkeypatch.setattr(topology, "GRAIN", 7)
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    try:
        b, tb = refine_marked(mesh, marked, validate=validate)
    finally:
        numba.set_num_threads(threads)
    assert_array_equal(a.triangles, b.triangles)
    assert_array_equal(ta.parent_triangle, tb.parent_triangle)
    for name in _TOPOLOGY:
        assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_nothing_marked_keeps_the_triangles():
    mesh = fm.Mesh.lshape(4)
    fine, transfer = refine_marked(mesh, np.zeros(mesh.n_triangles, dtype=bool))
    assert transfer.n_new_vertices == 0
    assert_array_equal(fine.vertices, mesh.vertices)
    assert_array_equal(np.sort(fine.triangles, axis=1), np.sort(mesh.triangles, axis=1))
    assert_array_equal(transfer.parent_triangle, np.arange(mesh.n_triangles))
    u = np.arange(mesh.n_vertices, dtype=float)
    assert_array_equal(transfer.prolong(u), u)


def test_mask_and_indices_agree(rng):
    mesh = perturbed_square(6, 0.3)
    idx = rng.choice(mesh.n_triangles, 10, replace=False)
    mask = np.zeros(mesh.n_triangles, dtype=bool)
    mask[idx] = True
    a, _ = refine_marked(mesh, mask)
    b, _ = refine_marked(mesh, np.concatenate([idx, idx[:3]]).astype(np.int32))  # repeats too
    assert_array_equal(a.triangles, b.triangles)


# --------------------------------------------------------------------------- transfer
@FEW
@given(MESHES, st.integers(0, 2**31 - 1), st.tuples(*[st.floats(-10, 10)] * 3))
def test_prolongation_is_exact_for_p1(spec, seed, coef):
    mesh = make_mesh(*spec)
    rng = np.random.default_rng(seed)
    lin = lambda x: coef[0] + coef[1] * x[:, 0] + coef[2] * x[:, 1]  # noqa: E731
    cur = mesh
    for _ in range(3):
        fine, transfer = refine_marked(cur, rng.random(cur.n_triangles) < 0.3)
        u = transfer.prolong(lin(cur.vertices))
        assert_allclose(u, lin(fine.vertices), rtol=0, atol=1e-14 * (1 + np.abs(coef).sum()))
        both = transfer.prolong(np.stack([lin(cur.vertices), cur.vertices[:, 0]], axis=1))
        assert_array_equal(both[:, 0], u)
        assert_allclose(transfer.prolongation_matrix() @ lin(cur.vertices), u, rtol=0, atol=1e-13)
        # new boundary vertices are exactly the new vertices on the new mesh's boundary
        assert_array_equal(transfer.new_boundary, fine.boundary_vertex_mask[cur.n_vertices :])
        assert_array_equal(
            transfer.new_boundary_vertices,
            np.flatnonzero(fine.boundary_vertex_mask[cur.n_vertices :]) + cur.n_vertices,
        )
        cur = fine


@FEW
@given(MESHES, st.integers(0, 2**31 - 1))
def test_children_lie_in_their_parent(spec, seed):
    mesh = make_mesh(*spec)
    rng = np.random.default_rng(seed)
    cur = mesh
    for _ in range(3):
        fine, transfer = refine_marked(cur, rng.random(cur.n_triangles) < 0.4)
        parent = transfer.parent_triangle
        assert_allclose(
            np.bincount(parent, weights=fine.areas, minlength=cur.n_triangles),
            cur.areas,
            rtol=1e-12,
        )
        # barycentric coordinates of each child's centroid in its parent
        p = cur.vertices[cur.triangles[parent]]
        c = fine.vertices[fine.triangles].mean(axis=1)
        d1, d2, dc = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], c - p[:, 0]
        det = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
        l1 = (dc[:, 0] * d2[:, 1] - dc[:, 1] * d2[:, 0]) / det
        l2 = (d1[:, 0] * dc[:, 1] - d1[:, 1] * dc[:, 0]) / det
        assert min(l1.min(), l2.min(), (1 - l1 - l2).min()) > 0
        mu = rng.random(cur.n_triangles)
        assert_array_equal(transfer.inherit(mu), mu[parent])
        cur = fine


def test_refine_bad_input():
    mesh = fm.Mesh.square(2)
    with pytest.raises(InputTypeError, match="Mesh"):
        refine_marked(mesh.vertices, [0])
    with pytest.raises(InputTypeError, match="marked"):
        refine_marked(mesh, [0.5])
    with pytest.raises(DataError, match="index 8"):
        refine_marked(mesh, [8])
    with pytest.raises(DataError, match="index -1"):
        refine_marked(mesh, [-1])
    with pytest.raises(DataError, match="mask of 3"):
        refine_marked(mesh, [True, False, True])
    with pytest.raises(DataError, match="one-dimensional"):
        refine_marked(mesh, [[0]])
    with pytest.raises(ParameterError, match="shortest"):
        refine_marked(mesh, [0], refinement_edge="shortest")
    with pytest.raises(DataError, match="got 3 at triangle 0"):
        refine_marked(mesh, [0], refinement_edge=np.full(8, 3))
    with pytest.raises(DataError, match=r"shape \(8,\)"):
        refine_marked(mesh, [0], refinement_edge=np.zeros(7, dtype=int))
    with pytest.raises(InputTypeError, match="refinement_edge"):
        refine_marked(mesh, [0], refinement_edge=np.zeros(8))
    with pytest.raises(InputTypeError, match="validate"):
        refine_marked(mesh, [0], validate=None)
    _, transfer = refine_marked(mesh, [0])
    with pytest.raises(DataError, match="one per old vertex"):
        transfer.prolong(np.zeros(3))
    with pytest.raises(DataError, match="one per old triangle"):
        transfer.inherit(np.zeros(3))


# --------------------------------------------------------------------------- Dörfler
@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.one_of(st.just(0.0), st.sampled_from([1.0, 2.0, 0.5]), st.floats(0, 1e6)),
        min_size=1,
        max_size=700,
    ),
    st.floats(1e-3, 1.0),
)
def test_dorfler_is_minimal(values, theta):
    eta2 = np.array(values)
    mask = dorfler_mark(eta2, theta)
    total = eta2.sum()
    if total == 0:
        assert not mask.any()
        return
    # the bulk condition, as written, up to the rounding of summing a subset in another
    # order (theta = 1: [1, 3.00001, 1.00001] among zeros summed to 1 ulp below the total)
    assert eta2[mask].sum() >= theta * total * (1 - 1e-12)
    if theta == 1.0:
        assert_array_equal(mask, eta2 > 0)
        return
    assert eta2[mask].min() >= eta2[~mask].max(initial=0.0)  # the largest ones
    assert (eta2[mask] > 0).all()
    k, csum = dorfler_reference(eta2, theta)
    count = int(mask.sum())
    # minimal; one more only where rounding of the two ways of summing disagrees
    assert count == k or (count == k + 1 and csum[k - 1] >= theta * total * (1 - 1e-12))


def test_dorfler_large_against_sort(rng):
    eta2 = rng.lognormal(0.0, 2.0, 200_001)
    eta2[rng.random(eta2.size) < 0.1] = 0.0
    for theta in (0.1, 0.5, 0.9, 0.999):
        mask = dorfler_mark(eta2, theta)
        k, _ = dorfler_reference(eta2, theta)
        assert mask.sum() == k
        assert eta2[mask].sum() >= theta * eta2.sum()
    assert_array_equal(dorfler_mark(eta2, 1.0), eta2 > 0)


def test_dorfler_edge_cases():
    assert_array_equal(dorfler_mark([0.0, 0.0], 0.5), [False, False])
    assert_array_equal(dorfler_mark([0.0, 3.0, 0.0], 1.0), [False, True, False])
    assert_array_equal(dorfler_mark([1, 1, 1, 1], 0.5).sum(), 2)  # ties: any two
    assert_array_equal(dorfler_mark([1e308, 1e308, 1.0], 0.6), [True, True, False])  # overflow
    assert dorfler_mark(np.zeros(0), 0.5).shape == (0,)


@pytest.mark.parametrize(
    "theta", [0.0, -0.5, 1.5, math.nan, math.inf, True, "0.5", None, 0.5j, np.float32(np.nan)]
)
def test_dorfler_refuses_bad_theta(theta):
    with pytest.raises(ParameterError, match="theta"):
        dorfler_mark([1.0, 2.0], theta)


@pytest.mark.parametrize(
    ("values", "error", "match"),
    [
        ([1.0, -2.0], DataError, "entry 1 = -2.0"),
        ([1.0, math.nan], DataError, "entry 1 = nan"),
        ([math.inf, 1.0], DataError, "entry 0 = inf"),
        ([[1.0, 2.0]], DataError, r"shape \(M,\)"),
        (["a", "b"], InputTypeError, "real numbers"),
        ([1 + 1j], InputTypeError, "real numbers"),
    ],
)
def test_dorfler_refuses_bad_indicators(values, error, match):
    with pytest.raises(error, match=match):
        dorfler_mark(values, 0.5)


# --------------------------------------------------------------------------- bisections > 1
def _marked_mask(mesh, seed=5, p=0.1):
    return np.random.default_rng(seed).random(mesh.n_triangles) < p


def test_two_bisections_are_two_rounds_on_the_children():
    mesh = perturbed_square(6, 0.2, seed=2)
    mask = _marked_mask(mesh)
    fine, rounds = refine_marked(mesh, mask, bisections=2)
    mid, first = refine_marked(mesh, mask)
    ref2, second = refine_marked(mid, mask[first.parent_triangle])
    assert_array_equal(fine.vertices, ref2.vertices)
    assert_array_equal(fine.triangles, ref2.triangles)
    assert rounds.n_old_vertices == mesh.n_vertices
    assert rounds.n_new_vertices == fine.n_vertices - mesh.n_vertices
    assert_array_equal(rounds.parent_triangle, first.parent_triangle[second.parent_triangle])
    # every marked triangle is bisected at least twice: four or more descendants
    assert rounds.n_children[mask].min() >= 4
    assert rounds.n_children.sum() == fine.n_triangles


@pytest.mark.parametrize("bisections", [2, 3])
def test_rounds_prolong_linear_functions_exactly(bisections):
    mesh = perturbed_square(5, 0.2, seed=4)
    fine, rounds = refine_marked(mesh, _marked_mask(mesh, p=0.2), bisections=bisections)
    lin = mesh.vertices @ np.array([1.7, -0.4]) + 0.3
    assert_allclose(rounds.prolong(lin), fine.vertices @ np.array([1.7, -0.4]) + 0.3, atol=1e-14)
    u = np.random.default_rng(1).random(mesh.n_vertices)
    assert_allclose(rounds.prolongation_matrix() @ u, rounds.prolong(u), rtol=0, atol=1e-15)
    assert_array_equal(rounds.prolong(u)[: mesh.n_vertices], u)
    w = np.arange(mesh.n_triangles, dtype=float)
    assert_array_equal(rounds.inherit(w), w[rounds.parent_triangle])
    # the weights of a vertex of a later round are positive and sum to one
    p = rounds.prolongation_matrix()
    assert p.data.min() > 0.0
    assert_allclose(np.asarray(p.sum(axis=1)).ravel(), 1.0, rtol=0, atol=1e-15)


@pytest.mark.parametrize(
    ("value", "error"), [(0, ParameterError), (1.5, InputTypeError), (True, InputTypeError)]
)
def test_bad_bisections_are_named(value, error):
    mesh = fm.Mesh.square(2)
    with pytest.raises(error, match="bisections"):
        refine_marked(mesh, [0], bisections=value)
