"""Triangular meshes: validation, topology, generators, file I/O, refinement and coarsening.

Layer 3 of docs/architecture.md: geometry and connectivity, no problem data.
"""

from .coarsen import coarse_mesh
from .mesh import Mesh
from .pattern import csr_structure
from .refine import Refinement, dorfler_mark, refine_marked

__all__ = ["Mesh", "Refinement", "coarse_mesh", "csr_structure", "dorfler_mark", "refine_marked"]
