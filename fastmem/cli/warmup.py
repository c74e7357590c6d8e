"""Compile (or load from Numba's cache) the kernels a solve needs, before the solve.

The first run of fastmem after an install compiles its Numba kernels (about
7 s on 2 cores for a default ``fastmem run``, mesh kernels included); later runs
load them from the on-disk cache (``cache=True``) in a fraction of a second.
The first use of another feature (a solve to a tolerance, another method, a
mesh read from a file, callable loads) compiles the kernels only it uses, once
(for a solve to a tolerance: the bisection kernels, and the multigrid, threaded
and large-mesh kernels its growing meshes reach, all before its solve).
:func:`warm_up` does that work on a tiny problem of the same kind, so that a
caller (the ``fastmem run`` command, a benchmark) can say what is happening and
time the solve apart from the compilation; :class:`KernelMeter` counts and
times what Numba does in other code (``fastmem run`` builds its mesh meanwhile).

Compiling is single-threaded Python work in Numba, and the flux patch kernel
is its largest part (about 40 % of a first ``fastmem run``'s).  With an empty
cache and a second core, :func:`warm_up` therefore compiles that kernel (with
the coefficient pass and the vertex colouring) in a helper process (it lands
in Numba's on-disk cache) while it compiles everything else itself, starting
with two of the patch kernel's callees (the first its typing meets, then the
largest), which the helper then loads from the cache (if it gets there first,
both compile them: slower, same result).
``fastmem run`` starts the helper before it builds its mesh.  The tiny
solve waits for the helper only when it reaches the flux reconstruction,
until the kernel it needs is in the cache (a helper asked for both patch
kernels goes on with the other), then loads it.  Before a solve to a
tolerance the helper then compiles the bisection kernels and the linear steps'
threaded passes, and the tiny adaptive solve's first refinement waits for it.
``FASTMEM_COMPILE_HELPER=0`` turns the helper off; if it fails, the kernel is
compiled in the calling process as without it.
"""

from __future__ import annotations

import importlib
import logging
import os
import pkgutil
import subprocess
import sys
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
from numba.core import event
from numba.core.dispatcher import Dispatcher

from .. import kernels
from ..errors import ParameterError, checked_keywords
from ..estimators.flux import band_plan, find_patch_classes, flux_norms, reconstruct
from ..fem.assembly import assemble_mass, assemble_stiffness
from ..fem.scene import Scene
from ..kernels import flux, rows, sparsity, sums, topology
from ..kernels import flux as _kflux
from ..linalg import gmg
from ..linalg.amg import precompile
from ..linalg.sparse import ThreadedCSR, masked_gap, read_only
from ..mesh import refine as _refine
from ..mesh.coarsen import locate
from ..mesh.mesh import Mesh
from ..pipeline import solve
from ..problems.obstacles import ball
from ..solver import linear, nested
from ..solver.options import METHODS

logger = logging.getLogger(__name__)

__all__ = ["KernelMeter", "WarmUp", "kernels_cached", "warm_up"]


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
    helper : bool
        Whether a helper process compiled some of them.
    helper_kernels : str
        Which, in words ("the flux kernel", "the bisection kernels", or both).
    """

    seconds: float
    compiled: int
    loaded: int
    helper: bool = False
    helper_kernels: str = "the flux kernel"

    def __str__(self) -> str:
        what = f"{self.compiled} compiled"
        if self.helper:
            what += f" here, {self.helper_kernels} in a helper process;"
        else:
            what += ","
        return f"{self.seconds:.2f} s ({what} {self.loaded} loaded from cache)"


def _dispatchers() -> list:
    """Every Numba dispatcher defined at module level in :mod:`fastmem.kernels`."""
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


class KernelMeter:
    """What Numba does for fastmem's kernels from the meter's creation on.

    ``compiled`` and ``loaded`` count the kernel specialisations compiled and
    loaded from Numba's cache since then (as :class:`WarmUp` does), in any code;
    :meth:`timing` adds the seconds Numba spends compiling inside a ``with``
    block to ``compile_seconds`` (Numba's ``"numba:compile"`` events, nested
    compilations counted once), so that a caller can book the compilation of
    kernels its own work triggers (``fastmem run``: building the mesh) as
    compilation, and the rest as that work.

    Parameters
    ----------
    dispatchers : list of numba dispatchers, optional
        The kernels to count (default: every kernel of :mod:`fastmem.kernels`).
    """

    def __init__(self, dispatchers=None):
        self._dispatchers = _dispatchers() if dispatchers is None else list(dispatchers)
        self._start = _counts(self._dispatchers)
        self.compile_seconds = 0.0

    @property
    def compiled(self) -> int:
        """Kernel specialisations compiled since the meter was created."""
        return _counts(self._dispatchers)[1] - self._start[1]

    @property
    def loaded(self) -> int:
        """Kernel specialisations loaded from Numba's cache since the meter was created."""
        return _counts(self._dispatchers)[0] - self._start[0]

    @contextmanager
    def timing(self):
        """Add the seconds Numba spends compiling inside the block to ``compile_seconds``."""

        def add(seconds: float) -> None:
            self.compile_seconds += seconds

        with event.install_timer("numba:compile", add):
            yield self


