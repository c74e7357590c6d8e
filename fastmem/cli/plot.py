"""Figures of a result: convergence history, membranes and contact set (``fastmem plot``).

Needs matplotlib (the ``plot`` extra: ``pip install 'fastmem[plot]'``); it is
imported only when a figure is drawn, so ``import fastmem.cli.plot`` and the
command-line glue work without it.

* :func:`plot_history` draws the convergence history: ``eta`` and its
  components against the cumulative number of CG iterations (against the
  Newton step for the ``"exact"`` method), every other mesh level shaded,
  the starts of Newton steps marked on the top edge, predicted (not
  computed) ``eta_disc`` values as hollow markers.
* :func:`plot_solution` draws ``u1``, ``u2`` and the gap ``u1 - u2`` with the
  contact set filled and outlined.
* :func:`plot_contact_pressure` draws the multiplier ``lam`` and
  :func:`plot_indicators` the error indicators ``eta_K`` per triangle.
* :func:`plot_adaptivity` draws a solve to a tolerance (``result.adaptivity``):
  ``eta`` and its components against the number of vertices of each mesh
  (log-log, with the optimal slope ``N^(-1/2)`` and, when given, the curve of
  uniform refinement), and the edges of the final adapted mesh.
* :func:`plot_result` combines them in one figure and optionally saves it.
* :func:`column_label` gives the words used as axis labels for result and
  sweep-table columns.
* :func:`add_parser` and :func:`run_plot` implement the ``fastmem plot``
  subcommand.

Figures are created as standalone :class:`matplotlib.figure.Figure` objects on
the non-interactive Agg canvas, without pyplot, so plotting never opens a
window or changes the global matplotlib backend; pyplot is used only when a
window is asked for (``show=True``, ``fastmem plot --show``).
"""

from __future__ import annotations

import errno
import logging
import os
import sys
import weakref
from pathlib import Path

import h5py
import numpy as np

from ..adapt.loop import indicators
from ..errors import FastmemError, ParameterError
from ..io.archive import info, load
from ..sweeps.grid import INDEX_FORMAT, INDEX_NAME

__all__ = [
    "COLUMN_LABELS",
    "MISSING_MATPLOTLIB",
    "add_parser",
    "column_label",
    "plot_adaptivity",
    "plot_contact_pressure",
    "plot_history",
    "plot_indicators",
    "plot_result",
    "plot_solution",
    "run_plot",
]

logger = logging.getLogger(__name__)

MISSING_MATPLOTLIB = "fastmem plot needs matplotlib: pip install 'fastmem[plot]'"
"""Message of the :class:`ImportError` raised when matplotlib is not installed."""

# (history column, legend label, marker) of the estimator curves of the adaptive methods
#: legend labels of the hollow markers of an adaptive table's ``cg_stop`` meshes
_LOOSE_LABEL = {
    "eta": r"$\eta$, intermediate mesh (can be loose)",
    "eta_alg": r"$\eta_\mathrm{alg}$, intermediate mesh (can be loose)",
}
_ESTIMATOR_CURVES = (
    ("eta", r"$\eta$ (bound)", "o"),
    ("eta_disc", r"$\eta_\mathrm{disc}$ (discretisation)", "s"),
    ("eta_lin", r"$\eta_\mathrm{lin}$ (linearisation)", "^"),
    ("eta_alg", r"$\eta_\mathrm{alg}$ (algebraic)", "v"),
)
# (history column, legend label, marker) of the curves of the "exact" method
_NEWTON_CURVES = (
    ("comp_norm", r"$\|\min(u_1 - u_2, \lambda)\|$", "o"),
    ("res_norm", r"$\|R\|$", "s"),
)
_PREDICTED_LABEL = r"$\eta_\mathrm{disc}$ predicted, not computed"
_NEWTON_STEP_LABEL = "a Newton step starts"
_LEVEL_LABEL = "mesh levels (alternate shading)"
_CONTACT_COLOUR = "#00d5ff"  # cyan: apart from viridis, magma and cividis
_SHOWN_DECADES = 3.0
"""Components more than this many decades below the smallest bound are not drawn.

The stopping tests compare the components with the bound; one a thousand times
smaller plays no part in them (typically ``eta_alg`` at round-off after a
direct solve on a coarse level), and drawing it would squeeze the useful range
into a fraction of the axes.  The legend counts the values left out.
"""

