"""Tests of the figures and the ``fastmem plot`` glue (fastmem.cli.plot)."""

from __future__ import annotations

import argparse
import dataclasses
import struct
import sys

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

import fastmem as fm
from fastmem.errors import ArchiveError, ParameterError

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")

from fastmem.cli import plot  # noqa: E402

# Matplotlib complaints (log of non-positive data, empty legends, ...) are bugs here.
pytestmark = [
    pytest.mark.filterwarnings("error::UserWarning"),
    pytest.mark.filterwarnings("error::RuntimeWarning"),
]

ESTIMATORS = ["eta", "eta_disc", "eta_lin", "eta_alg"]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SCENE = fm.Scene(fm.Mesh.square(8), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)


@pytest.fixture(scope="module")
def exact():
    """A converged "exact" result on square(8), without estimate."""
    r = fm.solve(SCENE, method="exact", estimate=False)
    assert r.method == "exact"
    assert {"k", "comp_norm", "res_norm"} <= set(r.history)
    return r


def adaptive_history():
    """A synthetic history of an adaptive method: 3 Newton steps, NaNs where not evaluated."""
    nan = np.nan
    return {
        "k": np.array([1, 1, 1, 2, 2, 3, 3, 3], dtype=np.int64),
        "inner": np.array([5, 10, 15, 5, 10, 5, 10, 15], dtype=np.int64),
        "inner_total": np.array([5, 10, 15, 20, 25, 30, 35, 40], dtype=np.int64),
        "n_active": np.array([0, 0, 0, 40, 40, 45, 45, 45], dtype=np.int64),
        "eta_disc": np.array([0.1, 0.1, 0.1, 0.05, 0.05, 0.02, 0.02, 0.02]),
        # NaN (not evaluated) and a zero: neither may reach the log axis
        "eta_lin": np.array([nan, 0.3, 0.3, 0.1, nan, 0.05, 0.0, 0.01]),
        "eta_alg": np.array([1.0, 0.5, 0.1, 0.3, 0.02, 0.1, 0.01, 1e-3]),
        "eta": np.array([1.2, 0.7, 0.4, 0.4, nan, 0.15, 0.05, 0.03]),
        "seconds": np.linspace(0.0, 0.7, 8),
    }


@pytest.fixture(scope="module")
def adaptive(exact):
    return dataclasses.replace(exact, history=adaptive_history(), method="inexact")


@pytest.fixture(scope="module")
def archive(exact, tmp_path_factory):
    path = tmp_path_factory.mktemp("plot") / "r.h5"
    exact.save(path)
    return path


def png_size(path):
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


MARKS = ("newton_steps",)


def curves(ax):
    """The history curves of an axes by column name (not the Newton-step marks)."""
    return {line.get_gid(): line for line in ax.lines if line.get_gid() not in MARKS}


def step_marks(ax):
    """x of the marks where a Newton step starts (none: empty)."""
    marks = [line for line in ax.lines if line.get_gid() == "newton_steps"]
    assert len(marks) <= 1
    return list(marks[0].get_xdata()) if marks else []


def level_bands(ax):
    """(start, end) of the shaded mesh levels."""
    bands = [p for p in ax.patches if p.get_gid() == "level"]
    return [(float(b.get_x()), float(b.get_x() + b.get_width())) for b in bands]


def legend_texts(ax):
    return [t.get_text() for t in ax.get_legend().get_texts()]


# ----------------------------------------------------------------------------- plot_result


@pytest.mark.parametrize("which", ["exact", "adaptive"])
def test_plot_result_writes_png(which, request, tmp_path):
    result = request.getfixturevalue(which)
    out = tmp_path / "fig.png"
    fig = plot.plot_result(result, out)
    assert out.stat().st_size > 10_000
    assert png_size(out) == (1800, 2070)  # 12 x 13.8 inches at 150 dpi
    # history, gap, u1, u2, lam, eta_K + one colorbar per field (no eta_K without estimate)
    assert len(fig.axes) == 10
    titles = [ax.get_title() for ax in fig.axes[:6]]
    assert "estimators" in titles[0]
    assert "gap" in titles[1]
    assert "u_1" in titles[2]
    assert "u_2" in titles[3]
    assert "contact pressure" in titles[4]
    assert "no error indicators" in fig.axes[5].texts[0].get_text()
    assert legend_texts(fig.axes[1]) == [f"contact set ({int(result.active.sum())} vertices)"]
    assert fig.axes[0].get_yscale() == "log"
    assert f"method {result.method}" in fig._suptitle.get_text()
    # a standalone figure on the Agg canvas, not registered with pyplot
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    assert isinstance(fig.canvas, FigureCanvasAgg)
    assert fig.canvas.manager is None


