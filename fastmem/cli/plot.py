"""Figures of a result: convergence history, membranes and contact set (``fastmem plot``).

Needs matplotlib (the ``plot`` extra: ``pip install 'fastmem[plot]'``); it is
imported only when a figure is drawn, so ``import fastmem.cli.plot`` and the
command-line glue work without it.

* :func:`plot_history` draws the convergence history.  Results of the
  adaptive methods (history columns ``inner_total`` and ``eta*``) show
  ``eta``, ``eta_disc``, ``eta_lin`` and ``eta_alg`` against the cumulative
  number of inner (linear-solver) iterations, with a dotted vertical line where
  each new Newton step begins (dashed where a new mesh level begins).  Results
  of the ``"exact"`` method (columns ``comp_norm`` and ``res_norm``) show both
  norms against the Newton step.
* :func:`plot_solution` draws ``u1``, ``u2`` and the gap ``u1 - u2`` with the
  contact set.
* :func:`plot_adaptivity` draws a solve to a tolerance (``result.adaptivity``):
  ``eta`` and its components against the number of vertices of each mesh
  (log-log, with the optimal slope ``N^(-1/2)`` and, when given, the curve of
  uniform refinement), and the final adapted mesh coloured by the refinement
  indicators ``eta_K``.
* :func:`plot_result` combines them in one figure and optionally saves it.
* :func:`add_parser` and :func:`run_plot` implement the ``fastmem plot``
  subcommand.

Figures are created as standalone :class:`matplotlib.figure.Figure` objects on
the non-interactive Agg canvas, without pyplot, so plotting never opens a
window or changes the global matplotlib backend; pyplot is used only when a
window is asked for (``show=True``, ``fastmem plot --show``).
"""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

import numpy as np

from ..adapt.loop import indicators
from ..errors import FastmemError, ParameterError
from ..io.archive import info, load

__all__ = [
    "MISSING_MATPLOTLIB",
    "add_parser",
    "plot_adaptivity",
    "plot_history",
    "plot_result",
    "plot_solution",
    "run_plot",
]

logger = logging.getLogger(__name__)

MISSING_MATPLOTLIB = "fastmem plot needs matplotlib: pip install 'fastmem[plot]'"
"""Message of the :class:`ImportError` raised when matplotlib is not installed."""

# (history column, legend label, marker) of the estimator curves of the adaptive methods
_ESTIMATOR_CURVES = (
    ("eta", r"$\eta$", "o"),
    ("eta_disc", r"$\eta_\mathrm{disc}$", "s"),
    ("eta_lin", r"$\eta_\mathrm{lin}$", "^"),
    ("eta_alg", r"$\eta_\mathrm{alg}$", "v"),
)
# (history column, legend label, marker) of the curves of the "exact" method
_NEWTON_CURVES = (
    ("comp_norm", r"$\|\min(u_1 - u_2, \lambda)\|$", "o"),
    ("res_norm", r"$\|R\|$", "s"),
)
_NEWTON_STEP_LABEL = "new Newton step"
_LEVEL_LABEL = "new mesh level"
_SOLUTION_SIZE = (3, 1)  # the three panels drawn by plot_solution


def _require_matplotlib():
    """Import matplotlib or raise ImportError with an installation hint."""
    try:
        import matplotlib
    except ImportError as exc:
        raise ImportError(MISSING_MATPLOTLIB) from exc
    return matplotlib


def _new_figure(figsize, *, pyplot: bool = False):
    """Create a constrained-layout figure: pyplot-managed if asked, else standalone on Agg."""
    if pyplot:
        import matplotlib.pyplot as plt

        return plt.figure(figsize=figsize, layout="constrained")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _axes_row(axes, count: int, figsize, what: str) -> list:
    """Return the given axes as a flat list of ``count``, or ``count`` new axes in a row."""
    if axes is None:
        fig = _new_figure(figsize)
        return [fig.add_subplot(1, count, i + 1) for i in range(count)]
    axes = list(np.ravel(np.asarray(axes, dtype=object)))
    if len(axes) != count:

        raise ParameterError(f"{what} needs {count} axes, got {len(axes)}")
    return axes