#: Words for the columns of results and sweep tables, used as axis labels.
COLUMN_LABELS = {
    "n": "cells per side $n$",
    "refine": "uniform refinements",
    "domain": "domain",
    "mu1": r"tension $\mu_1$ of membrane 1",
    "mu2": r"tension $\mu_2$ of membrane 2",
    "f1": "load $f_1$ on membrane 1",
    "f2": "load $f_2$ on membrane 2",
    "g": "boundary value $g$ of membrane 1",
    "tol": "tolerance on the error bound",
    "rtol": "relative tolerance on the error bound",
    "method": "method",
    "converged": "converged",
    "eta": r"error bound $\eta$",
    "eta_disc": r"discretisation estimator $\eta_\mathrm{disc}$",
    "eta_lin": r"linearisation estimator $\eta_\mathrm{lin}$",
    "eta_alg": r"algebraic estimator $\eta_\mathrm{alg}$",
    "contact_fraction": "contact fraction (share of vertices in contact)",
    "newton_steps": "Newton steps",
    "cg_iterations": "CG iterations (all levels)",
    "vertices": "vertices",
    "triangles": "triangles",
    "seconds": "solve time (s)",
}


def column_label(name: str) -> str:
    r"""Return the axis label of a result or sweep-table column: words, with the name as fallback.

    Parameters
    ----------
    name : str
        A column name, e.g. ``"mu2"`` or ``"contact_fraction"``.

    Returns
    -------
    str
        For example ``"tension $\mu_2$ of membrane 2"``; a column without a
        description (a parameter of a user's factory) gets its name with
        underscores as spaces.
    """
    return COLUMN_LABELS.get(name, name.replace("_", " "))


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


def _one_axes(ax, figsize):
    return _new_figure(figsize).add_subplot() if ax is None else ax


def _column(history: dict, name: str) -> np.ndarray:
    return np.asarray(history[name], dtype=np.float64).ravel()


def _positive(y: np.ndarray) -> np.ndarray:
    return np.isfinite(y) & (y > 0)


def _shown_floor(table: dict) -> float:
    """Smallest value drawn on an estimator axis: ``_SHOWN_DECADES`` below the smallest bound.

    The bound is ``eta`` (or ``eta_disc`` where no ``eta`` was evaluated);
    without either, nothing is left out (0).
    """
    for name in ("eta", "eta_disc"):
        if name in table:
            y = _column(table, name)
            y = y[_positive(y)]
            if y.size:
                return float(y.min()) * 10.0**-_SHOWN_DECADES
    return 0.0


def _plot_curves(ax, table: dict, x: np.ndarray, curves, *, floor: float = 0.0) -> list:
    """Plot the columns of ``curves`` present in ``table`` against ``x`` on a log axis.

    Points that are NaN, infinite, zero or negative have no place on a log
    axis and are left out per curve (estimators are NaN where they were not
    evaluated).  Points below ``floor`` are left out too; the legend says how
    many.  Where the table has ``fresh_disc``, the ``eta_disc`` values not
    computed from a flux of that row's iterate (predicted from the coarser
    level, or carried over) are drawn as hollow markers without a line, gid
    ``eta_disc_predicted``; likewise, where an adaptive table has ``cg_stop``,
    ``eta`` and ``eta_alg`` of its intermediate meshes (gids ``eta_loose`` and
    ``eta_alg_loose``: their CG could stop by its own error estimate, so these
    bounds can be loose).  Curves without a point left are not drawn.

    Returns the y values drawn (one array per curve drawn).
    """
    drawn = []
    fresh = None
    if "fresh_disc" in table:
        fresh = _column(table, "fresh_disc") > 0
    loose = None  # adaptive meshes whose CG could stop by its own estimate (cg_stop)
    if "cg_stop" in table and np.any(_column(table, "cg_stop") > 0):
        loose = _column(table, "cg_stop") > 0
    for name, label, marker in curves:
        if name not in table:
            continue
        y = _column(table, name)
        n = min(len(x), len(y))
        xs, ys = x[:n], y[:n]
        keep = np.isfinite(xs) & _positive(ys)
        below = keep & (ys < floor)
        keep &= ~below
        if below.any():
            label = f"{label}, {int(below.sum())} < {floor:.0e} left out"
        parts = [(name, keep, label, dict(marker=marker, markersize=4))]
        if name == "eta_disc" and fresh is not None and not fresh[:n].all():
            predicted = dict(
                marker=marker, markersize=4, linestyle="none", markerfacecolor="none", alpha=0.6
            )
            parts = [
                (name, keep & fresh[:n], label, dict(marker=marker, markersize=4)),
                ("eta_disc_predicted", keep & ~fresh[:n], _PREDICTED_LABEL, predicted),
            ]
        if name in ("eta", "eta_alg") and loose is not None:
            hollow = dict(
                marker=marker, markersize=4, linestyle="none", markerfacecolor="none", alpha=0.6
            )
            parts = [
                (name, keep & ~loose[:n], label, dict(marker=marker, markersize=4)),
                (f"{name}_loose", keep & loose[:n], _LOOSE_LABEL[name], hollow),
            ]
        colour = None
        for gid, mask, text, style in parts:
            if not mask.any():
                logger.debug("history column %s has no point to draw", gid)
                continue
            (line,) = ax.plot(xs[mask], ys[mask], label=text, color=colour, **style)
            colour = line.get_color()  # predicted points in the colour of their curve
            line.set_gid(gid)
            drawn.append(ys[mask])
    return drawn


