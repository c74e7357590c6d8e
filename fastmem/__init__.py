"""fastmem: the two-membrane contact problem on large P1 meshes, with guaranteed error bounds.

Quick start::

    import fastmem as fm
    scene = fm.Scene(fm.Mesh.square(128), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    result = fm.solve(scene, estimate=True)
    print(result.eta, result.eta_components)
    result.save("run.h5")
"""

from importlib.metadata import PackageNotFoundError, version

from . import errors
from .archive import load
from .bound import estimate
from .config import get_threads, set_threads
from .errors import FastmemError
from .manufactured import Manufactured
from .mesh import Mesh
from .result import Estimate, Result
from .scene import Scene
from .solver import solve

try:
    __version__ = version("fastmem")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

__all__ = [
    "Estimate",
    "FastmemError",
    "Manufactured",
    "Mesh",
    "Result",
    "Scene",
    "__version__",
    "errors",
    "estimate",
    "get_threads",
    "load",
    "set_threads",
    "solve",
]
