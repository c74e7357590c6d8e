"""Parameter sweeps: many scenes solved on dask.distributed, resumable and fault tolerant.

A sweep solves one scene per parameter set and keeps every result as its own
archive::

    import fastmem as fm

    def make_scene(mu2, g, n=64):          # module level: workers import it by name
        mesh = fm.Mesh.square(n)
        return fm.Scene(mesh, mu=(1.0, mu2), f=(-1.0, 1.0), g=g)

    table = fm.sweep(make_scene, {"mu2": [0.5, 1, 2], "g": [0.0, 0.1]}, "study/")
    table = fm.load_sweep("study/")       # the same table later, without solving

Needs the ``dask`` extra (``pip install "fastmem[dask]"``: dask.distributed
and pandas), imported only when a sweep runs or a table is built.

The study folder::

    study/sweep-index.h5     the index: one row per run (rewritten atomically)
    study/runs/<name>.h5     one fastmem result archive per finished run
    study/archive-writes.log one JSON line per archive written (audit of "none twice")
    study/claims/            one claim file per run and attempt (fastmem.sweeps.claims)
    study/.sweep.lock        held (flock) by the client running the sweep

Rules (docs/sweeps.md has the reasons):

* **Runs.** ``grid`` is a dict of parameter lists (their cartesian product, in
  the order given; a scalar is a fixed value) or a list of dicts.  Values are
  numbers, strings, booleans or None; names are Python identifiers, passed to
  the factory as keywords.  A run's identity is the canonical JSON of its
  parameters (keys sorted): the archive name is ``<readable fields>__<first 12
  hex digits of its SHA-256>.h5``, the same in every process and on every
  machine.  ``1`` and ``1.0`` are different parameter values.  A factory with
  a ``validate`` attribute has every run checked by it before anything starts.
* **Done.** A run is done when its archive exists, :func:`fastmem.load`
  validates it (fastmem's checksummed format) and it records the same
  parameters.  A sweep first checks this for every run (in the client) and
  submits only the others; the task checks again before solving and before
  writing, so that a task retried after its worker died once the archive was
  written does not solve it again.
* **Once.** Before making its scene a task claims its run (a claim file in
  ``claims/``, see :mod:`fastmem.sweeps.claims`); a task that finds a live
  claim waits for that owner's archive instead of solving.  This covers the
  orphans of a dead client on an existing cluster, which dask keeps executing
  while it hands the restarted sweep's runs to other workers.
* **Failures.** A factory or solve that raises is recorded (status
  ``failed``, the exception text in ``error``, the traceback in the index)
  and the other runs go on.  A worker that dies (killed, out of memory) has
  its tasks retried on other workers by the scheduler, up to ``max_retries``
  deaths per task (dask's ``distributed.scheduler.allowed-failures``); then
  the run is recorded as failed with dask's ``KilledWorker`` message.  A new
  sweep of the same study tries every run without a valid archive again.
* **Index.** HDF5 (h5py, already a core dependency; no pyarrow), rewritten
  after every completed run through a temporary file renamed onto
  ``sweep-index.h5``: readers never see half a table.  The archives are the
  truth, the index their summary: a client killed between an archive and the
  index write loses nothing, the next sweep finds the archive.
* **Threads.** With ``client=None`` a :class:`distributed.LocalCluster` of
  processes: ``workers`` (default: the number of cores) processes with one
  task thread each; Numba threads per worker = cores // workers (each task
  calls :func:`numba.set_num_threads` before solving); BLAS threads 1
  (dask's ``OMP/OPENBLAS/MKL_NUM_THREADS=1`` in its workers, and
  :func:`fastmem.solve` limits BLAS to 1 in its solver phases anyway).  On an
  existing cluster each task sets Numba threads = cores of its host // task
  threads of all workers on that host (or ``numba_threads``).
* **Workers and the main script.** LocalCluster workers are spawned and run
  the main script again: a sweep from the top level of a script without an
  ``if __name__ == "__main__":`` guard, or from a script read from stdin, is
  refused up front (:mod:`fastmem.sweeps.spawn`).
* **Quiet.** distributed's INFO log is off while the sweep's cluster or client
  is open (WARNING and above pass), in the workers too, and the LocalCluster
  has no dashboard (:mod:`fastmem.sweeps.engine`).
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import numbers
import os
import time
import traceback
import uuid
from pathlib import Path

import numpy as np

from ..errors import InputTypeError, ParameterError
from ..fem.scene import Scene
from ..mesh.mesh import Mesh

# The pieces of a sweep live in fastmem.sweeps.grid (grid, names, checks),
# fastmem.sweeps.task (the worker's task and the rows), fastmem.sweeps.index (index,
# table, status, lock) and fastmem.sweeps.engine (cluster, threads); their names are
# re-exported here, the module users and fastmem.cli.sweep import.
from .engine import _connect as _connect
from .engine import _host as _host
from .engine import _restored_environ as _restored_environ
from .engine import _threads_by_host as _threads_by_host
from .grid import INDEX_NAME as INDEX_NAME
from .grid import LOCK_NAME as LOCK_NAME
from .grid import MISSING_DASK as MISSING_DASK
from .grid import RUNS_DIR as RUNS_DIR
from .grid import TABLE_COLUMNS as TABLE_COLUMNS
from .grid import WRITE_LOG as WRITE_LOG
from .grid import _check_runs as _check_runs
from .grid import _check_signature as _check_signature
from .grid import _check_solve_options as _check_solve_options
from .grid import _factory_name as _factory_name
from .grid import _positive as _positive
from .grid import _require_dask as _require_dask
from .grid import _require_pandas as _require_pandas
from .grid import expand_grid as expand_grid
from .grid import run_name as run_name
from .index import _frame as _frame
from .index import _read_index as _read_index
from .index import _study_lock as _study_lock
from .index import _write_index as _write_index
from .index import load_sweep as load_sweep
from .index import sweep_status as sweep_status
from .spawn import check_main_script
from .task import _failed_row as _failed_row
from .task import _Job as _Job
from .task import _pending_row as _pending_row
from .task import _run_job as _run_job
from .task import _summary as _summary
from .task import _valid_archive as _valid_archive

__all__ = [
    "INDEX_NAME",
    "MISSING_DASK",
    "TABLE_COLUMNS",
    "expand_grid",
    "load_sweep",
    "run_name",
    "standard_scene",
    "sweep",
    "sweep_status",
]

_GATE_SECONDS = 0.5  # progress "tick" period while no run completes


# ----------------------------------------------------------------------------- one run


def standard_scene(
    n: int = 128,
    domain: str = "square",
    refine: int = 0,
    mu1: float = 1.0,
    mu2: float = 1.0,
    f1: float = -1.0,
    f2: float = 1.0,
    g: float = 0.1,
):
    """Build the scene of ``fastmem run`` from its options (default factory of ``fastmem sweep``).

    Parameters
    ----------
    n : int
        Cells per side of the structured mesh.
    domain : {"square", "lshape"}
        ``Mesh.square(n)`` on (-1, 1)^2 or ``Mesh.lshape(n)``.
    refine : int
        Uniform refinements applied to the mesh.
    mu1, mu2, f1, f2, g : float
        Tensions, constant loads and the boundary value of ``u1``.

    Returns
    -------
    fastmem.Scene

    Notes
    -----
    ``standard_scene.validate(**params)`` runs the same checks without building
    the mesh (the mesh options as the generators check them, the data as
    :class:`fastmem.Scene` does, on two triangles); :func:`sweep` calls it for
    every run before anything starts.
    """
    _check_mesh_options(n, domain, refine)
    mesh = Mesh.lshape(n) if domain == "lshape" else Mesh.square(n)
    for _ in range(refine):
        mesh = mesh.refine()
    return Scene(mesh, mu=(mu1, mu2), f=(f1, f2), g=g)


def _check_mesh_options(n, domain, refine) -> None:
    """Check the mesh options of :func:`standard_scene` as the mesh generators do."""
    if domain not in ("square", "lshape"):
        raise ParameterError(f"domain must be 'square' or 'lshape', got {domain!r}")
    if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 1:
        raise ParameterError(f"n must be a positive integer, got {n!r}")
    if domain == "lshape" and n % 2:
        raise ParameterError(f"n must be even for the L-shaped domain, got {n}")
    if isinstance(refine, bool) or not isinstance(refine, int) or refine < 0:
        raise ParameterError(f"refine must be an integer >= 0, got {refine!r}")


@functools.lru_cache(maxsize=1)
def _unit_square() -> Mesh:
    """Two triangles on (-1, 1)^2: the mesh on which a run's scene data are checked."""
    vertices = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    return Mesh(vertices, np.array([[0, 1, 2], [0, 2, 3]]))


