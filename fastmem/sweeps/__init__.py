"""Parameter studies: many scenes solved on dask.distributed, resumable and fault tolerant.

Layer 11 of docs/architecture.md (docs/sweeps.md).  Importing it needs nothing optional;
running a sweep needs the ``dask`` extra (dask[distributed], pandas).
"""

from .study import load_sweep, standard_scene, sweep, sweep_status

__all__ = ["load_sweep", "standard_scene", "sweep", "sweep_status"]

# The default factory's public address, as study files and sweep indexes name it
# ("fastmem.sweeps:standard_scene"); workers import it from there.
standard_scene.__module__ = __name__
