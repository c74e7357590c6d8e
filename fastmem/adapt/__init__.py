"""Solving to a tolerance: the loop SOLVE -> ESTIMATE -> MARK -> REFINE (docs/method.md §9).

Layer 8 of docs/architecture.md.
"""

from .loop import indicators, refine_scene, solve_to_tolerance

__all__ = ["indicators", "refine_scene", "solve_to_tolerance"]