def _validate_standard_scene(**params) -> None:
    """Check the parameters of a :func:`standard_scene` run without building its mesh.

    ``standard_scene.validate``: :func:`sweep` calls it for every run before
    anything starts.  The mesh options get the generators' checks; mu1, mu2,
    f1, f2 and g the checks of :class:`fastmem.Scene`, on two triangles (data
    that only a fine mesh puts out of range are still found by the run).
    """
    args = inspect.signature(standard_scene).bind(**params)
    args.apply_defaults()
    p = args.arguments
    _check_mesh_options(p["n"], p["domain"], p["refine"])
    Scene(_unit_square(), mu=(p["mu1"], p["mu2"]), f=(p["f1"], p["f2"]), g=p["g"])


standard_scene.validate = _validate_standard_scene


# ----------------------------------------------------------------------------- the sweep


def _study_folder(out, spec) -> Path:
    try:
        folder = Path(os.fspath(out))
    except TypeError as exc:
        raise InputTypeError(f"out must be a folder path, got {out!r}") from exc
    if folder.exists() and not folder.is_dir():
        raise ParameterError(f"out={folder} exists and is not a folder")
    if (folder / INDEX_NAME).exists():
        old = _read_index(folder)[0]["spec"]
        for part in ("factory", "solve_options"):
            if old.get(part) != spec[part]:
                raise ParameterError(
                    f"study {folder} was run with {part} {old.get(part)!r}, this sweep asks for "
                    f"{spec[part]!r}: a study holds the runs of one factory and one set of "
                    "solve options; use another folder"
                )
    return folder