def _fit_log_range(ax, drawn: list) -> None:
    """Set the y limits of a log axis to the values drawn, with a little margin."""
    if not drawn:
        return
    values = np.concatenate(drawn)
    lo, hi = float(values.min()), float(values.max())
    ax.set_ylim(lo / 2.0, hi * 2.0)


def _changes(history: dict, name: str, n: int) -> np.ndarray:
    """Rows ``i`` (``< n - 1``) after which column ``name`` changes."""
    c = _column(history, name)[:n]
    return np.flatnonzero(c[1:] != c[:-1])


def _mark_levels_and_steps(ax, history: dict, x: np.ndarray, *, by_inner: bool) -> None:
    """Shade every other mesh level and mark where Newton steps start.

    A level spans from the ``x`` of the last row of the previous level to
    the ``x`` of its own last row; odd levels get a grey band (gid
    ``"level"``).  With ``by_inner`` (one row per estimator evaluation), the
    starts of the Newton steps that do not start a level are marked by small
    triangles on the top edge (a :class:`~matplotlib.lines.Line2D` with gid
    ``"newton_steps"``).
    """
    n = len(x)
    if n < 2:
        return
    level_ends = _changes(history, "level", n) if "level" in history else np.empty(0, int)
    if level_ends.size:
        first = 0.5
        if by_inner:  # where the first row's step began
            first = x[0] - (_column(history, "inner")[0] if "inner" in history else 0.0)
        edges = np.concatenate(([first], x[level_ends], [x[n - 1]]))
        labelled = False
        for i in range(1, len(edges) - 1, 2):
            span = ax.axvspan(
                edges[i],
                edges[i + 1],
                color="0.90",
                zorder=0,
                linewidth=0,
                label="_nolegend_" if labelled else _LEVEL_LABEL,
            )
            span.set_gid("level")
            labelled = True
    if by_inner and "k" in history:
        step_ends = np.setdiff1d(_changes(history, "k", n), level_ends)
        starts = x[step_ends]
        starts = starts[np.isfinite(starts)]
        if starts.size:
            (ticks,) = ax.plot(
                starts,
                np.ones_like(starts),
                transform=ax.get_xaxis_transform(),
                linestyle="none",
                marker="v",
                markersize=5,
                color="0.35",
                clip_on=False,
                label=_NEWTON_STEP_LABEL,
            )
            ticks.set_gid("newton_steps")


_HISTORY_LEVELS = 8
"""The history panel shows at most this many mesh levels, the last ones (adaptive loops)."""


