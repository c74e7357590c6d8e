"""Adaptive against uniform refinement: eta and error against N, time to a tolerance.

Two cases:

* ``lshape``: the L-shaped domain (-1, 1)^2 minus [0, 1) x (-1, 0] with the
  default data (mu = (1, 1), f = (-1, 1), g = 0.1); the true error is unknown.
* ``manufactured``: the default manufactured solution of docs/method.md §7 on
  the square (-1, 1)^2; the true energy error is computed on every mesh
  (``Manufactured.energy_error``, quadrature of degree 7).

Uniform refinement: the structured meshes ``Mesh.lshape(n)`` /
``Mesh.square(n)`` for n = 16, 32, ..., ``--uniform-max``, each solved by
``fm.solve(scene)`` (inexact Newton-min, nested iteration over the coarser
structured meshes, the guaranteed bound of the returned triple).  Timed: a
fresh scene on the mesh (loads, assembly, nested iteration, bound); the mesh
and its topology are built before the timing (``mesh_seconds`` on its own).

Adaptive refinement: ``fm.solve(scene, tol=tol, theta=--theta,
min_growth=--min-growth, bisections=--bisections)`` from the
coarsest uniform mesh (n = ``--start``), the public call, timed as a whole
(the mesh of n = ``--start`` built inside the timing).  Tolerances: by
default the bound eta reached by uniform refinement (times 1 + 1e-6, so that
uniform refinement needs exactly that n) at n = uniform-max/4, uniform-max/2
and uniform-max on the L-shape (the tightest: the tightest tolerance uniform
refinement reaches by n = uniform-max), and at n = uniform-max/8, /4, /2 for
the manufactured solution (smooth: adaptive refinement needs about as many
vertices as uniform there, and 5M vertices at n = 2048 would double the run
time and approach the machine's memory); ``--tol-n-lshape`` /
``--tol-n-manufactured`` choose other n, ``--tols-lshape`` /
``--tols-manufactured`` set the tolerances themselves.  For each tolerance:
the loop's time against the time of the uniform solve at the smallest n of
the doubling sequence whose eta <= tol (and against the whole doubling
sequence up to that n), the vertex counts, and the loop's time against a
solve from scratch with the same method on the final adapted mesh
(``fm.solve(scene_on_final_mesh)``: auxiliary coarse meshes for nested
iteration, as for any mesh without a coarser version; topology built).

One more adaptive run per case at the tightest tolerance, not timed as a
whole, records each level's solution (``fastmem.adapt.loop``'s per-mesh solve is
wrapped): the true energy error and the effectivity eta / error per level
(manufactured case), and the Poisson unit of every level mesh with at least
``--refine-min-vertices`` vertices, so that each level's refinement time
(marking, bisection with closure, new mesh structures, moving the scene and
the triple: the ``refine_seconds`` column of ``result.adaptivity``, median
over the timed runs) is expressed in Poisson units of the mesh it refines.
Its meshes are checked to be the timed runs' meshes (``matches_timed_meshes``).

Rates: least-squares slope of log eta (and log error) against log N over the
points with N >= ``--fit-min-vertices`` ("asymptotic part"; the points used
are recorded), p in eta ~ N^-p.  Times are medians of up to ``--repeat``
runs (fewer once a measurement has used ``--budget`` seconds), after a
warm-up of every kind of run on tiny meshes (its first-call times are
recorded: JIT cache loading); ``first`` is the first timed repetition.
Poisson units: ``bench._common.poisson_unit`` on the same mesh, same run.

``--big`` adds a separate stage in a subprocess (its own peak RSS): the
adaptive loop on the L-shape with ``--big-tol`` (unreachably small) and
``--big-max-vertices`` (default 6M), recording the triangles reached, the
peak resident memory and the time; ``--big-only`` runs only that stage and
merges it into the existing result file.  ``--merge`` (with ``--cases``)
likewise replaces only the cases measured now and records, per case, the
run that measured it (``cases_measured``).

    python -m bench.adaptivity [--quick] [--uniform-max 2048] [--big | --big-only]

Expected duration on the 2-core reference machine (extrapolated from a run
with ``--uniform-max 512``, 3 minutes): ``--quick`` about 10 s; the full run
(uniform-max 2048) about 20-25 minutes (L-shape ~7, manufactured ~13; the
uniform solves at n = 2048 and the adaptive manufactured loop to about 1.3M
vertices dominate), peak memory that of the uniform square n = 2048 (about
12-16 GB); ``--big`` adds about 10-15 minutes and up to about 20 GB.
"""

