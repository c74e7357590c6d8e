"""Figures of the benchmark results: one function per benchmark, all drawn from the JSON payload.

Needs matplotlib (the ``bench`` or ``plot`` extra); without it every function
prints a message and returns None, so the benchmarks still run and write
their JSON.  Figures are standalone :class:`matplotlib.figure.Figure` objects
on the Agg canvas (no pyplot, no window, no global backend change).

:func:`figure` dispatches on the benchmark name; ``python -m bench.report
--figures`` redraws every figure from the JSON files.
"""

import sys

import numpy as np

MISSING = "matplotlib not installed: no figure (pip install 'fastmem[bench]')"

_COLORS = {
    "inexact": "tab:blue",
    "exact-amg": "tab:orange",
    "exact": "tab:green",
    "naive": "tab:red",
}


def _new(ncols=1, nrows=1, size=(6.4, 4.6)):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(size[0] * ncols, size[1] * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, axes.ravel()


def _median(v):
    return v["median"] if isinstance(v, dict) else v


def _title(fig, payload, text):
    m = payload.get("machine", {})
    quick = " (quick)" if payload.get("quick") else ""
    fig.suptitle(
        f"{text}{quick}\n{m.get('cores', '?')} cores, numba threads "
        f"{m.get('numba_threads', '?')}, BLAS threads "
        f"{m.get('fastmem_threads', {}).get('blas', '?')}, {m.get('date', '')}",
        fontsize=9,
    )


def _reference_line(ax, xs, ys, power=1.0, label="O(N)"):
    """Dotted x**power line through the first point of the steepest-starting curve."""
    if not xs or not ys:
        return
    x0, y0 = xs[0], max(ys)
    x1 = xs[-1]
    ax.plot([x0, x1], [y0, y0 * (x1 / x0) ** power], "k:", lw=1, label=label)


def _save(fig, path):
    fig.savefig(path, dpi=110)
    return path


# ------------------------------------------------------------------ per benchmark


def plot_assembly(payload, path):
    rows = payload["rows"]
    fig, (ax,) = _new()
    m = [r["triangles"] for r in rows]
    curves = [
        ("assemble_stiffness_fused_s", "fastmem (fused kernel, CSR out)", "tab:blue", "o-"),
        ("coo_kernel_s", "fastmem local kernel only", "tab:cyan", "s--"),
        ("scipy_tocsr_s", "scipy COO->CSR of the same values", "tab:gray", "^:"),
        ("skfem_s", "scikit-fem laplace.assemble", "tab:red", "D-"),
    ]
    for key, label, color, style in curves:
        pts = [(mm, mm / _median(r[key])) for mm, r in zip(m, rows, strict=True) if key in r]
        if pts:
            ax.loglog(*zip(*pts, strict=True), style, color=color, label=label)
    ax.set_xlabel("triangles")
    ax.set_ylabel("triangles per second (stiffness matrix)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    _title(fig, payload, "P1 stiffness assembly: fastmem vs scikit-fem")
    return _save(fig, path)


def plot_poisson_unit(payload, path):
    rows = payload["rows"]
    fig, (ax, ax2) = _new(ncols=2)
    nn = [r["unknowns"] for r in rows]
    for key, style in (("setup_s", "o-"), ("solve_s", "s-"), ("total_s", "D-")):
        ax.loglog(nn, [r[key]["median"] for r in rows], style, label=key[:-2])
    _reference_line(ax, nn, [rows[0]["total_s"]["median"]])
    ax.set_xlabel("unknowns (interior vertices)")
    ax.set_ylabel("seconds (median)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax2.semilogx(nn, [r["iterations"] for r in rows], "o-", label="CG iterations")
    ax2.set_xlabel("unknowns")
    ax2.set_ylabel("CG iterations to 1e-8")
    ax2.set_ylim(bottom=0)
    ax2.grid(True, which="both", alpha=0.3)
    _title(fig, payload, "Poisson unit: pyamg smoothed aggregation + CG")
    return _save(fig, path)


def _run_label(r):
    if r["method"] == "naive":
        return "naive spsolve"
    nested = {"auto": "nested", False: "plain", True: "nested"}.get(r.get("nested"), "")
    path = r.get("path", "")
    return f"{r['method']} {nested} {path}".strip()


def plot_contact_solve(payload, path):
    rows = payload["rows"]
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    fig, axes = _new(ncols=len(scenes), size=(7.5, 5.2))
    for ax, scene in zip(axes, scenes, strict=True):
        sub = [r for r in rows if r["scene"] == scene]
        sizes = list(dict.fromkeys(r["n"] for r in sub))
        labels = list(dict.fromkeys(_run_label(r) for r in sub))
        width = 0.8 / max(1, len(labels))
        for j, label in enumerate(labels):
            xs, ys = [], []
            for i, n in enumerate(sizes):
                for r in sub:
                    if r["n"] == n and _run_label(r) == label:
                        xs.append(i + (j - (len(labels) - 1) / 2) * width)
                        ys.append(r["poisson_units"])
            method = label.split()[0]
            hatch = "//" if "general" in label else ("..." if "plain" in label else None)
            ax.bar(
                xs,
                ys,
                width,
                label=label,
                color=_COLORS.get(method if method != "naive" else "naive"),
                hatch=hatch,
                edgecolor="k",
                linewidth=0.4,
            )
        ax.set_xticks(range(len(sizes)), [f"n={n}" for n in sizes])
        ax.set_yscale("log")
        ax.set_ylabel("time in Poisson units")
        ax.set_title(f"{scene} scene", fontsize=9)
        ax.grid(True, axis="y", which="both", alpha=0.3)
    handles, labels = {}, {}
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(lab, h)
    labels = list(handles)
    fig.legend([handles[k] for k in labels], labels, loc="outside lower center", ncol=5, fontsize=7)
    _title(fig, payload, "Contact solve in Poisson units (lower is better)")
    return _save(fig, path)


def plot_estimate(payload, path):
    rows = payload["rows"]
    fig, (ax, ax2) = _new(ncols=2)
    nv = [r["vertices"] for r in rows]
    ax.semilogx(nv, [r["patches_per_s"] for r in rows], "o-", label="flux (repeated)")
    if all("flux_first_s" in r for r in rows):
        ax.semilogx(
            nv, [r["vertices"] / _median(r["flux_first_s"]) for r in rows], "s--", label="first"
        )
    ax.set_xlabel("vertices (patches)")
    ax.set_ylabel("patches per second (both membranes)")
    ax.set_ylim(bottom=0)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax2.semilogx(nv, [r["estimate_poisson_units"] for r in rows], "o-")
    ax2.set_xlabel("vertices")
    ax2.set_ylabel("whole estimate in Poisson units")
    ax2.set_ylim(bottom=0)
    ax2.grid(True, which="both", alpha=0.3)
    _title(fig, payload, "Flux reconstruction and estimators")
    return _save(fig, path)


def plot_exact_solve(payload, path):
    rows = payload["rows"]
    fig, (ax,) = _new()
    for scene, marker in (("default", "o"), ("manufactured", "s")):
        for p, style in (("decoupled", "-"), ("general", "--")):
            pts = [
                (r["vertices"], r["wall_s"]) for r in rows if r["scene"] == scene and r["path"] == p
            ]
            if pts:
                ax.loglog(*zip(*pts, strict=True), marker + style, label=f"{scene} {p}")
    ax.set_xlabel("vertices")
    ax.set_ylabel("seconds")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    _title(fig, payload, "Exact Newton-min (sparse direct solves)")
    return _save(fig, path)


def plot_work_precision(payload, path):
    rows = payload["rows"]
    fig, (ax,) = _new(size=(7.0, 5.2))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    for method in methods:
        sub = sorted((r for r in rows if r["method"] == method), key=lambda r: r["n"])
        t = [r["seconds"]["median"] for r in sub]
        color = _COLORS.get(method)
        ax.loglog(t, [r["energy_error"] for r in sub], "o-", color=color, label=f"{method}: error")
        ax.loglog(t, [r["eta"] for r in sub], "s--", color=color, label=f"{method}: $\\eta$")
        for r, tt in zip(sub, t, strict=True):
            if method == methods[0]:
                ax.annotate(
                    f"n={r['n']}",
                    (tt, r["energy_error"]),
                    textcoords="offset points",
                    xytext=(4, -10),
                    fontsize=7,
                )
    ax.set_xlabel("wall time of the solve (s)")
    ax.set_ylabel("energy error  |||u - u_h|||   (solid)   /   bound $\\eta$ (dashed)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    _title(fig, payload, "Work-precision on the manufactured solution (docs/method.md §7)")
    return _save(fig, path)


def plot_scaling(payload, path):
    rows = payload["rows"]
    fig, (ax, ax2) = _new(ncols=2)
    nv = [r["vertices"] for r in rows]
    phases = payload.get("phases", [])
    ex = payload.get("exponents", {})
    for ph in phases:
        p = ex.get(ph)
        label = ph if p is None else f"{ph} (N^{p:.2f})"
        ax.loglog(nv, [r["phases"][ph]["median"] for r in rows], "o-", label=label)
    with_unit = [r for r in rows if "poisson_s" in r]
    if with_unit:  # the unit of solver cost on the same meshes, beside the phases
        p = ex.get("poisson_unit")
        label = "Poisson unit" if p is None else f"Poisson unit (N^{p:.2f})"
        ax.loglog(
            [r["vertices"] for r in with_unit],
            [r["poisson_s"] for r in with_unit],
            "k--",
            label=label,
        )
    tops = [max(r["phases"][ph]["median"] for ph in phases) for r in rows[:1]]
    _reference_line(ax, nv, tops)
    ax.set_xlabel("vertices N")
    ax.set_ylabel("seconds per phase (median)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax2.loglog(nv, [r["peak_rss_mb"] for r in rows], "o-", label="peak RSS")
    if all(r.get("rss_before_mb") for r in rows):
        ax2.loglog(
            nv, [r["rss_before_mb"] for r in rows], "s:", label="before the work (imports, JIT)"
        )
    ax2.legend(fontsize=8)
    ax2.set_xlabel("vertices N")
    ax2.set_ylabel("peak resident memory (MB)")
    ax2.grid(True, which="both", alpha=0.3)
    _title(fig, payload, "Pipeline mesh -> solve -> estimate -> archive")
    return _save(fig, path)


def plot_threads(payload, path):
    rows = payload["rows"]
    fig, (ax,) = _new()
    kernels = list(dict.fromkeys(r["kernel"] for r in rows))
    sizes = list(dict.fromkeys(r["n"] for r in rows))
    width = 0.8 / max(1, len(sizes))
    for j, n in enumerate(sizes):
        xs, ys = [], []
        for i, k in enumerate(kernels):
            for r in rows:
                if r["kernel"] == k and r["n"] == n:
                    xs.append(i + (j - (len(sizes) - 1) / 2) * width)
                    ys.append(r["speedup"])
        ax.bar(xs, ys, width, label=f"n={n}", edgecolor="k", linewidth=0.4)
    threads = payload.get("parameters", {}).get("threads", [1, 2])
    ax.axhline(max(threads), color="k", ls=":", lw=1, label="ideal")
    ax.axhline(1.0, color="gray", lw=0.8)
    ax.set_xticks(range(len(kernels)), kernels, fontsize=8)
    ax.set_ylabel(f"speed-up {max(threads)} vs {min(threads)} threads")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    _title(fig, payload, "Thread scaling of the parallel Numba kernels")
    return _save(fig, path)


def _rate_label(text, fit):
    return text if not fit else f"{text} (N^-{fit['rate']:.2f})"


def _slope_guide(ax, xs, ys, power, label, style):
    """Line ~ N^-power through the first point (xs, ys sorted by xs)."""
    if len(xs) < 2:
        return
    ax.loglog(
        [xs[0], xs[-1]], [ys[0], ys[0] * (xs[-1] / xs[0]) ** -power], style, lw=1, label=label
    )


def plot_adaptivity(payload, path):
    rows = payload["rows"]
    cases = payload.get("cases", {})
    names = [c for c in ("lshape", "manufactured") if any(r["case"] == c for r in rows)]
    if not names:
        return None
    fig, axes = _new(ncols=len(names) + 1, size=(6.0, 5.0))
    titles = {
        "lshape": "L-shape, default data (error unknown)",
        "manufactured": "square, manufactured solution (docs/method.md §7)",
    }
    colors = {"uniform": "tab:orange", "adaptive": "tab:blue"}
    for ax, name in zip(axes, names, strict=False):
        rates = cases.get(name, {}).get("rates", {})
        for kind in ("uniform", "adaptive"):
            sub = sorted(
                (r for r in rows if r["case"] == name and r["kind"] == kind),
                key=lambda r: r["vertices"],
            )
            if not sub:
                continue
            nv = [r["vertices"] for r in sub]
            ax.loglog(
                nv,
                [r["eta"] for r in sub],
                "o-" if kind == "uniform" else "s-",
                ms=4,
                color=colors[kind],
                label=_rate_label(f"{kind}: $\\eta$", rates.get(f"{kind}_eta")),
            )
            if all("energy_error" in r for r in sub):
                ax.loglog(
                    nv,
                    [r["energy_error"] for r in sub],
                    "o--" if kind == "uniform" else "s--",
                    ms=3,
                    mfc="none",
                    color=colors[kind],
                    label=_rate_label(f"{kind}: true error", rates.get(f"{kind}_error")),
                )
        big = payload.get("big") if name == "lshape" else None
        if big and big.get("table"):
            ax.loglog(
                big["table"]["n_vertices"],
                big["table"]["eta"],
                "-",
                lw=0.8,
                color="tab:purple",
                label=f"adaptive, big stage ({big['triangles'] / 1e6:.1f}M triangles)",
            )
        allv = sorted(r["vertices"] for r in rows if r["case"] == name)
        top = max(r["eta"] for r in rows if r["case"] == name)
        _slope_guide(ax, [allv[0], allv[-1]], [top], 0.5, "N^-1/2", "k:")
        if name == "lshape":
            _slope_guide(ax, [allv[0], allv[-1]], [top], 1.0 / 3.0, "N^-1/3", "k-.")
        ax.set_xlabel("vertices N")
        ax.set_ylabel("guaranteed bound $\\eta$ (solid), true energy error (dashed)")
        ax.set_title(titles.get(name, name), fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    ax = axes[len(names)]
    markers = {"lshape": "o", "manufactured": "s"}
    for name in names:
        recs = cases.get(name, {}).get("tolerances", [])
        tol = [t["tol"] for t in recs]
        ax.loglog(
            tol,
            [t["seconds"] for t in recs],
            markers[name] + "-",
            color=colors["adaptive"] if name == "lshape" else "tab:cyan",
            label=f"{name}: adaptive loop",
        )
        pts = [(t["tol"], t["uniform_seconds"]) for t in recs if "uniform_seconds" in t]
        if pts:
            ax.loglog(
                *zip(*pts, strict=True),
                markers[name] + "--",
                color=colors["uniform"] if name == "lshape" else "tab:red",
                label=f"{name}: uniform (smallest n with $\\eta$ <= tol)",
            )
        ax.loglog(
            tol,
            [t["final_solve_seconds"] for t in recs],
            markers[name] + ":",
            color="tab:gray",
            mfc="none",
            label=f"{name}: final adapted mesh solved alone",
        )
    ax.invert_xaxis()
    ax.set_xlabel("tolerance on $\\eta$")
    ax.set_ylabel("seconds to reach $\\eta$ <= tol (median)")
    ax.set_title("time to a guaranteed tolerance", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    _title(fig, payload, "Adaptive (Dörfler + newest-vertex bisection) vs uniform refinement")
    return _save(fig, path)


def plot_twophase(payload, path):
    """Profiles (S_g, P, chi) at the kept times and the cumulated iterations per strategy."""
    rows = payload["rows"]
    profiles = payload.get("profiles", [])
    fig, axes = _new(ncols=4, size=(4.4, 4.0))
    for prof in profiles:
        label = f"t = {prof['t_years']:.3g} years"
        axes[0].plot(prof["x"], prof["s_gas"], lw=1.2, label=label)
        axes[1].plot(prof["x"], np.asarray(prof["p"]) / 1e6, lw=1.2, label=label)
        axes[2].plot(prof["x"], np.asarray(prof["chi"]) * 1e4, lw=1.2, label=label)
    for ax, ylabel in zip(
        axes[:3],
        ("gas saturation $S_g$", "liquid pressure P (MPa)", r"dissolved $\chi$ ($10^{-4}$)"),
        strict=True,
    ):
        ax.set_xlabel("x (m)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    if profiles:
        axes[0].legend(fontsize=8)
    colors = {"exact": "tab:red", "inexact": "tab:orange", "adaptive": "tab:blue"}
    styles = {"ilu": "-", "cpr": "--", "direct": ":"}
    ax = axes[3]
    main = [
        r
        for r in rows
        if r.get("complementarity", "min") == "min"
        and r.get("weights", "volume") == "volume"
        and r.get("gamma", 1e-3) == 1e-3
    ]
    for r in main:
        steps = np.arange(1, len(r["cumulative_linear"]) + 1)
        name = f"{r['strategy']}/{r['linear_solver']}"
        style, color = styles[r["linear_solver"]], colors[r["strategy"]]
        ax.semilogy(steps, r["cumulative_linear"], style, color=color, lw=1.8, label=name)
        ax.semilogy(steps, r["cumulative_newton"], style, color=color, lw=0.8, alpha=0.6)
    ax.set_xlabel("time step")
    ax.set_ylabel("cumulated iterations (thick: linear, thin: Newton-min)")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3, which="both")
    _title(fig, payload, "Liquid-gas hydrogen column (MoMaS viscosities)")
    return _save(fig, path)


_PLOTTERS = {
    "assembly": plot_assembly,
    "poisson_unit": plot_poisson_unit,
    "contact_solve": plot_contact_solve,
    "estimate": plot_estimate,
    "exact_solve": plot_exact_solve,
    "work_precision": plot_work_precision,
    "scaling": plot_scaling,
    "threads": plot_threads,
    "adaptivity": plot_adaptivity,
    "twophase": plot_twophase,
}


def figure(name, payload, path):
    """Draw the figure of benchmark ``name`` into ``path``; None without matplotlib or rows."""
    fn = _PLOTTERS.get(name)
    if fn is None or not payload.get("rows"):
        return None
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        print(MISSING, file=sys.stderr, flush=True)  # not _common.progress: _common imports us
        return None
    return fn(payload, path)