def _column(history: dict, name: str) -> np.ndarray:
    return np.asarray(history[name], dtype=np.float64).ravel()


def _plot_curves(ax, history: dict, x: np.ndarray, curves) -> int:
    """Plot the columns of ``curves`` present in ``history`` against ``x``, log-safe.

    Non-finite and non-positive points are left out per curve (they have no
    place on a log axis); curves without any remaining point are not drawn.
    Returns the number of curves drawn.
    """
    drawn = 0
    for name, label, marker in curves:
        if name not in history:
            continue
        y = _column(history, name)
        n = min(len(x), len(y))
        xs, ys = x[:n], y[:n]
        keep = np.isfinite(xs) & np.isfinite(ys) & (ys > 0)
        if not keep.any():
            logger.debug("history column %s has no positive finite value: not plotted", name)
            continue
        (line,) = ax.plot(xs[keep], ys[keep], marker=marker, markersize=4, label=label)
        line.set_gid(name)
        drawn += 1
    return drawn


def _newton_step_starts(history: dict, x: np.ndarray):
    """Cumulative inner-iteration counts at which a new Newton step begins.

    A new step begins where ``k`` (or the mesh ``level``, when the history has
    that column) changes between consecutive rows; its start is the
    ``inner_total`` of the last row of the previous step.  Returns the starts
    and, for each, whether it also starts a new mesh level.
    """
    if "k" not in history:
        return np.empty(0), np.empty(0, dtype=bool)
    keys = [_column(history, "k")]
    if "level" in history:
        keys.append(_column(history, "level"))
    n = min([len(x)] + [len(c) for c in keys])
    if n < 2:
        return np.empty(0), np.empty(0, dtype=bool)
    changed = [c[1:n] != c[: n - 1] for c in keys]
    rows = np.flatnonzero(np.logical_or.reduce(changed))  # row i + 1 starts a new step
    new_level = changed[1][rows] if len(changed) > 1 else np.zeros(rows.size, dtype=bool)
    starts = x[rows]
    finite = np.isfinite(starts)
    return starts[finite], new_level[finite]