import math
import statistics
import time

import numpy as np

from bench._common import (
    emit_worker_result,
    finish,
    fit_exponent,
    parse,
    parser,
    peak_rss_mb,
    poisson_unit,
    progress,
    run_worker,
    summary,
)

CASES = ("lshape", "manufactured")
QUICK_UNIFORM_MAX = 64
FULL_UNIFORM_MAX = 2048
TOL_SLACK = 1e-6  # tolerance = uniform eta * (1 + TOL_SLACK)
MODULE = __spec__.name if __spec__ is not None else "bench.adaptivity"


# ------------------------------------------------------------------ the two cases


class Case:
    """Mesh generator, scene factory and (optionally) the exact solution of one case."""

    def __init__(self, name):
        import fastmem as fm

        self.name = name
        self.manufactured = fm.Manufactured() if name == "manufactured" else None
        self._mesh = fm.Mesh.square if name == "manufactured" else fm.Mesh.lshape

    def mesh(self, n):
        return self._mesh(n)

    def scene(self, mesh):
        import fastmem as fm

        if self.manufactured is not None:
            return self.manufactured.scene(mesh)
        return fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)

    def error(self, mesh, u1, u2):
        if self.manufactured is None:
            return None
        return float(self.manufactured.energy_error(mesh, u1, u2))


def _prepare(mesh):
    """Mesh topology built outside the timings (as in bench.contact_solve)."""
    _ = mesh.edges, mesh.triangle_edges, mesh.edge_triangles, mesh.patch_ptr
    _ = mesh.interior_vertices, mesh.boundary_vertices, mesh.lumped_mass


def _repeat(fn, repeat, budget, keep=None):
    """Run ``fn`` up to ``repeat`` times (at least once, stop once ``budget`` s are used).

    Returns (last output, summary of the seconds with ``first``, [keep(output) per run]).
    The previous output is dropped before the next run (memory of large meshes).
    """
    times, kept, out = [], [], None
    while len(times) < max(1, repeat):
        out = None
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
        if keep is not None:
            kept.append(keep(out))
        if sum(times) > budget:
            break
    stats = summary(times)
    stats["first"] = times[0]
    return out, stats, kept


def _unit(mesh, repeat):
    """Poisson unit of ``mesh``; fewer repetitions on meshes of a million vertices and more."""
    big = mesh.n_vertices >= 1_000_000
    info = poisson_unit(mesh, repeat=min(repeat, 2) if big else repeat, warmup=0 if big else 1)
    return {k: info[k] for k in ("seconds", "iterations", "unknowns", "relative_residual")}


def _fit(points, min_vertices):
    """Rate p of y ~ N^-p over the points (N, y, label) with N >= min_vertices."""
    pts = [(n, y, lab) for n, y, lab in points if n >= min_vertices and y is not None and y > 0]
    if len(pts) < 2:
        return None
    slope = fit_exponent([p[0] for p in pts], [p[1] for p in pts])
    if slope is None:
        return None
    return {
        "rate": -slope,
        "min_vertices": min_vertices,
        "points": len(pts),
        "from": pts[0][2],
        "to": pts[-1][2],
        "vertices": [pts[0][0], pts[-1][0]],
    }


# ------------------------------------------------------------------ warm-up


def warm_up():
    """A tiny run of every kind (JIT caches loaded / compiled): first and second call times."""
    import fastmem as fm

    out = {}
    for name in CASES:
        case = Case(name)
        for kind in ("uniform", "adaptive"):
            calls = []
            for _ in range(2):
                mesh = case.mesh(8)
                t0 = time.perf_counter()
                if kind == "uniform":
                    r = fm.solve(case.scene(mesh))
                else:
                    r = fm.solve(case.scene(mesh), tol=0.5 * fm.solve(case.scene(mesh)).eta)
                if case.manufactured is not None:
                    case.error(r.mesh, r.u1, r.u2)
                calls.append(time.perf_counter() - t0)
            out[f"{name}_{kind}"] = {"first_call_s": calls[0], "second_call_s": calls[1]}
    t0 = time.perf_counter()
    poisson_unit(fm.Mesh.square(8), repeat=1, warmup=0)
    out["poisson_unit_first_call_s"] = time.perf_counter() - t0
    progress(
        "adaptivity: warm-up "
        + ", ".join(f"{k} {v['first_call_s']:.2f} s" for k, v in out.items() if isinstance(v, dict))
    )
    return out


