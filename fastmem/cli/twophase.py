"""``fastmem twophase``: run the liquid–gas scenes, draw and export their archives.

``fastmem twophase run benchmark --strategy adaptive`` runs the Couplex-Gas /
MoMaS hydrogen column (docs/twophase.md) with one progress line per time step
and writes a time-series archive; ``variant`` stops the injection halfway and
runs twice as long (the gas phase appears, then vanishes); ``section`` is the
2D section.  ``fastmem twophase plot FILE`` draws an archive,
``fastmem twophase export FILE OUT.pvd`` writes it for ParaView, and
``fastmem info FILE`` summarises it.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from ..errors import ParameterError

__all__ = ["add_twophase_parser", "export_twophase", "print_info"]

SCENES = ("benchmark", "variant", "section")


def _out(text: str = "") -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def add_twophase_parser(sub) -> None:
    """Add ``fastmem twophase {run,plot,export}`` to the subcommands ``sub``."""
    tp = sub.add_parser("twophase", help="liquid-gas flow with gas appearance (docs/twophase.md)")
    tsub = tp.add_subparsers(dest="twophase_command", metavar="COMMAND")
    tsub.required = True
    r = tsub.add_parser("run", help="run a scene and write its time-series archive")
    r.set_defaults(func=_cmd_run)
    r.add_argument(
        "scene",
        help="benchmark (the column), variant (injection stops halfway), section (2D), "
        "or a scene file FILE.toml (docs/twophase.md §7)",
    )
    r.add_argument("--viscosity", choices=("momas", "paper"), default=None, help="(momas)")
    r.add_argument(
        "--strategy", choices=("exact", "inexact", "adaptive"), default=None, help="(adaptive)"
    )
    r.add_argument(
        "--linear-solver",
        choices=("ilu", "cpr", "direct"),
        default=None,
        help="inner solver (default: ilu in 1D, cpr for the section)",
    )
    r.add_argument("--cells", type=int, default=None, help="cells of the column (1000)")
    r.add_argument("--nx", type=int, default=None, help="section: rectangles along x (500)")
    r.add_argument("--ny", type=int, default=None, help="section: rectangles along y (50)")
    r.add_argument(
        "--steps", type=int, default=None, help="time steps (default 100; variant 200; section 20)"
    )
    r.add_argument("--dt-years", type=float, default=None, help="time step, years (5000)")
    r.add_argument("--gamma-alg", type=float, default=None, help="(1e-3)")
    r.add_argument("--gamma-lin", type=float, default=None, help="(1e-3)")
    r.add_argument(
        "--nu", type=int, default=None, help="GMRES iterations between estimator checks (1)"
    )
    r.add_argument(
        "--weights",
        choices=("volume", "mass"),
        default="volume",
        help="how the estimators weigh water and hydrogen (docs/twophase.md §4)",
    )
    r.add_argument(
        "--keep-every",
        type=int,
        default=None,
        help="keep every k-th profile in the archive (default 1; section 5)",
    )
    r.add_argument(
        "-o",
        "--output",
        type=Path,
        default=None,
        help="archive to write (default twophase-SCENE.h5)",
    )
    r.add_argument(
        "--complementarity",
        choices=("min", "fb"),
        default=None,
        help="Newton-min (min), or Newton on Fischer-Burmeister",
    )
    r.add_argument(
        "--max-front-cells",
        type=int,
        default=None,
        help="halve a step in which more cells change phase (and say so)",
    )
    r.add_argument("--quiet", action="store_true", help="no progress lines")
    p = tsub.add_parser("plot", help="draw a two-phase archive (needs matplotlib)")
    p.set_defaults(func=_cmd_plot)
    p.add_argument("file", type=Path)
    p.add_argument("-o", "--output", type=Path, default=None)
    p.add_argument("--times", type=float, nargs="*", default=None, help="years to draw")
    e = tsub.add_parser("export", help="write a two-phase archive as VTU (.vtu) or a series (.pvd)")
    e.set_defaults(func=_cmd_export)
    e.add_argument("file", type=Path)
    e.add_argument("out", type=Path)


def _positive(name, value):
    if value is not None and not (math.isfinite(value) and value > 0):
        raise ParameterError(f"--{name} must be positive, got {value!r}")


def _cmd_run(args) -> int:
    from ..twophase import YEAR, benchmark, section, simulate  # lazy: pyamg, 30-40 ms
    from ..twophase.archive import save_run  # lazy: fastmem.twophase loads pyamg, 30-40 ms
    from ..twophase.scene import load_scene  # lazy: fastmem.twophase loads pyamg, 30-40 ms

    _positive("dt-years", args.dt_years)
    for name in ("cells", "nx", "ny", "steps", "nu", "keep-every", "max-front-cells"):
        value = getattr(args, name.replace("-", "_"))
        if value is not None and value < 1:
            raise ParameterError(f"--{name} must be a positive integer, got {value!r}")
    from_file = args.scene.endswith(".toml")
    if not from_file and args.scene not in SCENES:
        raise ParameterError(
            f"scene must be one of {', '.join(SCENES)} or a scene file FILE.toml, got "
            f"{args.scene!r}"
        )
    stem = Path(args.scene).stem if from_file else args.scene
    out = args.output or Path(f"{stem}.h5" if from_file else f"twophase-{stem}.h5")
    if out.suffix not in (".h5", ".hdf5"):
        raise ParameterError(f"--output must end in .h5 or .hdf5, got {str(out)!r}")
    if not out.resolve().parent.is_dir():
        raise ParameterError(f"--output: the folder {str(out.resolve().parent)!r} does not exist")
    options = {"strategy": "adaptive", "gamma_alg": 1e-3, "gamma_lin": 1e-3, "nu": 1}
    scene_flags = ("viscosity", "cells", "nx", "ny", "complementarity")
    if from_file:
        given = [f"--{n}" for n in scene_flags if getattr(args, n) is not None]
        if given:
            raise ParameterError(
                f"{', '.join(given)} do not apply to a scene file: set them in {args.scene}"
            )
        problem, found = load_scene(args.scene)  # refuses bad units before any work
        dt = found.pop("dt")
        t_end = found.pop("t_end")
        options.update(found)
        if args.dt_years is not None:
            dt = args.dt_years * YEAR
        if args.steps:
            t_end = args.steps * dt
        steps = math.ceil(t_end / dt * (1 - 1e-12))
    else:
        steps = args.steps or {"benchmark": 100, "variant": 200, "section": 20}[args.scene]
        dt = (args.dt_years or 5000.0) * YEAR
        t_end = steps * dt
        viscosity = args.viscosity or "momas"
        complementarity = args.complementarity or "min"
        if args.scene == "section":
            problem = section(
                args.nx or 500, args.ny or 50, viscosity, complementarity=complementarity
            )
        else:
            stop = steps / 2 * dt / YEAR if args.scene == "variant" else None
            problem = benchmark(
                viscosity, args.cells or 1000, stop_injection=stop, complementarity=complementarity
            )
    for name in ("strategy", "gamma_alg", "gamma_lin", "nu"):
        if getattr(args, name) is not None:
            options[name] = getattr(args, name)
    two_d = problem.grid.dim == 2
    solver = args.linear_solver or options.pop("linear_solver", None) or ("cpr" if two_d else "ilu")
    options.pop("linear_solver", None)
    every = args.keep_every or (5 if two_d else 1)
    if not args.quiet:
        _out(
            f"fastmem twophase: {stem}, {problem.grid.n} cells, {steps} steps of "
            f"{dt / YEAR:g} years, strategy {options['strategy']}, "
            + (f"GMRES-{solver}" if solver != "direct" else "SuperLU")
        )
        _out(
            f"{'step':>5} {'t (years)':>10} {'Newton':>6} {'linear':>6} {'gas cells':>9} "
            f"{'front (m)':>9} {'eta_disc':>9} {'eta_lin':>9} {'eta_alg':>9}"
        )

    def progress(row):
        if args.quiet:
            return
        front = "-" if math.isnan(row["front"]) else f"{row['front']:.1f}"
        etas = " ".join(f"{row.get(k, math.nan):9.2e}" for k in ("eta_disc", "eta_lin", "eta_alg"))
        _out(
            f"{row['step']:5d} {row['t_years']:10.4g} {row['newton']:6d} {row['linear']:6d} "
            f"{row['gas_cells']:9d} {front:>9} {etas}"
        )

    run = simulate(
        problem,
        dt=dt,
        t_end=t_end,
        linear_solver=solver,
        weights=args.weights,
        **options,
        keep=every,
        max_front_cells=args.max_front_cells,
        progress=progress,
    )
    save_run(run, out)
    if not args.quiet:
        tot = run.totals()
        _out(
            f"done in {run.seconds:.2f} s: {tot['newton']} Newton-min steps, {tot['linear']} "
            f"linear iterations, gas first in step {run.first_gas_step}, hydrogen balance "
            f"{abs(run.balance).max():.1e} kg"
            + (
                f" ({abs(run.balance_equilibrated).max():.1e} kg with the equilibrated flux)"
                if run.balance_equilibrated.size
                else ""
            )
            + f"; wrote {out}"
        )
    return 0


def _cmd_plot(args) -> int:
    from ..twophase.plot import plot_run  # lazy: fastmem.twophase loads pyamg, 30-40 ms

    try:
        import matplotlib  # noqa: F401  (lazy: the plot extra)
    except ImportError:
        sys.stderr.write("fastmem: error: plots need matplotlib: pip install 'fastmem[plot]'\n")
        return 2
    _out(f"wrote {plot_run(args.file, args.output, args.times)}")
    return 0


def _cmd_export(args) -> int:
    return export_twophase(args.file, args.out)


def export_twophase(path, out) -> int:
    """``fastmem export`` / ``fastmem twophase export`` of a two-phase archive."""
    from ..twophase.archive import export_run  # lazy: fastmem.twophase loads pyamg, 30-40 ms

    _out(f"wrote {export_run(path, out)}")
    return 0


def print_info(path, as_json: bool) -> int:
    """``fastmem info`` for a two-phase archive."""
    from ..twophase.archive import info_run  # lazy: fastmem.twophase loads pyamg, 30-40 ms

    s = info_run(path)
    if as_json:
        _out(json.dumps(s, indent=2, default=str))
        return 0
    scene = s["scene"]
    _out(
        f"{path}: fastmem two-phase archive (format {s['format_version']}, written by fastmem "
        f"{s['fastmem_version']} on {s['created']})"
    )
    _out(
        f"  scene             {scene.get('name', '?')}, {scene.get('viscosity', '?')} viscosities, "
        f"{s['cells']} cells ({s['dim']}D)"
    )
    _out(f"  strategy          {s['strategy']}, {s['linear_solver']}")
    _out(f"  steps             {s['steps']} to {s['t_end_years']:.6g} years")
    _out(f"  iterations        {s['newton']} Newton-min steps, {s['linear']} linear iterations")
    appears = "never" if s["gas_appears_years"] is None else f"{s['gas_appears_years']:.6g} years"
    vanishes = "-" if s["gas_vanishes_years"] is None else f"{s['gas_vanishes_years']:.6g} years"
    _out(
        f"  gas               appears {appears}, vanishes {vanishes}, "
        f"at most {s['max_gas_cells']} cells"
    )
    eq = s["balance_equilibrated_max_kg"]
    eq_text = "" if eq is None else f"; {eq:.2e} kg with the equilibrated flux"
    _out(f"  hydrogen balance  {s['balance_max_kg']:.2e} kg (largest over the steps){eq_text}")
    _out(f"  profiles kept     {s['kept_profiles']}")
    _out(f"  run time          {s['seconds']:.2f} s")
    return 0
