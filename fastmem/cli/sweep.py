"""Command line of parameter sweeps: ``fastmem sweep STUDY.toml``, ``--status``, and their plot.

``fastmem sweep study.toml`` runs the sweep a TOML file describes
(:func:`read_study`) with :func:`fastmem.sweeps.study.sweep` and shows a live table:
one line per finished run with the counts of finished, failed, running and
remaining runs, the elapsed time and an estimate of the time left (ETA).
Running the same command again completes only the missing runs; the grid is
checked run by run before any worker starts, and dask's own log lines stay
off the console (warnings are printed under their logger's name).  A study
folder (or another folder, or an archive) given instead of the study file
gets a pointer to the command that was probably meant.
``fastmem sweep --status study/`` summarises a study from its index (it
needs neither dask nor pandas, and works while a sweep is running).
``fastmem plot study/ --x mu2 --y contact_fraction`` draws a column of the
table against a parameter (:func:`plot_sweep`), one line per combination of
the other parameters that vary.

The study file::

    [sweep]                      # all optional
    factory = "scenes:make_scene"  # module:function; default fastmem.sweeps:standard_scene
    out = "study"                # the study folder, relative to this file (default: its stem)
    scheduler = "tcp://host:8786"  # an existing cluster (default: a LocalCluster)
    workers = 2                  # LocalCluster processes (default: the cores)
    numba_threads = 1            # per task (default: cores // workers)
    max_retries = 3              # worker deaths a run survives (LocalCluster)
    pythonpath = ["."]           # folders to import the factory from (default: this file's)

    [solve]                      # keywords of fastmem.solve for every run
    method = "inexact"
    tol = 1e-3

    [grid]                       # lists: their cartesian product; scalars: fixed
    n = 64
    mu2 = [0.5, 1.0, 2.0]
    g = [0.0, 0.1]

    # or, instead of [grid], one table per run:
    # [[runs]]
    # mu2 = 0.5

:func:`add_sweep_parser` adds the ``sweep`` subcommand to the ``fastmem``
parser; :func:`extend_plot_parser` adds ``--x``/``--y`` to the ``plot``
subcommand and sends it to :func:`plot_sweep_command` when its argument is a
study folder.
"""

from __future__ import annotations

import contextlib
import functools
import importlib
import json
import logging
import os
import sys
import time
from pathlib import Path

from ..errors import FastmemError, InputTypeError, ParameterError
from ..sweeps.study import INDEX_NAME, TABLE_COLUMNS, load_sweep, sweep, sweep_status
from .plot import _image_format, _new_figure, _require_matplotlib, column_label

try:
    import tomllib
except ImportError:  # pragma: no cover - Python 3.10
    try:
        import tomli as tomllib
    except ImportError:
        tomllib = None

__all__ = [
    "add_sweep_parser",
    "extend_plot_parser",
    "plot_sweep",
    "plot_sweep_command",
    "read_study",
    "run_sweep_command",
]

logger = logging.getLogger(__name__)

DEFAULT_FACTORY = "fastmem.sweeps:standard_scene"
_SWEEP_KEYS = (
    "factory",
    "out",
    "scheduler",
    "workers",
    "numba_threads",
    "max_retries",
    "pythonpath",
)
_FIGSIZE = (6.4, 4.6)
_TICK_LINE_SECONDS = 10.0  # a line while runs are on workers and none finished


def _out(text: str = "") -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def _error(text: str) -> int:
    sys.stderr.write(f"fastmem: error: {text}\n")
    return 2


# ----------------------------------------------------------------------------- study file