def kernels_cached(which: str = "pipeline") -> bool | None:
    """Whether Numba's cache holds compiled code for fastmem's kernels (a hint).

    ``which="pipeline"`` (default) looks at the largest kernels of a default
    solve, so that it turns True after the first ``fastmem run``; ``"all"``
    at every kernel, including those a default solve never uses (mesh
    refinement, nested dissection).  Looks for the cache index file of each
    kernel (where Numba would write it, including its fallback cache
    directory).  Returns None when that cannot be determined (a Numba version
    with another cache layout).  A cached kernel whose source changed since is
    still recompiled: this is a hint for progress messages, not a promise.
    """
    if which not in ("pipeline", "all"):
        raise ValueError(f"which must be 'pipeline' or 'all', got {which!r}")

    try:
        if which == "all":
            kernels = [d for d in _dispatchers() if d._can_compile]
        else:
            # (no mesh-topology or assembly kernel: small meshes build them with NumPy)
            kernels = [flux._reconstruct_chunk, flux._reduced_solve2, flux._coefficients_chunk]
        return all(_cached(d) for d in kernels)
    except Exception:  # noqa: BLE001 - private Numba layout, any failure means "unknown"
        return None


def _cached(dispatcher) -> bool:
    return os.path.exists(dispatcher._cache._cache_file._index_path)


def _cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


#: Python code the helper process runs (a module run with -m would be imported twice)
#: (the bound's contact terms first: meanwhile the caller compiles two callees of
#: the patch kernel, which the helper then finds in the cache; should the patch
#: kernel's typing reach them first, it waits for them, up to 5 s after the
#: helper's start: on a loaded machine both compiled them, 1.6 s more CPU).  It
#: imports ``fastmem.kernels`` (numpy and numba only) without running
#: ``fastmem/__init__.py``, whose imports (scipy, h5py, pyamg, the whole API: 0.35 s)
#: the helper does not need; argv: the folders of ``fastmem`` and of its kernels, then
#: the parts to compile: patch kernels (parts of :func:`fastmem.kernels.flux.precompile`)
#: and, last, ``"refinement"`` (:func:`fastmem.mesh.refine.precompile` and
#: :func:`fastmem.solver.linear.precompile`, which import the mesh and solver layers:
#: scipy too).
_HELPER_CODE = """
import importlib.util, sys, types
package = types.ModuleType("fastmem")
package.__path__ = [sys.argv[1]]
sys.modules["fastmem"] = package
spec = importlib.util.spec_from_file_location(
    "fastmem.kernels", sys.argv[2] + "/__init__.py", submodule_search_locations=[sys.argv[2]]
)
package.kernels = sys.modules["fastmem.kernels"] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(package.kernels)
import os
import time

from fastmem.kernels import flux

#: when the helper stops waiting for the caller's solvers (one deadline for both)
deadline = time.monotonic() + 5.0


def after_the_caller(dispatcher):
    # The caller compiles this callee of the patch kernel into the cache meanwhile:
    # when the patch kernel's typing reaches one before the caller has saved it (a
    # loaded machine), wait for the caller's save instead of compiling it twice.
    cache_file = dispatcher._cache._cache_file
    compile_ = dispatcher.compile

    def saved():
        if not os.path.exists(cache_file._index_path):
            return False
        names = list(cache_file._load_index().values())
        return bool(names) and all(os.path.exists(cache_file._data_path(n)) for n in names)

    def compile(sig):
        while time.monotonic() < deadline and not saved():
            time.sleep(0.01)
        return compile_(sig)

    dispatcher.compile = compile


try:
    for callee in (flux.rt1_local_xy, flux._reduced_solve2):
        after_the_caller(callee)
except Exception:  # another Numba cache layout: compile them here if they are not there
    pass
# the bound's contact terms while the caller compiles the solvers and the coefficient
# pass (the caller then loads them from the cache)
from fastmem.kernels import cut
cut.precompile()
for part in sys.argv[3:]:
    if part == "refinement":
        from fastmem.mesh.refine import precompile
        from fastmem.solver.linear import precompile as precompile_steps

        precompile()
        precompile_steps()
    else:
        flux.precompile(part)
import gc
gc.freeze()  # the caller waits for the exit: skip the shutdown collections (see fastmem.cli.main)
"""