# ------------------------------------------------------------------ uniform refinement


def uniform(case, sizes, a):
    """One row per uniform mesh: eta, error, timed solve, Poisson unit."""
    import fastmem as fm

    rows = []
    elapsed = 0.0
    for n in sizes:
        t0 = time.perf_counter()
        mesh = case.mesh(n)
        _prepare(mesh)
        mesh_s = time.perf_counter() - t0
        unit = _unit(mesh, a.repeat)
        r, t, etas = _repeat(
            lambda m=mesh: fm.solve(case.scene(m)),
            a.repeat,
            a.budget,
            keep=lambda r: float(r.eta),
        )
        elapsed += t["median"]
        est = r.estimate.totals
        row = {
            "case": case.name,
            "kind": "uniform",
            "n": n,
            "vertices": mesh.n_vertices,
            "triangles": mesh.n_triangles,
            "eta": float(r.eta),
            "eta_disc": float(est["eta_disc"]),
            "eta_lin": float(est["eta_lin"]),
            "eta_alg": float(est["eta_alg"]),
            "eta_spread_over_runs": max(etas) - min(etas),
            "converged": bool(r.converged),
            "newton_finest": int(r.n_newton),
            "newton_total": int(sum(lv["newton"] for lv in r.parameters["solver"]["levels"])),
            "seconds": t["median"],
            "seconds_stats": t,
            "mesh_seconds": mesh_s,
            "sequence_seconds": elapsed,  # doubling sequence n = 16 .. this n (medians)
            "poisson": unit,
            "poisson_units": t["median"] / unit["seconds"],
            "peak_rss_mb": peak_rss_mb(),
        }
        err = case.error(mesh, r.u1, r.u2)
        if err is not None:
            row["energy_error"] = err
            row["effectivity"] = row["eta"] / err
        rows.append(row)
        extra = f" err {err:.3e} eff {row['effectivity']:.3f}" if err is not None else ""
        progress(
            f"adaptivity: {case.name:12s} uniform n={n:5d} N={mesh.n_vertices:8d} "
            f"eta {row['eta']:.4e}{extra}  {t['median']:.3f} s = {row['poisson_units']:.2f} PU"
        )
        r = mesh = None  # free the large mesh before the next one
    return rows


def default_tolerances(rows, sizes):
    """Uniform eta at the sizes n (times 1 + TOL_SLACK), loosest first."""
    return [r["eta"] * (1.0 + TOL_SLACK) for r in rows if r["n"] in sizes]


def tolerance_sizes(name, sizes, given):
    """The n whose uniform eta are the tolerances of case ``name`` (module docstring)."""
    if given:
        bad = sorted(set(given) - set(sizes))
        if bad:
            raise SystemExit(f"--tol-n-{name}: {bad} not in the uniform sequence {sizes}")
        return sorted(given)
    if name == "manufactured" and len(sizes) >= 4:
        return sizes[-4:-1]
    return sizes[-3:]


def uniform_match(rows, tol):
    """The first row of the doubling sequence with eta <= tol, or None."""
    return next((r for r in rows if r["eta"] <= tol), None)


# ------------------------------------------------------------------ adaptive refinement


def _adaptive_call(case, tol, a):
    import fastmem as fm

    return fm.solve(
        case.scene(case.mesh(a.start)),
        tol=tol,
        theta=a.theta,
        min_growth=a.min_growth,
        bisections=a.bisections,
        max_vertices=a.max_vertices,
    )


def _table_lists(table):
    return {k: np.asarray(v).tolist() for k, v in table.items()}