def test_plot_result_without_path_writes_nothing(exact, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    fig = plot.plot_result(exact)
    assert len(fig.axes) == 10
    assert list(tmp_path.iterdir()) == []


def test_plot_result_format_from_suffix(exact, tmp_path):
    pdf = tmp_path / "fig.pdf"
    plot.plot_result(exact, pdf)
    assert pdf.read_bytes()[:5] == b"%PDF-"
    # no suffix: PNG under exactly the given name (matplotlib would append ".png")
    bare = tmp_path / "figure"
    plot.plot_result(exact, str(bare))
    assert png_size(bare)[0] > 0
    assert not (tmp_path / "figure.png").exists()


def test_plot_result_bad_suffix(exact, tmp_path):
    out = tmp_path / "fig.h5"
    with pytest.raises(ParameterError, match=r"image format 'h5' is not supported.*\.png"):
        plot.plot_result(exact, out)
    assert not out.exists()


def test_plot_result_missing_folder(exact, tmp_path):
    """A missing folder is refused before anything is drawn, naming the folder."""
    with pytest.raises(FileNotFoundError, match=r"its folder .*nope does not exist"):
        plot.plot_result(exact, tmp_path / "nope" / "fig.png")
    (tmp_path / "file").write_text("")
    with pytest.raises(FileNotFoundError, match=r"its folder .*file is not a folder"):
        plot.plot_result(exact, tmp_path / "file" / "fig.png")


def test_plot_result_show_uses_pyplot(exact, tmp_path, monkeypatch):
    import matplotlib.pyplot as plt

    shown = []
    monkeypatch.setattr(plt, "show", lambda *a, **k: shown.append(plt.get_fignums()))
    fig = plot.plot_result(exact, tmp_path / "fig.png", show=True)
    try:
        assert len(shown) == 1
        assert fig.number in shown[0]
        assert (tmp_path / "fig.png").stat().st_size > 0
    finally:
        plt.close(fig)


# ----------------------------------------------------------------------------- plot_history


def test_history_exact(exact):
    """Method "exact" has the same columns; no CG: the estimators against the row number."""
    ax = plot.plot_history(exact)
    assert ax.get_yscale() == "log"
    lines = curves(ax)
    h = exact.history
    assert (h["inner_total"] == 0).all()
    drawn = [n for n in ESTIMATORS if (np.isfinite(h[n]) & (h[n] > 0)).any()]
    assert drawn == ["eta_lin", "eta_alg"]  # no flux without estimate=True
    assert list(lines) == drawn
    assert step_marks(ax) == []  # one row per Newton step: nothing to mark
    assert level_bands(ax) == []  # one level
    rows = np.arange(1.0, len(h["k"]) + 1.0)
    for name, line in lines.items():
        keep = np.isfinite(h[name]) & (h[name] > 0)  # no bound: nothing else left out
        assert_array_equal(line.get_xdata(), rows[keep])
        assert_array_equal(line.get_ydata(), h[name][keep])
    assert ax.get_xlabel() == "Newton step"
    assert legend_texts(ax) == [line.get_label() for line in lines.values()]


def test_history_of_an_older_archive_shows_the_newton_norms(exact):
    """A history without estimator columns (older versions of "exact") draws the two norms."""
    h = {k: exact.history[k] for k in ("k", "n_active", "comp_norm", "res_norm", "seconds")}
    ax = plot.plot_history(dataclasses.replace(exact, history=h))
    lines = curves(ax)
    assert list(lines) == ["comp_norm", "res_norm"]
    # the converged step has comp_norm exactly 0: masked, not a crash
    assert h["comp_norm"][-1] == 0.0
    assert len(lines["comp_norm"].get_xdata()) == len(h["k"]) - 1
    assert "Newton step" in ax.get_xlabel()


def test_history_adaptive(adaptive):
    h = adaptive.history
    ax = plot.plot_history(adaptive)
    assert ax.get_yscale() == "log"
    lines = curves(ax)
    assert list(lines) == ESTIMATORS
    assert ax.get_xlabel() == "CG iterations so far (all levels)"
    assert ax.get_ylabel()
    x = h["inner_total"].astype(float)
    for name in ESTIMATORS:
        keep = np.isfinite(h[name]) & (h[name] > 0)
        assert_array_equal(lines[name].get_xdata(), x[keep])
        assert_array_equal(lines[name].get_ydata(), h[name][keep])
        assert lines[name].get_marker() not in (None, "", "None")
    assert len(lines["eta_lin"].get_xdata()) == 5  # two NaNs and one zero left out
    assert len(lines["eta"].get_xdata()) == 7
    # marks where k changes: after inner_total 15 (k 1 -> 2) and 25 (k 2 -> 3)
    assert step_marks(ax) == [15.0, 25.0]
    legend = legend_texts(ax)
    assert legend == [lines[n].get_label() for n in ESTIMATORS] + ["a Newton step starts"]
    # the y range is the range drawn (1e-3 ... 1.2), with a factor 2 of margin
    assert_allclose(ax.get_ylim(), (1e-3 / 2, 1.2 * 2))


@pytest.mark.parametrize("method", ["inexact", "exact-amg"])
def test_history_of_adaptive_solve(method):
    """The history written by the adaptive solvers takes the estimator branch."""
    r = fm.solve(SCENE, method=method)
    h = r.history
    assert "inner_total" in h
    ax = plot.plot_history(r)
    assert ax.get_yscale() == "log"
    lines = curves(ax)
    drawn = [n for n in ESTIMATORS if n in h and (np.isfinite(h[n]) & (h[n] > 0)).any()]
    assert drawn
    assert [n for n in lines if n != "eta_disc_predicted"] == drawn
    predicted = (h["fresh_disc"] == 0) & np.isfinite(h["eta_disc"])
    assert ("eta_disc_predicted" in lines) == bool(predicted.any())
    for name in drawn:
        assert np.isfinite(lines[name].get_ydata()).all()
        assert (lines[name].get_ydata() > 0).all()
    level, k = h["level"], h["k"]
    new_step = (k[1:] != k[:-1]) & (level[1:] == level[:-1])
    assert new_step.any()
    assert_array_equal(step_marks(ax), h["inner_total"][:-1][new_step])
    # nothing drawn three decades or more below the smallest bound
    bounds = h["eta"][np.isfinite(h["eta"])]
    floor = bounds.min() * 1e-3 if bounds.size else 0.0  # exact-amg: no bound, none left out
    for name in drawn:
        assert (lines[name].get_ydata() >= floor).all()
    low = (h["eta_alg"] > 0) & (h["eta_alg"] < floor)
    label = lines["eta_alg"].get_label()
    assert (f"{int(low.sum())} < " in label) == bool(low.any())


def test_history_adaptive_missing_and_empty_columns(exact):
    h = adaptive_history()
    del h["eta_lin"]
    h["eta_alg"] = np.full(8, np.nan)  # never evaluated
    h["k"] = np.ones(8, dtype=np.int64)  # a single Newton step: no step line
    ax = plot.plot_history(dataclasses.replace(exact, history=h, method="exact-amg"))
    assert list(curves(ax)) == ["eta", "eta_disc"]
    assert step_marks(ax) == []


def test_history_mesh_levels(exact):
    # two mesh levels (k restarts at 1); level 1 has a single Newton step, so only the
    # level column tells that row 3 starts a new step
    h = {
        "level": np.array([0, 0, 0, 1, 1, 1]),
        "k": np.array([1, 1, 2, 1, 1, 2]),
        "inner": np.array([4, 8, 4, 5, 10, 5]),
        "inner_total": np.array([4, 8, 12, 17, 22, 27]),
        "eta": np.array([1.0, 0.5, 0.2, 0.3, 0.1, 0.05]),
    }
    ax = plot.plot_history(dataclasses.replace(exact, history=h, method="exact-amg"))
    assert list(curves(ax)) == ["eta"]
    # level 1 runs from the end of level 0 (inner_total 12) to the last row (27): shaded
    assert level_bands(ax) == [(12.0, 27.0)]
    # Newton steps start after rows 1 and 4; row 2 ends a level (the band shows it)
    assert step_marks(ax) == [8.0, 22.0]
    legend = legend_texts(ax)
    assert sorted(legend[1:]) == ["a Newton step starts", "mesh levels (alternate shading)"]


def test_history_predicted_disc_and_round_off(exact):
    """Predicted eta_disc values are hollow points; components far below eta are left out."""
    h = {
        "level": np.array([0, 0, 1, 1]),
        "k": np.array([1, 2, 1, 2]),
        "inner": np.array([3, 6, 2, 4]),
        "inner_total": np.array([3, 6, 8, 10]),
        "eta_disc": np.array([0.2, 0.2, 0.1, 0.05]),
        "fresh_disc": np.array([1, 0, 0, 1]),
        "eta": np.array([0.5, np.nan, np.nan, 0.06]),
        "eta_alg": np.array([0.1, 1e-15, 1e-15, 1e-3]),  # round-off: exact coarse solves
    }
    ax = plot.plot_history(dataclasses.replace(exact, history=h, method="inexact"))
    lines = curves(ax)
    assert_array_equal(lines["eta_disc"].get_xdata(), [3.0, 10.0])
    assert_array_equal(lines["eta_disc_predicted"].get_xdata(), [6.0, 8.0])
    assert lines["eta_disc_predicted"].get_linestyle() == "None"
    assert lines["eta_disc_predicted"].get_markerfacecolor() == "none"
    assert lines["eta_disc_predicted"].get_color() == lines["eta_disc"].get_color()
    assert_array_equal(lines["eta_alg"].get_ydata(), [0.1, 1e-3])
    assert "2 < 6e-05 left out" in lines["eta_alg"].get_label()
    assert ax.get_ylim()[0] == pytest.approx(1e-3 / 2)


def test_history_keeps_the_last_levels(exact):
    """An adaptive loop's 20 levels: the panel shows the last 8 and says so."""
    level = np.repeat(np.arange(20), 2)
    h = {
        "level": level,
        "k": np.tile([1, 2], 20),
        "inner": np.tile([2, 4], 20),
        "inner_total": np.cumsum(np.tile([2, 2], 20)),
        "eta": 1.0 / (1.0 + level),
    }
    ax = plot.plot_history(dataclasses.replace(exact, history=h, method="inexact"))
    assert_array_equal(curves(ax)["eta"].get_xdata(), h["inner_total"][level >= 12])
    assert "last 8 of 20 mesh levels" in ax.get_title()
    # level 12 begins where its first row's step began; level 13 (shaded) after row 25
    assert level_bands(ax)[0] == (float(h["inner_total"][25]), float(h["inner_total"][27]))


def test_history_nothing_plottable(exact):
    for history in ({}, {"k": np.array([1, 2]), "comp_norm": np.zeros(2)}):
        ax = plot.plot_history(dataclasses.replace(exact, history=history))
        assert len(ax.lines) == 0
        assert ax.get_legend() is None
        assert [t.get_text() for t in ax.texts] == ["no plottable history"]


def test_history_on_given_axes(adaptive):
    from matplotlib.figure import Figure

    fig = Figure()
    ax = fig.add_subplot()
    assert plot.plot_history(adaptive, ax=ax) is ax
    assert fig.axes == [ax]


# ----------------------------------------------------------------------------- plot_solution


def test_solution_panels(exact):
    axes = plot.plot_solution(exact)
    assert len(axes) == 3
    fig = axes[0].figure
    assert len(fig.axes) == 6  # three panels, three colorbars
    for ax, values in zip(axes, (exact.u1, exact.u2, exact.gap), strict=True):
        tpc = ax.collections[0]
        assert tpc.get_array().shape == (exact.mesh.n_vertices,)  # gouraud: vertex values
        assert_allclose(tpc.get_array(), values)
        assert ax.get_aspect() == 1.0
        assert ax.get_title()
    assert len(axes[0].collections) == len(axes[1].collections) == 1
    (region,) = [c for c in axes[2].collections if c.get_gid() == "active"]
    inside = np.zeros(exact.mesh.n_vertices, dtype=bool)
    for path in region.get_paths():
        inside |= path.contains_points(exact.mesh.vertices)
    assert 0 < exact.active.sum() < exact.mesh.n_vertices
    assert_array_equal(inside, exact.active)  # the region holds the contact vertices only
    n = int(exact.active.sum())
    assert legend_texts(axes[2]) == [f"contact set ({n} vertices)"]


def test_solution_without_contact(exact):
    none = dataclasses.replace(exact, active=np.zeros_like(exact.active))
    axes = plot.plot_solution(none)
    assert [c.get_gid() for c in axes[2].collections if c.get_gid()] == []
    assert legend_texts(axes[2]) == ["contact set (0 vertices)"]


def test_contact_pressure_panel(exact):
    ax = plot.plot_contact_pressure(exact)
    (shading,) = [c for c in ax.collections if c.get_gid() == "lam"]
    assert_allclose(shading.get_array(), exact.lam)
    assert shading.norm.vmin == 0.0  # linear from 0: lam >= 0 at a solution
    assert shading.norm.vmax == pytest.approx(exact.lam.max())
    assert [c.get_gid() for c in ax.collections].count("active") == 1  # the outline
    assert "contact pressure" in ax.get_title()


def test_indicator_panel_scales(exact):
    """eta_K: linear from 0 when the values span less than two decades, log beyond."""
    from matplotlib.colors import LogNorm

    r = fm.solve(SCENE, method="exact")  # with the estimate
    ax = plot.plot_indicators(r)
    (coll,) = [c for c in ax.collections if c.get_gid() == "eta_K"]
    assert coll.get_array().shape == (r.mesh.n_triangles,)
    eta_k = np.sqrt(fm.adapt.indicators(r.estimate))
    norm, _ = plot._indicator_scale(eta_k)
    assert coll.norm.vmax == pytest.approx(norm.vmax)
    meaningful = eta_k[eta_k > eta_k.max() * 1e-8]
    assert coll.norm.vmax == pytest.approx(np.percentile(meaningful, 99.5))
    spread = np.percentile(meaningful, 99.5) / np.percentile(meaningful, 1.0)
    assert isinstance(coll.norm, LogNorm) == (spread >= 100)
    wide = np.concatenate([np.geomspace(1e-6, 1e-2, 200), np.zeros(10)])
    narrow = np.concatenate([np.linspace(1e-4, 5e-4, 200), np.zeros(10)])
    assert isinstance(plot._indicator_scale(wide)[0], LogNorm)
    linear, extend = plot._indicator_scale(narrow)
    assert not isinstance(linear, LogNorm)
    assert linear.vmin == 0.0
    assert extend == "max"  # the top half percent lies beyond the scale
    ax = plot.plot_indicators(exact)  # no estimate
    assert "no error indicators" in ax.texts[0].get_text()


def test_solution_needs_three_axes(exact):
    from matplotlib.figure import Figure

    fig = Figure()
    with pytest.raises(ParameterError, match="3 axes"):
        plot.plot_solution(exact, axes=[fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)])