_helper = None


def start_compile_helper(parts: tuple[str, ...] = ("patches",)) -> bool:
    """Start compiling the flux patch kernel in a helper process, if that will help.

    Only with an empty cache for that kernel, two or more usable CPUs and
    ``FASTMEM_COMPILE_HELPER`` not set to 0.  :func:`warm_up` calls it; a caller
    that has other work to do first (``fastmem run`` builds its mesh) calls it
    earlier so that the helper starts sooner.  ``parts``: the patch kernels, in
    order: ``"patches"`` (constant tensions) and/or ``"weighted"`` (per-triangle
    tensions), then optionally ``"refinement"`` (what an adaptive loop adds: the
    bisection kernels and the linear steps' threaded passes).  Returns whether a
    helper runs.
    """
    global _helper
    if _helper is not None and _helper.poll() is None:
        return True
    _helper = spawn_compile_helper(*parts)
    if _helper is None:
        return False
    # two of the patch kernel's callees here, in the order its typing meets them,
    # while the helper imports the kernels and compiles the bound's contact terms: it
    # then loads them from the cache; and the flux's coefficient pass, so that the
    # helper's share (the rest of the patch kernel, about 4.5 s) ends about when this
    # process needs it (measured: the caller waits 0.1-0.4 s; the local matrices'
    # callee, 0.6-0.9 s, moved here once small meshes stopped compiling the assembly)
    flux.precompile("callees")
    flux.precompile("solvers")
    flux.precompile("coefficients")
    return True


def _parts_of(proc) -> tuple[str, ...]:
    """Return the parts a helper compiles (those not cached when it started), from its argv."""
    return () if proc is None else tuple(proc.args[5:])  # (argv: see _HELPER_CODE)


def _patch_kernel(part: str):
    """Return the largest kernel of a helper's part (its cache entry tells the part is done)."""
    if part == "refinement":  # (its last kernel: fastmem.solver.linear.precompile's)
        return rows.decoupled_triple_range
    if part not in ("patches", "weighted"):
        raise ValueError(f"part must be 'patches', 'weighted' or 'refinement', got {part!r}")
    return flux._reconstruct_chunk_weighted if part == "weighted" else flux._reconstruct_chunk


