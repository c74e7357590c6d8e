"""Command line: ``fastmem run``, ``info``, ``export``, ``plot`` and ``sweep`` (docs/cli.md).

``fastmem run`` with no option solves the default scene (docs/method.md §8):
the square (-1, 1)^2, mu1 = mu2 = 1, f1 = -1, f2 = 1, g = 0.1, on a structured
mesh, with the adaptive inexact Newton-min (nested iteration over coarser
meshes), prints one monitor line per estimator evaluation (or per Newton step
for ``--method exact``) and a summary, and writes an HDF5 archive.  Errors in
the input are reported in one line on stderr (exit status 2), without a
traceback.
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import os
import sys
import time
from pathlib import Path

import h5py
import numpy as np

from ..about import package_version
from ..adapt.obstacle import refine_problem
from ..config import set_threads
from ..errors import FastmemError, MemoryLimitError, ParameterError, closest_name
from ..fem.obstacle import Obstacle
from ..fem.scene import Scene
from ..io.archive import export, info, load
from ..io.writer import ARCHIVE_SUFFIXES, EXPORT_SUFFIXES, check_output, companion_files
from ..linalg.sparse import THREADED_ROWS
from ..memory import MEMORY_LIMIT_ENV, check_memory, memory_limit
from ..mesh.mesh import Mesh
from ..pipeline import solve
from ..problems.obstacles import REFERENCE_OBSTACLES, exact_error, reference_obstacle
from ..solver.nested import interpolation_matrix
from .plot import add_parser as _add_plot
from .sweep import add_sweep_parser, extend_plot_parser
from .twophase import add_twophase_parser, export_twophase, print_info
from .warmup import KernelMeter, WarmUp, kernels_cached, start_compile_helper, warm_up

__all__ = ["main"]

logger = logging.getLogger(__name__)

DEFAULT_N = 128
DEFAULT_OUTPUT = "fastmem-result.h5"
METHOD_CHOICES = ("inexact", "exact-amg", "exact")
#: ``fastmem run --problem``: the two membranes, a constant obstacle, the reference obstacles
PROBLEM_CHOICES = ("membranes", "obstacle", *REFERENCE_OBSTACLES)
#: boundary value of membrane 1 in the default scene
DEFAULT_G = 0.1


#: the two-membrane data of ``fastmem run`` and their defaults
MEMBRANE_DEFAULTS = {"mu1": 1.0, "mu2": 1.0, "f1": -1.0, "f2": 1.0}
#: the constant obstacle problem's data and their defaults
OBSTACLE_DEFAULTS = {"mu": 1.0, "f": -10.0}


def _check_problem_options(args) -> None:
    """Refuse data of one problem given to another, naming the option and the fix."""
    given = lambda names: [n for n in names if getattr(args, n) is not None]  # noqa: E731
    if args.problem == "membranes":
        extra = given(("lower", "upper", "mu", "f"))
        if extra:
            raise ParameterError(
                f"--{extra[0]} is an option of --problem obstacle; the two-membrane scene "
                "takes --mu1, --mu2, --f1, --f2 (or add --problem obstacle)"
            )
        for name, value in MEMBRANE_DEFAULTS.items():
            if getattr(args, name) is None:
                setattr(args, name, value)
        return
    extra = given(MEMBRANE_DEFAULTS)
    if extra:
        raise ParameterError(
            f"--{extra[0]} is an option of the two-membrane scene; --problem {args.problem} "
            "takes --mu, --f, --g, --lower, --upper (obstacle) or none (reference problems)"
        )
    if args.problem != "obstacle":
        extra = given(("lower", "upper", "mu", "f", "g"))
        if extra:
            raise ParameterError(
                f"--{extra[0]} cannot change the reference problem {args.problem} "
                "(docs/obstacle.md §8); use --problem obstacle for your own data"
            )
        return
    for name, value in OBSTACLE_DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, value)


def _describe_obstacle(args, problem) -> str:
    if args.problem != "obstacle":
        return f"{args.problem} (docs/obstacle.md §8)"
    sides = ", ".join(
        f"{name} = {value:g}"
        for name, value in (("lower", args.lower), ("upper", args.upper))
        if value is not None
    )
    return f"obstacle: mu = {args.mu:g}, f = {args.f:g}, g = {problem.g:g}, {sides}"


def _out(text: str = "") -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


class _Parser(argparse.ArgumentParser):
    """An argument parser that refuses unknown arguments itself, suggesting the closest option.

    argparse hands a subcommand's unknown arguments up to the top-level parser,
    which then prints the top-level usage (``fastmem run --N 64`` showed
    ``usage: fastmem [-h] [--version] COMMAND ...``).  Every parser of the
    command line is of this class (``add_subparsers`` makes its subparsers of
    the parent's class), so the subcommand that received an unknown option
    refuses it, with its own usage and the closest of its options.
    """

    def parse_known_args(self, args=None, namespace=None):
        namespace, extras = super().parse_known_args(args, namespace)
        if extras:
            self.error(self._unrecognized(extras))
        return namespace, extras

    def _unrecognized(self, extras: list[str]) -> str:
        options = [o for action in self._actions for o in action.option_strings]
        fixes = []
        for arg in extras:
            name = arg.split("=", 1)[0]
            if not name.startswith("-") or name in ("-", "--"):
                continue
            best = closest_name(name, options)
            if best is not None:
                fixes.append(f"{best} instead of {name}")
        text = f"unrecognized arguments: {' '.join(extras)}"
        if fixes:
            return f"{text}; did you mean {', '.join(fixes)}?"
        return f"{text}; {self.prog} --help lists the options"


def _build_parser() -> argparse.ArgumentParser:

    p = _Parser(
        prog="fastmem",
        description="Two-membrane contact problem: P1 finite elements, Newton-min.",
    )
    p.add_argument("--version", action="version", version=f"fastmem {package_version('0+unknown')}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    r = sub.add_parser(
        "run", help="solve a scene (default: the square, docs/method.md §8) and save it"
    )
    r.set_defaults(func=_cmd_run)
    mesh = r.add_mutually_exclusive_group()
    mesh.add_argument(
        "--n",
        type=int,
        default=None,
        help=f"cells per side of the structured square mesh (default {DEFAULT_N})",
    )
    mesh.add_argument(
        "--mesh", type=Path, default=None, help="mesh file readable by meshio (e.g. gmsh .msh)"
    )
    r.add_argument(
        "--domain",
        choices=("square", "lshape"),
        default="square",
        help="domain of the structured mesh of --n: the square (-1, 1)^2 (default) or the "
        "L-shape (-1, 1)^2 minus [0, 1) x (-1, 0]",
    )
    r.add_argument(
        "--refine", type=int, default=0, help="uniform refinements applied to the mesh (default 0)"
    )
    r.add_argument(
        "--problem",
        default="membranes",
        metavar="{" + ",".join(PROBLEM_CHOICES) + "}",
        help="membranes: the two-membrane scene (default); obstacle: one membrane above "
        "--lower and/or below --upper (constants) with load --f, tension --mu and boundary "
        "value --g; ball, step41, twosided: the reference obstacle problems "
        "(docs/obstacle.md §8) on --n cells per side",
    )
    o = r.add_argument_group("the obstacle problem (--problem obstacle)")
    o.add_argument("--lower", type=float, default=None, help="constant lower obstacle")
    o.add_argument("--upper", type=float, default=None, help="constant upper obstacle")
    o.add_argument("--mu", type=float, default=None, help="tension (default 1)")
    o.add_argument("--f", type=float, default=None, help="constant load (default -10)")
    r.add_argument("--mu1", type=float, default=None, help="tension of membrane 1 (default 1)")
    r.add_argument("--mu2", type=float, default=None, help="tension of membrane 2 (default 1)")
    r.add_argument("--f1", type=float, default=None, help="constant load f1 (default -1)")
    r.add_argument("--f2", type=float, default=None, help="constant load f2 (default 1)")
    r.add_argument(
        "--g",
        type=float,
        default=None,
        help="boundary value of u1 (default 0.1); of the obstacle problem's membrane (default 0)",
    )
    r.add_argument(
        "--method",
        default=None,
        metavar="{" + ",".join(METHOD_CHOICES) + "}",
        help="inexact: AMG-CG stopped by the estimators (default); exact-amg: AMG-CG to "
        "round-off (default with --no-estimate); exact: sparse direct solves (small meshes)",
    )
    r.add_argument(
        "--gamma-alg", type=float, default=0.1, help="inner stopping parameter (default 0.1)"
    )
    r.add_argument(
        "--gamma-lin", type=float, default=0.1, help="outer stopping parameter (default 0.1)"
    )
    r.add_argument(
        "--no-nested",
        action="store_true",
        help="start on the given mesh (no nested iteration over coarser meshes)",
    )
    r.add_argument(
        "--path",
        default="auto",
        choices=("auto", "general", "decoupled"),
        help="linear-step formulation (default auto)",
    )
    r.add_argument("--max-newton", type=int, default=1000, help="Newton-min step limit")
    r.add_argument("--threads", type=int, default=None, help="Numba threads (default: all)")
    r.add_argument(
        "--blas-threads", type=int, default=None, help="BLAS threads in solver phases (default 1)"
    )
    r.add_argument(
        "-o",
        "--output",
        type=Path,
        action="append",
        default=None,
        metavar="FILE",
        help=f"where to write the result (default {DEFAULT_OUTPUT}): .h5/.hdf5 a fastmem "
        "archive, .vtu/.xdmf an export for ParaView (.xdmf with its heavy data in FILE.h5); "
        "repeat for several files (-o run.h5 -o run.vtu).  Checked before the solve; an "
        "existing file is replaced, and the run says so",
    )
    r.add_argument("--no-save", action="store_true", help="write no file")
    r.add_argument(
        "--no-estimate",
        action="store_true",
        help="skip the a posteriori error bound (no flux reconstruction; the default method "
        "becomes exact-amg, since inexact stops by the estimators)",
    )
    r.add_argument(
        "--memory-limit",
        default=None,
        metavar="BYTES",
        help="refuse runs whose estimated peak memory exceeds this (e.g. 40G; 0 disables the "
        "check; default: the machine's memory, or $FASTMEM_MEMORY_LIMIT)",
    )
    r.add_argument("-q", "--quiet", action="store_true", help="no per-step monitor")
    a = r.add_argument_group(
        "solving to a tolerance (adaptive mesh refinement, starting from the mesh above)"
    )
    a.add_argument(
        "--tol", type=float, default=None, help="refine until the guaranteed bound eta <= TOL"
    )
    a.add_argument(
        "--rtol",
        type=float,
        default=None,
        help="refine until eta <= RTOL * |||u_h||| (energy norm of the discrete solution)",
    )
    a.add_argument(
        "--theta", type=float, default=None, help="Dörfler marking fraction (default 0.5)"
    )
    a.add_argument(
        "--min-growth",
        type=float,
        default=None,
        help="least vertex growth per refinement, in [1, 4] (default 1: Dörfler's)",
    )
    a.add_argument(
        "--bisections",
        type=int,
        default=None,
        help="rounds of bisection of the marked triangles per refinement, 1-3 (default 2)",
    )
    a.add_argument(
        "--max-vertices", type=int, default=None, help="vertex limit (default 5M; exact: 1M)"
    )
    a.add_argument("--max-levels", type=int, default=None, help="mesh limit (default 100)")
    a.add_argument(
        "--time-budget", type=float, default=None, help="seconds (stop before exceeding it)"
    )

    i = sub.add_parser("info", help="summarise a result archive")
    i.set_defaults(func=_cmd_info)
    i.add_argument("file", type=Path, help="result archive (.h5)")
    i.add_argument("--json", action="store_true", help="print the summary as JSON")

    e = sub.add_parser("export", help="export a result archive to VTU or XDMF")
    e.set_defaults(func=_cmd_export)
    e.add_argument("file", type=Path, help="result archive (.h5)")
    e.add_argument(
        "out",
        type=Path,
        help="file to write: .vtu (one file) or .xdmf (with its heavy data in OUT.h5)",
    )

    extend_plot_parser(_add_plot(sub))  # plot: an archive, or a sweep study folder
    add_sweep_parser(sub)
    add_twophase_parser(sub)
    return p


class _Table:
    """A live table on stdout: the header when enabled, then one line per call."""

    header = ""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        if enabled:
            _out(self.header)
            _out("-" * len(self.header))


class _Monitor(_Table):
    """Live table of a solve: one line per history row (:mod:`fastmem.solver.history`).

    ``eta_disc`` and ``eta`` are printed on rows whose flux was reconstructed
    (a fresh, guaranteed bound of that row's iterate) and left blank elsewhere.
    """

    header = (
        f"{'lev':>3} {'k':>3} {'inner':>5} {'total':>6} {'|A|':>8} {'changed':>7} "
        f"{'eta_disc':>10} {'eta_lin':>10} {'eta_alg':>10} {'eta':>10} {'sec':>7}"
    )

    @staticmethod
    def _number(value, fresh=True) -> str:
        return f"{value:>10.3e}" if fresh and np.isfinite(value) else " " * 10

    def __call__(self, row: dict) -> None:
        if not self.enabled:
            return
        fresh = bool(row["fresh_disc"])
        _out(
            f"{row['level']:>3d} {row['k']:>3d} {row['inner']:>5d} {row['inner_total']:>6d} "
            f"{row['n_active']:>8d} {row['n_changed']:>7d} "
            f"{self._number(row['eta_disc'], fresh)} {self._number(row['eta_lin'])} "
            f"{self._number(row['eta_alg'])} {self._number(row['eta'], fresh)} "
            f"{row['seconds']:>7.2f}" + ("  (safeguard)" if row["safeguard"] else "")
        )


class _LevelMonitor(_Table):
    """One line per mesh of a solve to a tolerance (a row of ``result.adaptivity``)."""

    header = (
        f"{'mesh':>4} {'vertices':>9} {'triangles':>10} {'eta':>10} {'target':>10} "
        f"{'eta_disc':>10} {'eta_lin':>10} {'eta_alg':>10} {'marked':>7} {'newton':>6} "
        f"{'cg':>5} {'sec':>7}"
    )

    #: after the table when a row was marked (:meth:`legend`)
    LEGEND = (
        "  * an intermediate mesh (it only marks and warm-starts the next one): its CG may\n"
        "    stop by its own error estimate, so the guaranteed eta_alg of its iterate, and\n"
        "    eta with it, can be loose; the returned mesh's is not"
    )

    def __init__(self, enabled: bool):
        super().__init__(enabled)
        self.marked = False

    def __call__(self, row: dict) -> None:
        if not self.enabled:
            return
        star = bool(row.get("cg_stop"))
        self.marked |= star
        alg = f"{row['eta_alg']:>9.3e}*" if star else f"{row['eta_alg']:>10.3e}"
        _out(
            f"{row['level']:>4d} {row['n_vertices']:>9d} {row['n_triangles']:>10d} "
            f"{row['eta']:>10.3e} {row['target']:>10.3e} {row['eta_disc']:>10.3e} "
            f"{row['eta_lin']:>10.3e} {alg} "
            f"{100 * row['marked_fraction']:>6.1f}% {row['newton']:>6d} {row['inner']:>5d} "
            f"{row['solve_seconds'] + row['refine_seconds']:>7.2f}"
        )

    def legend(self) -> None:
        """Print what the ``*`` of a row means, if a row had one."""
        if self.enabled and self.marked:
            _out(self.LEGEND)


def _adapt_keywords(args) -> dict:
    keys = (
        "tol",
        "rtol",
        "theta",
        "min_growth",
        "bisections",
        "max_vertices",
        "max_levels",
        "time_budget",
    )
    return {k: getattr(args, k) for k in keys if getattr(args, k) is not None}


def _outputs(args) -> list[tuple[Path, bool]]:
    """Check the files ``fastmem run`` will write, before any work: [(path, exists)]."""
    if args.no_save:
        if args.output:
            raise ParameterError("--no-save and -o/--output contradict each other: drop one")
        return []
    paths = args.output or [Path(DEFAULT_OUTPUT)]
    if len({p.resolve() for p in paths}) != len(paths):
        raise ParameterError(f"-o/--output names the same file twice: {[str(p) for p in paths]}")
    return [check_output(p) for p in paths]


def _write_outputs(result, outputs) -> None:

    for path, existed in outputs:
        if path.suffix.lower() in ARCHIVE_SUFFIXES:
            result.save(path)
            label = "archive"
        else:
            result.export(path)
            label = "export"
        extra = [str(c) for c in companion_files(path)]
        notes = ([f"with {', '.join(extra)}"] if extra else []) + (
            ["replaced the existing file"] if existed else []
        )
        _out(f"  {label:<17} {path}" + (f"  ({'; '.join(notes)})" if notes else ""))


#: printed under the kernels line by a run that compiled any kernel
FIRST_USE_NOTE = (
    "  note: kernels compile on first use and stay cached on disk; the first run with another\n"
    "        feature (--tol/--rtol, --mesh, another --method, --no-estimate) compiles more, once"
)


def _kernels_label(quiet: bool) -> None:
    """Say, before any kernel compiles, that kernels come next (the outcome follows)."""
    if quiet:
        return
    if kernels_cached() is False:
        text = "  compiling Numba kernels (first use) ..."
    else:  # cached kernels load; a feature used for the first time still compiles its own
        text = "  Numba kernels (loading from cache, compiling any not there) ..."
    sys.stdout.write(text)
    sys.stdout.flush()


def _build_mesh(args) -> Scene:
    if args.problem in REFERENCE_OBSTACLES:
        if args.mesh is not None:
            raise ParameterError(
                f"--problem {args.problem} brings its own domain: use --n, not --mesh"
            )
        problem = reference_obstacle(args.problem, DEFAULT_N if args.n is None else args.n)
        for _ in range(args.refine):
            problem = _refined_obstacle(problem)
        return problem
    if args.mesh is not None:
        mesh = Mesh.read(args.mesh)
    else:
        n = DEFAULT_N if args.n is None else args.n
        mesh = Mesh.lshape(n) if args.domain == "lshape" else Mesh.square(n)
    for _ in range(args.refine):
        mesh = mesh.refine()
    if args.problem == "obstacle":
        if args.lower is None and args.upper is None:
            raise ParameterError("--problem obstacle needs --lower, --upper or both")
        g = 0.0 if args.g is None else args.g
        return Obstacle(mesh, mu=args.mu, f=args.f, g=g, lower=args.lower, upper=args.upper)
    for name, value in MEMBRANE_DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    g = DEFAULT_G if args.g is None else args.g
    return Scene(mesh, mu=(args.mu1, args.mu2), f=(args.f1, args.f2), g=g)


def _refined_obstacle(problem):
    """Return the same reference problem on the red refinement of its mesh."""
    fine = problem.mesh.refine()

    class _Red:  # red refinement keeps the coarse vertices first; midpoints average
        @staticmethod
        def prolong(v):
            return interpolation_matrix(problem.mesh, fine) @ v

        @staticmethod
        def inherit(v):
            return np.repeat(v, 4)

    return refine_problem(problem, fine, _Red)


def _scene_and_kernels(args, method: str, adaptive: bool) -> tuple[Scene, float, float]:
    """Build the scene and compile or load the kernels; return (scene, mesh s, kernels s).

    Every compilation of the span is booked as kernels: the solver kernels the
    warm-up compiles, the callees of the flux kernel compiled while its helper
    process starts, and the mesh kernels that building the mesh compiles
    (timed by Numba's compile events and taken out of the mesh's seconds).
    """
    meter = KernelMeter()
    _kernels_label(args.quiet)
    t0 = time.perf_counter()
    try:
        if method == "inexact" or not args.no_estimate:
            # an empty cache: the flux kernel (and for a solve to a tolerance the
            # bisection kernels) compile in a helper process beside the mesh
            start_compile_helper(("patches", "refinement") if adaptive else ("patches",))
        t_mesh = time.perf_counter()
        with meter.timing():
            scene = _build_mesh(args)
        t_mesh = time.perf_counter() - t_mesh - meter.compile_seconds
        done = warm_up(
            method,
            estimate=not args.no_estimate,
            adaptive=adaptive,
            unstructured=scene.mesh.coarser() is None,
            obstacle=isinstance(scene, Obstacle),
            large=scene.mesh.n_vertices >= THREADED_ROWS,
        )
    except BaseException:
        if not args.quiet:
            _out(" stopped")  # end the line: the error follows on stderr
        raise
    total = WarmUp(
        seconds=time.perf_counter() - t0 - t_mesh,
        compiled=meter.compiled,
        loaded=meter.loaded,
        helper=done.helper,
        helper_kernels=done.helper_kernels,
    )
    if not args.quiet:
        _out(f" {total}")
        if total.compiled:
            _out(FIRST_USE_NOTE)
    return scene, t_mesh, total.seconds


def _cmd_run(args) -> int:

    if args.method is not None and args.method not in METHOD_CHOICES:
        raise ParameterError(
            f"--method must be one of {', '.join(METHOD_CHOICES)}, got {args.method!r}"
        )
    adaptive = args.tol is not None or args.rtol is not None
    if adaptive and args.no_estimate:
        raise ParameterError("--tol/--rtol need the error bound: drop --no-estimate")
    method = args.method
    if method is None:
        method = "exact-amg" if args.no_estimate else "inexact"
    elif method == "inexact" and args.no_estimate:
        raise ParameterError(
            "--no-estimate cannot be combined with --method inexact: its stopping test needs "
            "the estimator (use --method exact-amg or exact)"
        )
    if args.refine < 0:
        raise ParameterError(f"--refine must be >= 0, got {args.refine}")
    if args.problem not in PROBLEM_CHOICES:
        hint = closest_name(args.problem, PROBLEM_CHOICES)
        raise ParameterError(
            f"--problem must be one of {', '.join(PROBLEM_CHOICES)}, got {args.problem!r}"
            + (f"; did you mean {hint!r}?" if hint else "")
        )
    if args.problem != "membranes" and args.path != "auto":
        raise ParameterError(
            f"--path {args.path} is an option of the two-membrane problem; "
            f"--problem {args.problem} has one formulation (drop --path)"
        )
    _check_problem_options(args)
    outputs = _outputs(args)  # before any work: a bad path must not cost a solve
    if args.memory_limit is not None:  # also for the mesh constructors' own check
        memory_limit(args.memory_limit)  # a bad value is refused here, naming it
        os.environ[MEMORY_LIMIT_ENV] = str(args.memory_limit)
    if args.mesh is None:  # a structured mesh that cannot fit is refused before it is built
        n = DEFAULT_N if args.n is None else args.n
        if n >= 1:
            size = 4 ** min(args.refine, 30)
            if args.domain == "lshape":
                nv, nt = 3 * n * n // 4 + 2 * n + 1, 3 * n * n // 2
            else:
                nv, nt = (n + 1) ** 2, 2 * n * n
            check_memory(nv * size, nt * size, method, not args.no_estimate, args.memory_limit)
    if args.threads is not None or args.blas_threads is not None:
        set_threads(numba=args.threads, blas=args.blas_threads)
    if args.problem in REFERENCE_OBSTACLES:
        source = f"{args.problem} n={DEFAULT_N if args.n is None else args.n}"
    elif args.mesh is not None:
        source = str(args.mesh)
    else:
        source = f"{args.domain} n={DEFAULT_N if args.n is None else args.n}"
    if args.refine:
        source += f", refined {args.refine} time{'s' if args.refine > 1 else ''}"
    _out(f"fastmem run: {source}")
    adapt = _adapt_keywords(args)
    scene, t_mesh, t_kernels = _scene_and_kernels(args, method, adaptive)
    mesh = scene.mesh
    _out(f"  mesh              {mesh.n_vertices} vertices, {mesh.n_triangles} triangles")
    if isinstance(scene, Obstacle):
        _out(f"  problem           {_describe_obstacle(args, scene)}, method = {method}")
    else:
        _out(
            f"  mu = ({args.mu1:g}, {args.mu2:g}), f = ({args.f1:g}, {args.f2:g}), "
            f"g = {scene.g:g}, method = {method}"
        )
    for path, existed in outputs:
        if existed:
            _out(f"  {path} exists and will be replaced when the run ends")
    if adaptive:
        goal = " or ".join(
            f"{name} {getattr(args, name):g}" for name in ("tol", "rtol") if getattr(args, name)
        )
        _out(f"  solving to {goal} by adaptive refinement")
        if not isinstance(scene, Obstacle):
            adapt["level_monitor"] = _LevelMonitor(not args.quiet)
    if isinstance(scene, Obstacle):
        return _run_obstacle(args, scene, method, adapt, adaptive, outputs, t_mesh, t_kernels)
    result = solve(
        scene,
        method=method,
        path=args.path,
        max_newton=args.max_newton,
        monitor=None if adaptive else _Monitor(not args.quiet),
        **adapt,
        estimate=not args.no_estimate,
        memory_limit=args.memory_limit,
        gamma_alg=args.gamma_alg,
        gamma_lin=args.gamma_lin,
        nested=False if args.no_nested else "auto",
    )
    result.timings["mesh"] = t_mesh
    result.timings["kernels"] = t_kernels
    if isinstance(adapt.get("level_monitor"), _LevelMonitor):
        adapt["level_monitor"].legend()
    reason = result.parameters["solver"].get("stop_reason", "step limit reached")
    if adaptive:
        reason = result.parameters["adaptivity"]["stop_reason"]
    status = "converged" if result.converged else f"NOT CONVERGED ({reason or 'criteria not met'})"
    _out()
    _out(f"  status            {status}")
    if adaptive:
        table = result.adaptivity
        _out(
            f"  adaptive meshes   {len(table['level'])}: {table['n_vertices'][0]} -> "
            f"{result.mesh.n_vertices} vertices, eta {table['eta'][0]:.3e} -> "
            f"{table['eta'][-1]:.3e}"
        )
    _out(f"  linear path       {result.path}")
    levels = result.parameters["solver"]["levels"]
    steps = ", ".join(str(lv["newton"]) for lv in levels)
    per_level = f" (per level: {steps})" if len(levels) > 1 else ""
    _out(f"  Newton steps on the finest mesh: {result.n_newton}{per_level}")
    if result.method != "exact":
        _out(f"  CG iterations     {sum(lv['inner'] for lv in levels)} (all levels)")
    _out(
        f"  contact fraction  {result.contact_fraction:.4f}  "
        f"({int(result.active.sum())} contact vertices)"
    )
    r_norm = float(np.sqrt(result.r1 @ result.r1 + result.r2 @ result.r2))
    _out(f"  final |R|         {r_norm:.3e}")
    if result.estimate is not None:
        parts = result.estimate.components
        _out(f"  error bound eta   {result.eta:.4e}   (guaranteed: |||u - u_h||| <= eta)")
        _out("  components        eta <= eta_disc + eta_lin + eta_alg; each bounds a part of")
        _out("                    the error, so eta may be smaller than eta_disc alone")
        for key, label in (
            ("eta_disc", "discretisation"),
            ("eta_lin", "linearisation"),
            ("eta_alg", "algebraic"),
        ):
            _out(f"    {key:<15} {parts[key]:.4e}   ({label})")
        if "estimate" in result.timings:
            _out(f"  estimate seconds  {result.timings['estimate']:.3f}")
    _out(
        f"  seconds           {result.timings['total']:.3f} solve, {t_kernels:.3f} kernels "
        f"(compile/load), {t_mesh:.3f} mesh"
    )
    _write_outputs(result, outputs)
    return 0 if result.converged else 1


class _ObstacleMonitor(_Table):
    """Live table of an obstacle solve: one line per Newton-min step."""

    header = (
        f"{'lev':>3} {'k':>3} {'vertices':>9} {'inner':>5} {'|A-|':>8} {'|A+|':>8} "
        f"{'changed':>7} {'eta_disc':>10} {'eta_lin':>10} {'eta_alg':>10} {'eta':>10}"
    )

    def __call__(self, row: dict) -> None:
        if not self.enabled:
            return
        num = _Monitor._number
        _out(
            f"{row['level']:>3d} {row['k']:>3d} {row['n_vertices']:>9d} {row['inner']:>5d} "
            f"{row['active_lower']:>8d} {row['active_upper']:>8d} {row['n_changed']:>7d} "
            f"{num(row['eta_disc'])} {num(row['eta_lin'])} {num(row['eta_alg'])} "
            f"{num(row['eta'])}"
        )


class _ObstacleLevels(_Table):
    """One line per mesh of an obstacle solve to a tolerance."""

    header = (
        f"{'mesh':>4} {'vertices':>9} {'eta':>10} {'target':>10} {'eta_disc':>10} "
        f"{'eta_lin':>10} {'eta_alg':>10} {'marked':>7} {'newton':>6} {'cg':>5} {'sec':>7}"
    )

    def __call__(self, row: dict) -> None:
        if not self.enabled:
            return
        _out(
            f"{row['level']:>4d} {row['n_vertices']:>9d} {row['eta']:>10.3e} "
            f"{row['target']:>10.3e} {row['eta_disc']:>10.3e} {row['eta_lin']:>10.3e} "
            f"{row['eta_alg']:>10.3e} {100 * row['marked_fraction']:>6.1f}% "
            f"{row['newton']:>6d} {row['inner']:>5d} "
            f"{row['solve_seconds'] + row['refine_seconds']:>7.2f}"
        )


def _run_obstacle(args, problem, method, adapt, adaptive, outputs, t_mesh, t_kernels) -> int:
    """Solve an obstacle problem for ``fastmem run`` and print the summary."""
    if adaptive:
        adapt["level_monitor"] = _ObstacleLevels(not args.quiet)
    result = solve(
        problem,
        method=method,
        max_newton=args.max_newton,
        monitor=None if adaptive else _ObstacleMonitor(not args.quiet),
        **adapt,
        estimate=not args.no_estimate,
        memory_limit=args.memory_limit,
        gamma_alg=args.gamma_alg,
        gamma_lin=args.gamma_lin,
        nested=False if args.no_nested else "auto",
    )
    result.timings["mesh"] = t_mesh
    result.timings["kernels"] = t_kernels
    reason = "criteria not met"
    if adaptive:
        reason = result.parameters["adaptivity"]["stop_reason"]
    status = "converged" if result.converged else f"NOT CONVERGED ({reason})"
    _out()
    _out(f"  status            {status}")
    if adaptive:
        table = result.adaptivity
        _out(
            f"  adaptive meshes   {len(table['level'])}: {table['n_vertices'][0]} -> "
            f"{result.mesh.n_vertices} vertices, eta {table['eta'][0]:.3e} -> "
            f"{table['eta'][-1]:.3e}"
        )
    _out(f"  Newton steps on the finest mesh: {result.n_newton}")
    lo, up = int(result.active_lower.sum()), int(result.active_upper.sum())
    _out(
        f"  contact           {lo} vertices on the lower obstacle, {up} on the upper one; "
        f"area {result.contact_area:.6g}"
    )
    if result.estimate is not None:
        parts = result.estimate.components
        label = "guaranteed" if result.estimate.totals.get("guaranteed", 1.0) else "ESTIMATED"
        _out(f"  error bound eta   {result.eta:.4e}   ({label}: |||u - u_h||| <= eta)")
        for key, name in (
            ("eta_disc", "discretisation"),
            ("eta_lin", "linearisation"),
            ("eta_alg", "algebraic"),
        ):
            _out(f"    {key:<15} {parts[key]:.4e}   ({name})")
        why = result.parameters.get("estimate", {}).get("reason")
        if why:
            _out(f"  note              {why}")
    error = None
    if args.problem in REFERENCE_OBSTACLES:
        error = exact_error(problem, result.u, result.mesh)
    if error is not None:
        _out(
            f"  exact error       {error:.4e}   (effectivity eta / error {result.eta / error:.3f})"
        )
    _out(
        f"  seconds           {result.timings['total']:.3f} solve, {t_kernels:.3f} kernels "
        f"(compile/load), {t_mesh:.3f} mesh"
    )
    _write_outputs(result, outputs)
    return 0 if result.converged else 1


def _cmd_info(args) -> int:

    if _is_twophase(args.file):
        return print_info(args.file, args.json)
    summary = info(args.file)
    if args.json:
        _out(json.dumps(summary, indent=2, default=str))
        return 0
    _out(
        f"{args.file}: fastmem result archive (format {summary['format_version']}, "
        f"written by fastmem {summary['fastmem_version']} on {summary['created']})"
    )
    _out(
        f"  mesh              {summary['n_vertices']} vertices, {summary['n_triangles']} triangles"
    )
    _out(f"  method / path     {summary['method']} / {summary['path']}")
    _out(f"  converged         {summary['converged']} after {summary['n_newton']} Newton steps")
    params = summary["parameters"]
    if params.get("problem") == "obstacle":
        kinds = {
            "p1": "P1",
            "guaranteed": "with envelope: guaranteed terms",
            "piecewise-constant": "piecewise constant",
            "estimated": "estimated terms",
        }
        _out("  problem           obstacle (docs/obstacle.md)")
        for side in ("lower", "upper"):
            value = params.get(side)
            if value is not None:
                desc = value.get("value", value.get("name", value["kind"]))
                _out(f"  {side:<17} {desc} ({kinds.get(params.get(side + '_kind'), '')})")
    for key in ("mu1", "mu2", "mu", "f1", "f2", "f", "g"):
        if key in params:
            value = params[key]
            if isinstance(value, dict) and value.get("kind") == "constant":
                value = value.get("value")
            elif isinstance(value, dict) and "kind" in value:
                value = value["kind"]
            _out(f"  {key:<17} {value}")
    if summary["has_estimate"]:
        totals = summary["estimator_totals"]
        if "eta" in totals:
            _out(f"  {'eta':<17} {totals['eta']:.4e}   (guaranteed bound of the energy error)")
        for k in ("eta_disc", "eta_lin", "eta_alg"):
            if k in totals:
                _out(f"    {k:<15} {totals[k]:.4e}")
    _out(
        f"  history           {summary['n_history_rows']} rows: "
        f"{', '.join(summary['history_columns'])}"
    )
    table = summary.get("adaptivity")
    if table:
        adapt = params.get("adaptivity", {})
        _out(
            f"  adaptivity        {len(table['level'])} meshes, {table['n_vertices'][0]} -> "
            f"{table['n_vertices'][-1]} vertices, eta {table['eta'][0]:.3e} -> "
            f"{table['eta'][-1]:.3e} ({adapt.get('stop_reason', '')})"
        )
    for k, v in summary["timings"].items():
        _out(f"  time {k:<12} {v:.3f} s")
    return 0


def _cmd_export(args) -> int:

    if _is_twophase(args.file):
        return export_twophase(args.file, args.out)
    out, existed = check_output(args.out, EXPORT_SUFFIXES)  # before reading the archive
    export(load(args.file), out)
    extra = [str(c) for c in companion_files(out)]
    note = f" (heavy data in {', '.join(extra)}; keep the files together)" if extra else ""
    _out(f"wrote {out}{note}" + (" (replaced the existing file)" if existed else ""))
    return 0


def _is_twophase(path) -> bool:
    """Tell whether ``path`` is a two-phase archive (its format attribute; never raises)."""
    try:
        with h5py.File(path, "r") as f:
            value = f.attrs.get("format", "")
    except (OSError, ValueError):
        return False
    return (value.decode() if isinstance(value, bytes) else str(value)) == "fastmem-twophase"


def main(argv=None) -> int:
    """Entry point of the ``fastmem`` console script; returns the exit status."""
    args = _build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="fastmem: %(levelname)s: %(message)s")
    try:
        return args.func(args)
    except FastmemError as exc:
        hint = " (command line: --memory-limit)" if isinstance(exc, MemoryLimitError) else ""
        sys.stderr.write(f"fastmem: error: {exc}{hint}\n")
        return 2
    finally:
        if argv is None:  # the program (console script, python -m fastmem) exits next
            _skip_exit_collections()


def _skip_exit_collections() -> None:
    """Move every object to the garbage collector's permanent generation (:func:`gc.freeze`).

    The interpreter's shutdown runs full collections over every object alive,
    and Numba's compiler leaves a great many: 0.35 s of the exit after a solve
    (of a first run of about 7 s), 0.03 s once they are frozen.  Only the
    process's exit follows, which reclaims the memory anyway; files are closed
    and flushed before (archives are written atomically, standard streams are
    flushed at exit regardless).
    """
    gc.freeze()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
