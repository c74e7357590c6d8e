"""The P1 sparsity pattern of a mesh: one row per vertex, one entry per vertex and edge end."""

from __future__ import annotations

import numpy as np

from ..errors import MeshError
from ..kernels import sparsity as _sp

__all__ = ["csr_structure"]


def csr_structure(mesh):
    """Return ``(indptr, indices, offsets)`` of the mesh's P1 pattern (cached on the mesh).

    ``indptr``/``indices`` are int32 while the number of stored entries fits,
    else int64; ``offsets`` (M, 3, 3) uint16 is the COO -> CSR position map.
    """
    cache = mesh._cache
    if "csr_structure" not in cache:
        n = mesh.n_vertices
        nnz = n + 2 * mesh.n_edges
        index_dtype = np.int32 if nnz < np.iinfo(np.int32).max else np.int64
        indptr, indices = _sp.csr_pattern(n, mesh.edges, index_dtype, mesh.n_triangles)
        longest = int(np.diff(indptr).max()) if n else 0  # (rows counted by the kernel)
        if longest > np.iinfo(np.uint16).max:
            raise MeshError(f"a vertex has {longest - 1} neighbours; at most 65534 are supported")
        offsets = _sp.position_map(mesh.triangles, indptr, indices)
        cache["csr_structure"] = (indptr, indices, offsets)
    return cache["csr_structure"]
