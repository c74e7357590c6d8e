"""Compile (or load from Numba's cache) the kernels a solve needs, before the solve.

The first run of fastmem after an install compiles its Numba kernels (about
20 s on 2 cores); later runs load them from the on-disk cache (``cache=True``)
in a fraction of a second.  :func:`warm_up` does that work on a tiny problem of
the same kind, so that a caller (the ``fastmem run`` command, a benchmark) can
say what is happening and time the solve apart from the compilation.
"""

from __future__ import annotations

import importlib
import logging
import pkgutil
import time
import warnings
from dataclasses import dataclass

__all__ = ["WarmUp", "kernels_cached", "warm_up"]


@dataclass(frozen=True)
class WarmUp:
    """What :func:`warm_up` did.

    Attributes
    ----------
    seconds : float
        Wall time of the warm-up (compilation or cache loading, plus a solve of
        a few hundred vertices).
    compiled : int
        Kernel specialisations compiled (not found in Numba's cache).
    loaded : int
        Kernel specialisations loaded from Numba's cache.
    """

    seconds: float
    compiled: int
    loaded: int

    def __str__(self) -> str:
        what = f"compiled {self.compiled}" if self.compiled else "none compiled"
        return f"{self.seconds:.2f} s ({what}, {self.loaded} loaded from cache)"


def _dispatchers() -> list:
    """Every Numba dispatcher defined at module level in :mod:`fastmem.kernels`."""
    from numba.core.dispatcher import Dispatcher

    from . import kernels

    found = []
    for info in pkgutil.iter_modules(kernels.__path__):
        module = importlib.import_module(f"{kernels.__name__}.{info.name}")
        for value in vars(module).values():
            if isinstance(value, Dispatcher) and value.__module__ == module.__name__:
                found.append(value)
    return found


def _counts(dispatchers) -> tuple[int, int]:
    hits = misses = 0
    for d in dispatchers:
        stats = d.stats
        hits += sum(stats.cache_hits.values())
        misses += sum(stats.cache_misses.values())
    return hits, misses


def kernels_cached() -> bool | None:
    """Whether Numba's cache holds compiled code for every fastmem kernel.

    Looks for the cache index file of each kernel (where Numba would write it,
    including its fallback cache directory).  Returns None when that cannot be
    determined (a Numba version with another cache layout).  A cached kernel
    whose source changed since is still recompiled: this is a hint for
    progress messages, not a promise.
    """
    import os

    try:
        return all(
            os.path.exists(d._cache._cache_file._index_path)
            for d in _dispatchers()
            if d._can_compile
        )
    except Exception:  # noqa: BLE001 - private Numba layout, any failure means "unknown"
        return None


def warm_up(
    method: str = "inexact",
    *,
    estimate: bool = True,
    adaptive: bool = False,
    unstructured: bool = False,
    general: bool = False,
) -> WarmUp:
    """Compile or load every kernel a solve of this kind needs, on a tiny problem.

    Parameters
    ----------
    method : {"inexact", "exact-amg", "exact"}
        The solver method of the solve to come.
    estimate : bool
        Whether the solve to come computes the error bound.
    adaptive : bool
        Whether it solves to a tolerance (mesh refinement kernels).
    unstructured : bool
        Whether its mesh has no coarser version (auxiliary coarse meshes).
    general : bool
        Whether it takes the general linear-step path (per-triangle mu).

    Returns
    -------
    WarmUp
        Seconds spent and the number of kernel specialisations compiled and
        loaded from the cache.

    Notes
    -----
    A 32 x 32 square (1089 vertices) is the smallest structured mesh whose
    nested iteration reaches every kernel of the default pipeline.  Kernels of
    callable loads are compiled by the scene that uses them, on first use.
    """
    import numpy as np

    from .mesh import Mesh
    from .options import METHODS
    from .scene import Scene
    from .solver import solve

    if method not in METHODS:
        from .errors import ParameterError

        raise ParameterError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    dispatchers = _dispatchers()
    hits0, misses0 = _counts(dispatchers)
    t0 = time.perf_counter()
    if adaptive:
        mesh = Mesh.lshape(4)
    elif unstructured:
        base = Mesh.square(32)
        rng = np.random.default_rng(0)
        vertices = base.vertices.copy()
        inner = ~base.boundary_vertex_mask
        vertices[inner] += rng.uniform(-0.2, 0.2, size=(int(inner.sum()), 2)) / 16
        mesh = Mesh(vertices, base.triangles)
    else:
        mesh = Mesh.square(32)
    if general:
        x = mesh.vertices[mesh.triangles, 0].mean(axis=1)
        mu1 = np.where(x < 0, 1.0, 2.0)
    else:
        mu1 = 1.0
    scene = Scene(mesh, mu=(mu1, 1.0), f=(-1.0, 1.0), g=0.1)
    keywords = {"tol": 1e-9, "max_levels": 3} if adaptive else {}
    log = logging.getLogger("fastmem")
    level = log.level
    log.setLevel(logging.ERROR)  # "stopped before the tolerance" and the like: expected here
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            solve(scene, method=method, estimate=estimate or adaptive, **keywords)
    finally:
        log.setLevel(level)
    seconds = time.perf_counter() - t0
    hits1, misses1 = _counts(dispatchers)
    return WarmUp(seconds=seconds, compiled=misses1 - misses0, loaded=hits1 - hits0)
