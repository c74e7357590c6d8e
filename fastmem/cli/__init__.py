"""The ``fastmem`` command (docs/cli.md), its plots, the sweep command and the kernel warm-up.

Layer 12 of docs/architecture.md, the top: it may use every layer below.
"""

from .main import main
from .plot import plot_result
from .warmup import warm_up

__all__ = ["main", "plot_result", "warm_up"]
