"""Results and their files: Result and Estimate, HDF5 archives, meshio export.

Layer 5 of docs/architecture.md: the data a solve returns and how it is written and read
(docs/archive.md).  It sits below the estimators and the solver, which build these objects.
"""

from .archive import export, info, load, save
from .result import Estimate, Result

__all__ = ["Estimate", "Result", "export", "info", "load", "save"]