def _last_levels(history: dict):
    """Keep the rows of the last ``_HISTORY_LEVELS`` mesh levels; return them and a title suffix.

    A solve to a tolerance records every mesh of the loop (20 or more
    levels): drawn at once, the early levels crowd into the left edge.  Its
    per-mesh totals are the adaptivity panel; the history panel keeps the
    last levels, with the cumulative CG count of the whole solve as x.
    """
    if "level" not in history:
        return history, ""
    level = _column(history, "level")
    levels = np.unique(level[np.isfinite(level)])
    if levels.size <= _HISTORY_LEVELS:
        return history, ""
    keep = level >= levels[-_HISTORY_LEVELS]
    cut = {k: np.ravel(v)[keep[: len(np.ravel(v))]] for k, v in history.items()}
    return cut, f"\n(last {_HISTORY_LEVELS} of {levels.size} mesh levels)"


def plot_history(result, ax=None):
    """Draw the convergence history of a result on a log scale.

    Parameters
    ----------
    result : fastmem.Result
        The result; only ``result.history`` (a dict of 1-D columns,
        :mod:`fastmem.solver.history`) is used, the same way for every method:
        the estimator columns ``eta``, ``eta_disc``, ``eta_lin`` and
        ``eta_alg`` that are present are drawn against the cumulative number
        of inner iterations ``inner_total`` (against the row number when no
        CG ran, method ``"exact"``).  Values of ``eta_disc`` that were
        predicted rather than computed (``fresh_disc`` 0) are hollow markers.
        Every other mesh level is shaded; small triangles on the top edge
        mark where a Newton step starts (CG methods).  A history without any
        estimator value (an archive of an older version) shows ``comp_norm``
        and ``res_norm`` against the row number instead.
    ax : matplotlib.axes.Axes, optional
        Axes to draw on.  By default a new standalone figure with one axes is
        created.

    Returns
    -------
    matplotlib.axes.Axes
        The axes drawn on.  Each curve is a :class:`~matplotlib.lines.Line2D`
        whose ``gid`` is its history column name (``eta_disc_predicted`` for
        the predicted values).

    Raises
    ------
    ImportError
        If matplotlib is not installed.

    Notes
    -----
    NaN, infinite, zero and negative values cannot be shown on a log axis:
    they are left out, per curve.  So are components more than three decades
    below the smallest bound ``eta`` (round-off after a direct coarse
    solve, for example), which would squeeze the useful range; the legend
    counts them.  The y limits fit the values drawn.  A history without any
    plottable column gives an axes saying so.
    """
    _require_matplotlib()
    from matplotlib.ticker import MaxNLocator

    ax = _one_axes(ax, (6.4, 4.8))
    history, shown = _last_levels(result.history or {})
    ax.set_yscale("log")
    n_rows = max((len(np.ravel(v)) for v in history.values()), default=0)
    by_inner = (
        "inner_total" in history and np.nanmax(_column(history, "inner_total"), initial=0) > 0
    )
    x = _column(history, "inner_total") if by_inner else np.arange(1.0, n_rows + 1.0)
    drawn = _plot_curves(ax, history, x, _ESTIMATOR_CURVES, floor=_shown_floor(history))
    if drawn:
        _mark_levels_and_steps(ax, history, x, by_inner=by_inner)
        ax.set_xlabel("CG iterations so far (all levels)" if by_inner else "Newton step")
        ax.set_ylabel("error estimator")
        ax.set_title(f"error estimators during the solve{shown}", pad=10)
    else:  # histories written before the estimators were recorded for every method
        drawn = _plot_curves(ax, history, x, _NEWTON_CURVES)
        ax.set_xlabel("Newton step $k$")
        ax.set_ylabel("norm")
        ax.set_title("Newton-min convergence")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    if drawn:
        _fit_log_range(ax, drawn)
        # below the axes: the curves fill the panel from corner to corner
        ax.legend(fontsize="x-small", loc="upper center", bbox_to_anchor=(0.5, -0.13), ncols=2)
        ax.grid(True, which="major", alpha=0.3)
    else:
        _no_data(ax, "no plottable history")
    return ax


def _no_data(ax, text: str) -> None:
    ax.text(0.5, 0.5, text, transform=ax.transAxes, ha="center", va="center", color="0.4")


#: One matplotlib Triangulation per mesh (meshes are immutable): the panels of a
#: figure share it, and its edges and contour finder, instead of one each.
_TRIANGULATIONS = weakref.WeakKeyDictionary()


