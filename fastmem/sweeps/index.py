"""Sweep index: the study's HDF5 index, its pandas table, its status and its lock.

Part of :mod:`fastmem.sweeps.study` (docs/sweeps.md describes the index format and
why it is HDF5).  The index is rewritten atomically after every completed run.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np

from ..errors import ArchiveError
from ..io.writer import atomic_file, fastmem_version
from .grid import (
    _FLOATS,
    _INTS,
    _TEXTS,
    INDEX_FORMAT,
    INDEX_NAME,
    INDEX_VERSION,
    LOCK_NAME,
    TABLE_COLUMNS,
    _require_pandas,
)

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: studies are not locked
    fcntl = None


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
    cols = _index_columns(rows)
    with atomic_file(folder / INDEX_NAME) as tmp:
        with h5py.File(tmp, "w", track_order=True) as f:
            f.attrs["format"] = INDEX_FORMAT
            f.attrs["format_version"] = np.int64(INDEX_VERSION)
            f.attrs["fastmem_version"] = fastmem_version()
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
