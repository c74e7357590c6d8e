"""HDF5 time-series archives of liquid–gas runs, their summary and VTU/PVD export.

Layout of a ``fastmem-twophase`` archive (written atomically: a temporary
file next to the target, renamed on success):

* root attributes: ``format`` (``"fastmem-twophase"``), ``format_version``,
  ``fastmem_version``, ``created``, ``problem`` (JSON: the physics, the
  scene's name and sizes), ``strategy``, ``linear_solver``, ``seconds``;
* ``grid/``: ``volume``, ``centres``, ``faces``, ``geometry``,
  ``boundary_cells``, ``boundary_geometry`` and, for a mesh, ``vertices``,
  ``triangles``, ``cell_vertex`` (the mesh vertex of every cell);
* ``steps/``: one row per accepted step: ``time`` (s), ``dt``, ``newton``,
  ``linear``, ``gas_cells``, ``front`` (m), ``s_gas``, ``pressure``, ``chi``
  (at the monitor cell), ``eta`` (disc, lin, alg), ``in_place``,
  ``injected``, ``outflow`` and ``outflow_equilibrated`` (kg, cumulated: the
  two-point and the equilibrated flux through the Dirichlet faces);
* ``profiles/``: ``time`` (K,), ``state`` (K, N, 3) = (S, P, chi) and ``gas``
  (K, N) for the kept steps.
"""

from __future__ import annotations

import json
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np

from ..about import package_version
from ..errors import ArchiveError, ParameterError
from ..io.writer import atomic_file
from .model import YEAR

__all__ = ["FORMAT", "export_run", "info_run", "is_archive", "load_run", "save_run"]

FORMAT = "fastmem-twophase"
FORMAT_VERSION = 1

_STEP_COLUMNS = (
    ("time", "times", "s"),
    ("dt", "dts", "s"),
    ("newton", "newton", ""),
    ("linear", "linear", ""),
    ("gas_cells", "gas_cells", ""),
    ("front", "front", "m"),
    ("s_gas", "s_gas0", ""),
    ("pressure", "p0", "Pa"),
    ("chi", "chi0", ""),
    ("in_place", "in_place", "kg"),
    ("injected", "injected", "kg"),
    ("outflow", "outflow", "kg"),
    ("outflow_equilibrated", "outflow_equilibrated", "kg"),
)


def _physics_dict(physics) -> dict:
    return {k: getattr(physics, k) for k in physics.__dataclass_fields__}


