"""Memory: the guard that refuses a run that cannot fit, and the probes it reads.

Before a solve (and before :meth:`fastmem.Mesh.rectangle` allocates a mesh) the
peak resident memory is estimated from the mesh size, the method and whether
the bound is computed (:func:`estimate_memory`), and a run that cannot fit in
the machine's memory is refused with :class:`~fastmem.errors.MemoryLimitError`
instead of being killed by the operating system (:func:`check_memory`).  The
limit is the machine's physical memory (or the cgroup limit when lower);
``fm.solve(..., memory_limit=...)`` or the environment variable
``FASTMEM_MEMORY_LIMIT`` (bytes, or with a K/M/G/T suffix; ``0``, ``off`` or
``none`` to disable) override it.  The probes (:func:`meminfo_bytes`,
:func:`rss_bytes`) are read by the solver's spilling and the layer bound's
choice of a direct solver.

This module sits on the ground floor with :mod:`fastmem.errors` and
:mod:`fastmem.config`: every layer may import it.
"""

from __future__ import annotations

import ctypes
import math
import os

import numpy as np

from .errors import MemoryLimitError, ParameterError

__all__ = [
    "MEMORY_LIMIT_ENV",
    "REUSE_HEAP_ENV",
    "check_memory",
    "estimate_memory",
    "fix_mmap_threshold",
    "meminfo_bytes",
    "keep_freed_memory",
    "memory_limit",
    "release_memory",
    "rss_bytes",
]

#: Environment variable overriding the memory limit of the guard: bytes, or a number with
#: a K, M, G or T suffix (powers of 1024); ``0``, ``off`` or ``none`` disable the check.
MEMORY_LIMIT_ENV = "FASTMEM_MEMORY_LIMIT"

#: Resident memory of a process with fastmem, numpy, scipy, numba and pyamg loaded and
#: the kernels compiled (0.21 GB measured by bench/memory.py), with a margin.
BASE_BYTES = 300_000_000

#: Peak resident bytes per vertex of a solve with the bound on a mesh with about two
#: triangles per vertex (mesh -> scene -> fm.solve -> result.save; bench/memory.py,
#: default scene, "inexact": 1070 B/vertex above BASE_BYTES at n = 2048, 1280 at n = 1024
#: where freed heap memory is not returned to the system), with a margin; "exact-amg" is
#: not measured and keeps its former figure.  "exact" adds the sparse factorisation
#: (about 3 GB per million vertices, see :data:`EXACT_MAX_VERTICES`).
SOLVE_BYTES_PER_VERTEX = {"inexact": 1350, "exact-amg": 1800, "exact": 4650}

#: Part of the peak due to the flux reconstruction (RT1 coefficients of both membranes,
#: 256 bytes per vertex, and its work arrays): not needed with ``estimate=False``.
FLUX_BYTES_PER_VERTEX = 300

#: Peak resident bytes per vertex of building a mesh and its topology (Mesh.square, edges,
#: patches; bench/memory.py phase "mesh": 470 B/vertex above BASE_BYTES), with a margin.
MESH_BYTES_PER_VERTEX = 550

_SUFFIX = {"k": 2**10, "m": 2**20, "g": 2**30, "t": 2**40}


def _effective_vertices(n_vertices: int, n_triangles: int) -> float:
    """Vertices of a two-triangles-per-vertex mesh with the same work (per-triangle arrays)."""
    return max(float(n_vertices), 0.5 * float(n_triangles))


def estimate_memory(
    n_vertices: int, n_triangles: int, method: str = "inexact", estimate: bool = True
) -> int:
    """Estimated peak resident memory (bytes) of a solve on a mesh of this size.

    A model fitted to bench/memory.py (``BASE_BYTES + bytes per vertex * N``, with
    ``N`` replaced by ``M / 2`` for meshes with more than two triangles per vertex);
    ``method=None`` estimates building the mesh alone.  Pure arithmetic: nothing is
    allocated.
    """
    nv = _effective_vertices(n_vertices, n_triangles)
    if method is None:
        per_vertex = MESH_BYTES_PER_VERTEX
    else:
        if method not in SOLVE_BYTES_PER_VERTEX:
            methods = tuple(SOLVE_BYTES_PER_VERTEX)
            raise ParameterError(f"method must be one of {methods}, got {method!r}")
        per_vertex = SOLVE_BYTES_PER_VERTEX[method]
        if not estimate and method != "inexact":
            per_vertex -= FLUX_BYTES_PER_VERTEX
    return int(BASE_BYTES + per_vertex * nv)


