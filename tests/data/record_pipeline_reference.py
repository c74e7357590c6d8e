"""Record reference results of ``fastmem.solve`` for the solver-pipeline refactor.

The recorded file ``pipeline_reference.json`` (next to this script) holds, for
each case (method x path x scene), a small fingerprint of the returned triple
``(u1, u2, lam)`` and the iteration counts and error estimates; the test
``tests/solver/test_pipeline_reference.py`` recomputes every case with the current
code and compares (tolerances documented there).  The reference was recorded
from the code before the refactor (commit in ``meta.git_commit``).

Run from the repository (or a worktree) whose code is to be recorded::

    python tests/data/record_pipeline_reference.py              # record
    python tests/data/record_pipeline_reference.py --check-determinism

The repository root of *this* script is put first on ``sys.path``, so that
``fastmem`` is imported from the same tree (an editable install elsewhere
would otherwise win: the script's own folder, not the working directory, is
``sys.path[0]``); the script stops when the import resolves elsewhere.

Cases (all with ``estimate=True`` and every other option at its default):

- ``default``: ``Scene(Mesh.square(64), mu=(1, 1), f=(-1, 1), g=0.1)``;
- ``manufactured``: ``Manufactured().scene(Mesh.square(64))`` (docs/method.md §7);
- ``gmsh``: the default data on the unstructured gmsh mesh of (-1, 1)^2 in
  ``gmsh_square.npz`` (about 4000 vertices, generated once by
  :func:`generate_gmsh_square`; the file, not gmsh, is the reference);
- ``refined``: the default data on ``Mesh.square(16).refine().refine()``
  (numbering of uniform refinement, nested levels from ``parent``);

each with methods "exact", "exact-amg", "inexact" and paths "general",
"decoupled"; and ``mujump``: ``Mesh.square(32)``, per-triangle ``mu1 = 1`` on
triangles with centroid ``x < 0`` and 10 elsewhere, ``mu2 = 1``, default
``f, g``, all three methods on the general path.

The test imports this file (``make_scene``, ``run_case``, ...) so that both
build the cases in the same way.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
MESH_FILE = os.path.join(HERE, "gmsh_square.npz")
REFERENCE_FILE = os.path.join(HERE, "pipeline_reference.json")

METHODS = ("exact", "exact-amg", "inexact")
PATHS = ("general", "decoupled")
SCENES = ("default", "manufactured", "gmsh", "refined")
#: Vertices sampled per array: ``np.random.default_rng(SAMPLE_SEED).choice(N, N_SAMPLES,
#: replace=False)``, sorted (the indices are recorded too).
N_SAMPLES = 64
SAMPLE_SEED = 0
#: Weights of the dot-product fingerprint: ``2 * default_rng(WEIGHT_SEED).random(N) - 1``.
WEIGHT_SEED = 1
#: Mesh size of the gmsh mesh (about 4000 vertices on (-1, 1)^2).
GMSH_SIZE = 0.0345
ARRAYS = ("u1", "u2", "lam")
ETA_KEYS = ("eta", "eta_disc", "eta_lin", "eta_alg")


def case_ids() -> list[str]:
    """All case ids ``scene-method-path``, in recording order."""
    ids = [f"{s}-{m}-{p}" for s in SCENES for m in METHODS for p in PATHS]
    ids += [f"mujump-{m}-general" for m in METHODS]
    return ids


def split_case(case_id: str) -> tuple[str, str, str]:
    """``"gmsh-exact-amg-general"`` -> ``("gmsh", "exact-amg", "general")``."""
    scene, rest = case_id.split("-", 1)
    method, path = rest.rsplit("-", 1)
    return scene, method, path


# ---------------------------------------------------------------------------- the gmsh mesh


def generate_gmsh_square(size: float = GMSH_SIZE) -> tuple[np.ndarray, np.ndarray, str]:
    """Unstructured gmsh mesh of (-1, 1)^2: vertices (N, 2), triangles (M, 3), gmsh version."""
    import gmsh

    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.add("square")
        gmsh.model.occ.addRectangle(-1.0, -1.0, 0.0, 2.0, 2.0)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.Algorithm", 6)  # Frontal-Delaunay
        gmsh.option.setNumber("Mesh.MeshSizeMin", size)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.model.mesh.generate(2)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        _, tri_nodes = gmsh.model.mesh.getElementsByType(2)
        version = gmsh.__version__
    finally:
        gmsh.finalize()
    coords = np.asarray(coords, dtype=np.float64).reshape(-1, 3)[:, :2]
    tags = np.asarray(tags, dtype=np.int64)
    index = np.full(tags.max() + 1, -1, dtype=np.int64)
    index[tags] = np.arange(tags.size)
    tri = index[np.asarray(tri_nodes, dtype=np.int64).reshape(-1, 3)]
    used = np.zeros(tags.size, dtype=bool)
    used[tri.ravel()] = True  # drop nodes of no triangle (none expected)
    renumber = np.cumsum(used) - 1
    return np.ascontiguousarray(coords[used]), renumber[tri].astype(np.int64), version


def mesh_arrays_digest(vertices: np.ndarray, triangles: np.ndarray) -> str:
    """SHA-256 of the float64 vertices and int64 triangles (C order)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(triangles, dtype=np.int64).tobytes())
    return h.hexdigest()


