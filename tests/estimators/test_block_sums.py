"""combine() on large meshes sums the maps in fixed blocks in the kernel threads
(fastmem.kernels.sums): the same totals as NumPy up to round-off, the same bits for
every thread count, and a bad map entry still named."""

import numpy as np
import pytest

import fastmem as fm
from fastmem.errors import DataError
from fastmem.estimators import terms

M = terms.BLOCK_SUM_TRIANGLES + 12345  # several blocks and a partial one
GLOB = {
    "eta_glob1": 0.01,
    "eta_glob2": 0.02,
    "rho_norm1": 0.003,
    "rho_norm2": 0.004,
    "lam_minus_norm": 0.005,
    "C_F": 0.45,
    "mu1": 1.0,
    "mu2": 2.0,
}


def maps(rng, m=M):
    scales = (1e-3, 2e-3, 1e-4, 1e-6)
    local = {k: rng.random(m) * s for k, s in zip(terms._LOCAL_KEYS, scales, strict=True)}
    return rng.random(m) * 1e-2, rng.random(m) * 3e-2, local


def numpy_totals(f1, f2, local):
    """The NumPy path: the same maps below the kernel's size threshold."""
    old = terms.BLOCK_SUM_TRIANGLES
    terms.BLOCK_SUM_TRIANGLES = 1 << 62
    try:
        return terms.combine(f1, f2, local, GLOB)["totals"]
    finally:
        terms.BLOCK_SUM_TRIANGLES = old


def test_block_sums_match_numpy():
    f1, f2, local = maps(np.random.default_rng(0))
    assert terms._block_sums(f1, f2, local) is not None  # the kernel path is taken
    got = terms.combine(f1, f2, local, GLOB)["totals"]
    ref = numpy_totals(f1, f2, local)
    assert got.keys() == ref.keys()
    for key in ref:
        assert got[key] == pytest.approx(ref[key], rel=1e-12, abs=0.0), key


def test_block_sums_do_not_depend_on_threads():
    f1, f2, local = maps(np.random.default_rng(1))
    threads = fm.get_threads()["numba"]
    try:
        fm.set_threads(numba=1)
        one = terms.combine(f1, f2, local, GLOB)["totals"]
        fm.set_threads(numba=2)
        two = terms.combine(f1, f2, local, GLOB)["totals"]
    finally:
        fm.set_threads(numba=threads)
    assert one == two  # bit for bit


@pytest.mark.parametrize("bad", [np.nan, np.inf, -1e-30])
@pytest.mark.parametrize("where", ["eta_C", "eta_F2"])
def test_bad_entry_is_named(bad, where):
    f1, f2, local = maps(np.random.default_rng(2))
    target = f2 if where == "eta_F2" else local["eta_C"]
    target[M - 7] = bad  # in the last, partial block
    message = "finite and non-negative"
    with pytest.raises(DataError, match=f"{where} must be {message}"):
        terms.combine(f1, f2, local, GLOB)


def _global_case(rng, mesh):
    n = mesh.n_vertices
    u1, u2 = rng.standard_normal(n), rng.standard_normal(n)
    lam = rng.standard_normal(n)  # both signs: lam^- is not zero everywhere
    r1, r2 = 1e-3 * rng.standard_normal(n), 1e-3 * rng.standard_normal(n)
    return u1, u2, lam, r1, r2


def _global_both(monkeypatch, scene, args, block):
    """global_terms by the triangle-block kernel (blocks of ``block`` triangles) and by
    the NumPy path (the mass-matrix products)."""
    monkeypatch.setattr(terms, "BLOCK_SUM_TRIANGLES", 0)
    monkeypatch.setattr(terms._sums, "BLOCK", block)
    assert terms._global_blocks(scene.mesh, *args) is not None  # the kernel path is taken
    got = terms.global_terms(scene, *args)
    monkeypatch.setattr(terms, "BLOCK_SUM_TRIANGLES", 1 << 62)
    return got, terms.global_terms(scene, *args)


@pytest.mark.parametrize("block", [32768, 7])
@pytest.mark.parametrize("mesh", ["square", "lshape-refined"])
def test_global_terms_by_triangle_blocks_match_the_mass_matrix(monkeypatch, block, mesh):
    """x^T M x summed triangle by triangle (element mass matrices) is the NumPy path's
    x . (M x), up to round-off, for the five norms; per-triangle tensions take their
    minimum in both."""
    m = fm.Mesh.square(12) if mesh == "square" else fm.Mesh.lshape(6).refine()
    mu1 = np.linspace(1.0, 3.0, m.n_triangles)
    scene = fm.Scene(m, mu=(mu1, 2.0), f=(-1.0, 1.0), g=0.1)
    got, want = _global_both(monkeypatch, scene, _global_case(np.random.default_rng(2), m), block)
    assert got.keys() == want.keys()
    for key in want:
        assert got[key] == pytest.approx(want[key], rel=1e-12, abs=0.0), key
    assert want["lam_minus_norm"] > 0.1  # the case tests something


