"""The NumPy paths of small meshes' P1 pattern and matrices against the kernels, bit for bit.

Meshes below :data:`fastmem.kernels.topology.NUMPY_BELOW` triangles build the CSR
pattern, the position map and the stiffness and mass matrices with NumPy while the
kernels are not in the process (no kernel compiled on a first small run); larger
meshes, and small ones once the kernels are in, take the kernels.  Both must give the
same arrays, to the last bit, and the kernels must still be reached from the threshold
on.
"""

import numpy as np
import pytest
from fastmem.kernels import assembly as ka
from fastmem.kernels import sparsity as ks
from fastmem.kernels import topology as kt

import fastmem as fm
from fastmem.fem import assemble_mass, assemble_stiffness
from fastmem.mesh import csr_structure
from fastmem.mesh.refine import refine_marked


def _perturbed(n, seed):
    base = fm.Mesh.square(n)
    rng = np.random.default_rng(seed)
    v = base.vertices.copy()
    inner = ~base.boundary_vertex_mask
    v[inner] += rng.uniform(-0.3, 0.3, size=(int(inner.sum()), 2)) / n
    return fm.Mesh(v, base.triangles)


def _bisected(rounds, seed):
    mesh = fm.Mesh.lshape(8)
    rng = np.random.default_rng(seed)
    for _ in range(rounds):
        marked = np.zeros(mesh.n_triangles, dtype=bool)
        marked[rng.choice(mesh.n_triangles, mesh.n_triangles // 4, replace=False)] = True
        mesh = refine_marked(mesh, marked)[0]
    return mesh


MESHES = {
    "square": lambda: fm.Mesh.square(24),
    "lshape": lambda: fm.Mesh.lshape(16),
    "perturbed": lambda: _perturbed(20, 3),
    "bisected": lambda: _bisected(4, 5),
}


def _both(call):
    """``call()`` with the NumPy paths forced and with the kernels forced."""
    with kt.numpy_paths():
        numpy_result = call()
    with kt.kernel_paths():
        kernel_result = call()
    return numpy_result, kernel_result


@pytest.mark.parametrize("name", sorted(MESHES))
def test_pattern_and_position_map_equal_the_kernels(name):
    mesh = MESHES[name]()
    assert mesh.n_triangles < kt.NUMPY_BELOW
    n = mesh.n_vertices
    for dtype in (np.int32, np.int64):
        (p_np, i_np), (p_k, i_k) = _both(
            lambda d=dtype: ks.csr_pattern(n, mesh.edges, d, mesh.n_triangles)
        )
        assert p_np.dtype == p_k.dtype == i_np.dtype == i_k.dtype == dtype
        np.testing.assert_array_equal(p_np, p_k)
        np.testing.assert_array_equal(i_np, i_k)
        o_np, o_k = _both(lambda p=p_k, i=i_k: ks.position_map(mesh.triangles, p, i))
        assert o_np.dtype == o_k.dtype == np.uint16
        np.testing.assert_array_equal(o_np, o_k)
    # and the map points at the right columns
    rows = np.asarray(mesh.triangles)[:, :, None]
    cols = np.broadcast_to(np.asarray(mesh.triangles)[:, None, :], o_np.shape)
    np.testing.assert_array_equal(i_np[p_np[rows] + o_np], cols)


@pytest.mark.parametrize("name", sorted(MESHES))
@pytest.mark.parametrize("coef", ["one", "scalar", "per-triangle"])
def test_stiffness_and_mass_equal_the_kernels_bit_for_bit(name, coef):
    mesh = MESHES[name]()
    rng = np.random.default_rng(11)
    c = {
        "one": np.ones(1),
        "scalar": np.array([0.37]),
        "per-triangle": rng.uniform(0.1, 3.0, mesh.n_triangles),
    }[coef]
    indptr, _, offsets = csr_structure(mesh)
    patches = (mesh.patch_ptr, mesh.patch_triangles, mesh.patch_local)
    s_np, s_k = _both(
        lambda: ka.stiffness_csr(mesh.vertices, mesh.triangles, c, indptr, offsets, *patches)
    )
    m_np, m_k = _both(lambda: ka.mass_csr(mesh.areas, c, indptr, offsets, *patches))
    assert np.array_equal(s_np, s_k), np.abs(s_np - s_k).max()
    assert np.array_equal(m_np, m_k), np.abs(m_np - m_k).max()
    # not both wrong the same way: the stiffness annihilates constants, the mass integrates c
    a = assemble_stiffness(mesh, c if c.size > 1 else float(c[0]))
    assert np.abs(a @ np.ones(mesh.n_vertices)).max() < 1e-12 * np.abs(a.data).max()
    total = np.ones(mesh.n_vertices) @ (
        assemble_mass(mesh, c if c.size > 1 else float(c[0])) @ np.ones(mesh.n_vertices)
    )
    want = float(np.sum(mesh.areas * (c if c.size > 1 else c[0])))
    assert total == pytest.approx(want, rel=1e-13)


class _Spy:
    """A kernel stand-in that records its calls; ``signatures`` as the real one's or empty."""

    def __init__(self, kernel, name, ran, loaded):
        self.kernel, self.name, self.ran = kernel, name, ran
        self.signatures = kernel.signatures if loaded else []

    def __call__(self, *args):
        self.ran.append(self.name)
        return self.kernel(*args)


def _spy_kernels(monkeypatch, loaded):
    ran = []
    for module, name in (
        (ks, "_position_map_range"),
        (ks, "_count_rows"),
        (ka, "_stiffness_csr_range"),
        (ka, "_mass_csr_range"),
    ):
        monkeypatch.setattr(module, name, _Spy(getattr(module, name), name, ran, loaded))
    monkeypatch.setattr(ks, "BLOCK_THREADS", 10**6)  # (the serial pattern kernels)
    return ran


def _assemble_small():
    mesh = fm.Mesh.square(8)
    assemble_stiffness(mesh)
    assemble_mass(mesh)
    return mesh


ALL = {"_position_map_range", "_count_rows", "_stiffness_csr_range", "_mass_csr_range"}


def test_small_meshes_skip_kernels_not_in_the_process(monkeypatch):
    """Below NUMPY_BELOW triangles a kernel that is not in the process is not called (nor
    compiled); from the threshold on it is."""
    ran = _spy_kernels(monkeypatch, loaded=False)
    mesh = _assemble_small()
    assert ran == []
    monkeypatch.setattr(kt, "NUMPY_BELOW", mesh.n_triangles)  # this mesh is no longer small
    _assemble_small()
    assert set(ran) == ALL


def test_small_meshes_take_kernels_already_in_the_process(monkeypatch):
    """A kernel in the process (compiled or loaded, e.g. by warm_up) costs no compilation
    and runs faster: small meshes take it (an adaptive loop's early meshes)."""
    with kt.kernel_paths():
        _assemble_small()  # (in the process from here on, if they were not)
    ran = _spy_kernels(monkeypatch, loaded=True)
    _assemble_small()
    assert set(ran) == ALL