def plot_history(result, ax=None):
    """Draw the convergence history of a result on a log scale.

    Parameters
    ----------
    result : fastmem.Result
        The result; only ``result.history`` (a dict of 1-D columns,
        :mod:`fastmem.solver.history`) is used, the same way for every method: the
        estimator columns ``eta``, ``eta_disc``, ``eta_lin`` and ``eta_alg``
        that are present are drawn against the cumulative number of inner
        iterations ``inner_total`` (against the row number when no CG ran,
        method ``"exact"``), with a dotted vertical line where ``k`` changes
        (a new Newton step begins, CG methods only) and a dashed one where the
        mesh ``level`` changes.  A history without any estimator value (an
        archive of an older version) shows ``comp_norm`` and ``res_norm``
        against the row number instead.
    ax : matplotlib.axes.Axes, optional
        Axes to draw on.  By default a new standalone figure with one axes is
        created.

    Returns
    -------
    matplotlib.axes.Axes
        The axes drawn on.  Each curve is a :class:`~matplotlib.lines.Line2D`
        whose ``gid`` is its history column name.

    Raises
    ------
    ImportError
        If matplotlib is not installed.

    Notes
    -----
    NaN, infinite, zero and negative values cannot be shown on a log axis: they
    are left out, per curve (estimators are NaN where they were not
    evaluated).  A curve without any positive finite value is not drawn; a
    history without any plottable column gives an axes saying so.
    """
    _require_matplotlib()
    from matplotlib.ticker import MaxNLocator

    if ax is None:
        ax = _new_figure((6.4, 4.8)).add_subplot()
    history = result.history or {}
    ax.set_yscale("log")
    n_rows = max((len(np.ravel(v)) for v in history.values()), default=0)
    by_inner = (
        "inner_total" in history and np.nanmax(_column(history, "inner_total"), initial=0) > 0
    )
    x = _column(history, "inner_total") if by_inner else np.arange(1.0, n_rows + 1.0)
    drawn = _plot_curves(ax, history, x, _ESTIMATOR_CURVES)
    if drawn:
        starts, new_level = _newton_step_starts(history, x)
        labelled = set()
        for start, level in zip(starts, new_level, strict=True):
            if not (level or by_inner):  # one row per Newton step: no line per step
                continue
            label = _LEVEL_LABEL if level else _NEWTON_STEP_LABEL
            ax.axvline(
                start,
                color="0.3" if level else "0.5",
                linestyle="--" if level else ":",
                linewidth=1.0,
                label="_nolegend_" if label in labelled else label,
            )
            labelled.add(label)
        ax.set_xlabel("cumulative inner iterations" if by_inner else "history row (Newton step)")
        ax.set_ylabel("error estimator")
        ax.set_title("a posteriori estimators")
    else:  # histories written before the estimators were recorded for every method
        drawn = _plot_curves(ax, history, x, _NEWTON_CURVES)
        ax.set_xlabel("Newton step $k$")
        ax.set_ylabel("norm")
        ax.set_title("Newton-min convergence")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    if drawn:
        ax.legend(fontsize="small")
        ax.grid(True, which="major", alpha=0.3)
    else:
        ax.text(
            0.5,
            0.5,
            "no plottable history",
            transform=ax.transAxes,
            ha="center",
            va="center",
            color="0.4",
        )
    return ax


def plot_solution(result, axes=None):
    """Draw the two membranes and the contact set of a result.

    Three panels: ``u1`` and ``u2`` (Gouraud-shaded, with colorbars) and the
    gap ``u1 - u2`` (with a colorbar) with the contact vertices
    (``result.active``) marked by dots.

    Parameters
    ----------
    result : fastmem.Result
        The result; ``mesh.vertices``, ``mesh.triangles``, ``u1``, ``u2`` and
        ``active`` are used.
    axes : sequence of 3 matplotlib.axes.Axes, optional
        Axes for ``u1``, ``u2`` and the gap.  By default a new standalone
        figure with three axes in a row is created.  The colorbars take space
        from these axes.

    Returns
    -------
    list of matplotlib.axes.Axes
        The three axes drawn on.  The contact markers are a
        :class:`~matplotlib.lines.Line2D` with ``gid`` ``"active"``.

    Raises
    ------
    ImportError
        If matplotlib is not installed.
    fastmem.errors.ParameterError
        If ``axes`` is not a sequence of three axes.
    """
    _require_matplotlib()
    from matplotlib.tri import Triangulation

    axes = _axes_row(axes, 3, (15.0, 4.6), "plot_solution (u1, u2, gap)")
    vertices = np.asarray(result.mesh.vertices, dtype=np.float64)
    tri = Triangulation(vertices[:, 0], vertices[:, 1], np.asarray(result.mesh.triangles))
    u1 = np.asarray(result.u1, dtype=np.float64)
    u2 = np.asarray(result.u2, dtype=np.float64)
    active = np.asarray(result.active, dtype=bool)
    n_active = int(active.sum())
    panels = (
        (u1, "$u_1$ (membrane 1)", "viridis"),
        (u2, "$u_2$ (membrane 2)", "viridis"),
        (u1 - u2, f"gap $u_1 - u_2$, contact set: {n_active} vertices", "magma"),
    )
    for ax, (values, title, cmap) in zip(axes, panels, strict=True):
        mappable = ax.tripcolor(tri, values, shading="gouraud", cmap=cmap)
        ax.figure.colorbar(mappable, ax=ax, shrink=0.9)
        ax.set_title(title)
        ax.set_aspect("equal")
        ax.set_xlabel("$x$")
        ax.set_ylabel("$y$")
    # Dots about a third of the mesh spacing on a square mesh, within readable limits.
    size = float(np.clip(150.0 / np.sqrt(max(len(vertices), 1)), 0.8, 5.0))
    (dots,) = axes[2].plot(
        vertices[active, 0],
        vertices[active, 1],
        linestyle="none",
        marker="o",
        markersize=size,
        markerfacecolor="cyan",
        markeredgecolor="black",
        markeredgewidth=0.3,
        label=f"contact set ({n_active} vertices)",
    )
    dots.set_gid("active")
    return axes