# ----------------------------------------------------------------------------- missing matplotlib


def test_missing_matplotlib(exact, archive, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # makes "import matplotlib" fail
    message = "fastmem plot needs matplotlib: pip install 'fastmem[plot]'"
    for call in (
        lambda: plot.plot_result(exact),
        lambda: plot.plot_history(exact),
        lambda: plot.plot_solution(exact),
    ):
        with pytest.raises(ImportError) as info:
            call()
        assert str(info.value) == message
    args = argparse.Namespace(file=archive, output=None, show=False)
    assert plot.run_plot(args) == 2
    err = capsys.readouterr().err
    assert err == f"fastmem: error: {message}\n"
    assert not archive.with_suffix(".png").exists()


# ----------------------------------------------------------------------------- CLI glue


def parse(argv):
    p = argparse.ArgumentParser(prog="fastmem")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    assert plot.add_parser(sub).prog == "fastmem plot"
    return p.parse_args(argv)


def test_cli_default_output(exact, archive, capsys):
    args = parse(["plot", str(archive)])
    assert args.command == "plot"
    assert args.func is plot.run_plot
    assert args.output is None
    assert args.show is False
    out = archive.with_suffix(".png")
    try:
        assert args.func(args) == 0
        assert png_size(out) == (1800, 2070)
        assert capsys.readouterr().out == f"wrote {out}\n"
    finally:
        out.unlink(missing_ok=True)


def test_cli_output_option(archive, tmp_path, capsys):
    out = tmp_path / "custom.png"
    args = parse(["plot", str(archive), "-o", str(out)])
    assert plot.run_plot(args) == 0
    assert out.stat().st_size > 10_000
    assert not archive.with_suffix(".png").exists()
    assert str(out) in capsys.readouterr().out


def test_cli_show(archive, tmp_path, monkeypatch, capsys):
    import matplotlib.pyplot as plt

    shown = []
    monkeypatch.setattr(plt, "show", lambda *a, **k: shown.append(capsys.readouterr().out))
    out = tmp_path / "shown.png"
    args = parse(["plot", str(archive), "--output", str(out), "--show"])
    try:
        assert plot.run_plot(args) == 0
    finally:
        plt.close("all")
    assert shown == [f"wrote {out}\n"]  # the path is printed before the (blocking) window
    assert out.is_file()


def test_cli_missing_archive(tmp_path):
    missing = tmp_path / "missing.h5"
    args = parse(["plot", str(missing)])
    with pytest.raises(ArchiveError, match=r"missing\.h5 does not exist"):
        plot.run_plot(args)
    assert list(tmp_path.iterdir()) == []


def test_cli_not_an_archive(tmp_path):
    bogus = tmp_path / "bogus.h5"
    bogus.write_text("not hdf5")
    with pytest.raises(ArchiveError, match="not an HDF5 file"):
        plot.run_plot(parse(["plot", str(bogus)]))
    assert not bogus.with_suffix(".png").exists()


def test_cli_bad_output(archive, tmp_path, capsys):
    with pytest.raises(ParameterError, match="not supported"):
        plot.run_plot(parse(["plot", str(archive), "-o", str(tmp_path / "x.h5")]))
    out = tmp_path / "no" / "such" / "dir.png"
    assert plot.run_plot(parse(["plot", str(archive), "-o", str(out)])) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert (
        captured.err
        == f"fastmem: error: cannot write {out}: its folder {out.parent} does not exist\n"
    )
    assert captured.err.count("\n") == 1


# ----------------------------------------------------------------------------- adaptivity


@pytest.fixture(scope="module")
def adapted():
    scene = fm.Scene(fm.Mesh.lshape(8), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    return fm.solve(scene, tol=0.05)


def test_adaptivity_panels(adapted):
    table = adapted.adaptivity
    uniform = {"n_vertices": [833, 65, 225], "eta": [0.03, 0.2, 0.1]}
    ax, mesh_ax = plot.plot_adaptivity(adapted, uniform=uniform)
    lines = curves(ax)
    assert {"eta", "eta_disc", "target", "uniform", "slope"} <= set(lines)
    # eta of the meshes solved by the solver's criterion on the line; of the intermediate
    # meshes whose CG could stop by its own estimate (cg_stop), as hollow markers apart
    loose = np.asarray(table["cg_stop"]) > 0
    assert loose.any()
    assert not loose[-1]
    assert_array_equal(lines["eta"].get_xdata(), table["n_vertices"][~loose])
    assert_array_equal(lines["eta"].get_ydata(), table["eta"][~loose])
    assert_array_equal(lines["eta_loose"].get_ydata(), table["eta"][loose])
    assert lines["eta_loose"].get_linestyle() == "None"
    assert_array_equal(lines["uniform"].get_xdata(), [65, 225, 833])  # sorted by N
    assert_array_equal(lines["uniform"].get_ydata(), [0.2, 0.1, 0.03])
    assert ax.get_xscale() == ax.get_yscale() == "log"
    assert str(adapted.mesh.n_vertices) in mesh_ax.get_title()
    (edges,) = [line for line in mesh_ax.lines if line.get_gid() == "mesh"]
    # triplot draws every edge once, each as a segment between NaN separators
    segments = np.isfinite(edges.get_xdata()).sum() // 2
    assert segments == adapted.mesh.n_edges
    assert f"contact set ({int(adapted.active.sum())} vertices)" in legend_texts(mesh_ax)
    # no component drawn three decades below the smallest eta; the tolerance is drawn
    floor = np.min(table["eta"]) * 1e-3
    assert all((line.get_ydata() >= floor).all() for line in lines.values())
    assert ax.get_ylim()[0] >= floor / 2


def test_adaptivity_errors(adapted, exact):
    with pytest.raises(ParameterError, match="tol"):
        plot.plot_adaptivity(exact)
    with pytest.raises(ParameterError, match="equal length"):
        plot.plot_adaptivity(adapted, uniform={"n_vertices": [1, 2], "eta": [1.0]})


def test_plot_result_of_a_solve_to_tolerance(adapted, tmp_path):
    out = tmp_path / "a.png"
    fig = plot.plot_result(adapted, out)
    assert png_size(out) == (1800, 2760)  # four rows of 4.6 inches
    titles = [ax.get_title() for ax in fig.axes]
    assert any("adaptive refinement" in t for t in titles)


def test_cli_uniform_archives(adapted, exact, tmp_path, capsys):
    a = tmp_path / "adapt.h5"
    adapted.save(a)
    u = tmp_path / "u.h5"
    fm.solve(fm.Scene(fm.Mesh.lshape(16), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)).save(u)
    out = tmp_path / "a.png"
    assert plot.run_plot(parse(["plot", str(a), "--uniform", str(u), "-o", str(out)])) == 0
    assert out.exists()
    plain = tmp_path / "plain.h5"
    exact.save(plain)  # no estimate: no eta to draw
    assert plot.run_plot(parse(["plot", str(a), "--uniform", str(plain), "-o", str(out)])) == 2
    assert "without an error bound" in capsys.readouterr().err


def test_cli_dpi(archive, tmp_path, capsys):
    out = tmp_path / "small.png"
    assert plot.run_plot(parse(["plot", str(archive), "-o", str(out), "--dpi", "60"])) == 0
    assert png_size(out) == (720, 828)  # 12 x 13.8 inches at 60 dpi
    with pytest.raises(ParameterError, match="dpi must be a number between 10 and 1200, got 0"):
        plot.plot_result(fm.load(archive), tmp_path / "x.png", dpi=0)
    assert not (tmp_path / "x.png").exists()


@pytest.mark.parametrize("name", ["sweep-index.h5", "renamed.h5"])
def test_cli_sweep_index_points_to_the_study(tmp_path, capsys, name):
    """`fastmem plot study/sweep-index.h5` names the command that plots a study."""
    import h5py

    from fastmem.sweeps.grid import INDEX_FORMAT

    study = tmp_path / "study"
    study.mkdir()
    with h5py.File(study / name, "w") as f:
        f.attrs["format"] = INDEX_FORMAT
    assert plot.run_plot(parse(["plot", str(study / name)])) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "is the index of the sweep study" in err
    assert f"fastmem plot {study} --x PARAMETER --y COLUMN" in err
    assert not (study / name).with_suffix(".png").exists()


def test_panels_share_one_triangulation(exact):
    """One Triangulation per mesh for every panel of a figure (built once, not per panel)."""
    tri = plot._triangulation(exact.mesh)
    assert plot._triangulation(exact.mesh) is tri
    other = fm.Mesh.square(4)
    assert plot._triangulation(other) is not tri
    assert plot._triangulation(other).triangles.shape == (other.n_triangles, 3)
