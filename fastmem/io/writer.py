"""Writing result archives and meshio exports: the layer below :class:`~fastmem.io.result.Result`.

The archive layout, its integrity header and the atomic writes are described
in :mod:`fastmem.io.archive`, the public interface (``save``, ``load``, ``info``,
``export``), which also reads archives.  The functions here take any object
with the fields of a Result and do not import :mod:`fastmem.io.result`, so that
``Result.save`` and ``Result.export`` call them without an import circle
(result -> archive_write <- archive -> result).  Callers check the result
first (:func:`fastmem.io.result.check_result`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import shutil
import socket
import tempfile
import time
import zlib
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np

from ..about import package_version
from ..errors import ArchiveError, ParameterError
from .schema import GROUPS, describe

__all__ = [
    "ARCHIVE_SUFFIXES",
    "EXPORT_SUFFIXES",
    "FORMAT",
    "FORMAT_VERSION",
    "atomic_file",
    "fastmem_version",
    "check_output",
    "companion_files",
    "remove_stale_temporaries",
    "write_archive",
    "write_export",
]

logger = logging.getLogger("fastmem.io.archive")  # one logger name for all archive I/O

FORMAT = "fastmem-result"
"""Value of the root attribute ``format`` of every fastmem archive."""

FORMAT_VERSION = 1
"""Archive layout version written by this fastmem; older or equal versions are readable."""

_COMPRESS_ABOVE = 2**16
_SOLUTION = {"u1": "u1", "u2": "u2", "lambda": "lam", "r1": "r1", "r2": "r2", "active": "active"}
_EXPORT_SUFFIXES = (".vtu", ".xdmf")
EXPORT_SUFFIXES = _EXPORT_SUFFIXES
"""Suffixes :func:`write_export` understands (meshio formats)."""
ARCHIVE_SUFFIXES = (".h5", ".hdf5")
"""Suffixes the command line takes for a fastmem archive (the API does not enforce one)."""
_USERBLOCK = 512  # bytes before the HDF5 superblock, for fastmem's integrity header
_MAGIC = b"FASTMEM-ARCHIVE\n"
_CHUNK = 1 << 20  # bytes per read while checksumming


def fastmem_version() -> str:
    """Return the version written into archives ("unknown" in a tree without metadata)."""
    return package_version("unknown")


# ----------------------------------------------------------------------------- writing helpers


def _json_default(obj):
    """Turn numpy scalars/arrays and paths into JSON-safe Python objects."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"object of type {type(obj).__name__} is not JSON serialisable")


def _scene_json(parameters) -> str:
    try:
        return json.dumps(dict(parameters), default=_json_default)
    except (TypeError, ValueError) as exc:
        raise ArchiveError(f"result.parameters cannot be stored as JSON: {exc}") from exc


def _check_name(kind: str, name) -> str:
    if not isinstance(name, str) or not name or "/" in name or name == ".":
        raise ArchiveError(
            f"{kind} name {name!r} cannot be stored: it must be a non-empty string without '/'"
        )
    return name