def adaptive_runs(case, tols, urows, a):
    """Timed adaptive loops, one record per tolerance (loosest first)."""
    import fastmem as fm

    records = []
    for tol in tols:
        r, t, tables = _repeat(
            lambda tol=tol: _adaptive_call(case, tol, a),
            a.repeat,
            a.budget,
            keep=lambda r: r.adaptivity,
        )
        info = r.parameters["adaptivity"]
        table = r.adaptivity
        final = r.mesh
        # the final level's solve alone, from scratch, same method, on the final adapted mesh
        r_final, t_final, _ = _repeat(lambda m=final: fm.solve(case.scene(m)), a.repeat, a.budget)
        unit = _unit(final, a.repeat)
        same = all(np.array_equal(x["n_vertices"], table["n_vertices"]) for x in tables)
        rec = {
            "case": case.name,
            "tol": tol,
            "converged": bool(info["converged"]),
            "stop_reason": info["stop_reason"],
            "meshes": int(info["meshes"]),
            "vertices": final.n_vertices,
            "triangles": final.n_triangles,
            "eta": float(r.eta),
            "seconds": t["median"],
            "seconds_stats": t,
            "poisson_final_mesh": unit,
            "poisson_units": t["median"] / unit["seconds"],
            "solve_seconds_sum": float(table["solve_seconds"].sum()),
            "refine_seconds_sum": float(table["refine_seconds"].sum()),
            "same_meshes_every_run": bool(same),
            "refine_seconds_per_run": [x["refine_seconds"].tolist() for x in tables]
            if same
            else None,
            "table": _table_lists(table),
            "final_solve_seconds": t_final["median"],
            "final_solve_stats": t_final,
            "final_solve_eta": float(r_final.eta),
            "final_solve_newton": int(r_final.n_newton),
            "loop_over_final_solve": t["median"] / t_final["median"],
            "peak_rss_mb": peak_rss_mb(),
        }
        err = case.error(final, r.u1, r.u2)
        if err is not None:
            rec["energy_error"] = err
            rec["effectivity"] = rec["eta"] / err
        u = uniform_match(urows, tol)
        if u is not None:
            rec["uniform_n"] = u["n"]
            rec["uniform_vertices"] = u["vertices"]
            rec["uniform_eta"] = u["eta"]
            rec["uniform_seconds"] = u["seconds"]
            rec["uniform_sequence_seconds"] = u["sequence_seconds"]
            rec["uniform_with_mesh_seconds"] = u["seconds"] + u["mesh_seconds"]
            rec["speedup_vs_uniform"] = u["seconds"] / t["median"]
            rec["speedup_vs_uniform_sequence"] = u["sequence_seconds"] / t["median"]
            rec["vertex_ratio_uniform_over_adaptive"] = u["vertices"] / final.n_vertices
        records.append(rec)
        vs = (
            f"uniform n={u['n']} {u['seconds']:.2f} s: {rec['speedup_vs_uniform']:.2f}x, "
            f"vertices {rec['vertex_ratio_uniform_over_adaptive']:.1f}x"
            if u is not None
            else "uniform never reached it"
        )
        progress(
            f"adaptivity: {case.name:12s} tol {tol:.4e}: {rec['meshes']} meshes, "
            f"N={final.n_vertices}, eta {rec['eta']:.4e}, loop {t['median']:.2f} s "
            f"({rec['poisson_units']:.1f} PU), final solve alone {t_final['median']:.2f} s "
            f"(loop/final {rec['loop_over_final_solve']:.2f}); {vs}"
        )
        r = r_final = final = None
    return records


def trace(case, tol, a):
    """Per-level solutions of one adaptive loop: error, effectivity, Poisson unit of the mesh.

    Wraps the per-mesh solve of :mod:`fastmem.adapt.loop` (not timed as a whole).
    Without that hook (renamed), reruns the loop with ``max_levels = 1, 2, ...``.
    """
    import fastmem.adapt.loop as afem

    levels = []
    last = [None]  # the mesh of the last entry: a second solve on it replaces the entry

    def record(mesh, u1, u2):
        again = last[0] is mesh
        row = {"vertices": mesh.n_vertices, "triangles": mesh.n_triangles}
        err = case.error(mesh, u1, u2)
        if err is not None:
            row["energy_error"] = err
        if again and "poisson" in levels[-1]:
            row["poisson"] = levels[-1]["poisson"]
        elif mesh.n_vertices >= a.refine_min_vertices:
            row["poisson"] = _unit(mesh, 1)
        if again:
            levels[-1] = row
        else:
            levels.append(row)
            last[0] = mesh

    inner = getattr(afem, "solve_levels", None)
    if inner is not None:

        def wrapped(scene, *args, **kwargs):
            res = inner(scene, *args, **kwargs)
            record(scene.mesh, res.u1, res.u2)
            return res

        afem.solve_levels = wrapped
        try:
            r = _adaptive_call(case, tol, a)
        finally:
            afem.solve_levels = inner
        method = "wrapped fastmem.adapt.loop.solve_levels"
    else:  # pragma: no cover - fallback
        import fastmem as fm

        r = _adaptive_call(case, tol, a)
        for k in range(1, len(r.adaptivity["level"]) + 1):
            rk = fm.solve(
                case.scene(case.mesh(a.start)),
                tol=tol,
                theta=a.theta,
                min_growth=a.min_growth,
        bisections=a.bisections,
                max_vertices=a.max_vertices,
                max_levels=k,
            )
            record(rk.mesh, rk.u1, rk.u2)
        method = "reruns with max_levels = 1, 2, ..."
    table = r.adaptivity
    matches = len(levels) == len(table["level"]) and all(
        lv["vertices"] == nv for lv, nv in zip(levels, table["n_vertices"].tolist(), strict=False)
    )
    for i, lv in enumerate(levels[: len(table["level"])]):
        lv["level"] = int(table["level"][i])
        lv["eta"] = float(table["eta"][i])
        if "energy_error" in lv:
            lv["effectivity"] = lv["eta"] / lv["energy_error"]
    return {"method": method, "matches_table": bool(matches), "levels": levels, "table": table}


