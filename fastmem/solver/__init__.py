"""Solving on a fixed mesh: nested iteration over levels, Newton-min, its linear steps, options.

Layer 7 of docs/architecture.md: levels -> Newton-min -> linear step (direct, AMG-CG to
round-off, or AMG-CG stopped by the estimators), one history schema for every method.
"""

from .history import HISTORY_COLUMNS
from .levels import solve_levels
from .newton import newton_min
from .options import METHODS, AdaptOptions, InnerOptions, NewtonOptions, RecordOptions, SolveOptions

__all__ = [
    "HISTORY_COLUMNS",
    "METHODS",
    "AdaptOptions",
    "InnerOptions",
    "NewtonOptions",
    "RecordOptions",
    "SolveOptions",
    "newton_min",
    "solve_levels",
]