def save_run(run, path) -> Path:
    """Write ``run`` (a :class:`~fastmem.twophase.run.Run`) to ``path`` (.h5) atomically."""
    target = Path(path)
    if target.suffix not in (".h5", ".hdf5"):
        raise ParameterError(f"a two-phase archive is written to .h5 or .hdf5, got {str(path)!r}")
    if not target.parent.is_dir():
        raise ParameterError(f"the folder of {str(path)!r} does not exist")
    prob = run.problem
    g = prob.grid
    meta = {
        "physics": _physics_dict(prob.physics),
        "scene": prob.scene,
        "cells": g.n,
        "dim": g.dim,
        "monitor": prob.monitor,
        "stop_injection": prob.stop_injection,
        "hydrogen_total": float(prob.hydrogen.sum()),
    }
    with atomic_file(target) as tmp:
        with h5py.File(tmp, "w", track_order=True) as f:
            f.attrs["format"] = FORMAT
            f.attrs["format_version"] = np.int64(FORMAT_VERSION)
            f.attrs["fastmem_version"] = package_version("0+unknown")
            f.attrs["created"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
            f.attrs["problem"] = json.dumps(meta, default=str)
            f.attrs["strategy"] = run.strategy
            f.attrs["linear_solver"] = run.linear_solver
            f.attrs["seconds"] = float(run.seconds)
            f.attrs["initial_in_place"] = float(run.initial_in_place)
            gg = f.create_group("grid")
            for name in ("volume", "centres", "faces", "geometry", "boundary_cells"):
                gg.create_dataset(name, data=getattr(g, name))
            gg.create_dataset("boundary_geometry", data=g.boundary_geometry)
            gg.create_dataset("boundary_state", data=prob.boundary)
            if prob.mesh is not None:
                gg.create_dataset("vertices", data=prob.mesh.vertices)
                gg.create_dataset("triangles", data=prob.mesh.triangles)
                gg.create_dataset("cell_vertex", data=prob.cell_vertex)
                gg.create_dataset("boundary_vertex", data=prob.boundary_vertex)
            s = f.create_group("steps")
            for name, attr, units in _STEP_COLUMNS:
                d = s.create_dataset(name, data=np.asarray(getattr(run, attr), dtype=float))
                if units:
                    d.attrs["units"] = units
            s.create_dataset("eta", data=np.asarray(run.eta, dtype=float).reshape(-1, 3))
            p = f.create_group("profiles")
            states = np.asarray(run.states, dtype=float).reshape(-1, g.n, 3)
            p.create_dataset("time", data=np.asarray(run.kept_times, dtype=float))
            p.create_dataset("state", data=states, compression="gzip", shuffle=True)
            gas = np.stack([prob.gas(x) for x in states]) if states.size else np.zeros((0, g.n))
            p.create_dataset("gas", data=gas.astype(np.uint8), compression="gzip")
    return target


def is_archive(path) -> bool:
    """Tell whether ``path`` is an HDF5 file of :data:`FORMAT`."""
    try:
        with h5py.File(path, "r") as f:
            value = f.attrs.get("format", "")
    except OSError:
        return False
    return (value.decode() if isinstance(value, bytes) else str(value)) == FORMAT


def _open(path):
    p = Path(path)
    if not p.exists():
        raise ArchiveError(f"no such archive: {str(path)!r}")
    if not is_archive(p):
        raise ArchiveError(f"{str(path)!r} is not a fastmem two-phase archive ({FORMAT})")
    return h5py.File(p, "r")


def load_run(path) -> dict:
    """Read a two-phase archive into a dict of arrays (``steps``, ``profiles``, ``grid``, meta)."""
    with _open(path) as f:
        out = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
        out["problem"] = json.loads(out["problem"])
        for group in ("grid", "steps", "profiles"):
            out[group] = {name: f[group][name][()] for name in f[group]}
    return out


def info_run(path) -> dict:
    """Summarise a two-phase archive: sizes, totals, gas appearance and disappearance."""
    d = load_run(path)
    st = d["steps"]
    gas = st["gas_cells"]
    first = int(np.argmax(gas > 0)) if (gas > 0).any() else None
    gone = [i for i in range(1, gas.size) if gas[i] == 0 and gas[i - 1] > 0]
    eta = st["eta"]
    year = YEAR
    start = float(d.get("initial_in_place", 0.0))
    return {
        "file": str(path),
        "format_version": int(d["format_version"]),
        "fastmem_version": d["fastmem_version"],
        "created": d["created"],
        "scene": d["problem"].get("scene", {}),
        "cells": d["problem"]["cells"],
        "dim": d["problem"]["dim"],
        "strategy": d["strategy"],
        "linear_solver": d["linear_solver"],
        "steps": int(st["time"].size),
        "t_end_years": float(st["time"][-1] / year) if st["time"].size else 0.0,
        "newton": int(st["newton"].sum()),
        "linear": int(st["linear"].sum()),
        "gas_appears_years": None if first is None else float(st["time"][first] / year),
        "gas_vanishes_years": float(st["time"][gone[0]] / year) if gone else None,
        "max_gas_cells": int(gas.max()) if gas.size else 0,
        "balance_max_kg": float(
            np.abs(st["in_place"] - start + st["outflow"] - st["injected"]).max()
            if gas.size
            else 0.0
        ),
        "balance_equilibrated_max_kg": (
            float(
                np.abs(st["in_place"] - start + st["outflow_equilibrated"] - st["injected"]).max()
            )
            if st["outflow_equilibrated"].size
            else None
        ),
        "eta_disc_max": float(eta[:, 0].max()) if eta.size else None,
        "kept_profiles": int(d["profiles"]["time"].size),
        "seconds": float(d["seconds"]),
    }


def export_run(path, out) -> Path:
    """Write the kept profiles of a two-phase archive for ParaView.

    ``out`` ending in ``.vtu``: the last kept profile.  Ending in ``.pvd``: a
    time series, one ``OUT_kkkk.vtu`` per kept profile and the ``.pvd``
    collection that lists them with their times (years).  1D columns become
    polylines through the cell points; 2D sections the triangular mesh, the
    Dirichlet vertices carrying their boundary state.  Point data: ``S_gas``,
    ``P``, ``chi``, ``gas`` (1 where the Henry branch holds).  Every file is
    written atomically.
    """
    import meshio  # lazy: meshio adds 0.04-0.05 s to import fastmem

    out = Path(out)
    if out.suffix not in (".vtu", ".pvd"):
        raise ParameterError(
            f"export writes .vtu (one profile) or .pvd (a series), got {str(out)!r}"
        )
    d = load_run(path)
    grid, prof = d["grid"], d["profiles"]
    if prof["time"].size == 0:
        raise ArchiveError(f"{str(path)!r} kept no profiles: run with keep='all' or keep times")
    if "vertices" in grid:
        points = np.column_stack([grid["vertices"], np.zeros(len(grid["vertices"]))])
        cells = [("triangle", grid["triangles"])]
        where = grid["cell_vertex"]
    else:
        c = grid["centres"]
        points = np.column_stack([c, np.zeros((len(c), 3 - c.shape[1]))])
        n = len(c)
        cells = [("line", np.stack([np.arange(n - 1), np.arange(1, n)], axis=1))]
        where = np.arange(n)

    def fields(k):
        values = np.zeros((len(points), 4))
        if "boundary_vertex" in grid:  # Dirichlet vertices: their boundary states
            b = grid["boundary_state"]
            values[grid["boundary_vertex"]] = np.column_stack(
                [1 - b[:, 0], b[:, 1], b[:, 2], 0 * b[:, 0]]
            )
        state = prof["state"][k]
        values[where] = np.column_stack([1 - state[:, 0], state[:, 1], state[:, 2], prof["gas"][k]])
        return dict(zip(("S_gas", "P", "chi", "gas"), values.T, strict=True))

    def write_vtu(target, k):
        with atomic_file(target, suffix=".vtu") as tmp:
            meshio.write(tmp, meshio.Mesh(points, cells, point_data=fields(k)), file_format="vtu")

    if out.suffix == ".vtu":
        write_vtu(out, -1)
        return out
    year = YEAR
    entries = []
    for k, t in enumerate(prof["time"]):
        name = f"{out.stem}_{k:04d}.vtu"
        write_vtu(out.parent / name, k)
        entries.append(f'    <DataSet timestep="{t / year:.10g}" part="0" file="{name}"/>')
    text = (
        '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n'
        + "\n".join(entries)
        + "\n  </Collection>\n</VTKFile>\n"
    )
    with atomic_file(out, suffix=".pvd") as tmp:
        tmp.write_text(text)
    return out
