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
    study/.sweep.lock        held (flock) by the client running the sweep

Rules (docs/sweeps.md has the reasons):

* **Runs.** ``grid`` is a dict of parameter lists (their cartesian product, in
  the order given; a scalar is a fixed value) or a list of dicts.  Values are
  numbers, strings, booleans or None; names are Python identifiers, passed to
  the factory as keywords.  A run's identity is the canonical JSON of its
  parameters (keys sorted): the archive name is ``<readable fields>__<first 12
  hex digits of its SHA-256>.h5``, the same in every process and on every
  machine.  ``1`` and ``1.0`` are different parameter values.
* **Done.** A run is done when its archive exists, :func:`fastmem.load`
  validates it (fastmem's checksummed format) and it records the same
  parameters.  A sweep first checks this for every run (in the client) and
  submits only the others; the task checks again before solving and before
  writing, so that a task retried after its worker died once the archive was
  written does not solve it again.
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
"""

from __future__ import annotations

import contextlib
import hashlib
import inspect
import itertools
import json
import keyword
import logging
import math
import numbers
import os
import pickle
import re
import socket
import time
import traceback
import types
import uuid
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from .errors import ArchiveError, InputTypeError, ParameterError

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: studies are not locked
    fcntl = None

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

logger = logging.getLogger(__name__)

MISSING_DASK = 'fastmem sweeps need dask.distributed and pandas: pip install "fastmem[dask]"'
"""Message of the :class:`ImportError` raised when the ``dask`` extra is missing."""

INDEX_NAME = "sweep-index.h5"
RUNS_DIR = "runs"
WRITE_LOG = "archive-writes.log"
LOCK_NAME = ".sweep.lock"
INDEX_FORMAT = "fastmem-sweep-index"
INDEX_VERSION = 1

_FLOATS = ("eta", "eta_disc", "eta_lin", "eta_alg", "contact_fraction", "seconds")
_INTS = ("newton_steps", "cg_iterations", "vertices", "triangles")
TABLE_COLUMNS = (
    "run",
    "status",
    "converged",
    *_FLOATS[:5],
    *_INTS,
    "seconds",
    "archive",
    "error",
)
"""Columns of the table after the parameters (see :func:`load_sweep`)."""

_TEXTS = ("run", "key", "params", "status", "archive", "error", "traceback")
_RESERVED = frozenset(TABLE_COLUMNS) | {"key", "params", "traceback"}
# keywords of fastmem.solve a sweep cannot pass: per-run objects, not options
_PER_RUN = ("monitor", "level_monitor", "initial", "scene")
_GATE_SECONDS = 0.5  # progress "tick" period while no run completes


def _require_dask():
    """Import dask.distributed or raise ImportError with the installation hint."""
    try:
        import distributed
    except ImportError as exc:
        raise ImportError(MISSING_DASK) from exc
    return distributed


def _require_pandas():
    try:
        import pandas
    except ImportError as exc:
        raise ImportError(MISSING_DASK) from exc
    return pandas


# ----------------------------------------------------------------------------- runs


def _canonical_value(value, where: str):
    """Return a JSON scalar for a parameter value, or raise naming ``where``."""
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        value = float(value)
        if not math.isfinite(value):
            raise ParameterError(f"grid entry {where} = {value!r} is not finite")
        return value
    raise InputTypeError(
        f"grid entry {where} = {value!r:.60} ({type(value).__name__}) is not a number, string, "
        "bool or None: sweep parameters are scalars (build arrays inside the scene factory)"
    )


def _check_name(name) -> str:
    if not isinstance(name, str):
        raise InputTypeError(f"grid parameter names must be strings, got {name!r}")
    if not name.isidentifier() or keyword.iskeyword(name):
        raise ParameterError(
            f"grid parameter name {name!r} is not a Python identifier (it is passed to the "
            "scene factory as a keyword)"
        )
    if name in _RESERVED:
        raise ParameterError(
            f"grid parameter name {name!r} is a column of the sweep table; rename it "
            f"(reserved: {', '.join(sorted(_RESERVED))})"
        )
    return name


def _values(name, value) -> list:
    if isinstance(value, (list, tuple, range, np.ndarray)):
        values = list(np.asarray(value).tolist() if isinstance(value, np.ndarray) else value)
        if not values:
            raise ParameterError(f"grid entry {name!r} has no values")
        return [_canonical_value(v, f"{name}[{i}]") for i, v in enumerate(values)]
    return [_canonical_value(value, repr(name))]  # a fixed value


def expand_grid(grid) -> list[dict]:
    """Return the runs of a grid as a list of parameter dicts, validated.

    Parameters
    ----------
    grid : dict or list of dict
        A dict ``{name: list of values}`` (its cartesian product, the first
        name varying slowest; a scalar is a fixed value), or a list of dicts,
        one per run.

    Returns
    -------
    list of dict
        One dict per run, values converted to plain Python scalars.

    Raises
    ------
    InputTypeError
        For a grid that is neither, a non-string name or a value that is not a
        number, string, bool or None.
    ParameterError
        For no runs, an empty value list, NaN or inf, a name that is not an
        identifier or is a column of the table, or the same run twice.
    """
    if isinstance(grid, Mapping):
        names = [_check_name(n) for n in grid]
        lists = [_values(n, grid[n]) for n in names]
        runs = [dict(zip(names, combo, strict=True)) for combo in itertools.product(*lists)]
    elif isinstance(grid, (list, tuple)):
        runs = []
        for i, entry in enumerate(grid):
            if not isinstance(entry, Mapping):
                raise InputTypeError(
                    f"grid[{i}] must be a dict of parameters, got {type(entry).__name__}"
                )
            runs.append(
                {_check_name(n): _canonical_value(v, f"grid[{i}][{n!r}]") for n, v in entry.items()}
            )
    else:
        raise InputTypeError(
            f"grid must be a dict of parameter lists or a list of dicts, got {type(grid).__name__}"
        )
    if not runs:
        raise ParameterError("the grid has no runs")
    seen = {}
    for i, params in enumerate(runs):
        key = _canonical(params)
        if key in seen:
            raise ParameterError(f"runs {seen[key]} and {i} have the same parameters {key}")
        seen[key] = i
    return runs


def _canonical(params: dict) -> str:
    return json.dumps(params, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _key(params: dict) -> str:
    return hashlib.sha256(_canonical(params).encode("utf-8")).hexdigest()


def run_name(params: dict) -> str:
    """File stem of a run: readable ``name=value`` fields and 12 hex digits of its hash.

    Parameters
    ----------
    params : dict
        The run's parameters (plain scalars, as returned by :func:`expand_grid`).

    Returns
    -------
    str
        E.g. ``"g=0.1_mu2=0.5__3f0c5e2b9a41"``: the fields sorted by name,
        characters other than letters, digits and ``._+-=`` replaced by ``-``,
        at most 80 characters of them; the suffix is the start of the SHA-256
        of the canonical JSON of ``params``, which identifies the run.
    """
    fields = "_".join(f"{k}={params[k]}" for k in sorted(params))
    readable = re.sub(r"[^A-Za-z0-9._+=-]", "-", fields)[:80]
    return f"{readable}__{_key(params)[:12]}"


@dataclass(frozen=True)
class _Job:
    """Everything a worker needs for one run (pickled to the worker)."""

    factory: object
    params: dict
    name: str
    archive: str
    solve_options: dict
    log: str
    threads: dict  # host -> Numba threads; "*" -> fixed count for every host


# ----------------------------------------------------------------------------- checks


def _factory_name(make_scene) -> str:
    """Check that the factory is a picklable module-level function; return ``module:name``."""
    if not callable(make_scene):
        raise InputTypeError(f"make_scene must be a function, got {type(make_scene).__name__}")
    desc = getattr(make_scene, "__qualname__", repr(make_scene))
    hint = (
        "workers on other machines import it by name: define it with def at the top level "
        "of a module (or of the script)"
    )
    if not isinstance(make_scene, types.FunctionType):
        raise InputTypeError(
            f"make_scene must be a plain function, got {type(make_scene).__name__} {desc}; {hint}"
        )
    if make_scene.__name__ == "<lambda>":
        raise InputTypeError(f"make_scene {desc} is a lambda; {hint}")
    if "<locals>" in make_scene.__qualname__:
        raise InputTypeError(f"make_scene {desc} is defined inside a function; {hint}")
    try:
        back = pickle.loads(pickle.dumps(make_scene))
    except Exception as exc:
        raise InputTypeError(
            f"make_scene {desc} cannot be pickled by name ({exc}); {hint}"
        ) from exc
    if back is not make_scene:
        raise InputTypeError(
            f"make_scene {desc}: its name {make_scene.__module__}.{make_scene.__qualname__} "
            f"refers to another object; {hint}"
        )
    return f"{make_scene.__module__}:{make_scene.__qualname__}"


def _check_signature(make_scene, runs) -> None:
    try:
        sig = inspect.signature(make_scene)
    except (TypeError, ValueError):  # pragma: no cover - builtins without a signature
        return
    for i, params in enumerate(runs):
        try:
            sig.bind(**params)
        except TypeError as exc:
            raise ParameterError(
                f"run {i} {_canonical(params)}: {make_scene.__qualname__}() cannot take these "
                f"parameters: {exc}"
            ) from None


def _check_solve_options(solve_options) -> dict:
    """Validate the keywords of :func:`fastmem.solve` once, before anything starts."""
    from dataclasses import fields

    from .options import AdaptOptions, InnerOptions, NewtonOptions, RecordOptions, SolveOptions
    from .solver import solve

    if solve_options is None:
        return {}
    if not isinstance(solve_options, Mapping):
        raise InputTypeError(
            f"solve_options must be a dict of fastmem.solve keywords, "
            f"got {type(solve_options).__name__}"
        )
    options = dict(solve_options)
    sig = inspect.signature(solve).parameters
    for name in options:
        if name in _PER_RUN:
            raise ParameterError(
                f"solve_options[{name!r}] cannot be used in a sweep (a per-run object, "
                "not an option)"
            )
        if name not in sig:
            raise ParameterError(
                f"solve_options[{name!r}] is not a keyword of fastmem.solve "
                f"(known: {', '.join(n for n in sig if n not in _PER_RUN)})"
            )
    try:
        json.dumps(options, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"solve_options must be JSON values ({exc})") from exc
    # the keywords fm.solve groups into option objects are checked by those objects;
    # the others (blas_threads, ...) are handled by fm.solve itself
    grouped = {
        f.name
        for cls in (NewtonOptions, InnerOptions, RecordOptions, AdaptOptions)
        for f in fields(cls)
    }
    keywords = {n: v for n, v in options.items() if n in grouped}
    SolveOptions.from_keywords(**keywords)  # raises ParameterError naming the option
    if options.get("blas_threads") is not None:
        from .config import _check_count

        _check_count("solve_options['blas_threads']", options["blas_threads"])
    return options


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
    """
    from .mesh import Mesh
    from .scene import Scene

    if domain not in ("square", "lshape"):
        raise ParameterError(f"domain must be 'square' or 'lshape', got {domain!r}")
    mesh = Mesh.lshape(n) if domain == "lshape" else Mesh.square(n)
    if isinstance(refine, bool) or not isinstance(refine, int) or refine < 0:
        raise ParameterError(f"refine must be an integer >= 0, got {refine!r}")
    for _ in range(refine):
        mesh = mesh.refine()
    return Scene(mesh, mu=(mu1, mu2), f=(f1, f2), g=g)


def _summary(result, name: str, params: dict, archive: str) -> dict:
    """Return the table row of a finished run, from its Result (in memory or loaded)."""
    totals = {} if result.estimate is None else result.estimate.totals
    if result.adaptivity is not None:
        cg = int(np.sum(result.adaptivity["inner"]))
    else:
        cg = int(sum(lv.get("inner", 0) for lv in result.parameters["solver"]["levels"]))
    return {
        "run": name,
        "key": _key(params),
        "params": params,
        "status": "done",
        "converged": bool(result.converged),
        **{k: float(totals.get(k, math.nan)) for k in _FLOATS[:4]},
        "contact_fraction": result.contact_fraction,
        "newton_steps": int(result.n_newton),
        "cg_iterations": cg,
        "vertices": int(result.mesh.n_vertices),
        "triangles": int(result.mesh.n_triangles),
        "seconds": float(result.timings.get("total", 0.0) + result.timings.get("scene", 0.0)),
        "archive": archive,
        "error": "",
        "traceback": "",
    }


def _failed_row(name, params, error, trace="") -> dict:
    return {
        "run": name,
        "key": _key(params),
        "params": params,
        "status": "failed",
        "converged": None,
        **dict.fromkeys(_FLOATS, math.nan),
        **dict.fromkeys(_INTS, -1),
        "archive": "",
        "error": error,
        "traceback": trace,
    }


def _pending_row(name, params) -> dict:
    row = _failed_row(name, params, "")
    row["status"] = "pending"
    return row


def _valid_archive(path: Path, params: dict):
    """Return the Result of ``path`` if it exists, validates, records ``params``; else None."""
    from .archive import load

    if not path.is_file():
        return None
    try:
        result = load(path)
    except ArchiveError as exc:
        logger.warning("sweep: %s is not a valid archive, solving the run again: %s", path, exc)
        return None
    recorded = result.parameters.get("sweep", {}).get("params")
    if recorded != params:
        logger.warning("sweep: %s records other parameters (%s), solving again", path, recorded)
        return None
    return result


_MMAP_THRESHOLD = 32 << 20  # bytes: heap (not mmap) for arrays below 32 MiB
_malloc_tuned = []


def _tune_malloc() -> None:
    """Undo the cost of dask's ``MALLOC_TRIM_THRESHOLD_`` in this worker process (glibc).

    dask's Nanny sets ``MALLOC_TRIM_THRESHOLD_=65536`` in its workers.  Any
    such setting switches off glibc's dynamic mmap threshold, so that every
    array above 128 KiB is a fresh mmap whose pages fault in again: a solve at
    n = 256 took 1.5x as long (1.21 s instead of 0.80 s, one thread).  A fixed
    mmap threshold of 32 MiB gives the time back (0.83 s) and keeps the trimming.
    Once per process, and only when the variable is set.
    """
    if _malloc_tuned or "MALLOC_TRIM_THRESHOLD_" not in os.environ:
        return
    _malloc_tuned.append(True)
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(ctypes.c_int(-3), ctypes.c_int(_MMAP_THRESHOLD))  # M_MMAP_THRESHOLD
    except (OSError, AttributeError):  # not glibc
        return


def _set_task_threads(threads: dict) -> None:
    """Numba threads of this task thread (``set_num_threads`` is per thread)."""
    import numba

    _tune_malloc()

    count = threads.get("*")
    if count is None:
        try:
            from distributed import get_worker

            host = _host(get_worker().address)
        except (ImportError, ValueError):  # called outside a dask worker
            return
        count = threads.get(host, min(threads.values(), default=None))
    if count:
        numba.set_num_threads(max(1, min(int(count), numba.config.NUMBA_NUM_THREADS)))


def _log_write(log: str, job: _Job, seconds: float) -> None:
    """Append one JSON line to the write log (one ``write`` with O_APPEND: atomic)."""
    line = json.dumps(
        {
            "run": job.name,
            "time": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "seconds": round(seconds, 6),
        }
    )
    fd = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, (line + "\n").encode("utf-8"))
    finally:
        os.close(fd)


