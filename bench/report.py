"""Fill the "Performance" section of docs/performance.md (template bench/PERFORMANCE.md).

Every ``{placeholder}`` of the template whose value can be computed from
``<results>/<name>.json`` is replaced; the others stay as they are, so a
missing full run is visible.  ``--quick`` reads the ``*_quick.json`` files
instead (for checking the machinery, not for publishing).  ``--figures``
redraws every PNG from its JSON.

By default the filled section is printed.  ``--write`` replaces the text
between the ``<!-- begin section -->`` and ``<!-- end section -->`` markers
of docs/performance.md (the rest of that page is written by hand);
``--check`` writes nothing and exits with status 1 when that text differs
from the filled section.

    python -m bench.report [--quick] [--results DIR] [--figures] [--missing]
                           [--write | --check] [--doc FILE]
"""

import argparse
import json
import re
import sys
from pathlib import Path

from bench._common import result_name, results_dir

TEMPLATE = Path(__file__).resolve().parent / "PERFORMANCE.md"
#: The page that holds the filled section, between the same markers as the template.
DOC = Path(__file__).resolve().parent.parent / "docs" / "performance.md"
BEGIN, END = "<!-- begin section -->", "<!-- end section -->"

#: Benchmarks in the order ``python -m bench`` runs them.
BENCHMARKS = (
    "assembly",
    "poisson_unit",
    "exact_solve",
    "contact_solve",
    "estimate",
    "work_precision",
    "scaling",
    "mesh_phase_profile",
    "threads",
    "unstructured",
    "direct_ordering",
    "adaptivity",
    "effectivity",
    "cross_points",
    "layers",
    "memory",
    "coldstart",
    "sweep",
    "obstacle",
    "peers",
    "twophase",
    "manycore",
    "critical_path",
)


def load(name, quick=False, folder=None):
    """The payload of ``<folder>/<name>[_quick].json``, or None."""
    path = Path(folder or results_dir()) / f"{result_name(name, quick)}.json"
    if not path.exists():
        return None
    return json.loads(path.read_text())


def _med(v):
    return v["median"] if isinstance(v, dict) else v


def _count(x):
    """4198401 -> '4.2M', 131072 -> '131k'."""
    if x >= 1e6:
        return f"{x / 1e6:.1f}M"
    if x >= 1e3:
        return f"{x / 1e3:.0f}k"
    return str(int(x))


def _x(r):
    return f"{r:.0f}" if r >= 10 else f"{r:.1f}"


def _largest(rows, **match):
    sub = [r for r in rows if all(r.get(k) == v for k, v in match.items())]
    return max(sub, key=lambda r: r["n"]) if sub else None


def _at(rows, n, **match):
    return next(
        (r for r in rows if r["n"] == n and all(r.get(k) == v for k, v in match.items())), None
    )


# ------------------------------------------------------------------ per benchmark values


def _assembly(d, v):
    rows = [r for r in d["rows"] if "skfem_s" in r]
    if not rows:
        return
    big = max(rows, key=lambda r: r["n"])
    v["assembly_n"] = big["n"]
    v["assembly_triangles"] = _count(big["triangles"])
    v["assembly_ratio"] = _x(big["ratio_skfem_over_fastmem"])
    v["assembly_mtris"] = f"{big['triangles'] / _med(big['assemble_stiffness_fused_s']) / 1e6:.0f}"
    v["skfem_mtris"] = f"{big['triangles'] / _med(big['skfem_s']) / 1e6:.1f}"
    v["tocsr_ratio"] = _x(_med(big["scipy_tocsr_s"]) / _med(big["coo_to_csr_gather_s"]))
    v["assembly_max_diff"] = f"{max(r['max_abs_diff_vs_skfem'] for r in rows):.1e}"
    v["assembly_ratio_range"] = (
        f"{_x(min(r['ratio_skfem_over_fastmem'] for r in rows))}–"
        f"{_x(max(r['ratio_skfem_over_fastmem'] for r in rows))}"
    )
    for r in rows:
        v[f"assembly_ratio_{_count(r['triangles'])}"] = _x(r["ratio_skfem_over_fastmem"])
    comp = d.get("compile") or {}
    if comp:
        v["compile_cold_s"] = f"{comp['cold_cache']['first_calls_s']:.1f}"
        v["compile_warm_s"] = f"{comp['warm_cache']['first_calls_s']:.2f}"


