"""fastmem: the two-membrane contact problem on large P1 meshes, with guaranteed error bounds.

Quick start::

    import fastmem as fm
    scene = fm.Scene(fm.Mesh.square(128), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    result = fm.solve(scene, estimate=True)
    print(result.eta, result.eta_components)
    result.save("run.h5")
"""

import importlib.util as _importlib_util
import os as _os
import sys as _sys

# OpenMP workers (Numba's "omp" threading layer) that spin while idle turn
# every short parallel kernel into a 5-15 ms wait as soon as another process
# or a BLAS thread holds a core (measured on a 2-core machine: 15 ms vs 40 us
# for an O(M) kernel on 131k triangles).  Passive waiting costs ~20 us per
# call at most.  Set before Numba starts its pool; an explicit user setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _source_tree_kernels():
    """Register ``fastmem.kernels`` when fastmem is imported from a source checkout.

    The installed package has ``fastmem/kernels`` (setup.cfg maps the top-level
    ``kernels/`` folder there).  Python started in the repository root (``python
    -m bench``, ``python -c ...``) finds the source folder ``fastmem/`` first,
    which has no ``kernels`` subfolder: load ``../kernels`` under that name.
    """
    here = _os.path.dirname(_os.path.abspath(__file__))
    if _os.path.isdir(_os.path.join(here, "kernels")) or "fastmem.kernels" in _sys.modules:
        return
    init = _os.path.join(_os.path.dirname(here), "kernels", "__init__.py")
    if not _os.path.isfile(init):
        return
    spec = _importlib_util.spec_from_file_location(
        "fastmem.kernels", init, submodule_search_locations=[_os.path.dirname(init)]
    )
    module = _importlib_util.module_from_spec(spec)
    _sys.modules["fastmem.kernels"] = module
    spec.loader.exec_module(module)
    globals()["kernels"] = module  # as the import system does for a submodule


_source_tree_kernels()

from . import errors  # noqa: E402
from .about import package_version as _package_version  # noqa: E402
from .cli.warmup import warm_up  # noqa: E402
from .config import get_threads, set_threads  # noqa: E402
from .errors import FastmemError  # noqa: E402
from .estimators.bound import estimate  # noqa: E402
from .fem.obstacle import Obstacle  # noqa: E402
from .fem.scene import Scene  # noqa: E402
from .io.archive import load  # noqa: E402
from .io.result import Estimate, Result  # noqa: E402
from .memory import keep_freed_memory as _keep_freed_memory  # noqa: E402
from .memory import release_memory  # noqa: E402
from .mesh.mesh import Mesh  # noqa: E402
from .pipeline import solve  # noqa: E402
from .problems.manufactured import Manufactured  # noqa: E402
from .sweeps.study import load_sweep, sweep  # noqa: E402

__version__ = _package_version("0+unknown")

# glibc keeps and reuses the memory fastmem frees instead of faulting it in again
# (fastmem.memory.keep_freed_memory; FASTMEM_REUSE_HEAP=0 leaves the allocator alone)
_keep_freed_memory()


def __getattr__(name):
    """``fm.twophase`` on first use (it imports pyamg: 30-40 ms of ``import fastmem``)."""
    if name == "twophase":
        import importlib  # lazy: fastmem.twophase loads pyamg, 30-40 ms measured

        return importlib.import_module(f"{__name__}.twophase")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "Estimate",
    "FastmemError",
    "Manufactured",
    "Mesh",
    "Obstacle",
    "Result",
    "Scene",
    "__version__",
    "errors",
    "estimate",
    "get_threads",
    "load",
    "load_sweep",
    "release_memory",
    "set_threads",
    "solve",
    "sweep",
    "twophase",
    "warm_up",
]