def _run_job(job: _Job) -> dict:
    """Solve one run and write its archive (the task a worker executes); return its row.

    A run whose archive is already valid is not solved again (a retry after a
    worker died once the archive was written).  Exceptions of the factory, the
    solve or the write are returned as a failed row with their text.
    """
    from .scene import Scene
    from .solver import solve

    archive = Path(job.archive)
    rel = f"{RUNS_DIR}/{archive.name}"
    done = _valid_archive(archive, job.params)
    if done is not None:
        return _summary(done, job.name, job.params, rel) | {"solved": False}
    _set_task_threads(job.threads)
    t0 = time.perf_counter()
    stage = "make_scene"
    try:
        scene = job.factory(**job.params)
        if not isinstance(scene, Scene):
            raise InputTypeError(
                f"{job.factory.__qualname__}() returned {type(scene).__name__}, not a fastmem.Scene"
            )
        t_scene = time.perf_counter() - t0
        stage = "solve"
        result = solve(scene, **job.solve_options)
        result.timings["scene"] = t_scene
        result.parameters["sweep"] = {"params": job.params, "run": job.name}
        stage = "save"
        done = _valid_archive(archive, job.params)  # written meanwhile by an orphaned task?
        if done is not None:
            return _summary(done, job.name, job.params, rel) | {"solved": False}
        result.save(archive)
    except Exception as exc:
        text = f"{type(exc).__name__} in {stage}: {exc}"
        return _failed_row(job.name, job.params, text, traceback.format_exc())
    _log_write(job.log, job, time.perf_counter() - t0)
    return _summary(result, job.name, job.params, rel) | {"solved": True}


