"""HDF5 result archives and meshio export.

One :class:`~fastmem.io.result.Result` is stored in one self-describing HDF5 file
(conventionally with the suffix ``.h5``)::

    /            attrs: format = "fastmem-result", format_version, fastmem_version,
                 created (ISO 8601, UTC), scene (JSON of result.parameters),
                 method, path, converged, n_newton
    /mesh        vertices (N, 2), triangles (M, 3)
    /solution    u1, u2, lambda, r1, r2, active (N,)
    /estimators  only with an estimate: one (M,) dataset per map; attrs = totals
    /history     one 1-D dataset per column; attr ``columns`` lists them in order
    /adaptivity  only for a solve to a tolerance: one row per mesh, same layout as /history
    /timings     attrs: phase name -> seconds

Arrays are stored with their own dtype and read back bit-exactly.  Arrays with
more than ``2**16`` elements are chunked and compressed losslessly (gzip level
1 with the shuffle filter: fast, and effective on float64 fields); smaller ones
are stored contiguously, where compression gains nothing.

Integrity: the file starts with a 512-byte HDF5 *user block* (ignored by
HDF5 and h5py) holding a plain-text header, ``FASTMEM-ARCHIVE`` followed by
the CRC-32 and the size of the rest of the file.  :func:`load` and
:func:`info` verify it before HDF5 parses a single byte, so random corruption
anywhere in the file is reported (:class:`~fastmem.errors.ArchiveError`)
instead of returning wrong numbers.  A file that fails the check, or has no
such header (a foreign HDF5 file, or an archive written before the header
existed), is first opened by HDF5 in a separate, time-limited process
(damaged HDF5 metadata can crash or hang the HDF5 library); only if that
succeeds is it read here, to report what is wrong with it (foreign format,
future version, missing or inconsistent datasets).  An archive whose
checksum does not match is refused in every case, also after a change made
with h5py: edit results in Python and save them again instead.

Writes are atomic: the archive is written to a temporary file in the target
folder (named ``.{name}.tmp-{host}-{pid}-<random suffix>``), flushed to disk and
renamed onto the final name.  If anything fails, the temporary file is removed and
an archive already present under the final name is left untouched.  A writer killed
on the way (``kill -9``) cannot remove it; the next write of the same name does
(:func:`fastmem.io.writer.remove_stale_temporaries`: only when that writer's
process is gone, or after a day without change when it cannot be checked).

Every problem with an archive raises :class:`~fastmem.errors.ArchiveError`
(a subclass of :class:`OSError`) naming the file.  Reading treats the file as
untrusted (see Integrity): sizes are checked against the file size before any
array is read (a corrupt header cannot trigger a huge allocation), and
whatever h5py, numpy or the mesh validation raise on a damaged file is
reported as ArchiveError.

The writing half (layout, integrity header, atomic files, meshio export) is
:mod:`fastmem.io.writer`, which ``Result.save`` and ``Result.export`` call
directly; this module checks its arguments, reads archives and builds Results.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import subprocess
import sys
from math import ceil
from pathlib import Path

import h5py
import numpy as np

from ..errors import ArchiveError, InputTypeError, checked_keywords
from ..mesh.mesh import Mesh
from .result import Estimate, ObstacleResult, Result, check_result
from .writer import (
    _MAGIC,
    _SOLUTION,
    _USERBLOCK,
    FORMAT,
    FORMAT_VERSION,
    _as_str,
    _file_crc,
    fastmem_version,
    write_archive,
    write_export,
)

__all__ = ["FORMAT", "FORMAT_VERSION", "export", "info", "load", "save"]

logger = logging.getLogger(__name__)

_REQUIRED_DATASETS = ("mesh/vertices", "mesh/triangles") + tuple(f"solution/{n}" for n in _SOLUTION)
_REQUIRED_GROUPS = ("history", "timings")
_REQUIRED_ATTRS = ("scene", "method", "path", "converged", "n_newton")
# Largest ratio of array bytes to file bytes: 1 for contiguous storage; deflate
# expands at most ~1032:1, so chunked (compressed) data gets a wider bound.
_MAX_EXPANSION = 1100
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"

#: Seconds (plus one per 20 MB) that the isolated HDF5 probe of an unverified file may take.
PROBE_TIMEOUT = 30.0


# ----------------------------------------------------------------------------- integrity


def _verify_integrity(p: Path) -> bool | None:
    """Check the integrity header: True if its checksum matches, False if not, None if absent."""
    with open(p, "rb") as fh:
        head = fh.read(_USERBLOCK)
        if not head.startswith(_MAGIC):
            return None
        try:
            fields = dict(
                line.split(" ", 1)
                for line in head[len(_MAGIC) :].rstrip(b"\0").decode().split("\n")
                if line
            )
            want_crc, want_size = int(fields["crc32"], 16), int(fields["size"])
        except (ValueError, KeyError, UnicodeDecodeError):
            return False
        return _file_crc(fh, _USERBLOCK) == (want_crc, want_size)


def _has_hdf5_signature(p: Path) -> bool:
    """Look for the HDF5 superblock signature where HDF5 does (offset 0, 512, 1024, ...)."""
    size = p.stat().st_size
    with open(p, "rb") as fh:
        offset = 0
        while offset + len(_HDF5_SIGNATURE) <= size:
            fh.seek(offset)
            if fh.read(len(_HDF5_SIGNATURE)) == _HDF5_SIGNATURE:
                return True
            offset = 512 if offset == 0 else 2 * offset
    return False


# Opens the file with h5py and touches everything load() reads, in a child process:
# exit 0 when HDF5 can read it all, 3 when a dataset claims more bytes than the file holds.
# SIGALRM (default action: terminate) ends the child even if its parent died meanwhile.
_PROBE = """
import os, signal, sys
path, expansion, seconds = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
if hasattr(signal, "alarm"):
    signal.alarm(seconds)