def _poisson(d, v):
    big = max(d["rows"], key=lambda r: r["n"])
    v["poisson_n"] = big["n"]
    v["poisson_unknowns"] = _count(big["unknowns"])
    v["poisson_s"] = f"{big['seconds']:.2f}"
    v["poisson_its"] = big["iterations"]
    v["poisson_setup_pct"] = f"{100 * big['setup_s']['median'] / big['seconds']:.0f}"
    v["poisson_peak_mb"] = f"{big['peak_rss_mb']:.0f}"
    ex = d.get("exponents", {}).get("total")
    if ex is not None:
        v["poisson_exp"] = f"{ex:.2f}"
    v["poisson_its_range"] = (
        f"{min(r['iterations'] for r in d['rows'])}–{max(r['iterations'] for r in d['rows'])}"
    )


def _contact(d, v):
    rows = d["rows"]

    def key(r, nested="auto", path="decoupled"):
        return r.get("nested") == nested and r.get("path", "decoupled") == path

    for scene, tag in (("default", ""), ("manufactured", "_mms")):
        inex = [r for r in rows if r["scene"] == scene and r["method"] == "inexact" and key(r)]
        amg = [r for r in rows if r["scene"] == scene and r["method"] == "exact-amg" and key(r)]
        if inex:
            big = max(inex, key=lambda r: r["n"])
            v["contact_n"] = big["n"]
            v["contact_vertices"] = _count(big["vertices"])
            v[f"contact_inexact_pu{tag}"] = _x(big["poisson_units"])
            v[f"contact_inexact_steps{tag}"] = big["newton_total"]
            other = _at(amg, big["n"])
            if other:
                v[f"contact_exact_amg_pu{tag}"] = _x(other["poisson_units"])
            if "energy_error" in big:
                v["contact_effectivity_mms"] = f"{big['effectivity']:.2f}"
    table = _contact_table(rows)
    v["contact_solve_date"] = d.get("machine", {}).get("date", "")[:10]
    if table:
        v["contact_table"] = table
    gen = [
        r
        for r in rows
        if r["scene"] == "default" and r["method"] == "inexact" and key(r, path="general")
    ]
    if gen:
        g = max(gen, key=lambda r: r["n"])
        dec = _at(rows, g["n"], scene="default", method="inexact", nested="auto", path="decoupled")
        if dec:
            v["general_n"] = g["n"]
            v["general_over_decoupled"] = f"{g['seconds'] / dec['seconds']:.1f}"
    naive = [r for r in rows if r["method"] == "naive" and r["scene"] == "default"]
    if naive:
        nv = max(naive, key=lambda r: r["n"])
        n = nv["n"]
        v["naive_n"] = n
        v["naive_vertices"] = _count(nv["vertices"])
        v["naive_pu"] = _x(nv["poisson_units"])
        v["naive_s"] = f"{nv['seconds']:.1f}"
        v["naive_steps"] = nv["newton_total"]
        inex = _at(rows, n, scene="default", method="inexact", nested="auto", path="decoupled")
        exact = _at(rows, n, scene="default", method="exact", nested=False, path="decoupled")
        if inex:
            v["naive_over_inexact"] = _x(nv["seconds"] / inex["seconds"])
            v["contact_inexact_pu_naive_n"] = _x(inex["poisson_units"])
        if exact:
            v["naive_over_exact"] = _x(nv["seconds"] / exact["seconds_without_estimate"])
            v["exact_steps_naive_n"] = exact["newton_total"]
        diffs = [r["max_abs_diff_u_vs_reference"] for r in rows if r["method"] == "naive"]
        v["naive_max_du"] = f"{max(diffs):.1e}"


