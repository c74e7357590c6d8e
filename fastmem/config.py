"""Run-time settings: the thread pools of the Numba kernels and of BLAS.

fastmem runs two kinds of parallel work: Numba kernels (serial kernels over
ranges of triangles or vertex patches, run by a pool of threads,
``fastmem.kernels.pool``) and BLAS calls inside scipy/pyamg.  On a small
machine the two pools compete for the same cores; measured on a 2-core machine,
OpenBLAS at its default of 2 threads made pyamg 2.5-20x slower than with one
thread.  fastmem therefore limits the BLAS pool to :data:`blas_threads` (default
1) inside its solver phases, and leaves the Numba pool at
:func:`numba.get_num_threads` unless :func:`set_threads` says otherwise.

The kernels' fastmath flags live with the kernels (``fastmem.kernels.FASTMATH``,
set in ``kernels/_jit.py``).
"""

from __future__ import annotations

import contextlib
import os
import sys

import numba as _nb
from threadpoolctl import ThreadpoolController

from .errors import InputTypeError, ParameterError

__all__ = ["blas_limits", "check_count", "get_threads", "set_threads"]

_settings = {"blas_threads": int(os.environ.get("FASTMEM_BLAS_THREADS", "1"))}


def check_count(name, value):
    """Return ``value`` as an int, refusing anything but a positive integer (naming ``name``)."""
    if isinstance(value, bool) or not hasattr(value, "__index__"):
        raise InputTypeError(f"{name} must be a positive integer, got {value!r}")
    value = int(value)
    if value < 1:
        raise ParameterError(f"{name} must be a positive integer, got {value!r}")
    return value


def set_threads(numba: int | None = None, blas: int | None = None) -> None:
    """Set the Numba thread count and the BLAS thread limit used in solver phases.

    Parameters
    ----------
    numba : int, optional
        Threads for the parallel Numba kernels (at most ``NUMBA_NUM_THREADS``).
    blas : int, optional
        Threads the BLAS pool (OpenBLAS, MKL) may use inside solver phases.
    """
    # validate everything before changing anything
    n = None if numba is None else check_count("numba threads", numba)
    b = None if blas is None else check_count("blas threads", blas)
    if n is not None and n > _nb.config.NUMBA_NUM_THREADS:
        raise ParameterError(
            f"numba threads must be <= NUMBA_NUM_THREADS={_nb.config.NUMBA_NUM_THREADS}, got {n}"
        )
    if n is not None:
        _nb.set_num_threads(n)
    if b is not None:
        _settings["blas_threads"] = b


def get_threads() -> dict:
    """Return the current thread settings as ``{"numba": int, "blas": int}``."""
    return {"numba": _nb.get_num_threads(), "blas": _settings["blas_threads"]}


#: threadpoolctl's view of the loaded BLAS libraries and ``len(sys.modules)`` when it was
#: taken: building it scans the process's shared libraries (2.2 ms, at every solve with
#: ``threadpool_limits``), so it is kept until a module has been imported since (a new
#: extension module may have loaded another BLAS).
_blas = {"controller": None, "modules": -1}


def _blas_controller() -> ThreadpoolController:
    if _blas["controller"] is None or _blas["modules"] != len(sys.modules):
        _blas["controller"] = ThreadpoolController()
        _blas["modules"] = len(sys.modules)
    return _blas["controller"]


@contextlib.contextmanager
def blas_limits(threads: int | None = None):
    """Limit the BLAS thread pool to ``threads`` (default: the configured value) in a block.

    The libraries are those loaded when the block starts (threadpoolctl's scan, kept
    between blocks while no module is imported: 0.04 ms per block instead of 2.2 ms).
    """
    n = _settings["blas_threads"] if threads is None else check_count("blas threads", threads)
    with _blas_controller().limit(limits=n, user_api="blas"):
        yield