def _triangulation(mesh):
    tri = _TRIANGULATIONS.get(mesh)
    if tri is None:
        from matplotlib.tri import Triangulation

        v = np.asarray(mesh.vertices, dtype=np.float64)
        tri = Triangulation(v[:, 0], v[:, 1], np.asarray(mesh.triangles))
        _TRIANGULATIONS[mesh] = tri
    return tri


def _decorate(ax, title: str) -> None:
    ax.set_title(title)
    ax.set_aspect("equal")
    ax.set_xlabel("$x$")
    ax.set_ylabel("$y$")


def _draw_contact(ax, tri, active: np.ndarray, *, fill: bool) -> None:
    """Outline the contact set (and fill it, translucent) on a panel; add its legend entry.

    The contact set is drawn as the region where the piecewise-linear
    indicator of the contact vertices exceeds 1/2: its outline runs halfway
    between contact and free vertices, and it reads the same on uniform and
    adapted meshes (per-vertex dots made a moiré on fine meshes).  The contour
    set has gid ``"active"``.
    """
    from matplotlib.patches import Patch

    n_active = int(active.sum())
    label = f"contact set ({n_active} vertices)"
    if 0 < n_active < active.size:
        indicator = active.astype(np.float64)
        if fill:
            filled = ax.tricontourf(
                tri, indicator, levels=[0.5, 1.5], colors=[_CONTACT_COLOUR], alpha=0.3
            )
            filled.set_gid("active")
        outline = ax.tricontour(
            tri, indicator, levels=[0.5], colors=[_CONTACT_COLOUR], linewidths=1.2
        )
        if not fill:
            outline.set_gid("active")
    proxy = Patch(
        facecolor=_CONTACT_COLOUR if fill else "none",
        alpha=0.6 if fill else 1.0,
        edgecolor=_CONTACT_COLOUR,
        linewidth=1.2,
        label=label,
    )
    ax.legend(handles=[proxy], loc="upper right", fontsize="small", framealpha=0.85)


_GAP_TITLE = {
    "lower": "gap $u_h - \\psi_h$ and contact set",
    "upper": "gap $\\chi_h - u_h$ and contact set",
    "both": "distance to the nearer obstacle and contact sets",
}


def _is_obstacle(result) -> bool:
    return (result.parameters or {}).get("problem") == "obstacle"


def _sides(result) -> str:
    lower = getattr(result, "lower", None) is not None
    upper = getattr(result, "upper", None) is not None
    return "both" if lower and upper else ("lower" if lower else "upper")


def plot_solution(result, axes=None):
    """Draw the two membranes and the contact set of a result.

    Three panels: ``u1`` and ``u2`` (Gouraud-shaded, with colorbars) and the
    gap ``u1 - u2`` (with a colorbar) with the contact set
    (``result.active``) filled in translucent cyan and outlined, with a legend.

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
        The three axes drawn on.  The contact set is a contour set with
        ``gid`` ``"active"`` (none when no vertex or every vertex is in
        contact: there is no boundary to draw).

    Raises
    ------
    ImportError
        If matplotlib is not installed.
    fastmem.errors.ParameterError
        If ``axes`` is not a sequence of three axes.
    """
    _require_matplotlib()
    axes = _axes_row(axes, 3, (15.0, 4.6), "plot_solution (u1, u2, gap)")
    tri = _triangulation(result.mesh)
    u1 = np.asarray(result.u1, dtype=np.float64)
    u2 = np.asarray(result.u2, dtype=np.float64)
    active = np.asarray(result.active, dtype=bool)
    panels = (
        (u1, "$u_1$ (membrane 1)", "viridis"),
        (u2, "$u_2$ (membrane 2)", "viridis"),
        (u1 - u2, "gap $u_1 - u_2$ and contact set", "magma"),
    )
    if _is_obstacle(result):
        lower = getattr(result, "lower", None)
        obstacle = lower if lower is not None else result.upper
        which = "lower obstacle $\\psi_h$" if lower is not None else "upper obstacle $\\chi_h$"
        panels = (
            (u1, "membrane $u_h$", "viridis"),
            (np.asarray(obstacle, dtype=np.float64), which, "viridis"),
            (np.asarray(result.gap, dtype=np.float64), _GAP_TITLE[_sides(result)], "magma"),
        )
    for ax, (values, title, cmap) in zip(axes, panels, strict=True):
        mappable = ax.tripcolor(tri, values, shading="gouraud", cmap=cmap)
        ax.figure.colorbar(mappable, ax=ax, shrink=0.9)
        _decorate(ax, title)
    _draw_contact(axes[2], tri, active, fill=True)
    return axes