def test_global_terms_by_triangle_blocks_do_not_depend_on_threads(monkeypatch):
    m = fm.Mesh.square(16)
    scene = fm.Scene(m, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    args = _global_case(np.random.default_rng(3), m)
    monkeypatch.setattr(terms, "BLOCK_SUM_TRIANGLES", 0)
    monkeypatch.setattr(terms._sums, "BLOCK", 5)
    threads = fm.get_threads()["numba"]
    try:
        fm.set_threads(numba=1)
        one = terms.global_terms(scene, *args)
        fm.set_threads(numba=2)
        two = terms.global_terms(scene, *args)
    finally:
        fm.set_threads(numba=threads)
    assert one == two


@pytest.mark.parametrize("name", ["u1", "u2", "lam", "r1", "r2"])
def test_global_terms_kernel_path_still_names_a_bad_value(monkeypatch, name):
    m = fm.Mesh.square(8)
    scene = fm.Scene(m, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    names = ("u1", "u2", "lam", "r1", "r2")
    args = dict(zip(names, _global_case(np.random.default_rng(4), m), strict=True))
    args[name][m.boundary_vertices[0]] = np.nan  # also a boundary value must be finite
    monkeypatch.setattr(terms, "BLOCK_SUM_TRIANGLES", 0)
    assert terms._global_blocks(m, *args.values()) is None
    with pytest.raises(DataError, match=name):
        terms.global_terms(scene, *args.values())


def test_lumped_norm_matches_the_mass_matrix_and_the_solve_assembles_none():
    """The s-share of eta_alg from the element mass matrices: the assembled norm, no matrix."""
    from fastmem.solver import inexact

    mesh = fm.Mesh.square(256)  # 131072 triangles: the kernel path
    scene = fm.Scene(mesh, mu=(1.0, 2.0), f=(-1.0, 1.0), g=0.1)
    r = np.random.default_rng(5).standard_normal(mesh.n_vertices)
    got = terms.lumped_norm(scene, r)
    rho = np.where(mesh.boundary_vertex_mask, 0.0, r / mesh.lumped_mass)
    ref = np.sqrt(rho @ (terms.mass_matrix(scene) @ rho))
    assert got == pytest.approx(ref, rel=1e-12, abs=0.0)
    zero = np.zeros(mesh.n_vertices)  # the rho1 column of the global terms' kernel, same bits
    assert got == np.sqrt(terms._global_blocks(mesh, zero, zero, zero, r, zero)[2])
    bad = r.copy()
    bad[7] = np.nan
    assert terms.lumped_norm(scene, bad) is None  # not finite: the matrix path names nothing
    small = fm.Scene(fm.Mesh.square(64))
    assert terms.lumped_norm(small, np.ones(small.mesh.n_vertices)) is None
    assert inexact._mass(small) is not None
    fresh = fm.Scene(mesh, mu=(1.0, 2.0), f=(-1.0, 1.0), g=0.1)
    assert inexact._mass(fresh) is None
    result = fm.solve(fresh, nested=False)
    assert result.converged
    assert "M" not in fresh._cache  # no consistent mass matrix on this mesh


def _check_case(rng, mesh, *, ratio=0.3):
    """An iterate whose gap u1 - u2 is negative on a share ``ratio`` of the vertices."""
    n = mesh.n_vertices
    u2 = rng.standard_normal(n)
    u1 = u2 + np.where(rng.random(n) < ratio, -1.0, 1.0) * rng.random(n)
    lam, r1, r2 = rng.standard_normal(n), 1e-3 * rng.standard_normal(n), rng.standard_normal(n)
    return u1, u2, lam, r1, r2


def _lin_alg_of_maps(scene, args):
    """eta_lin, eta_alg as the checks formed them before check_totals: the maps of
    local_terms and global_terms, through combine with zero flux and oscillation."""
    loc = terms.local_terms(scene, *args[:3], oscillation=False)
    glob = terms.global_terms(scene, *args)
    zero = np.zeros(scene.mesh.n_triangles)
    totals = terms.combine(zero, zero, {**loc, "eta_osc1": zero, "eta_osc2": zero}, glob)
    return totals["totals"]["eta_lin"], totals["totals"]["eta_alg"], glob


@pytest.mark.parametrize("tension", ["constant", "per-triangle"])
def test_check_totals_are_the_maps_totals_bit_for_bit(monkeypatch, tension):
    """One pass of sums gives eta_lin, eta_alg and the global terms with the bits of the
    maps' path (eta_nc summed in the same blocks and order), on several blocks."""
    monkeypatch.setattr(terms._sums, "BLOCK", 4096)  # 32 blocks, the last one partial
    mesh = fm.Mesh.square(260)  # 135,200 triangles: both paths take their kernels
    rng = np.random.default_rng(6)
    mu2 = rng.uniform(0.5, 2.0, mesh.n_triangles) if tension == "per-triangle" else 2.5
    scene = fm.Scene(mesh, mu=(1.3, mu2), f=(-1.0, 1.0), g=0.1)
    args = _check_case(rng, mesh)
    got = terms.check_totals(scene, *args)
    assert got is not None
    assert got == _lin_alg_of_maps(scene, args)
    nc = terms.local_terms(scene, *args[:3], oscillation=False)["eta_nc"]
    assert (nc > 0).mean() > 0.2  # the case has non-conformity to sum


def test_check_totals_fall_back_where_the_maps_path_is_needed():
    """None on small meshes and for a value that is not finite: the checks then take the
    maps' path, which names the bad field."""
    small = fm.Scene(fm.Mesh.square(64))
    args = _check_case(np.random.default_rng(7), small.mesh)
    assert terms.check_totals(small, *args) is None
    mesh = fm.Mesh.square(256)
    scene = fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    args = list(_check_case(np.random.default_rng(8), mesh))
    assert terms.check_totals(scene, *args) is not None
    args[1][12345] = np.inf
    assert terms.check_totals(scene, *args) is None
    with pytest.raises(DataError, match="u2"):
        terms.global_terms(scene, *args)


def test_nonconformity_is_zero_where_the_gap_is_not_negative():
    """eta_nc = 0 exactly on triangles where u1 >= u2 (delta = 0 there), also where the
    gradient of the gap would overflow; elsewhere (mu |grad gap|^2 |{gap < 0}|)^(1/2)."""
    from fastmem.kernels.cut import nonconformity

    corners = (0.0, 0.0, 1.0, 0.0, 0.0, 1.0)  # area 1/2
    assert nonconformity(*corners, 1e300, -1e300 + 1e300, 1e300, 4.0) == (0.0, 0.5)
    assert nonconformity(*corners, 0.0, 3e307, -3e307 + 6e307, 4.0)[0] == 0.0
    # gap = -x: gradient (-1, 0), negative on all of K but the edge x = 0
    nc, area = nonconformity(*corners, 0.0, -1.0, 0.0, 4.0)
    assert area == 0.5
    assert nc == pytest.approx(np.sqrt(4.0 * 1.0 * 0.5), rel=1e-15)
    # gap = x - 1/2: negative on {x < 1/2}, area 1/2 - 1/8 = 3/8
    nc, _ = nonconformity(*corners, -0.5, 0.5, -0.5, 1.0)
    assert nc == pytest.approx(np.sqrt(3.0 / 8.0), rel=1e-14)


def _global_reference(mesh, u1, u2, lam, r1, r2, mu2, block):
    """The block sums of _global_blocks by the per-corner formulas in plain Python
    (each corner's rho and lam^- computed where it is used, boundary corners skipped)."""
    from fastmem.kernels.cut import nonconformity

    tri, xy, b = mesh.triangles, mesh.vertices, mesh.lumped_mass
    boundary = mesh.boundary_vertex_mask
    m = tri.shape[0]
    rows = np.zeros((-(-m // block), 6))
    for k in range(m):
        s1 = s2 = sl = q0 = q1 = q2 = q3 = q4 = 0.0
        for v in tri[k]:
            if boundary[v]:
                continue
            x1, x2 = r1[v] / b[v], r2[v] / b[v]
            lm = max(lam[v], 0.0) - lam[v]
            s1, s2, sl = s1 + x1, s2 + x2, sl + lm
            q0, q1 = q0 + (x1 + lm) * (x1 + lm), q1 + (x2 - lm) * (x2 - lm)
            q2, q3, q4 = q2 + x1 * x1, q3 + x2 * x2, q4 + lm * lm
        w = mesh.areas[k] / 12.0
        row = rows[k // block]
        row[0] += w * (q0 + (s1 + sl) * (s1 + sl))
        row[1] += w * (q1 + (s2 - sl) * (s2 - sl))
        row[2] += w * (q2 + s1 * s1)
        row[3] += w * (q3 + s2 * s2)
        row[4] += w * (q4 + sl * sl)
        g = [u1[v] - u2[v] for v in tri[k]]
        if min(g) < 0.0:
            (a, c, d) = tri[k]
            nc, _ = nonconformity(*xy[a], *xy[c], *xy[d], *g, mu2)
            row[5] += nc * nc
    return tuple(float(t) for t in rows.sum(axis=0))


@pytest.mark.parametrize("block", [7, 32768])
def test_global_blocks_are_the_per_corner_sums(monkeypatch, block):
    """The vertex values computed once per vertex (kernels.sums.vertex_values) give the
    sums of the formulas evaluated at every triangle corner, boundary corners skipped
    (to the last bits: Numba may fuse a multiply and an add where Python rounds twice;
    the solver's estimates kept their bits, docs/performance.md)."""
    m = fm.Mesh.lshape(6).refine()
    args = _global_case(np.random.default_rng(7), m)
    monkeypatch.setattr(terms, "BLOCK_SUM_TRIANGLES", 0)
    monkeypatch.setattr(terms._sums, "BLOCK", block)
    got = terms._global_blocks(m, *args, mu2=2.0)
    want = _global_reference(m, *args, 2.0, block)
    assert got == pytest.approx(want, rel=1e-14, abs=0.0)
    assert min(want) > 0.0  # every sum, eta_nc's included, is exercised
