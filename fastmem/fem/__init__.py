"""The discretisation: the Scene (problem data on a mesh), P1 assembly, quadrature, residuals.

Layer 4 of docs/architecture.md: everything that turns data on a mesh into matrices and
vectors, and a triple back into its discrete residual.
"""

from .assembly import assemble_load, assemble_mass, assemble_stiffness
from .quadrature import quadrature_points, triangle_rule
from .residual import residuals
from .scene import Scene

__all__ = [
    "Scene",
    "assemble_load",
    "assemble_mass",
    "assemble_stiffness",
    "quadrature_points",
    "residuals",
    "triangle_rule",
]