def plot_contact_pressure(result, ax=None):
    """Draw the contact pressure ``lam`` (the multiplier λ) with the outline of the contact set.

    Parameters
    ----------
    result : fastmem.Result
        The result; ``mesh``, ``lam`` and ``active`` are used.
    ax : matplotlib.axes.Axes, optional
        Axes to draw on; a new standalone figure by default.

    Returns
    -------
    matplotlib.axes.Axes
        The axes.  The shading has gid ``"lam"``; the colour scale is linear
        from 0 (λ ≥ 0 at a solution, and is 0 off the contact set).
    """
    _require_matplotlib()
    ax = _one_axes(ax, (6.4, 4.8))
    tri = _triangulation(result.mesh)
    lam = np.asarray(result.lam, dtype=np.float64)
    top = float(np.nanmax(lam)) if lam.size else 0.0
    low = float(np.nanmin(lam)) if lam.size else 0.0
    low = low if low < -1e-9 * abs(top) else 0.0  # round-off below 0 is not a scale
    vmin, vmax, extend = low, max(top, low + 1e-300), "neither"
    if _is_obstacle(result) and lam.size:
        # line loads at the jumps of a rough obstacle (nodal values ~ q / h, on refined
        # meshes many vertices) would flatten the rest: beyond 5 times the median
        # percentile of |lam| on the contact set the scale is cut, the bar extended
        act = np.asarray(result.active, dtype=bool)
        if act.any():
            cap = 3.0 * float(np.median(np.abs(lam[act])))
            if cap > 0.0 and max(top, -low) > 5.0 * cap:
                vmin, vmax, extend = max(low, -cap), min(top, cap), "both"
    mappable = ax.tripcolor(tri, lam, shading="gouraud", cmap="cividis", vmin=vmin, vmax=vmax)
    mappable.set_gid("lam")
    ax.figure.colorbar(mappable, ax=ax, shrink=0.9, extend=extend)
    _draw_contact(ax, tri, np.asarray(result.active, dtype=bool), fill=False)
    span = f"max {top:.3g}" + (f", min {low:.2g}" if low < 0.0 else "")  # min < 0: an iterate
    title = rf"contact pressure $\lambda$ ({span})"
    if _is_obstacle(result):
        title = rf"multiplier $\lambda$ ({span}; > 0: lower obstacle, < 0: upper)"
    _decorate(ax, title)
    return ax


def _indicator_scale(eta_k: np.ndarray):
    """(norm, extend) of the colour scale of the indicators: log only where they span decades.

    The scale runs over the meaningful values: those above 1e-8 of the
    largest (contact interiors have zero error up to round-off), from their
    1st to 99.5th percentile, so that a few extreme triangles do not flatten
    the picture; the colorbar is extended where values lie beyond.
    """
    from matplotlib.colors import LogNorm, Normalize

    top = float(eta_k.max()) if eta_k.size else 0.0
    if not top > 0:
        return Normalize(0.0, 1.0), "neither"
    meaningful = eta_k[eta_k > top * 1e-8]
    lo, hi = (float(v) for v in np.percentile(meaningful, [1.0, 99.5]))
    extend_max = top > hi
    if hi >= 100.0 * lo:
        extend = "both" if extend_max else "min"
        return LogNorm(vmin=lo, vmax=hi), extend
    return Normalize(vmin=0.0, vmax=hi), "max" if extend_max else "neither"


