"""Peer solvers on the ball obstacle problem: PETSc SNES VI against fastmem, time against error.

The problem is docs/obstacle.md §8.1 (PETSc's snes tutorial ex9, Bueler) on
n x n cells of (-2, 2)^2.  PETSc runs in its own interpreter (petsc4py is not
in fastmem's venv; docs/peers.md says how it was installed): this script starts
``bench/_petsc_ball.py`` there once per variant, hands it the sizes as JSON on
stdin and reads back JSON plus one ``.npy`` solution per size (in a temporary
folder).  Variants (each ``-snes_type vinewtonrsls``, PETSc's default
tolerances, KSP GMRES):

* ``mg``: ex9's recommended run, ``-snes_grid_sequence k -pc_type mg`` from
  a 4 x 4-cell grid (k = log2(n/4));
* ``gamg``: ``-pc_type gamg`` on the final grid from u = 0 (no grid
  sequence: the active set grows by about a ring of points per Newton step,
  so the step count grows like n, and ``-snes_max_it max(50, n)`` replaces
  the default limit of 50, which n = 512 already exceeds);
* ``gamg_gs``: the grid sequence of ``mg`` with ``-pc_type gamg``.

For every PETSc solution this script computes, in fastmem's venv, the energy
error :math:`|||u - u_h|||` with ``fastmem.problems.ball.ball_energy_error``
on ``Mesh.rectangle(n, n, (-2, 2, -2, 2), diagonal)`` (``--diagonal``,
default "symmetric"; the 5-point solution read as a P1 function: on this mesh
the P1 stiffness matrix is the 5-point Laplacian, §8.1, but the P1 function,
and so its energy error, depends on the diagonal pattern) and the max nodal error, after mapping the
DMDA's natural ordering to the mesh's vertex order by coordinates.  fastmem's own rows come from
:func:`fastmem_side` (to be written: see there).

Where no interpreter with petsc4py is found, the script says so on one line
(pointing at docs/peers.md), writes ``{"skipped": reason}`` and exits 0.

    python -m bench.peers [--quick] [--sizes 64 128 256 512 1024]
        [--variants mg gamg gamg_gs] [--repeat 3] [--petsc-python PATH]

The PETSc interpreter is, in this order: ``--petsc-python``, the environment
variable ``FASTMEM_PETSC_PYTHON``, ``<repo>/../petsc-venv/bin/python``
(``/work/petsc-venv`` here: PETSc built from PyPI), then ``python3`` on PATH
and ``/usr/bin/python3`` (Debian's ``python3-petsc4py``), the first that
imports petsc4py.  Debian's package installs petsc4py under
``/usr/lib/petscdir/petsc*/*-real`` and finds it only through ``PETSC_DIR``
(or the ``/usr/lib/petsc`` link that ``petsc-dev`` adds); the probe sets
``PETSC_DIR`` to that folder when it is not set.
"""

import glob
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench._common import finish, parse, parser, progress

FULL_SIZES = [64, 128, 256, 512, 1024]
QUICK_SIZES = [16, 32]
VARIANTS = ("mg", "gamg", "gamg_gs")
#: Largest n for the ``gamg`` variant without grid sequence by default (its
#: Newton step count grows like n: about n/8 steps, one GAMG setup each).
GAMG_PLAIN_MAX = 1024
#: Diagonal pattern of fastmem's mesh (``Mesh.rectangle``); the P1 energy error of the
#: same nodal values depends on it (at n = 64: 0.0709 "symmetric", 0.0682 "right"/"left").
DIAGONAL = "symmetric"
DIAGONALS = ("symmetric", "right", "left")

HERE = Path(__file__).resolve().parent
WORKER = HERE / "_petsc_ball.py"
ENV_VAR = "FASTMEM_PETSC_PYTHON"
INSTALL_HINT = (
    "PETSc (petsc4py) not found: install it as docs/peers.md describes "
    "(Debian: apt-get install python3-petsc4py; or PyPI into a separate venv), "
    f"or point {ENV_VAR} at a Python that imports petsc4py"
)