def _write_array(group: h5py.Group, name: str, data) -> h5py.Dataset:
    """Store ``data`` as ``group/name`` with its dtype; compress large arrays."""
    arr = np.asarray(data)
    if arr.dtype.kind not in "biufc":
        raise ArchiveError(
            f"cannot store {group.name.rstrip('/')}/{name} with dtype {arr.dtype}: "
            "only boolean and numeric arrays round-trip exactly"
        )
    kwargs = {}
    if arr.size > _COMPRESS_ABOVE:
        # Chunks of whole rows, about 2**16 elements each (512 KiB of float64), so that a
        # chunk fits the default 1 MiB HDF5 chunk cache and rows are never split.
        row = max(1, arr.size // arr.shape[0])
        chunks = (max(1, min(arr.shape[0], _COMPRESS_ABOVE // row)),) + arr.shape[1:]
        kwargs = {"chunks": chunks, "compression": "gzip", "compression_opts": 1, "shuffle": True}
    try:
        dataset = group.create_dataset(name, data=arr, **kwargs)
    except TypeError as exc:
        raise ArchiveError(
            f"cannot store {group.name.rstrip('/')}/{name} with dtype {arr.dtype}: {exc}"
        ) from exc
    text, units = describe(f"{group.name.strip('/')}/{name}")
    dataset.attrs["description"] = text
    if units:
        dataset.attrs["units"] = units
    return dataset


def _group(f: h5py.File, name: str, **kwargs) -> h5py.Group:
    g = f.create_group(name, **kwargs)
    if name not in ("estimators", "timings"):  # their attributes are data (totals, seconds)
        g.attrs["description"] = GROUPS[name]
    return g


def _write_header(f: h5py.File, result) -> None:
    f.attrs["format"] = FORMAT
    f.attrs["format_version"] = np.int64(FORMAT_VERSION)
    f.attrs["fastmem_version"] = fastmem_version()
    f.attrs["created"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
    f.attrs["scene"] = _scene_json(result.parameters)
    f.attrs["method"] = str(result.method)
    f.attrs["path"] = str(result.path)
    f.attrs["converged"] = np.bool_(result.converged)
    f.attrs["n_newton"] = np.int64(result.n_newton)


def _write_mesh(f: h5py.File, mesh) -> None:
    g = _group(f, "mesh")
    _write_array(g, "vertices", mesh.vertices)
    _write_array(g, "triangles", mesh.triangles)


def _write_solution(f: h5py.File, result) -> None:
    g = _group(f, "solution")
    for name, field in _SOLUTION.items():
        _write_array(g, name, getattr(result, field))
    for name in ("lower", "upper"):  # an obstacle result's obstacles
        value = getattr(result, name, None)
        if value is not None:
            _write_array(g, name, value)


def _write_estimate(f: h5py.File, estimate) -> None:
    g = f.create_group("estimators", track_order=True)
    for key, value in estimate.totals.items():
        g.attrs[key] = value
    for key, value in estimate.maps.items():
        _write_array(g, _check_name("estimator map", key), value)


def _write_history(f: h5py.File, history: dict, group: str = "history") -> None:
    g = _group(f, group, track_order=True)
    names = [_check_name("history column", k) for k in history]
    g.attrs.create("columns", names, dtype=h5py.string_dtype())
    for name in names:
        column = np.asarray(history[name])
        if column.ndim != 1:
            raise ArchiveError(f"{group} column {name!r} must be 1-D, got shape {column.shape}")
        _write_array(g, name, column)


def _write_timings(f: h5py.File, timings: dict) -> None:
    g = f.create_group("timings", track_order=True)
    for key, seconds in timings.items():
        g.attrs[str(key)] = float(seconds)


def _umask() -> int:
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _final_mode(path: Path) -> int:
    """Permissions the file would get from a plain ``open(path, "w")``."""
    try:
        return path.stat().st_mode & 0o7777
    except OSError:
        return 0o666 & ~_umask()


def _target(path) -> Path:
    try:
        p = Path(os.fspath(path))
    except TypeError as exc:
        raise ArchiveError(f"archive path must be str or os.PathLike, got {path!r}") from exc
    parent = p.parent
    if not parent.is_dir():
        raise ArchiveError(f"cannot write {p}: directory {parent} does not exist")
    if p.is_dir():
        raise ArchiveError(f"cannot write {p}: it is a directory")
    return p


def check_output(path, suffixes=ARCHIVE_SUFFIXES + EXPORT_SUFFIXES) -> tuple[Path, bool]:
    """Check, before any work, that a result can be written to ``path``.

    Parameters
    ----------
    path : str or os.PathLike
        The file to write.
    suffixes : tuple of str
        Accepted suffixes (lower case, with the dot).

    Returns
    -------
    (Path, bool)
        The path, and whether a file of that name exists (and would be replaced).

    Raises
    ------
    ParameterError
        The suffix is not one of ``suffixes``.
    ArchiveError
        The directory does not exist or is not writable, or ``path`` is a directory.
    """
    target = _target(path)
    suffix = target.suffix.lower()
    if suffix not in suffixes:
        raise ParameterError(
            f"output {os.fspath(path)}: unknown suffix {suffix or '(none)'!r}; use one of "
            f"{', '.join(suffixes)} (.h5/.hdf5: fastmem archive; .vtu/.xdmf: export for ParaView)"
        )
    parent = target.parent
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ArchiveError(f"cannot write {target}: directory {parent} is not writable")
    exists = target.exists()
    if exists and not os.access(target, os.W_OK) and not os.access(parent, os.W_OK):
        raise ArchiveError(f"cannot replace {target}: not writable")
    return target, exists


def companion_files(path) -> list[Path]:
    """Files written beside ``path`` by an export: ``run.xdmf`` has ``run.xdmf.h5``."""
    p = Path(os.fspath(path))
    return [p.with_name(p.name + ".h5")] if p.suffix.lower() == ".xdmf" else []


def _fsync(path: Path) -> None:
    with open(path, "rb") as fh:
        os.fsync(fh.fileno())


def _file_crc(fh, start: int) -> tuple[int, int]:
    """CRC-32 and byte count of an open binary file from ``start`` to its end."""
    fh.seek(start)
    crc, size = 0, 0
    while chunk := fh.read(_CHUNK):
        crc = zlib.crc32(chunk, crc)
        size += len(chunk)
    return crc, size


def _write_integrity_header(path: Path) -> None:
    """Fill the user block: magic line, then CRC-32 and size of everything after it."""
    with open(path, "r+b") as fh:
        crc, size = _file_crc(fh, _USERBLOCK)
        header = _MAGIC + f"crc32 {crc:08x}\nsize {size}\n".encode("ascii")
        fh.seek(0)
        fh.write(header.ljust(_USERBLOCK, b"\0"))


def _fsync_dir(folder: Path) -> None:
    """Make a rename durable (best effort: not every platform can open a folder)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


#: seconds without a change after which a temporary file of a writer that cannot be
#: checked (another host, an older fastmem's name, no process check) counts as left behind
STALE_AFTER = 24 * 3600.0


def _host() -> str:
    """Return the machine's name for temporary names: its letters and digits, at most 24."""
    return re.sub(r"[^A-Za-z0-9]", "", socket.gethostname())[:24]


def _temporary_prefix(target: Path) -> str:
    """``.NAME.tmp-HOST-PID-``: whose temporary file it is, for :func:`remove_stale_temporaries`."""
    return f".{target.name}.tmp-{_host()}-{os.getpid()}-"


def _process_gone(pid: int) -> bool:
    """Whether no process ``pid`` exists on this machine (False when that cannot be told)."""
    if os.name != "posix":  # os.kill(pid, 0) would terminate the process on Windows
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:  # PermissionError: it exists, under another user
        return False
    return False


def remove_stale_temporaries(target: Path, now: float | None = None) -> list[Path]:
    """Remove the temporary files an interrupted writer of ``target`` left beside it.

    A write of ``target`` goes to ``.NAME.tmp-HOST-PID-RANDOM`` in the same
    folder (``RANDOM`` eight random characters, plus the export's suffix; a folder for an
    XDMF export) and is renamed onto ``target`` when complete; a writer killed
    on the way (``kill -9``, a power cut) leaves it there.  Removed here, before
    the next write of the same ``target``: the entries of exactly that name
    pattern whose writer, on this machine (``HOST``), is no longer running
    (``PID``); and those that have not changed for :data:`STALE_AFTER` seconds
    when the writer cannot be checked (another machine sharing the folder, the
    names of older fastmem versions, ``.NAME.tmp-RANDOM``, or a system
    without the process check).  A running writer's file is left alone.
    Failures to remove are ignored (the next write tries again).

    Parameters
    ----------
    target : Path
        The file about to be written.
    now : float, optional
        The current time (``time.time()``; for tests).

    Returns
    -------
    list of Path
        What was removed.
    """
    pattern = re.compile(
        rf"\.{re.escape(target.name)}\.tmp-(?:([A-Za-z0-9]*)-([0-9]+)-)?[a-z0-9_]{{8}}(\.[A-Za-z0-9]+)?"
    )
    now = time.time() if now is None else now
    host, removed = _host(), []
    try:
        entries = list(os.scandir(target.parent))
    except OSError:
        return removed
    prefix = f".{target.name}.tmp-"
    for entry in entries:
        if not entry.name.startswith(prefix):  # (cheap first: a study folder holds many files)
            continue
        match = pattern.fullmatch(entry.name)
        if match is None:
            continue
        owner, pid = match.group(1), match.group(2)
        try:
            if (
                pid is not None
                and owner == host
                and int(pid) != os.getpid()
                and _process_gone(int(pid))
            ):
                stale = True
            else:
                stale = now - entry.stat(follow_symlinks=False).st_mtime > STALE_AFTER
            if not stale:
                continue
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(entry.path)
            else:
                os.unlink(entry.path)
        except OSError as exc:
            logger.debug("left %s in place: %s", entry.path, exc)
            continue
        removed.append(Path(entry.path))
        logger.info("removed %s, left behind by an interrupted write of %s", entry.path, target)
    return removed


@contextlib.contextmanager
def atomic_file(target: Path, suffix: str = ""):
    """Yield a temporary path next to ``target``; rename it onto ``target`` on success.

    Temporary files that interrupted writes of ``target`` left behind are removed
    first (:func:`remove_stale_temporaries`).
    """
    remove_stale_temporaries(target)
    fd, tmp_name = tempfile.mkstemp(
        prefix=_temporary_prefix(target), suffix=suffix, dir=target.parent
    )
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        _fsync(tmp)
        os.chmod(tmp, _final_mode(target))
        os.replace(tmp, target)
        _fsync_dir(target.parent)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


# ----------------------------------------------------------------------------- archive


def write_archive(result, path) -> None:
    """Write a checked result to ``path`` atomically (see :func:`fastmem.io.archive.save`)."""
    target = _target(path)
    try:
        with atomic_file(target) as tmp:
            with h5py.File(tmp, "w", track_order=True, userblock_size=_USERBLOCK) as f:
                _write_header(f, result)
                _write_mesh(f, result.mesh)
                _write_solution(f, result)
                if result.estimate is not None:
                    _write_estimate(f, result.estimate)
                _write_history(f, result.history)
                if result.adaptivity is not None:
                    _write_history(f, result.adaptivity, "adaptivity")
                _write_timings(f, result.timings)
            _write_integrity_header(tmp)
    except ArchiveError:
        raise
    except OSError as exc:
        raise ArchiveError(f"cannot write archive {target}: {exc}") from exc
    logger.info("saved result archive %s", target)


# ----------------------------------------------------------------------------- export


def _as_str(value) -> str:
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.ndarray) and value.shape == ():
        return _as_str(value[()])
    return str(value)


def _meshio_mesh(result, pad_3d: bool):
    import meshio  # lazy: meshio adds 0.05 s to import fastmem

    points = np.asarray(result.mesh.vertices, dtype=np.float64)
    if pad_3d and points.shape[1] == 2:
        points = np.column_stack([points, np.zeros(points.shape[0])])
    point_data = {
        "u1": np.asarray(result.u1),
        "u2": np.asarray(result.u2),
        "lambda": np.asarray(result.lam),
        "gap": np.asarray(result.u1) - np.asarray(result.u2),
        "active": np.asarray(result.active, dtype=np.float64),
        "r1": np.asarray(result.r1),
        "r2": np.asarray(result.r2),
    }
    if (result.parameters or {}).get("problem") == "obstacle":
        point_data = {
            "u": np.asarray(result.u1),
            "lambda": np.asarray(result.lam),
            "active": np.asarray(result.active, dtype=np.float64),
            "residual": np.asarray(result.r1),
        }
        for name in ("lower", "upper"):
            if getattr(result, name, None) is not None:
                point_data[name] = np.asarray(getattr(result, name))
    cell_data = {}
    if result.estimate is not None:
        cell_data = {k: [np.asarray(v)] for k, v in result.estimate.maps.items()}
    return meshio.Mesh(
        points,
        [("triangle", np.asarray(result.mesh.triangles))],
        point_data=point_data,
        cell_data=cell_data,
    )


def _export_xdmf(mesh, target: Path) -> Path:
    """Write ``target`` (.xdmf) and its companion ``target.name + '.h5'`` via a temp folder."""
    import meshio  # lazy: meshio adds 0.05 s to import fastmem

    companion = target.with_name(target.name + ".h5")
    if companion.is_file() and h5py.is_hdf5(companion):
        with h5py.File(companion, "r") as f:
            is_archive = _as_str(f.attrs.get("format", "")) == FORMAT
        if is_archive:
            raise ArchiveError(
                f"refusing to export {target}: its data file {companion} is a fastmem archive"
            )
    remove_stale_temporaries(target)
    tmpdir = Path(tempfile.mkdtemp(prefix=_temporary_prefix(target), dir=target.parent))
    try:
        # meshio names the heavy-data file after the .xdmf file (suffix replaced by .h5)
        # and references it by basename, so write "<name>.xdmf" to get "<name>.h5".
        staged = tmpdir / (target.name + ".xdmf")
        meshio.write(staged, mesh, file_format="xdmf")
        staged_h5 = staged.with_suffix(".h5")
        _fsync(staged_h5)
        _fsync(staged)
        os.replace(staged_h5, companion)
        os.replace(staged, target)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)
    return companion


def write_export(result, path) -> None:
    """Export a checked result through meshio (see :func:`fastmem.io.archive.export`)."""
    try:
        suffix = Path(os.fspath(path)).suffix.lower()
    except TypeError as exc:
        raise ArchiveError(f"export path must be str or os.PathLike, got {path!r}") from exc
    if suffix not in _EXPORT_SUFFIXES:
        raise ParameterError(
            f"export format {suffix or '(no suffix)'!r} of {os.fspath(path)} is not supported; "
            f"use one of {', '.join(_EXPORT_SUFFIXES)}"
        )
    target = _target(path)
    try:
        if suffix == ".vtu":
            import meshio  # lazy: meshio adds 0.05 s to import fastmem

            mesh = _meshio_mesh(result, pad_3d=True)
            with atomic_file(target, suffix=suffix) as tmp:
                meshio.write(tmp, mesh, file_format="vtu")
            logger.info("exported %s", target)
        else:
            companion = _export_xdmf(_meshio_mesh(result, pad_3d=False), target)
            logger.info("exported %s (heavy data in %s)", target, companion)
    except ArchiveError:
        raise
    except OSError as exc:
        raise ArchiveError(f"cannot export {target}: {exc}") from exc
