r"""Assembly of P1 matrices and load vectors.

All P1 matrices of a mesh share one CSR sparsity pattern, the vertex graph
(diagonal plus one entry per edge neighbour, columns sorted), built once per
mesh together with a COO -> CSR position map (:mod:`fastmem.kernels.sparsity`)
and cached on the mesh.  An assembly is then one parallel Numba pass over rows
that recomputes each patch triangle's local row and adds it through the map
(:mod:`fastmem.kernels.assembly`, ``stiffness_csr``); the two-pass COO route
(local matrices per triangle, then :func:`gather_to_csr`) gives the same
matrix bit for bit and serves general local matrices.  scipy's ``tocsr()`` (a
sort and a duplicate sum) is never called.

.. math::

    A_{ab} = (\nabla\psi_b, \nabla\psi_a), \qquad
    M_{ab} = (\psi_b, \psi_a), \qquad
    B_a = (\psi_a, 1) = |\omega_a| / 3, \qquad
    F_a = (f, \psi_a).

Pattern decision: the stored pattern is the full vertex graph, also where an
entry vanishes for geometric reasons (the stiffness across the hypotenuse of
a right triangle pair is exactly zero).  Stiffness and mass then share
``indptr``/``indices``, so sums such as ``A + c M`` keep the pattern; a solver
that iterates many times with one operator may drop the zeros once
(``eliminate_zeros``).

Load vectors: a constant ``f`` is integrated exactly as ``f B`` (no
quadrature); per-vertex values (P1 data) exactly as ``M f``; a callable
``f(x, y)`` by a quadrature rule of degree ``degree`` (default 5), evaluated
vectorised on the quadrature points, block by block
(:func:`fastmem.fem.callables.callable_integrals`; :func:`evaluate_callable` is
re-exported from there).
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp

from ..errors import DataError
from ..kernels import assembly as _k
from ..mesh.pattern import csr_structure
from .callables import callable_integrals, evaluate_callable

__all__ = [
    "DEFAULT_LOAD_DEGREE",
    "assemble_load",
    "assemble_mass",
    "assemble_stiffness",
    "evaluate_callable",
    "gather_to_csr",
]

logger = logging.getLogger(__name__)

DEFAULT_LOAD_DEGREE = 5


def _coef_array(mesh, coef, name):
    if coef is None:
        return np.ones(1)
    c = np.ascontiguousarray(coef, dtype=np.float64).reshape(-1)
    if c.size not in (1, mesh.n_triangles):
        raise DataError(
            f"{name} must be a scalar or have one value per triangle ({mesh.n_triangles}), "
            f"got {c.size} values"
        )
    return c


def gather_to_csr(mesh, vals) -> sp.csr_matrix:
    """CSR matrix from per-triangle local matrices ``vals`` (M, 3, 3) (the COO route)."""
    indptr, _, offsets = csr_structure(mesh)
    data = _k.gather_csr(
        vals, indptr, offsets, mesh.patch_ptr, mesh.patch_triangles, mesh.patch_local
    )
    return _csr(mesh, data)


def _csr(mesh, data):
    indptr, indices, _ = csr_structure(mesh)
    n = mesh.n_vertices
    mat = sp.csr_matrix((data, indices, indptr), shape=(n, n), copy=False)
    mat.has_sorted_indices = True
    return mat


def assemble_stiffness(mesh, coef=None) -> sp.csr_matrix:
    """P1 stiffness matrix ``(coef grad psi_b, grad psi_a)`` in CSR form.

    Parameters
    ----------
    mesh : Mesh
    coef : float or ndarray of shape (M,), optional
        Piecewise-constant coefficient (default 1).

    Notes
    -----
    Convenience wrapper around the Numba kernel ``stiffness_csr`` (local
    matrices fused with the gather into CSR, parallel over rows).
    """
    return _fused(mesh, _k.stiffness_csr, mesh.vertices, mesh.triangles, coef)


def assemble_mass(mesh, coef=None) -> sp.csr_matrix:
    """Consistent P1 mass matrix ``(coef psi_b, psi_a)`` in CSR form (same pattern as A)."""
    return _fused(mesh, _k.mass_csr, mesh.areas, coef)


def _fused(mesh, kernel, *args):
    """Run a fused local-matrix + gather kernel; the last of ``args`` is the coefficient."""
    indptr, _, offsets = csr_structure(mesh)
    coef = _coef_array(mesh, args[-1], "coef")
    patches = (mesh.patch_ptr, mesh.patch_triangles, mesh.patch_local)
    return _csr(mesh, kernel(*args[:-1], coef, indptr, offsets, *patches))


def assemble_load(mesh, f, degree: int = DEFAULT_LOAD_DEGREE, name: str = "f") -> np.ndarray:
    """Load vector ``F_a = (f, psi_a)``.

    Parameters
    ----------
    mesh : Mesh
    f : float, ndarray of shape (N,), or callable
        Constant (integrated exactly: ``f * B``), nodal values of a P1
        function (exactly: ``M f``), or ``f(x, y)`` evaluated vectorised at the
        points of a quadrature rule of degree ``degree``.
    degree : int
        Quadrature degree for callables.
    name : str
        Name used in error messages.

    Returns
    -------
    ndarray of shape (N,)
    """
    pp, pt, pl = mesh.patch_ptr, mesh.patch_triangles, mesh.patch_local
    if callable(f):  # blocked pass over the quadrature points (shared with the estimators)
        return callable_integrals(mesh, f, degree, name)["F"]
    arr = np.asarray(f, dtype=np.float64)
    if arr.ndim == 0:
        return float(arr) * mesh.lumped_mass
    if arr.shape != (mesh.n_vertices,):
        raise DataError(
            f"{name} as an array must have one value per vertex, shape ({mesh.n_vertices},), "
            f"got {arr.shape}"
        )
    ft = arr[mesh.triangles]  # (M, 3)
    local = (ft + ft.sum(axis=1, keepdims=True)) * (mesh.areas / 12.0)[:, None]
    return _k.gather_vector(local, pp, pt, pl)