def sweep(
    make_scene,
    grid,
    out,
    *,
    solve_options: dict | None = None,
    client=None,
    workers: int | None = None,
    numba_threads: int | None = None,
    max_retries: int = 3,
    progress=None,
):
    """Solve one scene per parameter set on dask.distributed; keep each result as an archive.

    Resumable: runs with a valid archive in ``out`` are not solved again, so
    calling the same sweep after an interruption (or with more grid points)
    completes only the missing runs.  See the module docstring for the rules
    and docs/sweeps.md for the reasons.

    Parameters
    ----------
    make_scene : function
        ``make_scene(**params) -> fastmem.Scene``, a function defined with
        ``def`` at the top level of a module (workers import it by name).
        Lambdas, nested functions and other callables are refused.  If it has
        a ``validate`` attribute, a function of the same keywords that raises
        for values the factory would refuse, every run is checked with it
        first (:func:`standard_scene` has one).
    grid : dict or list of dict
        The runs (see :func:`expand_grid`).
    out : str or os.PathLike
        The study folder (created).  It belongs to one factory and one set of
        solve options; runs of earlier sweeps stay in its index.
    solve_options : dict, optional
        Keywords of :func:`fastmem.solve` for every run (JSON values: method,
        tol, ...; not ``monitor``, ``level_monitor``, ``initial``).
    client : None, str or distributed.Client
        None: a new :class:`distributed.LocalCluster` of ``workers`` processes
        (closed at the end).  A scheduler address (``"tcp://host:8786"``): an
        existing cluster.  A Client: used as it is (not closed).
    workers : int, optional
        Worker processes of the LocalCluster (default: the number of cores).
    numba_threads : int, optional
        Numba threads per task (default: cores // workers per host).
    max_retries : int
        LocalCluster only: how many worker deaths a task survives before it is
        recorded as failed (dask's ``allowed-failures``; an existing cluster
        keeps its scheduler's setting).
    progress : callable, optional
        Called with a dict after every completed run (``event="run"``,
        ``row``), about twice a second while runs are on workers
        (``event="tick"``), and at ``"start"`` and ``"end"``; keys ``total``,
        ``done``, ``failed``, ``running``, ``remaining``, ``skipped`` (done
        before this sweep), ``elapsed`` and ``eta`` (seconds, or None).

    Returns
    -------
    pandas.DataFrame
        The rows of this grid's runs, in grid order (columns as in
        :func:`load_sweep`).

    Raises
    ------
    InputTypeError, ParameterError
        For an unusable factory, grid, solve options or folder, runs that
        ``make_scene.validate`` refuses, or (``client=None``) a call from the
        top level of a script without an ``if __name__ == "__main__":`` guard
        or from a script read from standard input, whose worker processes
        could not start (:mod:`fastmem.sweeps.spawn`); before anything is
        created or started.
    ArchiveError
        If another sweep is running in ``out``.
    ImportError
        Without the ``dask`` extra.
    """
    factory = _factory_name(make_scene)
    runs = expand_grid(grid)
    _check_signature(make_scene, runs)
    options = _check_solve_options(solve_options)
    workers = _positive("workers", workers)
    numba_threads = _positive("numba_threads", numba_threads)
    max_retries = _positive("max_retries", max_retries, allow_none=False)
    if progress is not None and not callable(progress):
        raise InputTypeError(f"progress must be callable, got {type(progress).__name__}")
    _check_runs(make_scene, runs)
    check_main_script(client)
    spec = {"factory": factory, "solve_options": options}
    folder = _study_folder(out, spec)
    _require_dask(), _require_pandas()
    (folder / RUNS_DIR).mkdir(parents=True, exist_ok=True)
    with _study_lock(folder):
        return _Sweep(make_scene, runs, folder, spec, progress).run(
            client, workers, numba_threads, max_retries
        )