# ----------------------------------------------------------------------------- index


def _index_columns(rows: list) -> dict:
    cols = {name: [] for name in (*_TEXTS, "converged", *_FLOATS, *_INTS)}
    for row in rows:
        for name in _TEXTS:
            value = row[name]
            cols[name].append(json.dumps(value) if name == "params" else str(value))
        c = row["converged"]
        cols["converged"].append(-1 if c is None else int(c))
        for name in _FLOATS:
            cols[name].append(row[name])
        for name in _INTS:
            cols[name].append(row[name])
    return cols


def _write_index(folder: Path, spec: dict, rows: list, state: dict) -> None:
    """Rewrite the index atomically (temporary file in ``folder``, then rename)."""
    import h5py

    from .archive_write import _atomic_file, _fastmem_version

    cols = _index_columns(rows)
    with _atomic_file(folder / INDEX_NAME) as tmp:
        with h5py.File(tmp, "w", track_order=True) as f:
            f.attrs["format"] = INDEX_FORMAT
            f.attrs["format_version"] = np.int64(INDEX_VERSION)
            f.attrs["fastmem_version"] = _fastmem_version()
            f.attrs["updated"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
            f.attrs["spec"] = json.dumps(spec)
            f.attrs["state"] = json.dumps(state)
            g = f.create_group("runs", track_order=True)
            g.attrs.create("columns", list(cols), dtype=h5py.string_dtype())
            for name, values in cols.items():
                if name in _TEXTS:
                    g.create_dataset(name, data=values, dtype=h5py.string_dtype())
                elif name == "converged":
                    g.create_dataset(name, data=np.asarray(values, dtype=np.int8))
                elif name in _INTS:
                    g.create_dataset(name, data=np.asarray(values, dtype=np.int64))
                else:
                    g.create_dataset(name, data=np.asarray(values, dtype=np.float64))


def _read_index(study) -> tuple[dict, list]:
    """Return ``(attrs, rows)`` of the index of ``study``; ArchiveError if there is none."""
    import h5py

    folder = Path(os.fspath(study))
    path = folder / INDEX_NAME
    if not path.is_file():
        raise ArchiveError(f"{folder} is not a sweep study: {INDEX_NAME} not found")
    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format")
            fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
            if fmt != INDEX_FORMAT:
                raise ArchiveError(f"{path} is not a fastmem sweep index (format {fmt!r})")
            if int(f.attrs["format_version"]) > INDEX_VERSION:
                raise ArchiveError(f"{path} was written by a newer fastmem: upgrade fastmem")
            attrs = {
                "spec": json.loads(f.attrs["spec"]),
                "state": json.loads(f.attrs["state"]),
                "updated": str(f.attrs["updated"]),
                "fastmem_version": str(f.attrs["fastmem_version"]),
            }
            g = f["runs"]
            cols = {}
            for name in g.attrs["columns"]:
                name = name.decode() if isinstance(name, bytes) else name
                data = g[name][()]
                cols[name] = [v.decode("utf-8") for v in data] if name in _TEXTS else data
    except ArchiveError:
        raise
    except Exception as exc:  # h5py, JSON or a missing column of a damaged index
        raise ArchiveError(f"cannot read sweep index {path}: {type(exc).__name__}: {exc}") from exc
    rows = []
    for i in range(len(cols["run"])):
        row = {name: cols[name][i] for name in _TEXTS}
        row["params"] = json.loads(row["params"])
        c = int(cols["converged"][i])
        row["converged"] = None if c < 0 else bool(c)
        row.update({n: float(cols[n][i]) for n in _FLOATS})
        row.update({n: int(cols[n][i]) for n in _INTS})
        rows.append(row)
    return attrs, rows


def _frame(rows: list, folder: Path):
    """Build the pandas table of index rows: run, parameters, then the result columns."""
    pd = _require_pandas()
    names = list(dict.fromkeys(n for row in rows for n in row["params"]))
    records = []
    for row in rows:
        rec = {"run": row["run"], **{n: row["params"].get(n) for n in names}}
        rec.update({c: row[c] for c in TABLE_COLUMNS[1:]})
        rec["archive"] = str(folder / row["archive"]) if row["archive"] else ""
        records.append(rec)
    df = pd.DataFrame.from_records(records, columns=["run", *names, *TABLE_COLUMNS[1:]])
    for c in _INTS:
        df[c] = df[c].astype("Int64").mask(df[c] < 0)
    df["converged"] = df["converged"].astype("boolean")
    return df


def load_sweep(study):
    """Read the table of a sweep study.

    Parameters
    ----------
    study : str or os.PathLike
        The study folder (the ``out`` of :func:`sweep`).

    Returns
    -------
    pandas.DataFrame
        One row per run: ``run`` (the archive's file stem), the parameters
        (one column each), ``status`` (``"done"``, ``"failed"`` or
        ``"pending"``), ``converged``, ``eta``, ``eta_disc``, ``eta_lin``,
        ``eta_alg`` (NaN without an estimate), ``contact_fraction``,
        ``newton_steps`` (on the final mesh), ``cg_iterations`` (all levels and
        meshes), ``vertices``, ``triangles`` (of the final mesh), ``seconds``
        (scene factory + solve), ``archive`` (absolute path) and ``error`` (the
        exception text of a failed run).  Missing values are NaN / <NA>.

    Raises
    ------
    ArchiveError
        If the folder has no readable sweep index.
    ImportError
        Without pandas (the ``dask`` extra).
    """
    folder = Path(os.fspath(study))
    _, rows = _read_index(folder)
    return _frame(rows, folder.resolve())


def _lock_holder(folder: Path) -> str | None:
    """``"pid P on HOST"`` of a client running a sweep of ``folder``, or None."""
    path = folder / LOCK_NAME
    if fcntl is None or not path.is_file():
        return None
    with open(path, "a+", encoding="utf-8") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            return fh.read().strip() or "another process"
        fcntl.flock(fh, fcntl.LOCK_UN)
    return None


def sweep_status(study) -> dict:
    """Summarise a study from its index (needs neither dask nor pandas).

    Parameters
    ----------
    study : str or os.PathLike
        The study folder.

    Returns
    -------
    dict
        ``total``, ``done``, ``failed``, ``pending`` (counts), ``running`` (tasks
        on workers at the last index write, when a sweep is active), ``active``
        (``"pid P on HOST"`` of the client running a sweep now, or None),
        ``updated`` (ISO time of the last index write), ``spec`` (factory and
        solve options) and ``failures`` (list of ``(run, error, traceback)``).
    """
    folder = Path(os.fspath(study))
    attrs, rows = _read_index(folder)
    count = {s: sum(r["status"] == s for r in rows) for s in ("done", "failed", "pending")}
    active = _lock_holder(folder)
    return {
        "study": str(folder),
        "total": len(rows),
        **count,
        "running": attrs["state"].get("running", 0) if active else 0,
        "active": active,
        "updated": attrs["updated"],
        "spec": attrs["spec"],
        "failures": [
            (r["run"], r["error"], r["traceback"]) for r in rows if r["status"] == "failed"
        ],
    }


# ----------------------------------------------------------------------------- the sweep


def _host(address: str) -> str:
    return address.split("://")[-1].rsplit(":", 1)[0]


@contextlib.contextmanager
def _study_lock(folder: Path):
    if fcntl is None:
        yield
        return
    path = folder / LOCK_NAME
    fh = open(path, "a+", encoding="utf-8")  # noqa: SIM115 - held for the whole sweep
    try:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.seek(0)
            holder = fh.read().strip() or "another process"
            raise ArchiveError(
                f"study {folder} is being run by another sweep ({holder}); wait for it or "
                "use another folder"
            ) from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        fh.flush()
        yield
    finally:
        fh.close()  # releases the lock


@contextlib.contextmanager
def _restored_environ(keys):
    """Undo the environment variables a dask Nanny sets in this process (pre-spawn-environ)."""
    saved = {k: os.environ.get(k) for k in keys}
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def _connect(client, workers, numba_threads, max_retries):
    """Yield ``(distributed.Client, threads)``: a new LocalCluster, an address or a Client."""
    distributed = _require_dask()
    import dask

    if client is None:
        cores = os.cpu_count() or 1
        n = cores if workers is None else workers
        per = max(1, cores // n) if numba_threads is None else numba_threads
        # Numba threads: numba.set_num_threads(per) in each task (_set_task_threads), not
        # NUMBA_NUM_THREADS: a worker whose main module imports fastmem may start Numba's
        # pool before a post-spawn variable is set, and a pre-spawn one leaks into this
        # process, whose next compilation would then refuse the changed value.
        pre_spawn = dict(dask.config.get("distributed.nanny.pre-spawn-environ"))
        config = {
            "distributed.scheduler.allowed-failures": max_retries,
            "distributed.scheduler.worker-saturation": 1.0,
            # see _tune_malloc: not set at all in our workers (the whole dict is
            # replaced: a dotted key set to None would delete the nanny section
            # from dask's config when the block ends)
            "distributed.nanny.pre-spawn-environ": {
                k: v for k, v in pre_spawn.items() if k != "MALLOC_TRIM_THRESHOLD_"
            },
        }
        touched = [*pre_spawn, "PYTHONHASHSEED"]
        with _restored_environ(touched), dask.config.set(config):
            with (
                distributed.LocalCluster(
                    n_workers=n,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                ) as cluster,
                distributed.Client(cluster) as c,
            ):
                yield c, {"*": per}
        return
    if isinstance(client, str):
        with distributed.Client(client) as c:
            yield c, _threads_by_host(c, numba_threads)
        return
    if isinstance(client, distributed.Client):
        yield client, _threads_by_host(client, numba_threads)
        return
    raise InputTypeError(
        f"client must be None, a scheduler address or a distributed.Client, "
        f"got {type(client).__name__}"
    )


def _threads_by_host(client, numba_threads) -> dict:
    """Numba threads per task on each host: cores // task threads of its workers."""
    if numba_threads is not None:
        return {"*": numba_threads}
    cores = client.run(os.cpu_count)
    slots, host_cores = {}, {}
    for address, nthreads in client.nthreads().items():
        host = _host(address)
        slots[host] = slots.get(host, 0) + nthreads
        host_cores[host] = cores.get(address) or 1
    return {h: max(1, host_cores[h] // slots[h]) for h in slots}


def _positive(name, value, allow_none=True):
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise InputTypeError(f"{name} must be a positive integer, got {value!r}")
    if value < 1:
        raise ParameterError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


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
        Lambdas, nested functions and other callables are refused.
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
        For an unusable factory, grid, solve options or folder, before anything
        is created or started.
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