def _machine_memory() -> int | None:
    """Physical memory of the machine, or the cgroup memory limit when it is lower."""
    total = None
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        pass
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            with open(path, encoding="ascii") as fh:
                text = fh.read().strip()
        except OSError:
            continue
        if text.isdigit() and int(text) < (total or math.inf):
            total = int(text)
    return total


def _parse_limit(value, name):
    if value is None or value is False:
        return None
    if isinstance(value, str):
        text = value.strip().lower()
        if text in ("", "0", "off", "none", "false", "no"):
            return None
        scale = 1
        if text[-1] == "b":
            text = text[:-1]
        if text and text[-1] in _SUFFIX:
            scale, text = _SUFFIX[text[-1]], text[:-1]
        try:
            value = float(text) * scale
        except ValueError:
            raise ParameterError(
                f"{name} must be a number of bytes, optionally with a K, M, G or T suffix "
                f"(e.g. 20G), or 0/off/none; got {value!r}"
            ) from None
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ParameterError(f"{name} must be a number of bytes, None or False, got {value!r}")
    if not math.isfinite(value) or value < 0:
        raise ParameterError(f"{name} must be a non-negative number of bytes, got {value!r}")
    return None if value == 0 else int(value)


def memory_limit(limit=None) -> tuple[int | None, str]:
    """Return the memory limit of the guard in bytes (None: no check) and its source.

    ``limit``: None (default) takes the environment variable :data:`MEMORY_LIMIT_ENV`
    if it is set, else the machine's memory; ``False`` or 0 disables the check; a
    number is a limit in bytes (a string may carry a K/M/G/T suffix).
    """
    if limit is not None:
        return _parse_limit(limit, "memory_limit"), "memory_limit"
    env = os.environ.get(MEMORY_LIMIT_ENV)
    if env is not None:
        return _parse_limit(env, MEMORY_LIMIT_ENV), MEMORY_LIMIT_ENV
    return _machine_memory(), "the machine's memory"


def _gb(x) -> str:
    return f"{x / 1e9:.1f} GB"


def check_memory(
    n_vertices: int,
    n_triangles: int,
    method: str | None = "inexact",
    estimate: bool = True,
    limit=None,
) -> int:
    """Refuse a run whose estimated peak memory exceeds the limit; return the estimate.

    Parameters
    ----------
    n_vertices, n_triangles : int
        Size of the mesh (nothing is allocated: a mesh that cannot fit is refused
        before it is built).
    method : str or None
        Solve method, or None for building the mesh alone.
    estimate : bool
        Whether the bound (flux reconstruction) is computed.
    limit : None, False, int or str
        See :func:`memory_limit`.

    Raises
    ------
    MemoryLimitError
        Naming the estimate, the limit and how to override it.
    """
    need = estimate_memory(n_vertices, n_triangles, method, estimate)
    lim, source = memory_limit(limit)
    if lim is not None and need > lim:
        what = "building this mesh" if method is None else f"solving with method={method!r}"
        bound = "" if method is None else (" with the bound" if estimate else " without the bound")
        raise MemoryLimitError(
            f"not enough memory: {what}{bound} on {n_vertices} vertices and {n_triangles} "
            f"triangles needs about {_gb(need)} (estimated peak), but {source} is "
            f"{_gb(lim)}; use a smaller mesh, or override the limit with "
            f"{'' if method is None else 'memory_limit=... (fm.solve) or '}the environment "
            f"variable {MEMORY_LIMIT_ENV} (bytes or e.g. 40G; 0 disables the check)"
        )
    return need