def plot_indicators(result, ax=None):
    """Draw the error indicators ``eta_K`` per triangle (the refinement indicators).

    Parameters
    ----------
    result : fastmem.Result
        A result with an error estimate (``result.estimate`` holding the
        per-triangle maps, ``fm.solve(..., estimate=True)``).
    ax : matplotlib.axes.Axes, optional
        Axes to draw on; a new standalone figure by default.

    Returns
    -------
    matplotlib.axes.Axes
        The axes.  The shading has gid ``"eta_K"`` and one value per
        triangle.  Its colour scale is logarithmic only when the indicators
        span two decades or more (see :func:`_indicator_scale`); a result
        without indicators gives an axes saying so.
    """
    _require_matplotlib()
    ax = _one_axes(ax, (6.4, 4.8))
    est = result.estimate
    if est is None or not ("eta_F1" in est.maps or "eta_K" in est.maps):
        _no_data(ax, "no error indicators\n(solve with estimate=True)")
        ax.set_title(r"error indicators $\eta_K$")
        ax.set_axis_off()
        return ax
    tri = _triangulation(result.mesh)
    eta_k = np.sqrt(indicators(est))
    norm, extend = _indicator_scale(eta_k)
    values = eta_k
    if norm.__class__.__name__ == "LogNorm":  # zeros (contact interiors) at the bottom colour
        values = np.maximum(eta_k, norm.vmin)
    coll = ax.tripcolor(tri, facecolors=values, cmap="inferno", norm=norm, antialiased=False)
    coll.set_gid("eta_K")
    ax.figure.colorbar(coll, ax=ax, shrink=0.9, extend=extend, label=r"$\eta_K$")
    _decorate(ax, r"error indicators $\eta_K$ per triangle")
    return ax


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
    """Draw a solve to a tolerance: eta against N, and the final adapted mesh.

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
        mesh edges ``mesh`` (drawn thinner on larger meshes, so that refined
        regions show as darker).  Components more than three decades below
        the smallest ``eta`` are left out (counted in the legend).

    Raises
    ------
    fastmem.errors.ParameterError
        If the result has no adaptivity table, or ``axes`` is not two axes.
    """
    _require_matplotlib()

    table = result.adaptivity
    if table is None:
        raise ParameterError("plot_adaptivity needs a result of fm.solve(scene, tol=...)")
    axes = _axes_row(axes, 2, (12.0, 5.0), "plot_adaptivity")
    ax, mesh_ax = axes
    n = np.asarray(table["n_vertices"], dtype=np.float64)
    drawn = _plot_curves(ax, table, n, _ESTIMATOR_CURVES, floor=_shown_floor(table))
    (line,) = ax.plot(n, table["target"], "k:", label="tolerance")
    line.set_gid("target")
    drawn.append(np.asarray(table["target"], dtype=np.float64))
    points = _uniform_points(uniform)
    if points is not None:
        (line,) = ax.plot(*points, "k--", marker="x", label=r"$\eta$, uniform refinement")
        line.set_gid("uniform")
        drawn.append(points[1])
    if n.size:
        ref = table["eta"][0] * (n / n[0]) ** -0.5
        (line,) = ax.plot(n, ref, color="0.6", linewidth=0.8, label=r"slope $N^{-1/2}$")
        line.set_gid("slope")
    ax.set_xscale("log")
    ax.set_yscale("log")
    drawn = [d[_positive(d)] for d in drawn]
    _fit_log_range(ax, [d for d in drawn if d.size])
    ax.set_xlabel("vertices $N$")
    ax.set_ylabel("error estimator")
    ax.set_title(f"adaptive refinement: {n.size} meshes")
    ax.grid(True, which="both", alpha=0.3)
    # below the axes (as the history panel's): eight entries would cover the curves
    ax.legend(fontsize="x-small", loc="upper center", bbox_to_anchor=(0.5, -0.13), ncols=2)
    tri = _triangulation(result.mesh)
    width = float(np.clip(40.0 / np.sqrt(max(result.mesh.n_triangles, 1)), 0.05, 0.6))
    (edges,) = mesh_ax.triplot(tri, color="k", linewidth=width)[:1]
    edges.set_gid("mesh")
    _draw_contact(mesh_ax, tri, np.asarray(result.active, dtype=bool), fill=False)
    mesh = result.mesh
    _decorate(mesh_ax, f"final mesh: {mesh.n_vertices} vertices, {mesh.n_triangles} triangles")
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
    """Return the image format selected by the suffix of ``path`` (PNG without a suffix).

    Called before anything is drawn: it also refuses a ``path`` whose folder does not
    exist (:class:`FileNotFoundError`), so that a mistyped folder costs no drawing.
    """
    fmt = path.suffix[1:].lower() or "png"
    supported = fig.canvas.get_supported_filetypes()
    if fmt not in supported:
        raise ParameterError(
            f"cannot save plot as {path}: image format {fmt!r} is not supported; "
            f"use one of {', '.join('.' + s for s in sorted(supported))}"
        )
    folder = path.parent
    if not folder.is_dir():
        what = "is not a folder" if folder.exists() else "does not exist"
        raise FileNotFoundError(errno.ENOENT, f"its folder {folder} {what}", str(path))
    return fmt