def _uniform_points(uniform):
    """(vertices, eta) arrays of the uniform-refinement curve, sorted, or None."""
    if uniform is None:
        return None
    n = np.asarray(uniform["n_vertices"], dtype=np.float64).ravel()
    eta = np.asarray(uniform["eta"], dtype=np.float64).ravel()
    if n.shape != eta.shape:

        raise ParameterError(
            f"uniform needs n_vertices and eta of equal length, got {n.size} and {eta.size}"
        )
    order = np.argsort(n)
    return n[order], eta[order]


def plot_adaptivity(result, axes=None, *, uniform=None):
    """Draw a solve to a tolerance: eta against N, and the adapted mesh with its indicators.

    Parameters
    ----------
    result : fastmem.Result
        A result of ``fm.solve(scene, tol=...)`` (or ``rtol=``), with
        ``result.adaptivity``.
    axes : sequence of 2 matplotlib.axes.Axes, optional
        Axes for the convergence curves and for the mesh; a new standalone
        figure by default.
    uniform : dict, optional
        ``{"n_vertices": [...], "eta": [...]}`` of uniformly refined meshes
        (for example from ``fm.solve`` on ``Mesh.lshape(n)`` for several n),
        drawn as a dashed curve.

    Returns
    -------
    list of matplotlib.axes.Axes
        The two axes.  The curves have ``gid`` ``eta``, ``eta_disc``,
        ``eta_lin``, ``eta_alg``, ``target``, ``uniform`` and ``slope``; the
        mesh collection ``mesh``.

    Raises
    ------
    fastmem.errors.ParameterError
        If the result has no adaptivity table, or ``axes`` is not two axes.
    """
    _require_matplotlib()
    from matplotlib.colors import LogNorm
    from matplotlib.tri import Triangulation


    table = result.adaptivity
    if table is None:
        raise ParameterError("plot_adaptivity needs a result of fm.solve(scene, tol=...)")
    axes = _axes_row(axes, 2, (12.0, 5.0), "plot_adaptivity")
    ax, mesh_ax = axes
    n = np.asarray(table["n_vertices"], dtype=np.float64)
    _plot_curves(ax, table, n, _ESTIMATOR_CURVES)
    (line,) = ax.plot(n, table["target"], "k:", label="target")
    line.set_gid("target")
    points = _uniform_points(uniform)
    if points is not None:
        (line,) = ax.plot(*points, "k--", marker="x", label=r"$\eta$, uniform refinement")
        line.set_gid("uniform")
    if n.size:
        ref = table["eta"][0] * (n / n[0]) ** -0.5
        (line,) = ax.plot(n, ref, color="0.6", linewidth=0.8, label=r"$N^{-1/2}$")
        line.set_gid("slope")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("vertices $N$")
    ax.set_ylabel("estimator")
    ax.set_title(f"adaptive refinement: {n.size} meshes")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize="small")
    v = np.asarray(result.mesh.vertices, dtype=np.float64)
    tri = Triangulation(v[:, 0], v[:, 1], np.asarray(result.mesh.triangles))
    if result.estimate is not None and "eta_F1" in result.estimate.maps:

        eta_k = np.sqrt(indicators(result.estimate))
        top = float(eta_k.max()) if eta_k.size else 0.0
        lo = top * 1e-6 if top > 0 else 1.0  # six decades: the contact set has ~0
        coll = mesh_ax.tripcolor(
            tri,
            facecolors=np.maximum(eta_k, lo),
            cmap="viridis",
            norm=LogNorm(vmin=lo, vmax=max(lo, top)),
            edgecolors="face",
        )
        mesh_ax.figure.colorbar(coll, ax=mesh_ax, shrink=0.9, label=r"$\eta_K$")
        title = "final mesh, indicators $\\eta_K$"
    else:
        coll = mesh_ax.triplot(tri, color="k", linewidth=0.2)[0]
        title = "final mesh"
    coll.set_gid("mesh")
    if result.mesh.n_triangles <= 20_000:  # edges stay readable
        mesh_ax.triplot(tri, color="w", linewidth=0.15, alpha=0.6)
    mesh_ax.set_aspect("equal")
    mesh_ax.set_title(f"{title} ({result.mesh.n_vertices} vertices)")
    return axes