def meminfo_bytes(key):
    """Return a field of /proc/meminfo in bytes (``"MemAvailable"``, ...), or None."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def rss_bytes():
    """Return the resident memory of this process in bytes (0 where unknown)."""
    try:
        with open("/proc/self/statm", encoding="ascii") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return 0


# ----------------------------------------------------------------------------- the heap

#: Environment variable: ``0``, ``no``, ``false`` or ``off`` leaves glibc's allocator as it
#: is (:func:`keep_freed_memory` does nothing).
REUSE_HEAP_ENV = "FASTMEM_REUSE_HEAP"

# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_MMAP_MAX = -1, -3, -4
_heap = {"libc": None, "probed": False, "kept": False}


def _glibc():
    """Return the C library (glibc: ``mallopt``, ``malloc_trim``), or None elsewhere."""
    if not _heap["probed"]:
        _heap["probed"] = True
        try:
            libc = ctypes.CDLL("libc.so.6")
            libc.mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
            libc.malloc_trim.argtypes = (ctypes.c_size_t,)
            _heap["libc"] = libc
        except (OSError, AttributeError):  # not Linux with glibc: the allocator as it is
            _heap["libc"] = None
    return _heap["libc"]


def keep_freed_memory() -> bool:
    """Let glibc keep freed memory in this process and reuse it (``import fastmem`` calls it).

    glibc maps every array above its mmap threshold (at most 32 MiB) into
    fresh pages and unmaps it when it is freed, and returns free memory at
    the top of its heap to the system; the next array then faults its pages
    in again.  fastmem allocates and frees such arrays in every phase (the
    mesh's topology, the matrices of each Newton step, the flux maps; at
    n = 2048 every vertex vector is 32 MiB), and fresh pages are slow on
    virtual machines (2.3-2.9 ms per MiB measured on the benchmark VM).
    Here glibc takes every allocation from its heap (``M_MMAP_MAX = 0``) and
    trims it only above 2 GiB of free top (``M_TRIM_THRESHOLD``), so freed
    arrays are reused in place.  Measured in one process, solves alternating
    between glibc's settings and these: at n = 2048 half the page faults,
    0.2-4 s of system time per solve instead of 3-9 s, medians 16.2 s against
    17.3 s (default scene); the peaks of ``bench.memory`` unchanged.

    The price: the process holds the memory of its largest phase until it
    exits or calls :func:`release_memory` (the sweep tasks do after each run).
    Returns True when the setting was made (glibc, and the environment
    variable :data:`REUSE_HEAP_ENV` not ``0``/``off``); a no-op elsewhere.
    """
    if _heap["kept"]:
        return True
    if os.environ.get(REUSE_HEAP_ENV, "1").strip().lower() in ("0", "no", "false", "off"):
        return False
    libc = _glibc()
    if libc is None:
        return False
    ok = libc.mallopt(_M_MMAP_MAX, 0) == 1
    ok = libc.mallopt(_M_TRIM_THRESHOLD, 2**31 - 1) == 1 and ok
    _heap["kept"] = ok
    return ok


def fix_mmap_threshold(nbytes: int) -> bool:
    """Set glibc's mmap threshold to ``nbytes`` (fixed: no longer adjusted by glibc).

    For processes where :func:`keep_freed_memory` is switched off: the sweep
    tasks in dask workers, whose ``MALLOC_TRIM_THRESHOLD_`` switches off glibc's
    dynamic threshold (:mod:`fastmem.sweeps.task`).  True when set; False
    elsewhere.
    """
    libc = _glibc()
    return libc is not None and libc.mallopt(_M_MMAP_THRESHOLD, int(nbytes)) == 1


def release_memory() -> bool:
    """Give the free memory of this process back to the system (glibc's ``malloc_trim``).

    After a large solve the process holds the memory it freed (see
    :func:`keep_freed_memory`); call this before other memory-hungry work
    that is not fastmem's.  The next fastmem run then faults its memory in
    again.  Returns True when memory was released; False elsewhere.
    """
    libc = _glibc()
    return libc is not None and bool(libc.malloc_trim(0))
