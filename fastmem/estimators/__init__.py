"""The guaranteed a posteriori bound: flux reconstruction, estimator terms, layer bounds.

Layer 6 of docs/architecture.md (docs/method.md §4-6): :func:`estimate` bounds the energy
error of any triple; :func:`evaluate` is the solver's entry with its reusable parts.
"""

from .bound import estimate, evaluate
from .flux import Fluxes, reconstruct

__all__ = ["Fluxes", "estimate", "evaluate", "reconstruct"]