def _check_dpi(dpi) -> float:
    if isinstance(dpi, bool) or not isinstance(dpi, (int, float)) or not 10 <= dpi <= 1200:
        raise ParameterError(f"dpi must be a number between 10 and 1200, got {dpi!r}")
    return float(dpi)


def plot_result(result, path=None, *, show: bool = False, uniform=None, dpi=150):
    """Draw the history, the solution and the error indicators of a result; optionally save it.

    Six panels in three rows: the convergence history (:func:`plot_history`)
    and the gap with the contact set; ``u1`` and ``u2``
    (:func:`plot_solution`); the contact pressure
    (:func:`plot_contact_pressure`) and the error indicators
    (:func:`plot_indicators`).  A solve to a tolerance adds a fourth row,
    the two panels of :func:`plot_adaptivity` (``uniform`` is passed on to
    it).

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
    uniform : dict, optional
        See :func:`plot_adaptivity`.
    dpi : float, default 150
        Resolution of a raster image (the figure is 12 inches wide).

    Returns
    -------
    matplotlib.figure.Figure
        The figure.

    Raises
    ------
    ImportError
        If matplotlib is not installed.
    fastmem.errors.ParameterError
        If the suffix of ``path`` is not an image format matplotlib can write,
        or ``dpi`` is not a number in [10, 1200].
    OSError
        If ``path`` cannot be written (e.g. its folder does not exist).
    """
    _require_matplotlib()
    fig = _draw_result(result, path, pyplot=show, uniform=uniform, dpi=_check_dpi(dpi))
    if show:
        import matplotlib.pyplot as plt

        plt.show()
    return fig


def _draw_result(result, path, *, pyplot: bool, uniform=None, dpi: float = 150.0):
    """Draw the figure of :func:`plot_result` and save it; do not show it."""
    rows = 3 if result.adaptivity is None else 4
    fig = _new_figure((12.0, 4.6 * rows), pyplot=pyplot)
    try:
        target = None if path is None else Path(os.fspath(path))
        fmt = None if target is None else _image_format(target, fig)
        panel = [fig.add_subplot(rows, 2, i + 1) for i in range(2 * rows)]
        plot_history(result, ax=panel[0])
        plot_solution(result, axes=[panel[2], panel[3], panel[1]])
        plot_contact_pressure(result, ax=panel[4])
        plot_indicators(result, ax=panel[5])
        if rows == 4:
            plot_adaptivity(result, axes=panel[6:8], uniform=uniform)
        fig.suptitle(_suptitle(result))
        if target is not None:
            fig.savefig(target, format=fmt, dpi=dpi)
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
        "--dpi", type=float, default=150.0, help="resolution of a raster image (default 150)"
    )
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


def _study_of_index(path: Path):
    """Return the study folder when ``path`` is the index file of a sweep study, else None."""
    if path.name == INDEX_NAME and path.is_file():
        return path.parent
    try:
        with h5py.File(path, "r") as f:
            is_index = str(f.attrs.get("format", "")) == INDEX_FORMAT
    except (OSError, ValueError):  # not HDF5, missing: load() says so
        return None
    return path.parent if is_index else None


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

    study = _study_of_index(Path(args.file))
    if study is not None:
        return _error(
            f"{args.file} is the index of the sweep study {study}, not a result archive; "
            f"plot the study with: fastmem plot {study} --x PARAMETER --y COLUMN "
            f"(fastmem sweep --status {study} shows its runs), "
            f"or plot one run's archive from {study}"
        )
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
        _draw_result(
            result,
            output,
            pyplot=args.show,
            uniform=uniform,
            dpi=_check_dpi(getattr(args, "dpi", 150.0)),
        )
    except FastmemError:
        raise
    except OSError as exc:
        return _error(f"cannot write {output}: {exc.strerror or exc}")
    _out(f"wrote {output}")
    if args.show:
        import matplotlib.pyplot as plt

        plt.show()
    return 0