def _toml(path: Path) -> dict:
    if tomllib is None:  # pragma: no cover - Python 3.10
        raise ImportError(
            "reading a study file needs Python >= 3.11 (tomllib) or: pip install tomli"
        )
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except OSError as exc:
        raise ParameterError(f"cannot read study file {path}: {exc.strerror or exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ParameterError(f"study file {path} is not valid TOML: {exc}") from exc


def _import_factory(spec: str, folders: list):
    """Import ``module:function`` with ``folders`` in front of ``sys.path``."""
    if not isinstance(spec, str) or spec.count(":") != 1:
        raise ParameterError(f"[sweep] factory must be 'module:function', got {spec!r}")
    module_name, name = spec.split(":")
    for folder in reversed(folders):
        if folder not in sys.path:
            sys.path.insert(0, folder)  # spawned LocalCluster workers inherit sys.path
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ParameterError(
            f"[sweep] factory {spec!r}: cannot import module {module_name!r} ({exc}); "
            f"searched also {', '.join(folders)}"
        ) from exc
    factory = getattr(module, name, None)
    if factory is None:
        raise ParameterError(f"[sweep] factory {spec!r}: module {module_name!r} has no {name!r}")
    return factory


def read_study(path) -> dict:
    """Read and check a study file (TOML, read with the standard library's tomllib).

    Parameters
    ----------
    path : str or os.PathLike
        The study file; its format is in the module docstring.

    Returns
    -------
    dict
        The keywords of :func:`fastmem.sweeps.study.sweep`: ``make_scene`` (the
        imported factory), ``grid``, ``out`` (a Path), ``solve_options``,
        ``client`` (the scheduler address or None), ``workers``,
        ``numba_threads``, ``max_retries``.

    Raises
    ------
    ParameterError
        For an unreadable file, invalid TOML, unknown sections or keys, both or
        neither of ``[grid]`` and ``[[runs]]``, or a factory that cannot be imported.
    """
    path = Path(os.fspath(path))
    data = _toml(path)
    unknown = sorted(set(data) - {"sweep", "solve", "grid", "runs"})
    if unknown:
        raise ParameterError(
            f"study file {path}: unknown section(s) {', '.join(unknown)} "
            "(known: [sweep], [solve], [grid], [[runs]])"
        )
    head = data.get("sweep", {})
    unknown = sorted(set(head) - set(_SWEEP_KEYS))
    if unknown:
        raise ParameterError(
            f"study file {path}: unknown key(s) {', '.join(unknown)} in [sweep] "
            f"(known: {', '.join(_SWEEP_KEYS)})"
        )
    if ("grid" in data) == ("runs" in data):
        raise ParameterError(f"study file {path} needs either a [grid] table or [[runs]] tables")
    base = path.resolve().parent
    folders = head.get("pythonpath", ["."])
    if not isinstance(folders, list) or not all(isinstance(f, str) for f in folders):
        raise InputTypeError(f"[sweep] pythonpath must be a list of folders, got {folders!r}")
    factory = _import_factory(
        head.get("factory", DEFAULT_FACTORY), [str(base / f) for f in folders]
    )
    out = head.get("out", path.stem)
    if not isinstance(out, str):
        raise InputTypeError(f"[sweep] out must be a folder name, got {out!r}")
    return {
        "make_scene": factory,
        "grid": data.get("grid", data.get("runs")),
        "out": base / out,
        "solve_options": data.get("solve", {}),
        "client": head.get("scheduler"),
        "workers": head.get("workers"),
        "numba_threads": head.get("numba_threads"),
        "max_retries": head.get("max_retries", 3),
    }


def _study_files_of(folder: Path) -> list:
    """Return the study files (beside or in ``folder``) whose ``out`` is ``folder``."""
    found = []
    target = folder.resolve()
    candidates = [*sorted(folder.parent.glob("*.toml")), *sorted(folder.glob("*.toml"))]
    for path in candidates[:50]:
        try:
            with open(path, "rb") as fh:
                head = tomllib.load(fh).get("sweep", {})
            out = head.get("out", path.stem)
            if (path.resolve().parent / out).resolve() == target:
                found.append(path)
        except (OSError, ValueError, TypeError, AttributeError):  # not a study file
            continue
    return found


def _not_a_study_file(target: Path):
    """Return the pointer to the right command for a target that is not a study file, or None.

    A study folder (or its index) gets the commands that read a finished study
    and the command that completes it; an archive, the commands for archives;
    another folder, the study files in it.
    """
    folder = target
    if target.is_file():
        if target.suffix.lower() not in (".h5", ".hdf5"):
            return None
        if target.name != INDEX_NAME:
            return (
                f"{target} is an HDF5 file, not a study file (TOML): for a result archive use "
                f"`fastmem info {target}` or `fastmem plot {target}`"
            )
        folder = target.parent
    elif not target.is_dir():
        return None
    if (folder / INDEX_NAME).is_file():
        files = _study_files_of(folder) if tomllib is not None else []
        again = (
            f"`fastmem sweep {files[0]}`"
            if len(files) == 1
            else "`fastmem sweep STUDY.toml` with the study file that made it"
        )
        what = "a sweep study" if folder is target else f"the index of the sweep study {folder}"
        return (
            f"{target} is {what}, not a study file: `fastmem sweep --status {folder}` "
            f"summarises it, `fastmem plot {folder} --x PARAMETER --y COLUMN` plots its table "
            f"(fastmem.load_sweep reads it), `fastmem info {folder / 'runs'}/<run>.h5` shows "
            f"one run; {again} completes its missing runs"
        )
    files = sorted(folder.glob("*.toml"))
    if files:
        return (
            f"{target} is a folder, not a study file: give one of its study files, e.g. "
            f"`fastmem sweep {files[0]}`"
        )
    return (
        f"{target} is a folder, not a study file: fastmem sweep runs the sweep a TOML file "
        "describes ([sweep], [solve] and [grid] tables; docs/sweeps.md, Command line)"
    )


# ----------------------------------------------------------------------------- live table


def _clock(seconds) -> str:
    if seconds is None:
        return "?"
    seconds = float(seconds)
    if seconds < 60:
        return f"{seconds:.1f}s"
    if seconds < 3600:
        return f"{int(seconds // 60)}m{int(seconds % 60):02d}s"
    return f"{int(seconds // 3600)}h{int(seconds % 3600 // 60):02d}m"


class _Progress:
    """Live table of a sweep: one line per finished run (and one now and then while waiting)."""

    header = (
        f"{'finished':>8} {'failed':>6} {'running':>7} {'remaining':>9} "
        f"{'elapsed':>8} {'ETA':>8}  run"
    )

    def __init__(self, enabled: bool, out):
        self.enabled = enabled
        self.out = out
        self.last = time.monotonic()

    def _counts(self, state) -> str:
        return (
            f"{state['done']:>8d} {state['failed']:>6d} {state['running']:>7d} "
            f"{state['remaining']:>9d} {_clock(state['elapsed']):>8} {_clock(state['eta']):>8}"
        )

    def __call__(self, state: dict) -> None:
        if not self.enabled:
            return
        event = state["event"]
        if event == "start":
            _out(
                f"fastmem sweep: {state['total']} runs ({state['skipped']} already done) "
                f"in {self.out}"
            )
            if state["skipped"] < state["total"]:
                _out(self.header)
                _out("-" * (len(self.header) + 30))
        elif event == "run":
            row = state["row"]
            what = f"eta {row['eta']:.3e}" if row["status"] == "done" else row["error"]
            _out(f"{self._counts(state)}  {row['run']}  {row['status']}: {what}")
        elif event == "tick" and time.monotonic() - self.last >= _TICK_LINE_SECONDS:
            _out(f"{self._counts(state)}  ...")
        else:
            return
        self.last = time.monotonic()


# ----------------------------------------------------------------------------- commands


def add_sweep_parser(subparsers):
    """Add the ``sweep`` subcommand to the subparsers of the ``fastmem`` command line.

    ``fastmem sweep STUDY.toml [--workers N] [--scheduler ADDRESS] [-q]`` runs
    a sweep; ``fastmem sweep --status STUDY_DIR`` summarises one.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The object returned by :meth:`argparse.ArgumentParser.add_subparsers`.

    Returns
    -------
    argparse.ArgumentParser
        The ``sweep`` parser; its defaults set ``func`` to :func:`run_sweep_command`.
    """
    p = subparsers.add_parser(
        "sweep",
        help="solve a parameter study on dask.distributed (resumable; needs the dask extra)",
        description="Run the parameter sweep of a study file (TOML), or summarise a study "
        "folder with --status.  Running the same study again completes only missing runs.",
    )
    p.add_argument("target", type=Path, help="study file (.toml), or study folder with --status")
    p.add_argument("--status", action="store_true", help="summarise the study folder TARGET")
    p.add_argument("--out", type=Path, default=None, help="study folder (overrides [sweep] out)")
    p.add_argument("--workers", type=int, default=None, help="LocalCluster worker processes")
    p.add_argument(
        "--scheduler", default=None, help="address of an existing cluster (tcp://host:8786)"
    )
    p.add_argument("--numba-threads", type=int, default=None, help="Numba threads per run")
    p.add_argument("-q", "--quiet", action="store_true", help="no live table")
    p.set_defaults(func=run_sweep_command)
    return p


def run_sweep_command(args) -> int:
    """Run ``fastmem sweep``: a study file, or ``--status`` of a study folder.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed arguments of the ``sweep`` subcommand.

    Returns
    -------
    int
        0 when every run is done, 1 when some failed, 2 for an error (one line
        on stderr: bad study file, missing dask extra, ...), 130 when interrupted.
    """
    try:
        if args.status:
            return _status(args.target)
        return _run(args)
    except (FastmemError, ImportError) as exc:
        return _error(str(exc))


@contextlib.contextmanager
def _named_dask_records():
    """Print distributed's log records as ``distributed.nanny: WARNING: ...`` for the block.

    The ``fastmem`` command's root handler writes ``fastmem: LEVEL: ...``, which
    would make dask's lines look like fastmem's own; they are written here under
    the name of their logger instead (the sweep lets WARNING and above through,
    :mod:`fastmem.sweeps.engine`).  distributed's own handler, where it installed
    one (no root handler when it was imported), is left alone.
    """
    try:
        import distributed  # noqa: F401 - its import decides where its records go
    except ImportError:  # the sweep reports the missing extra
        yield
        return
    log = logging.getLogger("distributed")
    if not log.propagate:
        yield
        return
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(name)s: %(levelname)s: %(message)s"))
    log.addHandler(handler)
    log.propagate = False
    try:
        yield
    finally:
        log.removeHandler(handler)
        log.propagate = True


def _run(args) -> int:
    hint = _not_a_study_file(args.target)
    if hint is not None:
        raise ParameterError(hint)
    study = read_study(args.target)
    overrides = {
        "out": args.out,
        "workers": args.workers,
        "client": args.scheduler,
        "numba_threads": args.numba_threads,
    }
    study.update({k: v for k, v in overrides.items() if v is not None})
    progress = _Progress(not args.quiet, study["out"])
    try:
        with _named_dask_records():
            table = sweep(**study, progress=progress)
    except KeyboardInterrupt:
        _out(
            f"\ninterrupted: finished runs are kept in {study['out']}; run the same command "
            "again to complete the others"
        )
        return 130
    done = int((table.status == "done").sum())
    failed = table[table.status == "failed"]
    _out()
    _out(
        f"sweep {study['out']}: {len(table)} runs: {done} done, {len(failed)} failed; "
        f"table: {Path(study['out']) / INDEX_NAME} (fastmem.load_sweep)"
    )
    for row in failed.itertuples():
        _out(f"  failed {row.run}: {row.error}")
    return 1 if len(failed) else 0


def _status(folder) -> int:
    folder = Path(folder)
    if folder.is_file() and folder.suffix.lower() == ".toml":
        out = folder.stem
        with contextlib.suppress(FastmemError, ImportError, AttributeError):
            out = _toml(folder).get("sweep", {}).get("out", out)
        raise ParameterError(
            f"--status reads a study folder, not its study file {folder}: "
            f"`fastmem sweep --status {folder.parent / str(out)}`"
        )
    if folder.is_file() and folder.name == INDEX_NAME:
        folder = folder.parent  # the index names its study
    s = sweep_status(folder)
    _out(f"{folder}: fastmem sweep study (index updated {s['updated']})")
    _out(f"  factory           {s['spec'].get('factory')}")
    _out(f"  solve options     {json.dumps(s['spec'].get('solve_options', {}))}")
    _out(
        f"  runs              {s['total']} runs: {s['done']} done, {s['failed']} failed, "
        f"{s['pending']} pending"
    )
    if s["active"]:
        _out(f"  active            a sweep is running ({s['active']}), {s['running']} runs running")
    else:
        _out("  active            no sweep is running")
    for run, error, _ in s["failures"]:
        _out(f"  failed {run}: {error}")
    return 0


# ----------------------------------------------------------------------------- plot


def _parameters(table) -> list:
    """Return the parameter columns of a sweep table (between ``run`` and ``status``)."""
    columns = list(table.columns)
    return columns[1 : columns.index("status")]


def _check_column(table, name, what, study, numeric):
    import pandas as pd

    if name in table.columns and (not numeric or pd.api.types.is_numeric_dtype(table[name])):
        return
    usable = [
        c
        for c in table.columns
        if c not in ("run", "status", "archive", "error")
        and (not numeric or pd.api.types.is_numeric_dtype(table[c]))
    ]
    raise ParameterError(
        f"{what} {name!r} is not a{' numeric' if numeric else ''} column of the sweep table "
        f"of {study}; use one of {', '.join(usable)}"
    )


def _log_if_wide(axis_set, values) -> None:
    values = [float(v) for v in values if v == v]
    if values and min(values) > 0 and max(values) / min(values) >= 100:
        axis_set("log")


def _short(name: str) -> str:
    """Return the words of a column's label, without the symbol or the parenthesis."""
    label = column_label(name)
    return label.split(" (", 1)[0].split(" $", 1)[0]


def _symbol(name: str) -> str:
    r"""Return a parameter as a legend writes it: ``mu2`` as $\mu_2$, others as they are."""
    symbols = {"mu1": r"$\mu_1$", "mu2": r"$\mu_2$", "f1": "$f_1$", "f2": "$f_2$"}
    return symbols.get(name, name)


def plot_sweep(study, x, y, out=None, *, ax=None):
    """Draw a column of a sweep table against a parameter.

    One line per combination of the other parameters that vary among the
    finished runs (labelled in the legend), points sorted by ``x``; an axis
    is logarithmic when its values are positive and span two decades or more.
    Failed and pending runs are left out (their number is in the title).

    Parameters
    ----------
    study : str or os.PathLike
        The study folder.
    x : str
        A parameter (or any column) of the table, e.g. ``"mu2"``.
    y : str
        A numeric column, e.g. ``"contact_fraction"``, ``"eta"``, ``"newton_steps"``.
    out : str or os.PathLike, optional
        Image file to write (format from the suffix, PNG without one).
    ax : matplotlib.axes.Axes, optional
        Axes to draw into; default a new standalone figure.

    Returns
    -------
    matplotlib.figure.Figure

    Raises
    ------
    ParameterError
        If ``x`` or ``y`` is not a (numeric) column, naming the usable ones.
    ArchiveError
        If ``study`` is not a sweep study.
    ImportError
        Without matplotlib or pandas.
    """
    _require_matplotlib()
    table = load_sweep(study)
    _check_column(table, x, "--x", study, numeric=False)
    _check_column(table, y, "--y", study, numeric=True)
    done = table[table.status == "done"]
    others = [p for p in _parameters(table) if p != x and done[p].nunique(dropna=False) > 1]
    if ax is None:
        ax = _new_figure(_FIGSIZE).add_subplot(1, 1, 1)
    groups = done.groupby(others, dropna=False, sort=True) if others else [((), done)]
    for key, group in groups:
        group = group.sort_values(x)
        key = key if isinstance(key, tuple) else (key,)
        label = ", ".join(f"{_symbol(k)} = {v}" for k, v in zip(others, key, strict=True)) or None
        ax.plot(group[x].to_numpy(), group[y].to_numpy(dtype=float), "o-", label=label)
    if not done.empty and x not in TABLE_COLUMNS[1:] and done[x].dtype.kind in "iuf":
        _log_if_wide(ax.set_xscale, done[x])
    _log_if_wide(ax.set_yscale, done[y])
    ax.set_xlabel(column_label(x))
    ax.set_ylabel(column_label(y))
    left_out = len(table) - len(done)
    note = f" ({left_out} runs not finished or failed: not shown)" if left_out else ""
    name = Path(os.fspath(study)).name
    title = f"{_short(y)} against {_symbol(x)} (study {name}/, {len(done)} runs){note}"
    ax.set_title(title, fontsize="medium")
    if others:
        ax.legend(fontsize="small")
    ax.grid(True, alpha=0.3)
    fig = ax.figure
    if out is not None:
        target = Path(os.fspath(out))
        fig.savefig(target, format=_image_format(target, fig), dpi=150)
        logger.info("wrote plot %s", target)
    return fig


def plot_sweep_command(args) -> int:
    """Run ``fastmem plot STUDY_DIR --x PARAM --y COLUMN [-o OUT] [--show]``.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed arguments of the ``plot`` subcommand with the options of
        :func:`extend_plot_parser`: ``file`` (the study folder), ``x``, ``y``,
        ``output`` (default ``STUDY_DIR/<y>-vs-<x>.png``) and ``show``.

    Returns
    -------
    int
        0 on success, 2 (one line on stderr) for a missing option, column,
        study, matplotlib or pandas.
    """
    x, y = getattr(args, "x", None), getattr(args, "y", None)
    if not x or not y:
        return _error("the plot of a sweep study needs --x PARAMETER and --y COLUMN")
    output = args.output if args.output is not None else Path(args.file) / f"{y}-vs-{x}.png"
    show = bool(getattr(args, "show", False))
    try:
        ax = None
        if show:  # a pyplot figure, to open a window after saving

            _require_matplotlib()
            ax = _new_figure(_FIGSIZE, pyplot=True).add_subplot(1, 1, 1)
        plot_sweep(args.file, x, y, out=output, ax=ax)
    except (FastmemError, ImportError) as exc:
        return _error(str(exc))
    except OSError as exc:
        return _error(f"cannot write {output}: {exc.strerror or exc}")
    _out(f"wrote {output}")
    if show:
        import matplotlib.pyplot as plt

        plt.show()
    return 0


def _plot_dispatch(args, single) -> int:
    """``fastmem plot``: a study folder (or --x/--y) to :func:`plot_sweep_command`."""
    if Path(args.file).is_dir() or getattr(args, "x", None) or getattr(args, "y", None):
        return plot_sweep_command(args)
    return single(args)


def extend_plot_parser(parser):
    """Teach the ``fastmem plot`` parser to draw sweep studies.

    Adds ``--x PARAMETER`` and ``--y COLUMN`` and replaces the parser's
    ``func`` by a dispatcher: a folder argument (or ``--x``/``--y``) goes to
    :func:`plot_sweep_command`, anything else to the previous ``func``.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The ``plot`` parser (returned by :func:`fastmem.cli.plot.add_parser`).

    Returns
    -------
    argparse.ArgumentParser
        The same parser.
    """
    g = parser.add_argument_group("sweep studies (FILE is a study folder of fastmem sweep)")
    g.add_argument("--x", default=None, metavar="PARAMETER", help="parameter on the x axis")
    g.add_argument("--y", default=None, metavar="COLUMN", help="table column on the y axis")
    parser.set_defaults(func=functools.partial(_plot_dispatch, single=parser.get_default("func")))
    return parser
