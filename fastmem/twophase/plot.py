"""Figures of two-phase archives: profiles at chosen times and the cumulated iterations."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import ParameterError
from .archive import load_run
from .model import YEAR

__all__ = ["plot_run"]


def _row(grid, monitor):
    """Cells on the monitor's line (all cells in 1D), ordered by x."""
    c = grid["centres"]
    if c.shape[1] == 1:
        cells = np.arange(len(c))
    else:
        cells = np.flatnonzero(np.isclose(c[:, 1], c[monitor, 1]))
    return cells[np.argsort(c[cells, 0])]


def plot_run(path, output=None, times=None):
    """Draw a two-phase archive and write the image; return its path.

    Panels: the gas saturation, the liquid pressure and the dissolved fraction
    along x at the kept times nearest to ``times`` (years; default: up to five
    spread over the run), on the monitor cell's line for a 2D section; then
    the cumulated Newton-min steps and linear iterations per time step, and
    the estimators per step.  Needs matplotlib.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # lazy: the plot extra
    from matplotlib.figure import Figure  # lazy: the plot extra

    d = load_run(path)
    prof, st, grid = d["profiles"], d["steps"], d["grid"]
    if prof["time"].size == 0:
        raise ParameterError(f"{str(path)!r} kept no profiles to draw")
    kept = prof["time"] / YEAR
    if times is None:
        picks = np.unique(np.linspace(0, kept.size - 1, min(5, kept.size)).round().astype(int))
    else:
        picks = np.unique([int(np.argmin(np.abs(kept - float(t)))) for t in times])
    cells = _row(grid, int(d["problem"]["monitor"]))
    x = grid["centres"][cells, 0]
    fig = Figure(figsize=(17.0, 4.2), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 5)
    for k in picks:
        state = prof["state"][k][cells]
        label = f"t = {kept[k]:.4g} years"
        axes[0].plot(x, 1.0 - state[:, 0], lw=1.3, label=label)
        axes[1].plot(x, state[:, 1] / 1e6, lw=1.3, label=label)
        axes[2].plot(x, state[:, 2] * 1e4, lw=1.3, label=label)
    labels = ("gas saturation $S_g$", "liquid pressure P (MPa)", r"dissolved $\chi$ ($10^{-4}$)")
    for ax, ylabel in zip(axes[:3], labels, strict=True):
        ax.set_xlabel("x (m)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    steps = np.arange(1, st["time"].size + 1)
    axes[3].semilogy(steps, np.cumsum(st["linear"]), lw=1.8, label="linear iterations")
    axes[3].semilogy(steps, np.cumsum(st["newton"]), lw=1.2, label="Newton-min steps")
    axes[3].set_xlabel("time step")
    axes[3].set_ylabel("cumulated")
    axes[3].legend(fontsize=8)
    axes[3].grid(alpha=0.3, which="both")
    eta = st["eta"]
    if eta.size:
        t = st["time"] / YEAR
        for j, name in enumerate((r"$\eta_{disc}$", r"$\eta_{lin}$", r"$\eta_{alg}$")):
            axes[4].semilogy(t, np.maximum(eta[:, j], 1e-30), lw=1.2, label=name)
        axes[4].set_xlabel("t (years)")
        axes[4].set_ylabel("estimators of the step")
        axes[4].legend(fontsize=8)
        axes[4].grid(alpha=0.3, which="both")
    scene = d["problem"].get("scene", {})
    fig.suptitle(
        f"{scene.get('name', 'two-phase run')} ({scene.get('viscosity', '')} viscosities), "
        f"{d['problem']['cells']} cells, strategy {d['strategy']}, {d['linear_solver']}: "
        f"{int(st['newton'].sum())} Newton-min steps, {int(st['linear'].sum())} linear iterations",
        fontsize=10,
    )
    out = Path(output) if output is not None else Path(path).with_suffix(".png")
    fig.savefig(out, dpi=110)
    return out