def adaptive_rows(case, tr, timed):
    """One row per adaptive level (the traced loop at the tightest tolerance)."""
    table = tr["table"]
    refine = table["refine_seconds"].tolist()
    # per-level refinement time: median over the timed runs when they built the same meshes
    same = (
        tr["matches_table"]
        and timed["same_meshes_every_run"]
        and timed["table"]["n_vertices"] == table["n_vertices"].tolist()
    )
    if same:
        refine = [
            statistics.median(col) for col in zip(*timed["refine_seconds_per_run"], strict=True)
        ]
    rows = []
    for i, lv in enumerate(tr["levels"]):
        row = {
            "case": case.name,
            "kind": "adaptive",
            "level": lv.get("level", i),
            "vertices": lv["vertices"],
            "triangles": lv["triangles"],
            "eta": lv.get("eta"),
            "eta_disc": float(table["eta_disc"][i]),
            "eta_lin": float(table["eta_lin"][i]),
            "eta_alg": float(table["eta_alg"][i]),
            "marked_fraction": float(table["marked_fraction"][i]),
            "newton": int(table["newton"][i]),
            "solve_seconds_traced": float(table["solve_seconds"][i]),
            "refine_seconds": refine[i],
            "refine_seconds_source": "median of the timed runs" if same else "traced run",
        }
        for key in ("energy_error", "effectivity"):
            if key in lv:
                row[key] = lv[key]
        if "poisson" in lv:
            row["poisson"] = lv["poisson"]
            row["refine_poisson_units"] = refine[i] / lv["poisson"]["seconds"]
        rows.append(row)
    return rows


def refinement_cost(rows, min_vertices):
    """Max and median of refine_seconds / PU over the refined levels with N >= min_vertices."""
    pts = [
        r
        for r in rows
        if r["vertices"] >= min_vertices
        and r["marked_fraction"] > 0
        and "refine_poisson_units" in r
    ]
    if not pts:
        return {"min_vertices": min_vertices, "levels": 0}
    pu = [r["refine_poisson_units"] for r in pts]
    return {
        "min_vertices": min_vertices,
        "levels": len(pts),
        "level_range": [pts[0]["level"], pts[-1]["level"]],
        "vertices_range": [pts[0]["vertices"], pts[-1]["vertices"]],
        "max": max(pu),
        "median": statistics.median(pu),
        "max_seconds": max(r["refine_seconds"] for r in pts),
    }


# ------------------------------------------------------------------ one case