def load_gmsh_square() -> tuple[np.ndarray, np.ndarray]:
    with np.load(MESH_FILE) as data:
        return data["vertices"].astype(np.float64), data["triangles"].astype(np.int64)


# ---------------------------------------------------------------------------- the scenes


def make_scene(name: str):
    """A new Scene (and new mesh) of the named case scene."""
    import fastmem as fm

    default = {"mu": (1.0, 1.0), "f": (-1.0, 1.0), "g": 0.1}
    if name == "default":
        return fm.Scene(fm.Mesh.square(64), **default)
    if name == "manufactured":
        return fm.Manufactured().scene(fm.Mesh.square(64))
    if name == "gmsh":
        vertices, triangles = load_gmsh_square()
        return fm.Scene(fm.Mesh(vertices, triangles), **default)
    if name == "refined":
        return fm.Scene(fm.Mesh.square(16).refine().refine(), **default)
    if name == "mujump":
        mesh = fm.Mesh.square(32)
        centroid_x = mesh.vertices[mesh.triangles, 0].mean(axis=1)
        mu1 = np.where(centroid_x < 0.0, 1.0, 10.0)
        return fm.Scene(mesh, mu=(mu1, 1.0), f=(-1.0, 1.0), g=0.1)
    raise ValueError(f"unknown scene {name!r}")


# ---------------------------------------------------------------------------- fingerprints


def sample_indices(n: int) -> np.ndarray:
    return np.sort(np.random.default_rng(SAMPLE_SEED).choice(n, N_SAMPLES, replace=False))


def weights(n: int) -> np.ndarray:
    return 2.0 * np.random.default_rng(WEIGHT_SEED).random(n) - 1.0


def fingerprint(x: np.ndarray, idx: np.ndarray, w: np.ndarray) -> dict:
    """Values at the sampled vertices, 2-norm, sum and dot product with the weights."""
    x = np.asarray(x, dtype=np.float64)
    return {
        "samples": [float(v) for v in x[idx]],
        "norm": float(np.linalg.norm(x)),
        "sum": float(np.sum(x)),
        "dot": float(np.dot(w, x)),
    }


def summarize(result) -> dict:
    """The recorded quantities of one Result (JSON-serialisable, floats exact)."""
    n = result.u1.size
    idx = sample_indices(n)
    w = weights(n)
    record = {
        "n_vertices": int(n),
        "indices": [int(i) for i in idx],
        "fingerprints": {name: fingerprint(getattr(result, name), idx, w) for name in ARRAYS},
        "n_newton": int(result.n_newton),
        "cg_total": 0,
        "level_newton": None,
        "converged": bool(result.converged),
        "eta": None if result.eta is None else float(result.eta),
    }
    if result.method != "exact":
        record["cg_total"] = int(np.asarray(result.history["inner_total"])[-1])
    levels = result.parameters.get("solver", {}).get("levels")
    if levels is not None:
        record["level_newton"] = [int(level["newton"]) for level in levels]
    components = result.eta_components or {}
    for key in ETA_KEYS[1:]:
        record[key] = float(components[key]) if key in components else None
    return record