import h5py
size = os.path.getsize(path)
def touch(name, obj):
    for key in obj.attrs:
        obj.attrs[key]
    if isinstance(obj, h5py.Dataset):
        if obj.size * obj.dtype.itemsize > size * (1 if obj.chunks is None else expansion):
            sys.exit(3)
        obj[()]
with h5py.File(path, "r") as f:
    touch("/", f)
    f.visititems(touch)
"""


def _probe(p: Path) -> None:
    """Let HDF5 read an unverified file in a separate process first (crash/hang isolation)."""
    timeout = PROBE_TIMEOUT + p.stat().st_size / 20e6
    try:
        proc = subprocess.run(
            [
                sys.executable,
                "-c",
                _PROBE,
                os.fspath(p),
                str(_MAX_EXPANSION),
                str(ceil(timeout) + 5),
            ],
            capture_output=True,
            timeout=timeout,
            check=False,
        )
    except subprocess.TimeoutExpired:
        raise ArchiveError(
            f"corrupt archive {p}: HDF5 did not finish reading it in {timeout:.0f} s "
            "(damaged metadata?)"
        ) from None
    except OSError as exc:  # no usable interpreter: read it here, unisolated
        logger.warning("cannot isolate the HDF5 probe of %s (%s); reading it directly", p, exc)
        return
    if proc.returncode == 3:
        raise ArchiveError(f"corrupt archive {p}: a dataset claims more bytes than the file holds")
    if proc.returncode != 0:
        lines = proc.stderr.decode("utf-8", "replace").strip().splitlines()
        why = lines[-1] if lines else f"exit status {proc.returncode}"
        raise ArchiveError(f"corrupt or truncated archive {p}: HDF5 cannot read it: {why}")


# ----------------------------------------------------------------------------- public: save


def save(result: Result, path) -> None:
    """Write a result to an HDF5 archive, atomically.

    Parameters
    ----------
    result : fastmem.io.result.Result
        The result to store (mesh, solution, optional estimate, history,
        timings, parameters and scalars).
    path : str or os.PathLike
        Destination file, conventionally with the suffix ``.h5`` (not enforced).
        An existing file is replaced only once the new archive is complete.

    Raises
    ------
    InputTypeError, DataError, NumericalError
        If ``result`` is not a Result or violates its invariants (see
        :func:`fastmem.io.result.check_result`); nothing is written.
    ArchiveError
        If the parent directory does not exist, a field cannot be stored
        (e.g. a history column name containing ``/`` or an unsupported dtype),
        or writing fails at the operating-system level.  Any exception leaves
        no temporary file behind and no (new) file under ``path``.

    Notes
    -----
    The layout is described in the module docstring.  ``result.parameters`` is
    stored as JSON; numpy scalars and arrays in it become Python numbers and
    lists.
    """
    if not isinstance(result, Result):
        raise InputTypeError(f"result must be a fastmem Result, got {type(result).__name__}")
    check_result(result)  # fields may have been reassigned since construction
    write_archive(result, path)


# ----------------------------------------------------------------------------- reading helpers


def _as_py(value):
    """Convert an attribute value read by h5py to a plain Python object."""
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.generic):
        return value.item()
    return value


def _check_header(f: h5py.File, p: Path) -> None:
    fmt = f.attrs.get("format")
    if fmt is None or _as_str(fmt) != FORMAT:
        raise ArchiveError(
            f"foreign HDF5 file {p}: root attribute format is {fmt!r}, expected {FORMAT!r}"
        )
    raw = f.attrs.get("format_version")
    try:
        version = int(raw)
    except (TypeError, ValueError):
        raise ArchiveError(
            f"corrupt or truncated archive {p}: bad format_version {raw!r}"
        ) from None
    if version > FORMAT_VERSION:
        written_by = _as_str(f.attrs.get("fastmem_version", "unknown"))
        raise ArchiveError(
            f"{p} has archive format_version {version} (written by fastmem {written_by}), "
            f"but this fastmem ({fastmem_version()}) reads format_version <= {FORMAT_VERSION}: "
            "it needs a newer fastmem"
        )
    missing = [f"attribute {a}" for a in _REQUIRED_ATTRS if a not in f.attrs]
    missing += [f"/{d}" for d in _REQUIRED_DATASETS if not isinstance(f.get(d), h5py.Dataset)]
    missing += [f"/{g}" for g in _REQUIRED_GROUPS if not isinstance(f.get(g), h5py.Group)]
    if missing:
        raise ArchiveError(f"corrupt or truncated archive {p}: missing {', '.join(missing)}")


@contextlib.contextmanager
def _reading(path):
    """Open an archive for reading after checking it; wrap read errors in ArchiveError."""
    try:
        p = Path(os.fspath(path))
    except TypeError as exc:
        raise ArchiveError(f"archive path must be str or os.PathLike, got {path!r}") from exc
    if not p.exists():
        raise ArchiveError(f"archive {p} does not exist")
    if not p.is_file():
        raise ArchiveError(f"archive {p} is not a regular file")
    verified = _verify_integrity(p)
    if verified is not True:
        if verified is None and not _has_hdf5_signature(p):
            raise ArchiveError(f"{p} is not an HDF5 file")
        _probe(p)
    mismatch = (
        "the checksum in its header does not match (damaged, or changed after fastmem wrote it)"
    )
    try:
        with h5py.File(p, "r") as f:
            _check_header(f, p)
            yield f, p
    except ArchiveError as exc:
        if verified is False:
            raise ArchiveError(f"{exc}; {mismatch}") from exc
        raise
    except Exception as exc:  # anything h5py, numpy or the validation raise on a damaged file
        more = f"; {mismatch}" if verified is False else ""
        raise ArchiveError(
            f"corrupt or truncated archive {p}: {type(exc).__name__}: {exc}{more}"
        ) from exc
    if verified is False:  # readable and consistent, but not what fastmem wrote
        raise ArchiveError(f"corrupt or modified archive {p}: {mismatch}")


def _read(f: h5py.File, name: str, p: Path) -> np.ndarray:
    """Read dataset ``name`` after checking its size against the file size."""
    dset = f[name]
    if not isinstance(dset, h5py.Dataset):
        raise ArchiveError(f"corrupt archive {p}: /{name} is not a dataset")
    limit = os.path.getsize(p) * (1 if dset.chunks is None else _MAX_EXPANSION)
    nbytes = dset.size * dset.dtype.itemsize
    if nbytes > limit:
        raise ArchiveError(
            f"corrupt archive {p}: /{name} claims shape {dset.shape} ({nbytes} bytes), "
            "more than the file can hold"
        )
    return dset[()]


def _history_names(g: h5py.Group, p: Path) -> list:
    if "columns" in g.attrs:
        names = [_as_str(n) for n in np.atleast_1d(g.attrs["columns"])]
    else:
        names = [k for k, v in g.items() if isinstance(v, h5py.Dataset)]
    for name in names:
        if not isinstance(g.get(name), h5py.Dataset):
            raise ArchiveError(f"corrupt or truncated archive {p}: missing {g.name}/{name}")
    return names


def _attrs_dict(obj) -> dict:
    return {str(k): _as_py(v) for k, v in obj.attrs.items()}


# ----------------------------------------------------------------------------- public: load, info


@checked_keywords("fastmem.load")
def load(path) -> Result:
    """Read a result archive written by :func:`save`.

    Parameters
    ----------
    path : str or os.PathLike
        The archive (``.h5``).

    Returns
    -------
    fastmem.io.result.Result
        Every field as saved, arrays bit-exact with their dtypes; ``estimate``
        is None when the archive has no ``/estimators`` group, and
        ``parameters`` is the decoded JSON (numpy values came back as Python
        numbers and lists).

    Raises
    ------
    ArchiveError
        If the file does not exist, is not HDF5, is a foreign HDF5 file, has a
        newer ``format_version`` than this fastmem reads, lacks a required group
        or dataset, is truncated, fails a checksum, holds an invalid mesh or
        non-finite solution, or is otherwise unreadable.
    """
    with _reading(path) as (f, p):
        vertices = _read(f, "mesh/vertices", p)
        triangles = _read(f, "mesh/triangles", p)
        n = vertices.shape[0] if vertices.ndim >= 1 else -1
        fields = {}
        for name, field in _SOLUTION.items():
            arr = _read(f, f"solution/{name}", p)
            if arr.shape != (n,):
                raise ArchiveError(
                    f"corrupt archive {p}: /solution/{name} has shape {arr.shape}, "
                    f"expected ({n},) to match /mesh/vertices"
                )
            fields[field] = arr
        estimate = None
        if "estimators" in f:
            g = f["estimators"]
            maps = {k: _read(f, f"estimators/{k}", p) for k in g}
            estimate = Estimate(totals=_attrs_dict(g), maps=maps)
        h = f["history"]
        history = {name: _read(f, f"history/{name}", p) for name in _history_names(h, p)}
        timings = {k: float(v) for k, v in f["timings"].attrs.items()}
        adaptivity = None
        if "adaptivity" in f:
            a = f["adaptivity"]
            adaptivity = {n: _read(f, f"adaptivity/{n}", p) for n in _history_names(a, p)}
        attrs = f.attrs
        parameters = json.loads(_as_str(attrs["scene"]))
        # archives hold validated counter-clockwise meshes: anything else is damage
        mesh = Mesh(vertices, triangles, orientation="raise")
        cls, extra = Result, {}
        if parameters.get("problem") == "obstacle":
            cls = ObstacleResult
            for name in ("lower", "upper"):
                if f"solution/{name}" in f:
                    extra[name] = _read(f, f"solution/{name}", p)
        result = cls(
            mesh=mesh,
            **fields,
            **extra,
            history=history,
            timings=timings,
            parameters=parameters,
            converged=bool(attrs["converged"]),
            n_newton=int(attrs["n_newton"]),
            method=_as_str(attrs["method"]),
            path=_as_str(attrs["path"]),
            estimate=estimate,
            adaptivity=adaptivity,
        )
    logger.info("loaded result archive %s", p)
    return result


def info(path) -> dict:
    """Summarise an archive without reading its large arrays.

    Parameters
    ----------
    path : str or os.PathLike
        The archive (``.h5``).

    Returns
    -------
    dict
        Keys: ``file`` (str), ``format_version`` (int), ``fastmem_version``,
        ``created`` (str), ``parameters`` (dict), ``method``, ``path`` (the
        linear-step path, str), ``converged`` (bool), ``n_newton`` (int),
        ``n_vertices``, ``n_triangles`` (int), ``has_estimate`` (bool),
        ``estimator_totals`` (dict of str to float, empty without an estimate),
        ``estimator_maps`` (list of str), ``timings`` (dict of str to float),
        ``history_columns`` (list of str) and ``n_history_rows`` (int, the
        length of the longest history column, 0 without history),
        ``adaptivity`` (dict of str to list: the per-mesh table of a solve
        to a tolerance, or None).

    Raises
    ------
    ArchiveError
        For the same reasons as :func:`load`.
    """
    with _reading(path) as (f, p):
        attrs = f.attrs
        h = f["history"]
        columns = _history_names(h, p)
        est = f.get("estimators")
        summary = {
            "file": str(p),
            "format_version": int(attrs["format_version"]),
            "fastmem_version": _as_str(attrs.get("fastmem_version", "unknown")),
            "created": _as_str(attrs.get("created", "")),
            "parameters": json.loads(_as_str(attrs["scene"])),
            "method": _as_str(attrs["method"]),
            "path": _as_str(attrs["path"]),
            "converged": bool(attrs["converged"]),
            "n_newton": int(attrs["n_newton"]),
            "n_vertices": int(f["mesh/vertices"].shape[0]),
            "n_triangles": int(f["mesh/triangles"].shape[0]),
            "has_estimate": est is not None,
            "estimator_totals": {} if est is None else _attrs_dict(est),
            "estimator_maps": [] if est is None else list(est.keys()),
            "timings": {k: float(v) for k, v in f["timings"].attrs.items()},
            "history_columns": columns,
            "n_history_rows": max((len(h[c]) for c in columns), default=0),
            "adaptivity": None,
        }
        if "adaptivity" in f:
            a = f["adaptivity"]
            summary["adaptivity"] = {
                n: _read(f, f"adaptivity/{n}", p).tolist() for n in _history_names(a, p)
            }
    return summary


# ----------------------------------------------------------------------------- public: export


def export(result: Result, path) -> None:
    """Write the mesh and nodal fields of a result for ParaView & co. through meshio.

    Point data: ``u1``, ``u2``, ``lambda``, ``gap`` (``u1 - u2``), ``active``
    (1.0 on the contact set, else 0.0), ``r1``, ``r2``.  Cell data: the
    per-triangle estimator maps, when the result has an estimate.

    Parameters
    ----------
    result : fastmem.io.result.Result
        The result to export.
    path : str or os.PathLike
        Destination; the suffix selects the format: ``.vtu`` (VTK XML, points
        padded to 3D with z = 0, one self-contained file) or ``.xdmf`` (XDMF3 with
        its heavy data in a companion HDF5 file named ``<path>.h5``, e.g.
        ``run.xdmf`` + ``run.xdmf.h5``, so it never collides with a ``run.h5``
        result archive; keep both files together).

    Raises
    ------
    InputTypeError, DataError, NumericalError
        If ``result`` is not a Result or violates its invariants.
    ParameterError
        If the suffix is neither ``.vtu`` nor ``.xdmf``.
    ArchiveError
        If the parent directory does not exist or writing fails.

    Notes
    -----
    Writing is atomic per file: everything is written under temporary names in
    the target folder and renamed when complete.  For ``.xdmf`` the companion
    is renamed first and the ``.xdmf`` last.
    """
    if not isinstance(result, Result):
        raise InputTypeError(f"result must be a fastmem Result, got {type(result).__name__}")
    check_result(result)
    write_export(result, path)