class _Sweep:
    """The client side of one sweep: bookkeeping, index writes, progress."""

    def __init__(self, make_scene, runs, folder, spec, progress):
        self.make_scene = make_scene
        self.folder = folder
        self.spec = spec
        self.progress = progress
        self.names = [run_name(p) for p in runs]
        self.params = dict(zip(self.names, runs, strict=True))
        self.rows = {}
        if (folder / INDEX_NAME).exists():  # runs of earlier sweeps stay in the index
            self.rows = {r["run"]: r for r in _read_index(folder)[1]}
        self.running = 0
        self.t0 = time.perf_counter()
        self.completed = 0

    def _archive(self, name) -> Path:
        return self.folder / RUNS_DIR / f"{name}.h5"

    def _precheck(self) -> list:
        todo = []
        for name in self.names:
            params = self.params[name]
            rel = f"{RUNS_DIR}/{name}.h5"
            result = _valid_archive(self._archive(name), params)
            if result is not None:
                self.rows[name] = _summary(result, name, params, rel)
            else:  # failed runs are tried again: pending until they finish
                self.rows[name] = _pending_row(name, params)
                todo.append(name)
        self.skipped = len(self.names) - len(todo)
        return todo

    def _state(self, event, row=None) -> dict:
        mine = [self.rows[n]["status"] for n in self.names]
        done, failed = mine.count("done"), mine.count("failed")
        left = len(mine) - done - failed
        elapsed = time.perf_counter() - self.t0
        eta = None
        if self.completed and left:
            eta = elapsed / self.completed * left
        running = min(self.running, left)
        return {
            "event": event,
            "row": row,
            "total": len(mine),
            "done": done,
            "failed": failed,
            "running": running,
            "remaining": left - running,
            "skipped": self.skipped,
            "elapsed": elapsed,
            "eta": eta if left else 0.0,
        }

    def _write(self, active: bool) -> None:
        ordered = [self.rows[n] for n in self.names]
        ordered += [r for n, r in self.rows.items() if n not in self.params]
        state = {"running": self.running if active else 0, "active": active}
        _write_index(self.folder, self.spec, ordered, state)

    def _report(self, event, row=None) -> None:
        if self.progress is not None:
            self.progress(self._state(event, row))

    def run(self, client, workers, numba_threads, max_retries):
        todo = self._precheck()
        self._write(active=bool(todo))
        self._report("start")
        if todo:
            with _connect(client, workers, numba_threads, max_retries) as (c, threads):
                self._execute(c, threads, todo)
        self._write(active=False)
        self._report("end")
        return _frame([self.rows[n] for n in self.names], self.folder.resolve())

    def _execute(self, client, threads, todo) -> None:
        distributed = _require_dask()
        token = uuid.uuid4().hex[:8]
        log = str(self.folder / WRITE_LOG)
        futures = {}
        for name in todo:
            job = _Job(
                factory=self.make_scene,
                params=self.params[name],
                name=name,
                archive=str(self._archive(name).resolve()),
                solve_options=self.spec["solve_options"],
                log=log,
                threads=threads,
            )
            key = f"fastmem-run-{name[-12:]}-{token}"
            futures[client.submit(_run_job, job, key=key, pure=False)] = name
        pending = set(futures)
        last_tick = time.perf_counter()
        try:
            while pending:
                finished = [f for f in pending if f.done()]
                if not finished:
                    with contextlib.suppress(TimeoutError):
                        distributed.wait(
                            list(pending), timeout=_GATE_SECONDS, return_when="FIRST_COMPLETED"
                        )
                    if time.perf_counter() - last_tick >= _GATE_SECONDS:
                        self._count_running(client, pending)
                        self._report("tick")
                        last_tick = time.perf_counter()
                    continue
                for f in finished:
                    pending.discard(f)
                    name = futures[f]
                    row = self._collect(f, name)
                    f.release()
                    self.rows[name] = row
                    self.completed += 1
                    self._count_running(client, pending)
                    self._write(active=True)
                    self._report("run", row)
        finally:
            if pending:
                client.cancel(list(pending))

    def _count_running(self, client, pending) -> None:
        # tasks assigned to workers, at most one per task thread (queued ones are not running)
        keys = {f.key for f in pending}
        busy = client.processing()
        slots = client.nthreads()
        self.running = sum(
            min(slots.get(w, 1), sum(k in keys for k in tasks)) for w, tasks in busy.items()
        )

    def _collect(self, future, name) -> dict:
        params = self.params[name]
        if future.status == "finished":
            row = future.result()
            row.pop("solved", None)
            return row
        if future.status == "error":
            exc = future.exception()
            tb = "".join(traceback.format_exception(exc))
            return _failed_row(name, params, f"{type(exc).__name__}: {exc}", tb)
        return _failed_row(name, params, f"task {future.status}")
