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


def curves(ax):
    """The history curves of an axes by column name (vertical step lines have no gid)."""
    return {line.get_gid(): line for line in ax.lines if line.get_gid() is not None}


def step_lines(ax):
    return [line for line in ax.lines if line.get_gid() is None]


# ----------------------------------------------------------------------------- plot_result


@pytest.mark.parametrize("which", ["exact", "adaptive"])
def test_plot_result_writes_png(which, request, tmp_path):
    result = request.getfixturevalue(which)
    out = tmp_path / "fig.png"
    fig = plot.plot_result(result, out)
    assert out.stat().st_size > 10_000
    assert png_size(out) == (1800, 1425)  # 12 x 9.5 inches at 150 dpi
    # history + u1, u2, gap + one colorbar per solution panel
    assert len(fig.axes) == 7
    titles = [ax.get_title() for ax in fig.axes[:4]]
    assert "u_1" in titles[1]
    assert "u_2" in titles[2]
    assert "gap" in titles[3]
    assert f"{int(result.active.sum())} vertices" in titles[3]
    assert fig.axes[0].get_yscale() == "log"
    assert f"method {result.method}" in fig._suptitle.get_text()
    # a standalone figure on the Agg canvas, not registered with pyplot
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    assert isinstance(fig.canvas, FigureCanvasAgg)
    assert fig.canvas.manager is None


def test_plot_result_without_path_writes_nothing(exact, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    fig = plot.plot_result(exact)
    assert len(fig.axes) == 7
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
    with pytest.raises(OSError):  # noqa: PT011 - whatever the OS says
        plot.plot_result(exact, tmp_path / "nope" / "fig.png")


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
    assert step_lines(ax) == []
    rows = np.arange(1.0, len(h["k"]) + 1.0)
    for name, line in lines.items():
        keep = np.isfinite(h[name]) & (h[name] > 0)
        assert_array_equal(line.get_xdata(), rows[keep])
        assert_array_equal(line.get_ydata(), h[name][keep])
    assert "row" in ax.get_xlabel()
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert legend == [line.get_label() for line in lines.values()]


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
    assert ax.get_xlabel() == "cumulative inner iterations"
    assert ax.get_ylabel()
    x = h["inner_total"].astype(float)
    for name in ESTIMATORS:
        keep = np.isfinite(h[name]) & (h[name] > 0)
        assert_array_equal(lines[name].get_xdata(), x[keep])
        assert_array_equal(lines[name].get_ydata(), h[name][keep])
        assert lines[name].get_marker() not in (None, "", "None")
    assert len(lines["eta_lin"].get_xdata()) == 5  # two NaNs and one zero left out
    assert len(lines["eta"].get_xdata()) == 7
    # dotted lines where k changes: after inner_total 15 (k 1 -> 2) and 25 (k 2 -> 3)
    steps = step_lines(ax)
    assert [line.get_xdata()[0] for line in steps] == [15.0, 25.0]
    assert all(line.get_linestyle() == ":" for line in steps)
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert legend == [lines[n].get_label() for n in ESTIMATORS] + ["new Newton step"]
    assert ax.get_ylim()[0] > 0


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
    assert list(lines) == drawn
    for name in drawn:
        assert np.isfinite(lines[name].get_ydata()).all()
        assert (lines[name].get_ydata() > 0).all()
    steps = list(zip(h.get("level", h["k"] * 0), h["k"], strict=True))
    n_new = sum(steps[i] != steps[i + 1] for i in range(len(steps) - 1))
    assert n_new >= 1
    assert len(step_lines(ax)) == n_new


def test_history_adaptive_missing_and_empty_columns(exact):
    h = adaptive_history()
    del h["eta_lin"]
    h["eta_alg"] = np.full(8, np.nan)  # never evaluated
    h["k"] = np.ones(8, dtype=np.int64)  # a single Newton step: no step line
    ax = plot.plot_history(dataclasses.replace(exact, history=h, method="exact-amg"))
    assert list(curves(ax)) == ["eta", "eta_disc"]
    assert step_lines(ax) == []


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
    steps = step_lines(ax)
    assert [line.get_xdata()[0] for line in steps] == [8.0, 12.0, 22.0]
    assert [line.get_linestyle() for line in steps] == [":", "--", ":"]
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert legend[1:] == ["new Newton step", "new mesh level"]


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
        (tpc,) = ax.collections
        assert tpc.get_array().shape == (exact.mesh.n_vertices,)  # gouraud: vertex values
        assert_allclose(tpc.get_array(), values)
        assert ax.get_aspect() == 1.0
        assert ax.get_title()
    (dots,) = [line for line in axes[2].lines if line.get_gid() == "active"]
    active = exact.mesh.vertices[exact.active]
    assert 0 < len(active) < exact.mesh.n_vertices
    assert_array_equal(dots.get_xdata(), active[:, 0])
    assert_array_equal(dots.get_ydata(), active[:, 1])


def test_solution_without_contact(exact):
    none = dataclasses.replace(exact, active=np.zeros_like(exact.active))
    axes = plot.plot_solution(none)
    (dots,) = axes[2].lines
    assert len(dots.get_xdata()) == 0
    assert "0 vertices" in axes[2].get_title()


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
        assert png_size(out) == (1800, 1425)
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
    assert captured.err.startswith(f"fastmem: error: cannot write {out}: ")
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
    assert_array_equal(lines["eta"].get_xdata(), table["n_vertices"])
    assert_array_equal(lines["eta"].get_ydata(), table["eta"])
    assert_array_equal(lines["uniform"].get_xdata(), [65, 225, 833])  # sorted by N
    assert_array_equal(lines["uniform"].get_ydata(), [0.2, 0.1, 0.03])
    assert ax.get_xscale() == ax.get_yscale() == "log"
    assert str(adapted.mesh.n_vertices) in mesh_ax.get_title()
    (coll,) = [c for c in mesh_ax.collections if c.get_gid() == "mesh"]
    assert len(coll.get_array()) == adapted.mesh.n_triangles  # one colour per triangle


def test_adaptivity_errors(adapted, exact):
    with pytest.raises(ParameterError, match="tol"):
        plot.plot_adaptivity(exact)
    with pytest.raises(ParameterError, match="equal length"):
        plot.plot_adaptivity(adapted, uniform={"n_vertices": [1, 2], "eta": [1.0]})


def test_plot_result_of_a_solve_to_tolerance(adapted, tmp_path):
    out = tmp_path / "a.png"
    fig = plot.plot_result(adapted, out)
    assert png_size(out) == (1800, 2137)  # three rows
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