def run_case(case_id: str, multigrid: str = "algebraic") -> dict:
    """Solve one case from scratch (new mesh and scene) and summarize the result.

    ``multigrid``: the preconditioner of the CG steps; the record was made with
    pyamg's on every level, ``"algebraic"`` since the geometric multigrid of
    nested chains (issue 33) became the default.
    """
    import fastmem as fm

    scene_name, method, path = split_case(case_id)
    scene = make_scene(scene_name)
    # mujump was recorded when per-triangle tensions had no coarse chain on the
    # structured generators (their transfer to Mesh.coarser() by point location came
    # later, fastmem.solver.nested._transfer_mu): solved here as recorded, without it
    options = {"nested": False} if scene_name == "mujump" else {}
    result = fm.solve(
        scene, method=method, path=path, estimate=True, multigrid=multigrid, **options
    )
    return summarize(result)


# ---------------------------------------------------------------------------- comparison


def differences(a: dict, b: dict) -> dict:
    """Largest difference of two records per quantity, scaled as in the test.

    Fingerprint entries: |difference| / (recorded norm / sqrt(N)); estimates:
    relative difference; integers and flags: 0 or 1 (different).
    """
    out = {}
    n = a["n_vertices"]
    for name in ARRAYS:
        fa, fb = a["fingerprints"][name], b["fingerprints"][name]
        scale = max(abs(fa["norm"]) / np.sqrt(n), np.finfo(float).tiny)
        diffs = [abs(x - y) for x, y in zip(fa["samples"], fb["samples"], strict=True)]
        diffs += [abs(fa[k] - fb[k]) for k in ("norm", "sum", "dot")]
        out[name] = max(diffs) / scale
    for key in ETA_KEYS:
        x, y = a[key], b[key]
        out[key] = 0.0 if x == y else abs(x - y) / max(abs(x), abs(y))
    for key in ("n_newton", "cg_total", "level_newton", "converged", "indices"):
        out[key] = int(a[key] != b[key])
    return out


def compare_runs(first: dict, second: dict, label: str) -> bool:
    """Print whether two {case: record} dicts are bitwise equal; return True if they are."""
    identical = True
    for case in first:
        if first[case] == second[case]:
            continue
        identical = False
        diff = {k: v for k, v in differences(first[case], second[case]).items() if v}
        print(f"  {label}: {case} differs: {diff}")
    print(f"{label}: {'bitwise identical' if identical else 'NOT identical'} ({len(first)} cases)")
    return identical


# ---------------------------------------------------------------------------- main


def _git(*args) -> str:
    try:
        out = subprocess.run(["git", "-C", ROOT, *args], capture_output=True, text=True, check=True)
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def record_all(ids, verbose=True) -> tuple[dict, dict]:
    cases, seconds = {}, {}
    for case in ids:
        t0 = time.perf_counter()
        cases[case] = run_case(case)
        seconds[case] = round(time.perf_counter() - t0, 3)
        if verbose:
            r = cases[case]
            print(
                f"{case:34s} {seconds[case]:7.2f} s  newton {r['n_newton']:3d}  "
                f"cg {r['cg_total']:4d}  levels {r['level_newton']}  eta {r['eta']:.6e}",
                flush=True,
            )
    return cases, seconds