def spawn_compile_helper(*parts: str):
    """Compile flux patch kernels (parts of :func:`fastmem.kernels.flux.precompile`) apart.

    And, after them, the bisection kernels and the linear steps' threaded passes
    (part ``"refinement"``).  Returns the
    process (wait for it with :func:`join_compile_helper`), or None where a
    helper would not help: those kernels are cached already, fewer than two
    CPUs, ``FASTMEM_COMPILE_HELPER=0``, or the process cannot start.
    """
    if parts and parts[0] == "refinement":
        raise ValueError("the helper's first part must be a patch kernel ('patches' or 'weighted')")
    kernels_of = [_patch_kernel(part) for part in parts]
    if os.environ.get("FASTMEM_COMPILE_HELPER", "1").strip().lower() in ("0", "no", "false", "off"):
        return None
    try:
        # (a cached patch kernel and "refinement" to do: a helper for that one alone,
        # as before the first solve to a tolerance after a first plain run)
        todo = [part for part, k in zip(parts, kernels_of, strict=True) if not _cached(k)]
        if _cpus() < 2 or not todo:
            return None
        package = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # fastmem/
        folders = [package, os.path.dirname(os.path.abspath(kernels.__file__))]
        return subprocess.Popen(
            [sys.executable, "-c", _HELPER_CODE, *folders, *todo],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
    except Exception as err:  # noqa: BLE001 - no helper: compile here, as without it
        logger.debug("no compile helper process: %s", err)
        return None


def _saved(dispatcher) -> bool:
    """Whether Numba's cache holds a complete entry for ``dispatcher`` (index and data)."""
    try:
        cache_file = dispatcher._cache._cache_file
        if not os.path.exists(cache_file._index_path):
            return False
        names = list(cache_file._load_index().values())
        return bool(names) and all(os.path.exists(cache_file._data_path(n)) for n in names)
    except Exception:  # noqa: BLE001 - being replaced, or another cache layout: not yet
        return False


def _wait_for_kernel(proc, part: str) -> bool:
    """Wait until the helper has saved the patch kernel ``part`` or has exited.

    A helper that compiles several kernels goes on with the next while the
    caller loads this one from the cache.
    """
    dispatcher = _patch_kernel(part)
    deadline = time.monotonic() + HELPER_TIMEOUT
    while proc.poll() is None and time.monotonic() < deadline:
        if _saved(dispatcher):
            return True
        time.sleep(0.01)
    return join_compile_helper(proc)


def _take_helper():
    global _helper
    proc, _helper = _helper, None
    return proc


#: seconds the tiny solve waits for the helper before compiling the kernel itself
HELPER_TIMEOUT = 300.0


def _after_the_helper(proc) -> None:
    """Wait for a helper that compiles the ``"refinement"`` part.

    If it failed, compile the linear steps' threaded passes here (the bisection
    kernels then compile as the refinement calls them).
    """
    if not join_compile_helper(proc):
        linear.precompile()


def join_compile_helper(proc) -> bool:
    """Wait for the helper; True when it finished cleanly (its kernel is in the cache)."""
    try:
        _, err = proc.communicate(timeout=HELPER_TIMEOUT)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        logger.debug("compile helper killed after %.0f s", HELPER_TIMEOUT)
        return False
    if proc.returncode != 0:
        tail = err.decode(errors="replace").strip().splitlines()[-3:]
        logger.debug("compile helper failed (exit %s): %s", proc.returncode, " | ".join(tail))
        return False
    return True


def _precompile_rows() -> None:
    """Compile Newton-min's history-row kernel with the argument types of a solve.

    Read-only mesh indices: otherwise it compiles after the wait for the helper
    (0.1 s more wall).
    """
    z = np.zeros(0)
    interior = np.zeros(0, dtype=np.int64)
    interior.setflags(write=False)
    rows.row_measures(z, z, z, interior, np.zeros(0, dtype=np.bool_), 1.0)


def _precompile_masked() -> None:
    """Compile the threaded gap-matrix and |A| |x| kernels with the argument types of a solve.

    The solvers use them from :data:`~fastmem.linalg.sparse.THREADED_ROWS` rows on
    (measured: 0.5 s of compilation inside the first solve of a ball at n = 256).
    """
    mesh = Mesh.square(4)
    a = assemble_stiffness(mesh)
    masked_gap(a, np.zeros(a.shape[0], dtype=bool))
    # and the scale of the CG's attainable residual (fastmem.linalg.amg.PCG.attainable)
    x = np.zeros(a.shape[0])
    ThreadedCSR((a.data, a.indices, a.indptr), shape=a.shape).abs_product_plus(x, x)


def _precompile_topology(edges: bool = True) -> None:
    """Compile the mesh-topology and assembly kernels (meshes of 65,536 triangles and more).

    Smaller meshes build their topology with NumPy
    (:data:`fastmem.kernels.topology.NUMPY_BELOW`), so the tiny solves never reach
    the kernels: here a tiny mesh takes them, with the types a ``Mesh`` passes.
    ``edges=False``: the checks, lumped mass and vertex patches of a mesh whose
    edges come from its parent's (:func:`fastmem.mesh.refine.refine_marked`), not
    the edge numbering of a mesh built from scratch (an adaptive loop's meshes).
    """
    base = Mesh.square(4)
    if not edges:  # (Mesh.square would compile the rows kernel of the structured triangles)
        mesh = Mesh(base.vertices.copy(), base.triangles.copy(), validate=False)
        _ = mesh.edges  # (by NumPy, outside the block: a refined mesh has its parent's)
    with topology.kernel_paths():
        if edges:
            mesh = Mesh.square(4)
            _ = mesh.edges
        _ = mesh.lumped_mass, mesh.patch_ptr, mesh.patch_triangles
        # the P1 pattern, position map, stiffness and mass kernels (smaller meshes
        # assemble with NumPy, kernels.assembly)
        assemble_stiffness(mesh)
        assemble_mass(mesh)
    # the P1 pattern of a mesh large enough for row blocks (kernels.sparsity)
    sparsity.precompile_blocks(base.n_vertices, base.edges, np.int32)


def _precompile_sums() -> None:
    """Compile the threaded sums of the bound (meshes of 131,072 triangles and more).

    The maps of :func:`fastmem.estimators.terms.combine`, the norms of
    :func:`fastmem.estimators.terms.global_terms` and of
    :func:`fastmem.estimators.terms.lumped_norm`, with the types a solve passes.
    """
    maps = [np.zeros(1) for _ in range(6)]
    sums.combine_blocks(0, 1, sums.BLOCK, *maps, np.empty((1, len(sums.COMBINE_SUMS))))
    mesh = Mesh.square(2)
    n = mesh.n_vertices
    vectors = [read_only(np.zeros(n)) for _ in range(5)]
    values = [np.zeros(n) for _ in range(4)] + [np.zeros(n, dtype=np.uint8)]
    sums.vertex_values(0, n, *vectors, mesh.lumped_mass, mesh.boundary_vertex_mask, *values)
    sums.global_blocks(
        0, 1, sums.BLOCK, mesh.triangles, mesh.areas, *values, mesh.vertices,
        read_only(np.ones(1)), np.empty((1, len(sums.GLOBAL_SUMS))),
    )  # fmt: skip
    sums.lumped_blocks(
        0, 1, sums.BLOCK, mesh.triangles, mesh.areas, vectors[0], mesh.lumped_mass,
        mesh.boundary_vertex_mask, np.empty((1, 2)),
    )  # fmt: skip


def _precompile_classes() -> None:
    """Compile the patch classes of the flux (meshes of 100,000 vertices and more).

    :func:`fastmem.estimators.flux.patch_classes` searches them only on such meshes,
    which the tiny solves do not reach: here the search runs on a 16 x 16 square (a
    few classes cover its vertices), set on the mesh, and one reconstruction with
    them compiles the class kernels with the types a solve passes; the sweep order
    of the patches on such meshes (:func:`fastmem.kernels.flux.sweep_order`) and the
    banded flux estimators (:func:`fastmem.estimators.flux.flux_norms`) too.
    """
    mesh = Mesh.square(16)
    mesh._cache["patch_classes"] = find_patch_classes(mesh)
    _kflux.precompile_grouping()  # (their hashes grouped in chunks, with many threads)
    order = np.arange(mesh.n_vertices)  # the sweep order of such meshes (one colour here)
    _kflux.sweep_order(
        order, np.array([0, order.size]), mesh.patch_ptr, mesh.patch_triangles, mesh.n_triangles
    )
    zero = np.zeros(mesh.n_vertices)
    scene = Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    reconstruct(scene, zero, zero, zero)
    # the banded flux estimators of such meshes: bands of 128 triangles here
    flux_norms(scene, zero, zero, zero, plan=band_plan(mesh, band=128))


def _precompile_cycles(large: bool, general: bool, adaptive: bool = False) -> None:
    """Compile the multigrid cycles' kernels (hybrid sweep, threaded products; nested MG).

    The hybrid sweep and the threaded products serve matrices of
    :data:`~fastmem.linalg.sparse.THREADED_ROWS` rows and more: those of a ``large``
    mesh, and the general path's reduced systems (up to two unknowns per vertex) from
    half that many vertices on; a default ``fastmem run`` (16,641 vertices) never calls
    them (0.8-1.0 s of its cold start); an ``adaptive`` loop's meshes grow to them.
    The geometric multigrid's only with ``large`` or ``adaptive``: ``multigrid="auto"``
    takes it on levels of :data:`fastmem.solver.levels.GEOMETRIC_MIN_UNKNOWNS`
    interior vertices and more (1.4 s of a cold first run otherwise spent on kernels
    a small solve never calls); the threaded nested interpolation of meshes of
    :data:`fastmem.solver.nested.KERNELS_FROM` vertices and more only with ``large``.
    """
    if large or general or adaptive:
        precompile()
    if large or adaptive:
        gmg.precompile()
    if large:  # (an adaptive loop's meshes are not nested by red refinement)
        nested.precompile()  # the nested interpolation of meshes of 65,536 vertices and more


def _precompile_locate() -> None:

    coarse = Mesh.square(2)
    locate(coarse, coarse.vertices)


@checked_keywords("fastmem.warm_up")
def warm_up(
    method: str = "inexact",
    *,
    estimate: bool = True,
    adaptive: bool = False,
    unstructured: bool = False,
    general: bool = False,
    obstacle: bool = False,
    large: bool = False,
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
        Whether its scene has per-triangle tensions: the general linear-step
        path, and the flux patch kernel of per-triangle tensions (compiled
        apart from the constant-tension one, :mod:`fastmem.kernels.flux`).
    obstacle : bool
        Whether it solves an obstacle problem (:class:`fastmem.Obstacle`): a
        tiny ball problem (docs/obstacle.md §8.1) is solved as well, which
        compiles the obstacle band kernel.
    large : bool
        Whether its mesh has at least :data:`fastmem.linalg.sparse.THREADED_ROWS`
        vertices: the active-set matrices are then built by the threaded kernels
        of :mod:`fastmem.kernels.masked`, sparse products and Gauss-Seidel sweeps
        run in the kernel threads (also with ``general``: its systems have up to
        two unknowns per vertex), nested iteration takes the geometric
        multigrid (:mod:`fastmem.kernels.mg`) and the flux reconstruction looks
        for patch classes (:func:`fastmem.kernels.flux.patch_classes`, from
        100,000 vertices on), which the tiny solves do not reach.

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
    if method not in METHODS:
        raise ParameterError(f"method must be one of {', '.join(METHODS)}, got {method!r}")

    dispatchers = _dispatchers()
    hits0, misses0 = _counts(dispatchers)
    t0 = time.perf_counter()
    uses_flux = method == "inexact" or estimate or adaptive
    part = "weighted" if general else "patches"
    parts = (part, "refinement") if adaptive else (part,)
    helper = _take_helper() if uses_flux and start_compile_helper(parts) else None
    # the bisection kernels in the helper, after the patch kernel (an adaptive
    # solve's refinement waits for it; a ``fastmem run`` started it with its parts)
    helper_parts = _parts_of(helper)
    refinement_apart = "refinement" in helper_parts
    if helper is not None:
        _kflux.compile_gate = lambda: _wait_for_kernel(helper, part)
        # meanwhile: the flux kernels the helper does not compile and, for a mesh
        # without a coarser version, the point location of its auxiliary coarse
        # mesh (otherwise compiled after the wait; nested structured meshes need none)
        _kflux.precompile("estimators")
        _precompile_rows()
        if unstructured:
            _precompile_locate()
    # an adaptive loop's meshes grow past the sizes of the threaded and nested
    # kernels: compile them here (while a helper compiles the patch kernel, on a
    # machine that has one), not inside the solve
    grows = large or adaptive
    _precompile_cycles(large, general, adaptive)  # (the tiny solve does not reach them)
    if grows:
        _precompile_masked()
        _precompile_topology(edges=large)
    if large and uses_flux:  # (meshes of 131,072 triangles and more)
        _precompile_sums()
    if large or (adaptive and not refinement_apart):
        linear.precompile()  # the linear steps' threaded passes
    if adaptive and not refinement_apart:
        _refine.precompile()
    if refinement_apart:
        _refine.compile_gate = lambda: _after_the_helper(helper)
    if uses_flux and large:
        _precompile_classes()  # meshes of 100,000 vertices and more
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
            if obstacle:
                solve(ball(16), method=method, estimate=estimate or adaptive)
    finally:
        log.setLevel(level)
        if helper is not None:
            _kflux.compile_gate = None
            _refine.compile_gate = None
            if helper.poll() is None:  # the solve never reached the flux kernel
                join_compile_helper(helper)
    seconds = time.perf_counter() - t0
    hits1, misses1 = _counts(dispatchers)
    return WarmUp(
        seconds=seconds,
        compiled=misses1 - misses0,
        loaded=hits1 - hits0,
        helper=helper is not None,
        helper_kernels=_in_words(helper_parts),
    )


def _in_words(parts: tuple[str, ...]) -> str:
    """Say what a helper with these parts compiled, for :class:`WarmUp`'s line."""
    flux_kernel = any(p in ("patches", "weighted") for p in parts)
    if flux_kernel and "refinement" in parts:
        return "the flux and bisection kernels"
    return "the bisection kernels" if "refinement" in parts else "the flux kernel"
