"""Linear algebra: algebraic multigrid (pyamg) with a resumable PCG, and sparse direct factors.

Layer 2 of docs/architecture.md: knows matrices and vectors, nothing of meshes.
"""

from .amg import PCG, LazyAMG, amg_preconditioner
from .direct import Factorization, factorize
from .sparse import threaded

__all__ = ["PCG", "Factorization", "LazyAMG", "amg_preconditioner", "factorize", "threaded"]