def format_reference(meta: dict, cases: dict) -> str:
    """JSON text: ``{"meta": ..., "cases": {id: record}}`` with one line per case.

    ``json`` writes a Python float by its ``repr``, the shortest string that
    reads back to the same double: the recorded values are exact.
    """
    lines = [f" {json.dumps(case)}: {json.dumps(record)}" for case, record in cases.items()]
    meta_text = json.dumps(meta, indent=1).replace("\n", "\n ")
    return '{\n "meta": ' + meta_text + ',\n "cases": {\n' + ",\n".join(lines) + "\n }\n}\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=REFERENCE_FILE, help="JSON file to write")
    parser.add_argument(
        "--check-determinism",
        action="store_true",
        help="solve every case twice here and once in a second process; "
        "compare bitwise (writes no reference)",
    )
    parser.add_argument(
        "--cases-only",
        action="store_true",
        help="write only {case: record} to --out (used by the determinism check)",
    )
    parser.add_argument(
        "--regenerate-mesh",
        action="store_true",
        help="regenerate gmsh_square.npz with gmsh (changes the reference)",
    )
    args = parser.parse_args(argv)

    sys.path.insert(0, ROOT)
    import fastmem as fm

    here = os.path.dirname(os.path.abspath(fm.__file__))
    print(f"fastmem {fm.__file__}  kernels {fm.kernels.__file__}", flush=True)
    if os.path.dirname(here) != ROOT:
        print(f"fastmem was not imported from {ROOT}: refusing to record", file=sys.stderr)
        return 2

    gmsh_version = None
    if args.regenerate_mesh or not os.path.exists(MESH_FILE):
        vertices, triangles, gmsh_version = generate_gmsh_square()
        np.savez_compressed(MESH_FILE, vertices=vertices, triangles=triangles)
        print(
            f"wrote {MESH_FILE}: {len(vertices)} vertices, {len(triangles)} triangles "
            f"(gmsh {gmsh_version})"
        )
    vertices, triangles = load_gmsh_square()

    ids = case_ids()
    if args.cases_only:
        cases, _ = record_all(ids, verbose=False)
        with open(args.out, "w") as fh:
            json.dump(cases, fh)
        return 0

    if args.check_determinism:
        first, _ = record_all(ids)
        second, _ = record_all(ids, verbose=False)
        ok = compare_runs(first, second, "same process, second run")
        tmp = os.path.join(HERE, ".determinism_other_process.json")
        env = dict(os.environ)
        subprocess.run(
            [sys.executable, os.path.abspath(__file__), "--cases-only", "--out", tmp],
            check=True,
            env=env,
        )
        with open(tmp) as fh:
            other = json.load(fh)
        os.remove(tmp)
        ok &= compare_runs(first, other, "second process")
        return 0 if ok else 1

    t0 = time.perf_counter()
    cases, seconds = record_all(ids)
    import numba
    import pyamg
    import scipy

    meta = {
        "description": "fastmem.solve reference results before the solver-pipeline refactor; "
        "see tests/data/record_pipeline_reference.py and tests/solver/test_pipeline_reference.py",
        "git_commit": _git("rev-parse", "HEAD"),
        "git_dirty": bool(_git("status", "--porcelain", "--untracked-files=no")),
        "recorded": time.strftime("%Y-%m-%d %H:%M:%S %z"),
        "fastmem_file": fm.__file__,
        "versions": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "scipy": scipy.__version__,
            "pyamg": pyamg.__version__,
            "numba": numba.__version__,
        },
        "machine": platform.machine(),
        "threads": {**fm.get_threads(), "numba_threading_layer": numba.threading_layer()},
        "n_samples": N_SAMPLES,
        "sample_seed": SAMPLE_SEED,
        "weight_seed": WEIGHT_SEED,
        "weights_head": [float(x) for x in weights(8)],  # the stream is prefix-stable
        "gmsh_mesh": {
            "file": os.path.basename(MESH_FILE),
            "n_vertices": int(len(vertices)),
            "n_triangles": int(len(triangles)),
            "sha256": mesh_arrays_digest(vertices, triangles),
            "mesh_size": GMSH_SIZE,
        },
        "seconds_per_case": seconds,
        "seconds_total": round(time.perf_counter() - t0, 2),
    }
    if gmsh_version is not None:
        meta["gmsh_mesh"]["gmsh_version"] = gmsh_version
    elif os.path.exists(args.out):  # keep the version the mesh was generated with
        with open(args.out) as fh:
            old = json.load(fh).get("meta", {}).get("gmsh_mesh", {})
        if old.get("sha256") == meta["gmsh_mesh"]["sha256"] and "gmsh_version" in old:
            meta["gmsh_mesh"]["gmsh_version"] = old["gmsh_version"]
    with open(args.out, "w") as fh:
        fh.write(format_reference(meta, cases))
    print(f"wrote {args.out} ({os.path.getsize(args.out)} bytes) in {meta['seconds_total']} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