_PROBE = (
    "import json, sys, petsc4py; petsc4py.init([]); from petsc4py import PETSc; "
    "v = PETSc.Sys.getVersion(); "
    "print(json.dumps({'petsc': '%d.%d.%d' % tuple(v), 'petsc4py': petsc4py.__version__, "
    "'python': sys.version.split()[0], 'executable': sys.executable, "
    "'petsc_dir': petsc4py.get_config().get('PETSC_DIR')}))"
)


# ------------------------------------------------------------------ finding PETSc


def _debian_petsc_dirs():
    """Debian's real-scalar PETSc folders, newest first."""
    return sorted(glob.glob("/usr/lib/petscdir/petsc*/*-real"), reverse=True)


def _candidates(explicit=None):
    out = []
    if explicit:
        out.append(("--petsc-python", str(explicit)))
    if os.environ.get(ENV_VAR):
        out.append((ENV_VAR, os.environ[ENV_VAR]))
    out.append(("petsc-venv", str(HERE.parent.parent / "petsc-venv" / "bin" / "python")))
    py3 = shutil.which("python3")
    if py3:
        out.append(("python3 on PATH", py3))
    out.append(("Debian python3", "/usr/bin/python3"))
    return out


def _probe(python, env, timeout=60):
    try:
        res = subprocess.run(
            [python, "-c", _PROBE],
            capture_output=True,
            text=True,
            env=env,
            timeout=timeout,
            check=False,
        )
    except (OSError, subprocess.SubprocessError) as exc:
        return None, f"{python}: {exc}"
    if res.returncode != 0:
        last = (res.stderr.strip().splitlines() or [f"exit code {res.returncode}"])[-1]
        return None, f"{python}: {last}"
    try:
        return json.loads(res.stdout.strip().splitlines()[-1]), None
    except (ValueError, IndexError):
        return None, f"{python}: unreadable probe output"


def find_petsc(explicit=None):
    """Return ``(python, env, info)`` of the first interpreter that imports petsc4py.

    ``info`` is the probe's dict (PETSc and petsc4py versions, ...) plus
    ``found_by``; ``(None, None, reasons)`` when none does, ``reasons`` the
    list of what each candidate said.
    """
    reasons = []
    seen = set()
    for how, python in _candidates(explicit):
        real = os.path.realpath(python)
        if real in seen:
            continue
        seen.add(real)
        if not os.path.exists(python):
            reasons.append(f"{python} ({how}): not found")
            continue
        envs = [dict(os.environ)]
        if "PETSC_DIR" not in os.environ:
            for d in _debian_petsc_dirs():
                envs.append({**os.environ, "PETSC_DIR": d})
        for env in envs:
            info, why = _probe(python, env)
            if info is not None:
                info["found_by"] = how
                if env.get("PETSC_DIR") and "PETSC_DIR" not in os.environ:
                    info["petsc_dir_set"] = env["PETSC_DIR"]
                return python, env, info
            extra = "" if env is envs[0] else f", PETSC_DIR={env['PETSC_DIR']}"
            reasons.append(f"{why} ({how}{extra})")
    return None, None, reasons


# ------------------------------------------------------------------ the PETSc runs