def _suptitle(result) -> str:
    mesh = result.mesh
    status = "converged" if result.converged else "not converged"
    parts = [
        f"method {result.method or '?'}",
        f"{mesh.n_vertices} vertices, {mesh.n_triangles} triangles",
        f"{status} after {result.n_newton} Newton steps",
    ]
    if result.estimate is not None and "eta" in result.estimate.totals:
        parts.append(rf"$\eta$ = {result.eta:.3e}")
    return "fastmem: " + ", ".join(parts)


def _image_format(path: Path, fig) -> str:
    """Return the image format selected by the suffix of ``path`` (PNG without a suffix)."""
    fmt = path.suffix[1:].lower() or "png"
    supported = fig.canvas.get_supported_filetypes()
    if fmt not in supported:

        raise ParameterError(
            f"cannot save plot as {path}: image format {fmt!r} is not supported; "
            f"use one of {', '.join('.' + s for s in sorted(supported))}"
        )
    return fmt


def plot_result(result, path=None, *, show: bool = False, uniform=None):
    """Draw the history and the solution of a result in one figure; optionally save it.

    The figure has four panels: the convergence history (:func:`plot_history`)
    and ``u1``, ``u2`` and the gap with the contact set
    (:func:`plot_solution`), plus one colorbar per solution panel; a solve to
    a tolerance adds the two panels of :func:`plot_adaptivity` (``uniform``
    is passed on to it).

    Parameters
    ----------
    result : fastmem.Result
        The result to draw, e.g. from :func:`fastmem.solve` or
        :func:`fastmem.load`.
    path : str or os.PathLike, optional
        Image file to write.  Its suffix selects the format (``.png``,
        ``.pdf``, ``.svg``, ...); PNG without a suffix (the name is kept as
        given).  Not written when None.
    show : bool, default False
        Create the figure through pyplot and open it in a window
        (``plt.show()``, blocking) after saving.  Otherwise the figure is a
        standalone figure on the non-interactive Agg canvas, not registered
        with pyplot (Jupyter still displays it when it is the cell's value).

    Returns
    -------
    matplotlib.figure.Figure
        The figure.

    Raises
    ------
    ImportError
        If matplotlib is not installed.
    fastmem.errors.ParameterError
        If the suffix of ``path`` is not an image format matplotlib can write.
    OSError
        If ``path`` cannot be written (e.g. its folder does not exist).
    """
    _require_matplotlib()
    fig = _draw_result(result, path, pyplot=show, uniform=uniform)
    if show:
        import matplotlib.pyplot as plt

        plt.show()
    return fig


