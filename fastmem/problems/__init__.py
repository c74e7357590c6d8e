"""Problems with known solutions: manufactured two-membrane solutions and Kellogg's cross point.

Layer 10 of docs/architecture.md (above :func:`fastmem.solve`): a new problem family is a
module here, plus what it needs in :mod:`fastmem.fem` and :mod:`fastmem.estimators`.
"""

from .kellogg import Kellogg
from .manufactured import Manufactured, energy_error

__all__ = ["Kellogg", "Manufactured", "energy_error"]