def run_petsc(
    python, env, sizes, variant, repeats, outdir, options=None, timeout=None, budget=60.0
):
    """Run ``_petsc_ball.py`` in the PETSc interpreter; return its JSON object."""
    cfg = {
        "sizes": list(sizes),
        "variant": variant,
        "repeats": repeats,
        "budget": budget,
        "outdir": str(outdir),
        "label": variant,
        "options": options or {},
    }
    # one MPI rank, one thread for any threaded BLAS: fastmem's solver phases run the same way
    env = {**env, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    res = subprocess.run(
        [python, str(WORKER), "-"],
        input=json.dumps(cfg),
        stdout=subprocess.PIPE,
        text=True,
        env=env,
        timeout=timeout,
        check=False,
    )
    if res.returncode != 0:
        raise RuntimeError(f"PETSc worker ({variant}) failed with exit code {res.returncode}")
    lines = [ln for ln in res.stdout.splitlines() if ln.strip()]
    out = json.loads(lines[-1])
    out["process_s"] = time.perf_counter() - t0
    return out


def vertex_map(mesh, xy, n):
    """Indices ``p`` with ``xy[p[k]]`` the point of mesh vertex ``k`` (vectorised).

    Both point sets are snapped to the (n+1) x (n+1) lattice of (-2, 2)^2;
    raises when a point is off the lattice or the two sets differ.
    """
    h = 4.0 / n

    def keys(pts):
        ij = np.rint((np.asarray(pts, dtype=float) + 2.0) / h)
        off = np.abs(ij * h - 2.0 - pts).max()
        if off > 1e-9 or ij.min() < 0 or ij.max() > n:
            raise ValueError(f"points off the {n} x {n} lattice of (-2, 2)^2 (by {off:.2e})")
        ij = ij.astype(np.int64)
        return ij[:, 1] * (n + 1) + ij[:, 0]

    kd = keys(xy)
    km = keys(mesh.vertices)
    npts = (n + 1) ** 2
    if kd.size != npts or km.size != npts:
        raise ValueError(f"expected {npts} points, PETSc has {kd.size}, the mesh {km.size}")
    pos = np.full(npts, -1, dtype=np.int64)
    pos[kd] = np.arange(kd.size)
    if (pos < 0).any():
        raise ValueError("PETSc's points are not the whole lattice")
    return pos[km]


def ball_mesh(n, diagonal=DIAGONAL):
    """fastmem's mesh of the ball problem: n x n cells of (-2, 2)^2, two triangles each."""
    from fastmem.mesh.mesh import Mesh

    return Mesh.rectangle(n, n, (-2.0, 2.0, -2.0, 2.0), diagonal=diagonal)


def petsc_errors(row, n, diagonal=DIAGONAL, all_diagonals=False):
    """Energy and max nodal error of one PETSc solution on fastmem's mesh of n x n cells.

    The nodal values are the same on every diagonal pattern (the 5-point
    solution), but the P1 function they define is not: ``energy_error`` is on
    ``diagonal`` (the mesh of :func:`fastmem_side`); with ``all_diagonals``,
    ``energy_error_by_diagonal`` has all three patterns.
    """
    from fastmem.problems.ball import ball_energy_error, ball_solution

    data = np.load(row["solution_file"])
    out = {}
    patterns = DIAGONALS if all_diagonals else (diagonal,)
    by_diag = {}
    for diag in patterns:
        mesh = ball_mesh(n, diag)
        p = vertex_map(mesh, data[:, :2], n)
        u_h = np.ascontiguousarray(data[p, 2])
        t0 = time.perf_counter()
        by_diag[diag] = ball_energy_error(mesh, u_h)
        if diag == diagonal:
            v = mesh.vertices
            out["energy_error"] = by_diag[diag]
            out["energy_error_seconds"] = time.perf_counter() - t0
            out["max_error_mesh"] = float(np.abs(u_h - ball_solution(v[:, 0], v[:, 1])).max())
    out["diagonal"] = diagonal
    if all_diagonals:
        out["energy_error_by_diagonal"] = by_diag
    return out


# ------------------------------------------------------------------ fastmem's side


def fastmem_side(sizes, diagonal=DIAGONAL, repeat=3):
    """fastmem on the same ball problem: one dict per (n, method).

    Each n is solved ``repeat`` times in this process after ``fm.warm_up()`` and
    one small solve, from the problem data on a mesh whose topology is built
    before the timing (as the PETSc rows time ``SNESSolve`` on a ready DMDA):
    ``method="inexact"`` (the default: AMG-CG stopped by the estimators, the
    guaranteed bound computed) and ``method="exact-amg", estimate=False`` (no
    bound: what PETSc computes).  ``seconds`` is the median, ``first_seconds``
    the first solve; errors from ``fastmem.problems.ball`` on :func:`ball_mesh`.
    """
    import numpy as np

    import fastmem as fm
    from fastmem.problems.ball import ball_energy_error, ball_solution
    from fastmem.problems.obstacles import ball

    fm.warm_up()
    fm.solve(ball(32))
    rows = []
    for n in sizes:
        for method, estimate in (("inexact", True), ("exact-amg", False)):
            times, res, problem = [], None, None
            for _ in range(max(1, repeat)):
                problem = ball(n, mesh=ball_mesh(n, diagonal))
                _ = problem.mesh.edges, problem.mesh.patch_ptr, problem.mesh.diameters
                t0 = time.perf_counter()
                res = fm.solve(problem, method=method, estimate=estimate)
                times.append(time.perf_counter() - t0)
            exact = ball_solution(*problem.mesh.vertices.T)
            row = {
                "n": n,
                "method": method,
                "bound": estimate,
                "seconds": float(np.median(times)),
                "first_seconds": times[0],
                "energy_error": ball_energy_error(problem.mesh, res.u),
                "max_error": float(np.abs(res.u - exact).max()),
                "eta": res.eta,
                "newton_finest": res.n_newton,
            }
            rows.append(row)
            progress(
                f"fastmem {method:9s} n={n:5d}: {row['seconds']:.3f} s (first "
                f"{row['first_seconds']:.3f}), max err {row['max_error']:.3e}, energy err "
                f"{row['energy_error']:.4e}" + (f", eta {res.eta:.4e}" if estimate else "")
            )
    return rows


def comparison(rows):
    """fastmem's time to PETSc's finest error (within 1 %), against the fastest PETSc variant."""
    petsc = [r for r in rows if r.get("solver") == "petsc" and r.get("converged", True)]
    ours = [r for r in rows if r.get("solver") == "fastmem"]
    if not petsc or not ours:
        return None
    finest = max(r["n"] for r in petsc)
    best = min((r for r in petsc if r["n"] == finest), key=lambda r: r["seconds"])
    target = best["energy_error"] * (1.0 + 1e-6)
    out = {
        "petsc_n": finest,
        "petsc_variant": best["variant"],
        "petsc_seconds": best["seconds"],
        "petsc_energy_error": best["energy_error"],
    }
    for method in sorted({r["method"] for r in ours}):
        reach = [r for r in ours if r["method"] == method and r["energy_error"] <= 1.01 * target]
        if reach:
            fastest = min(reach, key=lambda r: r["seconds"])
            out[method] = {
                "n": fastest["n"],
                "seconds": fastest["seconds"],
                "first_seconds": fastest["first_seconds"],
                "ratio_to_petsc": fastest["seconds"] / best["seconds"],
            }
    return out


# ------------------------------------------------------------------ main


def main(argv=None):
    p = parser(__doc__, repeat=3)
    p.add_argument("--variants", nargs="*", choices=VARIANTS, default=list(VARIANTS))
    p.add_argument(
        "--petsc-python", default=None, help=f"Python with petsc4py (else ${ENV_VAR}, ...)"
    )
    p.add_argument(
        "--gamg-plain-max",
        type=int,
        default=GAMG_PLAIN_MAX,
        help="largest n for the gamg variant without grid sequence",
    )
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds per PETSc variant")
    p.add_argument(
        "--budget",
        type=float,
        default=60.0,
        help="stop repeating a PETSc size once its runs add up to this many seconds",
    )
    p.add_argument(
        "--diagonal",
        choices=DIAGONALS,
        default=DIAGONAL,
        help="diagonal pattern of the mesh on which the energy error is measured",
    )
    p.add_argument(
        "--all-diagonals",
        action="store_true",
        help="also record the PETSc energy errors on all three diagonal patterns",
    )
    args = parse(p, argv)
    sizes = args.sizes or (QUICK_SIZES if args.quick else FULL_SIZES)
    bad = [n for n in sizes if n < 4 or n % 4]
    if bad:
        p.error(f"sizes must be multiples of 4 (the coarse grid of the grid sequence): {bad}")

    parameters = {k: (str(v) if k == "results" else v) for k, v in vars(args).items()}
    python, env, info = find_petsc(args.petsc_python)
    if python is None:
        print(f"bench.peers: skipped: {INSTALL_HINT}", flush=True)
        for why in info:
            progress(f"  {why}")
        # fastmem's side alone: the rows a run with PETSc would set beside it
        fm_rows = fastmem_side(sizes, args.diagonal, args.repeat)
        payload = {
            "skipped": INSTALL_HINT,
            "probes": info,
            "parameters": parameters,
            "sizes": sizes,
            "fastmem": fm_rows,
            "rows": [{"solver": "fastmem", **r} for r in fm_rows],
        }
        finish("peers", payload, args.quick)
        return 0
    progress(
        f"PETSc {info['petsc']} (petsc4py {info['petsc4py']}) in {python} "
        f"(Python {info['python']}, found by {info['found_by']})"
    )

    rows, runs = [], {}
    with tempfile.TemporaryDirectory(prefix="fastmem-peers-") as tmp:
        for variant in args.variants:
            vs = [n for n in sizes if variant != "gamg" or n <= args.gamg_plain_max]
            if not vs:
                continue
            try:
                out = run_petsc(
                    python,
                    env,
                    vs,
                    variant,
                    args.repeat,
                    tmp,
                    timeout=args.timeout,
                    budget=args.budget,
                )
            except (RuntimeError, subprocess.TimeoutExpired, ValueError) as exc:
                progress(f"WARNING: petsc {variant}: {exc}")
                runs[variant] = {"error": str(exc)}
                continue
            runs[variant] = {k: v for k, v in out.items() if k != "rows"}
            for r in out["rows"]:
                if not r.get("converged", True):
                    progress(
                        f"WARNING: petsc {variant} n={r['n']} did not converge "
                        f"(SNES reason {r['converged_reason']})"
                    )
                r.update(petsc_errors(r, r["n"], args.diagonal, args.all_diagonals))
                r.pop("solution_file", None)  # a temporary file
                rows.append({"solver": "petsc", "variant": variant, **r})
                progress(
                    f"petsc {variant:8s} n={r['n']:5d}: {r['seconds']:.3f} s, "
                    f"SNES {r['snes_its']} ({r['snes_its_total']} in all), "
                    f"KSP {r['ksp_its_total']}, "
                    f"max err {r['max_error']:.3e}, energy err {r['energy_error']:.4e}"
                )

    fm_rows = fastmem_side(sizes, args.diagonal, args.repeat)
    rows.extend({"solver": "fastmem", **r} for r in fm_rows)
    versus = comparison(rows)
    if versus:
        for method in ("inexact", "exact-amg"):
            if method in versus:
                v = versus[method]
                progress(
                    f"PETSc {versus['petsc_variant']} reaches energy error "
                    f"{versus['petsc_energy_error']:.4e} at n={versus['petsc_n']} in "
                    f"{versus['petsc_seconds']:.3f} s; fastmem {method} at n={v['n']}: "
                    f"{v['seconds']:.3f} s ({v['ratio_to_petsc']:.2f}x PETSc's time)"
                )

    payload = {
        "parameters": parameters,
        "sizes": sizes,
        "repeat": args.repeat,
        "petsc": info,
        "petsc_python": python,
        "petsc_runs": runs,
        "diagonal": args.diagonal,
        "fastmem": fm_rows,
        "comparison": versus,
        "rows": rows,
    }
    finish("peers", payload, args.quick)
    return 0


if __name__ == "__main__":
    sys.exit(main())