def _contact_table(rows):
    """Markdown table: nested decoupled inexact / exact-amg per size and scene (PU, steps)."""
    lines = [
        "| n | scene | inexact: Newton steps (finest) | CG its | PU | exact-amg: steps (finest)"
        " | CG its | PU |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for n in sorted({r["n"] for r in rows}):
        for scene in ("default", "manufactured"):
            cells = []
            for method in ("inexact", "exact-amg"):
                r = _at(rows, n, scene=scene, method=method, nested="auto", path="decoupled")
                if r is None:
                    break
                cells += [
                    f"{r['newton_total']} ({r['newton_finest']})",
                    str(r["inner_total"]),
                    f"{r['poisson_units']:.2f}",
                ]
            if len(cells) == 6:
                lines.append(f"| {n} | {scene} | " + " | ".join(cells) + " |")
    return "\n".join(lines) if len(lines) > 2 else None


def _contact_pu(d, v):
    """``contact_pu.json`` (``bench.contact_solve --only-inexact``): the default solve in PU."""
    rows = d["rows"]
    lines = [
        "| n | scene | first solve (PU) | median (PU) | Newton steps (finest) | CG its | eta |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in sorted(rows, key=lambda r: (r["n"], r["scene"])):
        lines.append(
            f"| {r['n']} | {r['scene']} | {r['first_poisson_units']:.2f} | "
            f"{r['poisson_units']:.2f} | {r['newton_total']} ({r['newton_finest']}) | "
            f"{r['inner_total']} | {r['eta']:.3e} |"
        )
    v["contact_pu_table"] = "\n".join(lines)
    v["contact_pu_date"] = d.get("machine", {}).get("date", "")[:10]


def _estimate(d, v):
    big = max(d["rows"], key=lambda r: r["n"])
    v["estimate_n"] = big["n"]
    v["estimate_vertices"] = _count(big["vertices"])
    v["estimate_pu"] = f"{big['estimate_poisson_units']:.1f}"
    v["patches_per_s"] = f"{big['patches_per_s'] / 1e3:.0f}k"
    v["patches_per_s_range"] = (
        f"{min(r['patches_per_s'] for r in d['rows']) / 1e3:.0f}k–"
        f"{max(r['patches_per_s'] for r in d['rows']) / 1e3:.0f}k"
    )


def _work_precision(d, v):
    rows = d["rows"]
    inex = [r for r in rows if r["method"] == "inexact"]
    if not inex:
        return
    big = max(inex, key=lambda r: r["n"])
    v["wp_n"] = big["n"]
    if "time_over_exact_amg_time" in big:
        v["wp_time_vs_exact_amg"] = f"{big['time_over_exact_amg_time']:.2f}"
        v["wp_error_vs_exact_amg"] = f"{big['error_over_exact_amg_error']:.4f}"
    with_exact = [r for r in inex if "time_over_exact_time" in r]
    if with_exact:
        e = max(with_exact, key=lambda r: r["n"])
        v["wp_exact_n"] = e["n"]
        v["wp_time_vs_exact"] = f"{e['time_over_exact_time']:.2f}"
        v["wp_error_vs_exact"] = f"{e['error_over_exact_error']:.4f}"
    eff = [r["effectivity"] for r in rows]
    v["wp_eff_range"] = f"{min(eff):.2f}–{max(eff):.2f}"
    v["wp_bound_holds"] = "yes" if all(r["bound_holds"] for r in rows) else "NO"
    rate = d.get("rates", {}).get("inexact", {}).get("error_rate_in_h")
    if rate is not None:
        v["wp_rate"] = f"{rate:.2f}"


def _scaling(d, v):
    big = max(d["rows"], key=lambda r: r["n"])
    v["scaling_n"] = big["n"]
    v["scaling_vertices"] = _count(big["vertices"])
    v["scaling_total_s"] = f"{big['total_s']['median']:.0f}"
    v["scaling_peak_gb"] = f"{big['peak_rss_mb'] / 1024:.1f}"
    for ph, p in d.get("exponents", {}).items():
        if isinstance(p, float):
            v[f"scaling_exp_{ph}"] = f"{p:.2f}"
    for ph in d.get("phases", []):
        v[f"scaling_{ph}_s"] = f"{big['phases'][ph]['median']:.2f}"
    if "solve_poisson_units" in big:  # rows measured since the unit joined the benchmark
        v["scaling_solve_pu"] = f"{big['solve_poisson_units']:.2f}"


def _threads(d, v):
    rows = d["rows"]
    big_n = max(r["n"] for r in rows)
    v["threads_n"] = big_n
    v["threads_k"] = max(d["parameters"]["threads"])
    for r in rows:
        if r["n"] == big_n:
            v[f"threads_speedup_{r['kernel']}"] = f"{r['speedup']:.2f}"
    v["threads_identical"] = "yes" if all(r["identical"] for r in rows) else "no"
    v["threads_max_rel_diff"] = f"{max(r['max_rel_diff'] for r in rows):.1e}"


def _manycore(d, v):
    rows = [r for r in d["rows"] if "solve_s" in r and not r.get("large")]
    n = max(r["n"] for r in rows)
    for r in rows:
        if r["n"] == n and r["threads"] > 1 and "solve_speedup" in r:
            tag = f"{r.get('scene', 'default')}_{r['multigrid']}_{r['threads']}"
            v[f"manycore_solve_speedup_{tag}"] = f"{r['solve_speedup']:.2f}"
            v[f"manycore_estimate_speedup_{tag}"] = f"{r['estimate_speedup']:.2f}"
    v["manycore_n"] = n
    first = [r for r in rows if r.get("first_solve_in_process")]
    if first:
        v["manycore_first_solve_pu"] = f"{first[0]['solve_pu']:.2f}"
    user = [r for r in d["rows"] if "user_first_pu" in r]
    if user:  # the solve a user meets: before the unit, on memory not yet touched
        v["manycore_user_first_solve_pu"] = f"{user[0]['user_first_pu']:.2f}"
    if "first_touch_ms_per_mib" in d:  # the machine's cost of fresh memory (bench._common)
        v["manycore_first_touch_ms_per_mib"] = f"{d['first_touch_ms_per_mib']:.2f}"


def _exact_solve(d, v):
    diffs = [
        r["max_abs_diff_u_vs_decoupled"] for r in d["rows"] if "max_abs_diff_u_vs_decoupled" in r
    ]
    if diffs:
        v["paths_max_du"] = f"{max(diffs):.1e}"


def _unstructured(d, v):
    rows = [r for r in d["rows"] if r["nested"] == "auto"]
    big_n = max(r["n"] for r in rows)
    for r in rows:
        if r["n"] == big_n:
            key = r["scene"].replace("-", "_")
            v[f"unstructured_{key}_speedup"] = f"{r['speedup_vs_unconstrained_start']:.1f}"
            v[f"unstructured_{key}_finest"] = r["newton_finest"]
    cold = {r["scene"]: r for r in d["rows"] if r["nested"] is False and r["n"] == big_n}
    v["unstructured_n"] = big_n
    v["unstructured_cold_steps"] = "/".join(str(cold[k]["newton_finest"]) for k in sorted(cold))
    v["unstructured_auto_steps"] = "/".join(
        str(r["newton_finest"]) for r in sorted(rows, key=lambda r: r["scene"]) if r["n"] == big_n
    )


def _direct_ordering(d, v):
    spread = [x for x in d.get("spread", []) if x["system"] == "reduced-active"]
    nd = [x for x in spread if x["ordering"] == "nested-dissection"]
    if nd:
        big = max(nd, key=lambda x: x["n"])
        v["direct_n"] = big["n"]
        v["direct_nd_max_s"] = f"{big['max_seconds']:.2f}"
        v["direct_nd_time_spread"] = f"{big['seconds_spread']:.2f}"
        v["direct_nd_fill_spread"] = f"{big['fill_spread']:.2f}"
        unknowns = [
            r["unknowns"]
            for r in d["rows"]
            if r["n"] == big["n"] and r["system"] == "reduced-active"
        ]
        v["direct_unknowns"] = _count(max(unknowns))
    mmd = [x for x in spread if x["ordering"] == "MMD_AT_PLUS_A"]
    if mmd:
        m = max(mmd, key=lambda x: x["n"])
        v["direct_mmd_n"] = m["n"]
        v["direct_mmd_max_s"] = f"{m['max_seconds']:.1f}"
        v["direct_mmd_time_spread"] = _x(m["seconds_spread"])


def _adaptivity(d, v):
    cases = d.get("cases", {})
    short = {"lshape": "lshape", "manufactured": "man"}
    for name, c in cases.items():
        k = short.get(name, name)
        for key, fit in c.get("rates", {}).items():
            if isinstance(fit, dict):
                v[f"adapt_{k}_{key}_rate"] = f"{fit['rate']:.2f}"
                v[f"adapt_{k}_{key}_fit"] = (
                    f"N = {_count(fit['vertices'][0])}–{_count(fit['vertices'][1])}, "
                    f"{fit['points']} meshes"
                )
        tight = c["tolerances"][-1]
        v[f"adapt_{k}_tol"] = f"{tight['tol']:.2e}"
        v[f"adapt_{k}_vertices"] = _count(tight["vertices"])
        v[f"adapt_{k}_s"] = f"{tight['seconds']:.2f}"
        v[f"adapt_{k}_loop_over_final"] = f"{tight['loop_over_final_solve']:.2f}"
        worst = max(t["loop_over_final_solve"] for t in c["tolerances"])
        v[f"adapt_{k}_loop_over_final_worst"] = f"{worst:.2f}"
        if "uniform_n" in tight:
            v[f"adapt_{k}_uniform_n"] = tight["uniform_n"]
            v[f"adapt_{k}_uniform_vertices"] = _count(tight["uniform_vertices"])
            v[f"adapt_{k}_uniform_s"] = f"{tight['uniform_seconds']:.2f}"
            v[f"adapt_{k}_speedup"] = _x(tight["speedup_vs_uniform"])
            v[f"adapt_{k}_vertex_ratio"] = _x(tight["vertex_ratio_uniform_over_adaptive"])
        rc = c.get("refinement_cost", {})
        if rc.get("levels"):
            v[f"adapt_{k}_refine_pu_max"] = f"{rc['max']:.2f}"
            v[f"adapt_{k}_refine_pu_median"] = f"{rc['median']:.2f}"
            v[f"adapt_{k}_refine_levels"] = rc["levels"]
        eff = c.get("effectivity")
        if eff:
            v[f"adapt_{k}_eff_final"] = f"{eff['final']:.2f}"
            v[f"adapt_{k}_eff_range"] = f"{eff['min']:.2f}–{eff['max']:.2f}"
    v["adapt_table"] = _adaptivity_table(cases)
    big = d.get("big")
    if big:
        v["adapt_big_triangles"] = _count(big["triangles"])
        v["adapt_big_vertices"] = _count(big["vertices"])
        v["adapt_big_peak_gb"] = f"{big['peak_rss_mb'] / 1024:.1f}"
        v["adapt_big_s"] = f"{big['seconds']:.0f}"
        v["adapt_big_meshes"] = big["meshes"]


def _adaptivity_table(cases):
    """Markdown table: per case and tolerance, the adaptive loop against uniform refinement."""
    lines = [
        "| case | tol | adaptive: N | s | loop / final solve | uniform: n (N) | s | speed-up"
        " | N ratio |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, c in cases.items():
        for t in c["tolerances"]:
            uni = ["–"] * 4
            if "uniform_n" in t:
                uni = [
                    f"{t['uniform_n']} ({_count(t['uniform_vertices'])})",
                    f"{t['uniform_seconds']:.2f}",
                    _x(t["speedup_vs_uniform"]),
                    _x(t["vertex_ratio_uniform_over_adaptive"]),
                ]
            cells = [
                name,
                f"{t['tol']:.2e}",
                _count(t["vertices"]),
                f"{t['seconds']:.2f}",
                f"{t['loop_over_final_solve']:.2f}",
                *uni,
            ]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _coldstart(d, v):
    v["cold_s"] = f"{_med(d['cold']):.1f}"
    v["warm_s"] = f"{_med(d['warm']):.1f}"
    v["import_s"] = f"{_med(d['import']):.1f}"
    if "cold_no_helper" in d:
        v["cold_no_helper_s"] = f"{_med(d['cold_no_helper']):.1f}"
    kernels = d.get("kernel_seconds_inclusive", {})
    patch = kernels.get("fastmem.kernels.flux._reconstruct_chunk")
    if patch is not None:
        v["cold_patch_s"] = f"{patch:.1f}"


def _obstacle(d, v):
    ball = d.get("ball") or {}
    rows = ball.get("rows") or []
    if rows:
        lo, hi = ball["effectivity_range"]
        v["obstacle_ball_n"] = f"{rows[0]['n']}-{rows[-1]['n']}"
        v["obstacle_ball_eff"] = f"{lo:.2f}-{hi:.2f}"
        v["obstacle_ball_rate"] = f"{ball['min_rate_h']:.2f}" if ball["min_rate_h"] else None
        if ball.get("max_nodal_error_256") is not None:
            v["obstacle_ball_max256"] = f"{ball['max_nodal_error_256']:.3e}"
    sp = d.get("speed") or {}
    if sp:
        v["obstacle_speed_n"] = sp["n"]
        v["obstacle_speed_pu"] = f"{sp['first_pu']:.2f}"
    ad = d.get("ball_adaptive") or {}
    if ad and ad.get("rate_eta_N") is not None:
        v["obstacle_adapt_rate"] = f"{ad['rate_eta_N']:.2f}"
        v["obstacle_adapt_eff_max"] = f"{ad['effectivity_max']:.2f}"


def _peers(d, v):
    if d.get("skipped"):
        v["peers_status"] = f"skipped ({d['skipped']})"
        return
    v["peers_status"] = f"{len(d.get('rows', []))} rows"


_EXTRACT = {
    "obstacle": _obstacle,
    "peers": _peers,
    "unstructured": _unstructured,
    "assembly": _assembly,
    "poisson_unit": _poisson,
    "exact_solve": _exact_solve,
    "contact_solve": _contact,
    "contact_pu": _contact_pu,
    "estimate": _estimate,
    "work_precision": _work_precision,
    "scaling": _scaling,
    "threads": _threads,
    "manycore": _manycore,
    "direct_ordering": _direct_ordering,
    "adaptivity": _adaptivity,
    "coldstart": _coldstart,
}


def values(quick=False, folder=None):
    """All placeholder values computable from the result files."""
    out = {}
    machines = []
    for name, fn in _EXTRACT.items():
        d = load(name, quick, folder)
        if d is None or not d.get("rows"):
            continue
        try:
            fn(d, out)
        except (KeyError, ValueError, TypeError, ZeroDivisionError) as exc:
            sys.stderr.write(f"report: {name}: incomplete results ({exc!r})\n")
        machines.append(d.get("machine", {}))
    if machines:
        m = machines[0]
        vers = m.get("versions", {})
        out["machine"] = (
            f"{m.get('cores')} cores, {m.get('platform', '?')}, Python {m.get('python')}, "
            f"numba {vers.get('numba')} ({m.get('numba_threading_layer')}, "
            f"{m.get('numba_threads')} threads), numpy {vers.get('numpy')}, scipy "
            f"{vers.get('scipy')}, pyamg {vers.get('pyamg')}, BLAS threads "
            f"{m.get('fastmem_threads', {}).get('blas')}"
        )
        dates = sorted(x.get("date", "") for x in machines if x.get("date"))
        if dates:
            first, last = dates[0][:10], dates[-1][:10]
            out["dates"] = first if first == last else f"{first} – {last}"
    return out


_PLACEHOLDER = re.compile(r"\{([a-zA-Z0-9_]+)\}")


def fill(text, vals):
    """Replace each ``{name}`` with its value; unknown names stay as they are."""
    return _PLACEHOLDER.sub(lambda m: str(vals.get(m.group(1), m.group(0))), text)


def missing(text, vals):
    return sorted({m.group(1) for m in _PLACEHOLDER.finditer(text)} - set(vals))


def summary_lines(quick=False, folder=None):
    """One line of key numbers per benchmark (for ``python -m bench``)."""
    v = values(quick, folder)
    g = v.get
    lines = [
        f"assembly      n={g('assembly_n')}: fastmem {g('assembly_ratio')}x faster than "
        f"scikit-fem, max |A - A_skfem| {g('assembly_max_diff')}",
        f"poisson_unit  n={g('poisson_n')}: {g('poisson_s')} s, {g('poisson_its')} CG its, "
        f"setup {g('poisson_setup_pct')}%",
        f"exact_solve   general vs decoupled: max |du| {g('paths_max_du')}",
        f"contact_solve n={g('contact_n')}: inexact {g('contact_inexact_pu')} PU, exact-amg "
        f"{g('contact_exact_amg_pu')} PU; naive at n={g('naive_n')}: {g('naive_pu')} PU "
        f"({g('naive_over_inexact')}x inexact), max |du| {g('naive_max_du')}",
        f"estimate      n={g('estimate_n')}: {g('estimate_pu')} PU, {g('patches_per_s')} patches/s",
        f"work_prec.    n={g('wp_n')}: inexact/exact-amg time {g('wp_time_vs_exact_amg')}, "
        f"error ratio {g('wp_error_vs_exact_amg')}, effectivity {g('wp_eff_range')}, "
        f"bound holds: {g('wp_bound_holds')}",
        f"scaling       n={g('scaling_n')}: exponents mesh {g('scaling_exp_mesh')} solve "
        f"{g('scaling_exp_solve')} estimate {g('scaling_exp_estimate')} archive "
        f"{g('scaling_exp_archive')}, peak {g('scaling_peak_gb')} GB",
        f"threads       n={g('threads_n')}: speed-up flux {g('threads_speedup_flux')} "
        f"assembly {g('threads_speedup_assembly')}, identical: {g('threads_identical')}",
        f"unstructured  n={g('unstructured_n')}: auxiliary coarse meshes "
        f"{g('unstructured_square_default_speedup')}x (square, default scene), "
        f"{g('unstructured_square_manufactured_speedup')}x (manufactured), "
        f"{g('unstructured_disk_default_speedup')}x (gmsh disk) faster than the "
        f"unconstrained start; finest steps {g('unstructured_auto_steps')} vs "
        f"{g('unstructured_cold_steps')}",
        f"direct_order. n={g('direct_n')} ({g('direct_unknowns')} unknowns): nested "
        f"dissection {g('direct_nd_max_s')} s, spread over meshes {g('direct_nd_time_spread')}x "
        f"time {g('direct_nd_fill_spread')}x fill; MMD as given at n={g('direct_mmd_n')}: "
        f"{g('direct_mmd_max_s')} s, spread {g('direct_mmd_time_spread')}x",
        f"adaptivity    L-shape: eta ~ N^-{g('adapt_lshape_adaptive_eta_rate')} adaptive, "
        f"N^-{g('adapt_lshape_uniform_eta_rate')} uniform; eta <= {g('adapt_lshape_tol')}: "
        f"{g('adapt_lshape_speedup')}x faster, {g('adapt_lshape_vertex_ratio')}x fewer vertices "
        f"than uniform n={g('adapt_lshape_uniform_n')}; loop/final solve "
        f"{g('adapt_lshape_loop_over_final')}; refine {g('adapt_lshape_refine_pu_max')} PU/level "
        f"(max); manufactured effectivity {g('adapt_man_eff_final')} (final level); big: "
        f"{g('adapt_big_triangles')} triangles, {g('adapt_big_peak_gb')} GB",
        f"obstacle      ball n={g('obstacle_ball_n')}: effectivity {g('obstacle_ball_eff')}, rate "
        f"{g('obstacle_ball_rate')}, max nodal error at 256 {g('obstacle_ball_max256')} (PETSc "
        f"9.34e-5); adaptive rate {g('obstacle_adapt_rate')} in N, effectivity <= "
        f"{g('obstacle_adapt_eff_max')}; first solve n={g('obstacle_speed_n')}: "
        f"{g('obstacle_speed_pu')} PU",
        f"peers         PETSc SNES VI: {g('peers_status')}",
    ]
    return lines


def _plots_available():
    """True when matplotlib can be imported (figures are drawn)."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def figures(quick=False, folder=None):
    """Redraw every benchmark figure from its JSON; return the written paths."""
    from bench import _plots

    out = []
    folder = Path(folder or results_dir())
    for name in BENCHMARKS:
        d = load(name, quick, folder)
        if d is None:
            continue
        png = _plots.figure(name, d, folder / f"{result_name(name, quick)}.png")
        if png is not None:
            out.append(png)
    return out


def section(text, strict=False):
    """The text between the markers (without them, and not ``strict``: all of ``text``)."""
    if BEGIN not in text or END not in text:
        if strict:
            raise ValueError(f"the markers {BEGIN} and {END} are missing")
    return text.split(BEGIN, 1)[-1].split(END, 1)[0]


def replace_section(page_text, body):
    """``page_text`` with the text between its markers replaced by ``body``."""
    head, rest = page_text.split(BEGIN, 1)
    tail = rest.split(END, 1)[1]
    body = body.strip("\n")
    return f"{head}{BEGIN}\n{body}\n{END}{tail}"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="read the *_quick.json files")
    p.add_argument("--results", type=Path, default=None)
    p.add_argument("--template", type=Path, default=TEMPLATE)
    p.add_argument("--figures", action="store_true", help="redraw the PNG figures too")
    p.add_argument("--missing", action="store_true", help="list unfilled placeholders")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument(
        "--write", action="store_true", help="replace the section between the markers of --doc"
    )
    mode.add_argument(
        "--check",
        action="store_true",
        help="write nothing; exit with status 1 when the section of --doc is out of date",
    )
    p.add_argument(
        "--doc",
        type=Path,
        default=DOC,
        help="the page that holds the section (docs/performance.md)",
    )
    args = p.parse_args(argv)
    if args.write and args.quick and args.doc.resolve() == DOC:
        p.error("--quick results are not for publishing: give --doc to write them elsewhere")
    vals = values(args.quick, args.results)
    body = section(args.template.read_text())
    filled = fill(body.strip("\n"), vals)
    status = 0
    if args.write or args.check:
        page = args.doc.read_text(encoding="utf-8")
        try:
            current = section(page, strict=True)
        except ValueError as exc:
            p.error(f"{args.doc}: {exc}")
        if current.strip("\n") == filled:
            sys.stderr.write(f"{args.doc}: the section is up to date\n")
        elif args.check:
            sys.stderr.write(f"{args.doc}: the section differs from the filled template\n")
            status = 1
        else:
            args.doc.write_text(replace_section(page, filled), encoding="utf-8")
            sys.stderr.write(f"wrote the section of {args.doc}\n")
    else:
        sys.stdout.write(filled + "\n")
    if args.missing:
        sys.stderr.write("unfilled: " + ", ".join(missing(body, vals)) + "\n")
    if args.figures:
        for path in figures(args.quick, args.results):
            sys.stderr.write(f"wrote {path}\n")
    return status


if __name__ == "__main__":
    sys.exit(main())