def run_case(name, a, tols=None, tol_n=None):
    case = Case(name)
    sizes = [16 * 2**k for k in range(int(math.log2(a.uniform_max // 16)) + 1)]
    tol_n = tolerance_sizes(name, sizes, tol_n)
    urows = uniform(case, sizes, a)
    given = bool(tols)
    tols = sorted(tols, reverse=True) if given else default_tolerances(urows, tol_n)
    records = adaptive_runs(case, tols, urows, a)
    tightest = records[-1]
    tr = trace(case, tightest["tol"], a)
    arows = adaptive_rows(case, tr, tightest)
    progress(
        f"adaptivity: {name:12s} traced loop ({tr['method']}): {len(arows)} levels, "
        f"same meshes as the timed runs: {tr['matches_table']}"
    )
    for r in arows:
        extra = ""
        if "effectivity" in r:
            extra += f" err {r['energy_error']:.3e} eff {r['effectivity']:.3f}"
        if "refine_poisson_units" in r:
            extra += f" refine {r['refine_seconds']:.3f} s = {r['refine_poisson_units']:.3f} PU"
        progress(f"    level {r['level']:3d} N={r['vertices']:8d} eta {r['eta']:.4e}{extra}")

    def pts(rows, key, label):
        return [(r["vertices"], r.get(key), r[label]) for r in rows]

    rates = {
        "uniform_eta": _fit(pts(urows, "eta", "n"), a.fit_min_vertices),
        "adaptive_eta": _fit(pts(arows, "eta", "level"), a.fit_min_vertices),
        "uniform_local_eta": [
            -math.log(q["eta"] / p["eta"]) / math.log(q["vertices"] / p["vertices"])
            for p, q in zip(urows, urows[1:], strict=False)
        ],
    }
    if case.manufactured is not None:
        rates["uniform_error"] = _fit(pts(urows, "energy_error", "n"), a.fit_min_vertices)
        rates["adaptive_error"] = _fit(pts(arows, "energy_error", "level"), a.fit_min_vertices)
    for key, fit in rates.items():
        if isinstance(fit, dict):
            progress(
                f"adaptivity: {name:12s} rate {key:15s} p = {fit['rate']:.3f} over "
                f"{fit['points']} points, N {fit['vertices'][0]}..{fit['vertices'][1]}"
            )
    out = {
        "rows": urows + arows,
        "tolerances": records,
        "rates": rates,
        "refinement_cost": refinement_cost(arows, a.refine_min_vertices),
        "trace": {"method": tr["method"], "matches_timed_meshes": tr["matches_table"]},
        "tolerance_sizes": None if given else tol_n,
    }
    eff = [r["effectivity"] for r in arows if "effectivity" in r]
    if eff:
        out["effectivity"] = {"final": eff[-1], "min": min(eff), "max": max(eff)}
    return out


# ------------------------------------------------------------------ targets


def targets(cases, big=None):
    """The issue's targets, with the measured values (None when not measured)."""
    out = []

    def add(name, value, target, ok):
        out.append({"name": name, "value": value, "target": target, "met": ok})

    ls = cases.get("lshape")
    if ls:
        fit = ls["rates"]["adaptive_eta"]
        p = fit["rate"] if fit else None
        add("lshape adaptive rate p", p, ">= 0.45", p is not None and p >= 0.45)
        fit = ls["rates"]["uniform_eta"]
        p = fit["rate"] if fit else None
        add("lshape uniform rate p", p, "near 1/3", None)
        tight = ls["tolerances"][-1]
        s = tight.get("speedup_vs_uniform")
        add("lshape speed-up at the tightest tol", s, ">= 10", s is not None and s >= 10)
        v = tight.get("vertex_ratio_uniform_over_adaptive")
        add("lshape vertex ratio at the tightest tol", v, ">= 10", v is not None and v >= 10)
    for name, c in cases.items():
        tight = c["tolerances"][-1]["loop_over_final_solve"]
        add(f"{name} loop / final solve (tightest tol)", tight, "<= 3", tight <= 3)
        worst = max(rec["loop_over_final_solve"] for rec in c["tolerances"])
        add(f"{name} loop / final solve (worst tol)", worst, "<= 3", worst <= 3)
        rc = c["refinement_cost"]
        if rc.get("levels"):
            add(f"{name} refinement PU per level (max)", rc["max"], "<= 0.2", rc["max"] <= 0.2)
            add(f"{name} refinement PU per level (median)", rc["median"], "<= 0.2", None)
    man = cases.get("manufactured")
    if man and "effectivity" in man:
        e = man["effectivity"]["final"]
        add("manufactured effectivity (final level)", e, "<= 1.3", e <= 1.3)
    if big:
        m = big["triangles"]
        add("big stage: triangles reached", m, ">= 10M", m >= 10_000_000)
        add(
            "big stage: peak RSS (GB)",
            big["peak_rss_mb"] / 1024,
            "< 24",
            big["peak_rss_mb"] < 24 * 1024,
        )
    return out


def _print_targets(rows):
    for t in rows:
        v = t["value"]
        met = "" if t["met"] is None else ("met" if t["met"] else "NOT met")
        progress(
            f"adaptivity target: {t['name']:45s} {'-' if v is None else f'{v:.3f}':>8s} "
            f"(target {t['target']}) {met}"
        )


# ------------------------------------------------------------------ the big stage


def big_worker(a):
    """Subprocess: one adaptive loop on the L-shape to ``--big-max-vertices``."""
    import fastmem as fm

    case = Case("lshape")
    fm.solve(case.scene(case.mesh(8)), tol=0.05)  # JIT caches

    def monitor(row):
        progress(
            f"adaptivity big: level {row['level']:3d} N={row['n_vertices']:9d} "
            f"M={row['n_triangles']:9d} eta {row['eta']:.4e} solve {row['solve_seconds']:.1f} s "
            f"refine {row['refine_seconds']:.2f} s, peak RSS {peak_rss_mb() / 1024:.1f} GB"
        )

    t0 = time.perf_counter()
    r = fm.solve(
        case.scene(case.mesh(a.start)),
        tol=a.big_tol,
        theta=a.theta,
        min_growth=a.min_growth,
        bisections=a.bisections,
        max_vertices=a.big_max_vertices,
        time_budget=a.big_time_budget,
        level_monitor=monitor,
    )
    seconds = time.perf_counter() - t0
    info = r.parameters["adaptivity"]
    emit_worker_result(
        {
            "tol": a.big_tol,
            "max_vertices": a.big_max_vertices,
            "time_budget": a.big_time_budget,
            "stop_reason": info["stop_reason"],
            "meshes": int(info["meshes"]),
            "vertices": r.mesh.n_vertices,
            "triangles": r.mesh.n_triangles,
            "eta": float(r.eta),
            "seconds": seconds,
            "peak_rss_mb": peak_rss_mb(),
            "table": _table_lists(r.adaptivity),
        }
    )


def big_stage(a):
    args = [
        "--big-worker",
        "--start",
        a.start,
        "--theta",
        a.theta,
        "--min-growth",
        a.min_growth,
        "--bisections",
        a.bisections,
        "--big-tol",
        a.big_tol,
        "--big-max-vertices",
        a.big_max_vertices,
    ]
    if a.big_time_budget is not None:
        args += ["--big-time-budget", a.big_time_budget]
    out = run_worker(MODULE, args)
    out["reached_10M_triangles"] = out["triangles"] >= 10_000_000
    progress(
        f"adaptivity big: {out['meshes']} meshes, {out['triangles']} triangles "
        f"({out['vertices']} vertices), eta {out['eta']:.3e}, {out['seconds']:.0f} s, "
        f"peak RSS {out['peak_rss_mb'] / 1024:.2f} GB; {out['stop_reason']}"
    )
    return out


# ------------------------------------------------------------------ merging a stage


def _merged(payload, a):
    """The existing result file with the cases of ``payload`` (measured now) replaced.

    Each case records the run that measured it (``cases_measured``: date, parameters,
    warm-up of that run); the other cases and the big stage are kept as they were.
    """
    from bench.report import load

    old = load("adaptivity", a.quick)
    if old is None:
        return payload
    stamp = {
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "parameters": payload["parameters"],
        "warmup": payload["warmup"],
        "seconds_total_main": payload["seconds_total_main"],
    }
    measured = old.get("cases_measured") or {
        name: {"parameters": old.get("parameters"), "note": "full run before --merge existed"}
        for name in old.get("cases", {})
    }
    for name, case in payload["cases"].items():
        old.setdefault("cases", {})[name] = case
        measured[name] = stamp
    old["cases_measured"] = measured
    new_rows = {r["case"] for r in payload["rows"]}
    old["rows"] = [r for r in old.get("rows", []) if r["case"] not in new_rows] + payload["rows"]
    if "big" in payload:
        old["big"] = payload["big"]
    for key in ("benchmark", "quick", "machine"):
        old.pop(key, None)
    return old


# ------------------------------------------------------------------ main


def main(argv=None):
    p = parser(__doc__)
    p.add_argument("--uniform-max", type=int, default=None, help="largest uniform n (power of 2)")
    p.add_argument("--start", type=int, default=16, help="n of the adaptive loop's first mesh")
    p.add_argument("--theta", type=float, default=0.5, help="Dörfler parameter")
    p.add_argument(
        "--min-growth", type=float, default=1.0, help="least vertex growth per refinement"
    )
    p.add_argument(
        "--bisections", type=int, default=2, help="rounds of bisection per refinement"
    )
    p.add_argument("--tols-lshape", type=float, nargs="*", default=None)
    p.add_argument("--tols-manufactured", type=float, nargs="*", default=None)
    p.add_argument("--tol-n-lshape", type=int, nargs="*", default=None)
    p.add_argument("--tol-n-manufactured", type=int, nargs="*", default=None)
    p.add_argument("--cases", nargs="*", choices=CASES, default=list(CASES))
    p.add_argument("--max-vertices", type=int, default=6_000_000, help="of the timed loops")
    p.add_argument("--budget", type=float, default=100.0, help="stop repeating after this")
    p.add_argument("--fit-min-vertices", type=int, default=None, help="rates: N >= this")
    p.add_argument("--refine-min-vertices", type=int, default=None, help="refinement in PU: N >=")
    p.add_argument("--big", action="store_true", help="add the large adaptive stage")
    p.add_argument("--big-only", action="store_true", help="only the large stage (merged)")
    p.add_argument("--big-tol", type=float, default=1e-5)
    p.add_argument("--big-max-vertices", type=int, default=6_000_000)
    p.add_argument("--big-time-budget", type=float, default=None)
    p.add_argument("--big-worker", action="store_true", help="(internal) the big stage itself")
    p.add_argument(
        "--merge",
        action="store_true",
        help="replace only the --cases measured now in the existing result file",
    )
    a = parse(p, argv)
    if a.big_worker:
        big_worker(a)
        return
    if a.uniform_max is None:
        a.uniform_max = QUICK_UNIFORM_MAX if a.quick else FULL_UNIFORM_MAX
    if a.uniform_max < 64 or a.uniform_max & (a.uniform_max - 1):
        p.error("--uniform-max must be a power of 2, at least 64")
    if a.quick and a.repeat == p.get_default("repeat"):
        a.repeat = 1
    if a.fit_min_vertices is None:
        a.fit_min_vertices = 0 if a.quick else 10_000
    if a.refine_min_vertices is None:
        a.refine_min_vertices = 0 if a.quick else 100_000
    params = {
        k: getattr(a, k)
        for k in (
            "quick",
            "uniform_max",
            "start",
            "theta",
            "min_growth",
            "bisections",
            "repeat",
            "budget",
            "max_vertices",
            "fit_min_vertices",
            "refine_min_vertices",
            "tols_lshape",
            "tols_manufactured",
            "tol_n_lshape",
            "tol_n_manufactured",
            "big",
            "big_tol",
            "big_max_vertices",
            "big_time_budget",
        )
    }
    params["method"] = "inexact (fm.solve defaults)"
    params["tolerance_rule"] = (
        f"uniform eta times 1 + {TOL_SLACK:g} at n = uniform_max/4, /2, uniform_max "
        "(lshape) and uniform_max/8, /4, /2 (manufactured), unless --tol-n-* or --tols-* given"
    )
    if a.big_only:
        from bench.report import load

        payload = load("adaptivity", a.quick) or {"parameters": params, "rows": []}
        for key in ("benchmark", "quick", "machine"):
            payload.pop(key, None)
        payload["big"] = big_stage(a)
        payload.setdefault("parameters", params)["big_run"] = {
            k: params[k] for k in ("big_tol", "big_max_vertices", "big_time_budget")
        }
        payload["targets"] = targets(payload.get("cases", {}), payload["big"])
        _print_targets(payload["targets"])
        finish("adaptivity", payload, a.quick)
        return
    t_start = time.perf_counter()
    payload = {"parameters": params, "warmup": warm_up(), "cases": {}, "rows": []}
    for name in a.cases:
        tols = a.tols_lshape if name == "lshape" else a.tols_manufactured
        tol_n = a.tol_n_lshape if name == "lshape" else a.tol_n_manufactured
        c = run_case(name, a, tols, tol_n)
        payload["rows"] += c.pop("rows")
        payload["cases"][name] = c
    payload["seconds_total_main"] = time.perf_counter() - t_start
    payload["peak_rss_mb"] = peak_rss_mb()
    if a.big:
        payload["big"] = big_stage(a)
    if a.merge:
        payload = _merged(payload, a)
    payload["targets"] = targets(payload["cases"], payload.get("big"))
    _print_targets(payload["targets"])
    finish("adaptivity", payload, a.quick)


if __name__ == "__main__":
    main()