def _draw_result(result, path, *, pyplot: bool, uniform=None):
    """Draw the figure of :func:`plot_result` and save it; do not show it."""
    rows = 2 if result.adaptivity is None else 3
    fig = _new_figure((12.0, 4.75 * rows), pyplot=pyplot)
    try:
        target = None if path is None else Path(os.fspath(path))
        fmt = None if target is None else _image_format(target, fig)
        plot_history(result, ax=fig.add_subplot(rows, 2, 1))
        plot_solution(result, axes=[fig.add_subplot(rows, 2, i) for i in (2, 3, 4)])
        if rows == 3:
            plot_adaptivity(
                result, axes=[fig.add_subplot(3, 2, i) for i in (5, 6)], uniform=uniform
            )
        fig.suptitle(_suptitle(result))
        if target is not None:
            fig.savefig(target, format=fmt, dpi=150)
            logger.info("wrote plot %s", target)
    except BaseException:
        if pyplot:
            import matplotlib.pyplot as plt

            plt.close(fig)
        raise
    return fig


# ----------------------------------------------------------------------------- command line


def add_parser(subparsers):
    """Add the ``plot`` subcommand to the subparsers of the ``fastmem`` command line.

    ``fastmem plot FILE.h5 [-o OUT.png] [--show]`` draws a result archive with
    :func:`plot_result` and writes the image (by default ``FILE`` with the
    suffix ``.png``, next to the archive).

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The object returned by :meth:`argparse.ArgumentParser.add_subparsers`.

    Returns
    -------
    argparse.ArgumentParser
        The ``plot`` parser; its defaults set ``func`` to :func:`run_plot`
        (and ``command`` to ``"plot"`` when ``dest="command"``).
    """
    p = subparsers.add_parser(
        "plot",
        help="draw the convergence history and solution of a result archive (needs matplotlib)",
    )
    p.add_argument("file", type=Path, help="result archive (.h5)")
    p.add_argument(
        "-o",
        "--output",
        type=Path,
        default=None,
        help="image to write; its suffix selects the format (default: FILE with suffix .png)",
    )
    p.add_argument("--show", action="store_true", help="also open the figure in a window")
    p.add_argument(
        "--uniform",
        type=Path,
        nargs="+",
        default=None,
        metavar="ARCHIVE",
        help="archives of the same problem on uniform meshes: their eta against N is drawn "
        "beside the adaptive curve (a solve to a tolerance only)",
    )
    p.set_defaults(func=run_plot)
    return p


def _out(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def _error(text: str) -> int:
    sys.stderr.write(f"fastmem: error: {text}\n")
    return 2


def run_plot(args) -> int:
    """Run ``fastmem plot``: load the archive, draw it and write the image.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed arguments of the ``plot`` subcommand: ``file`` (Path),
        ``output`` (Path or None) and ``show`` (bool).

    Returns
    -------
    int
        0 on success; 2 (with a one-line message on stderr) when matplotlib is
        missing or the image cannot be written.

    Raises
    ------
    fastmem.errors.ArchiveError
        If the archive cannot be read (missing, not HDF5, corrupt, ...).
    fastmem.errors.ParameterError
        If the output suffix is not an image format.  Like every
        :class:`~fastmem.errors.FastmemError`, these are reported by
        ``fastmem.cli.main.main`` in one line with exit status 2.
    """
    try:
        _require_matplotlib()
    except ImportError as exc:
        return _error(str(exc))

    result = load(args.file)
    uniform = None
    if getattr(args, "uniform", None):
        points = [info(f) for f in args.uniform]
        missing = [
            str(f) for f, s in zip(args.uniform, points, strict=True) if not s["has_estimate"]
        ]
        if missing:
            return _error(f"--uniform archives without an error bound: {', '.join(missing)}")
        uniform = {
            "n_vertices": [s["n_vertices"] for s in points],
            "eta": [s["estimator_totals"]["eta"] for s in points],
        }
    output = args.output if args.output is not None else Path(args.file).with_suffix(".png")
    try:
        _draw_result(result, output, pyplot=args.show, uniform=uniform)
    except FastmemError:
        raise
    except OSError as exc:
        return _error(f"cannot write {output}: {exc.strerror or exc}")
    _out(f"wrote {output}")
    if args.show:
        import matplotlib.pyplot as plt

        plt.show()
    return 0
