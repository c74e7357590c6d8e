"""The contact solve in Poisson units: inexact vs exact-amg vs exact vs naive.

For each mesh size: one pyamg smoothed-aggregation Poisson solve (setup + CG
to 1e-8 on the interior Laplacian, f = 1, BLAS limited to one thread;
``bench._common.poisson_unit``) measured in the same run as the unit.  Then,
for each scene (the default scene of docs/method.md §8 and the default
manufactured solution of section 7), every configuration with its Newton
steps (per nested level and in total), CG iterations, time (median of up to
``--repeat`` runs, fewer when one run exceeds ``--budget`` seconds), time in
Poisson units, the bound eta and, for the manufactured scene, the true
energy error:

* fastmem ``inexact`` and ``exact-amg`` with nested iteration, on the
  decoupled path and (up to ``--general-max``) on the general path;
* the same without nested iteration (up to ``--plain-max``);
* fastmem ``exact`` (sparse direct, decoupled up to ``--exact-max``, general
  up to ``--exact-general-max``);
* the naive baseline (``bench._naive``): the 3N x 3N coupled system
  rebuilt with scipy.sparse.bmat and solved with spsolve at every step of the
  active-set loop, from zero, until the active set repeats (up to
  ``--naive-max``, and only while one naive run takes less than
  ``--naive-budget`` seconds).

Every row records its distance to the reference solution of the same mesh
and scene (fastmem exact where it ran, else exact-amg nested decoupled):
max |u - u_ref| over both membranes and max |lam - lam_ref|.  The scene
matrices and mesh topology are built before any timing, so every method
starts from the same state.

    python -m bench.contact_solve [--quick] [--sizes 256 512 1024 2048]
    python -m bench.contact_solve --only-inexact --sizes 1024 2048   # contact_pu.json

``--only-inexact`` runs only fastmem's default solve (the issue-15 figure in
Poisson units, with the first solve of each scene in the process beside the
median) and writes ``contact_pu.json`` instead of ``contact_solve.json``.
"""

import numpy as np

from bench._common import finish, parse, parser, peak_rss_mb, poisson_unit, progress, timed_budget

FULL_SIZES = [256, 512, 1024, 2048]
QUICK_SIZES = [16, 32]


def _prepare(scene):
    """Build the mesh topology and the stiffness matrices outside the timings.

    The loads are not prepared: evaluating a callable load (the manufactured
    scene's) is part of the timed solve, as it is for a user.
    """
    mesh = scene.mesh
    _ = mesh.edges, mesh.triangle_edges, mesh.patch_ptr, mesh.interior_vertices
    _ = scene.weighted_stiffness(1), scene.weighted_stiffness(2)


def run_one(scene, method, nested, path, repeat, budget, ms=None):
    import fastmem as fm
    from fastmem.fem.loaddata import forget

    def once():
        # every repetition evaluates the loads afresh (their values are cached on the scene)
        forget(scene)
        return fm.solve(scene, method=method, path=path, nested=nested, estimate=True)

    r, t = timed_budget(once, repeat, budget)
    solver = r.parameters["solver"]
    row = {
        "method": method,
        "nested": nested,
        "path": r.path,
        "converged": bool(r.converged),
        "seconds": t["median"],
        "seconds_stats": t,
        "timings": r.timings,
        # the naive loop computes no bound: fastmem's time without the final estimate
        "seconds_without_estimate": t["median"] - r.timings.get("estimate", 0.0),
        "eta": r.eta,
        "eta_disc": r.estimate.totals["eta_disc"],
        "eta_lin": r.estimate.totals["eta_lin"],
        "eta_alg": r.estimate.totals["eta_alg"],
        "contact_fraction": r.contact_fraction,
    }
    # every method runs the same levels and writes the same history (fastmem.solver.history)
    levels = solver["levels"]
    row["levels"] = levels
    row["newton_per_level"] = [lv["newton"] for lv in levels]
    row["newton_total"] = int(sum(row["newton_per_level"]))
    row["newton_finest"] = r.n_newton
    row["inner_total"] = int(r.history["inner_total"][-1])
    row["flux_evaluations"] = int(sum(lv["flux_evaluations"] for lv in levels))
    if method == "exact":
        row["factorizations"] = solver["factorizations"]
    else:
        row["amg_setups"] = int(sum(lv["amg_setups"] for lv in levels))
    row["safeguard_uses"] = solver.get("safeguard", {}).get("uses")
    if ms is not None:
        row["energy_error"] = ms.energy_error(scene.mesh, r.u1, r.u2)
        row["effectivity"] = r.eta / row["energy_error"]
    return row, r


def run_naive(scene, repeat, budget, ms=None):
    import fastmem as fm
    from bench._naive import naive_active_set

    out, t = timed_budget(lambda: naive_active_set(scene), repeat, budget)
    row = {
        "method": "naive",
        "nested": False,
        "path": "coupled",
        "formulation": "3N x 3N (u1, u2, lam), scipy.sparse.bmat + spsolve per step",
        "converged": out["converged"],
        "cycled": out["cycled"],
        "seconds": t["median"],
        "seconds_stats": t,
        "timings": {"bmat_build": out["build_s"], "spsolve": out["spsolve_s"]},
        "seconds_without_estimate": t["median"],
        "newton_total": out["steps"],
        "newton_finest": out["steps"],
        "inner_total": None,
        "unknowns": out["unknowns"],
        "complementarity_max": out["complementarity"],
        "contact_fraction": float(
            scene.mesh.lumped_mass[out["active"]].sum() / scene.mesh.lumped_mass.sum()
        ),
    }
    # the bound of the naive triple, so that its row is comparable (not timed)
    row["eta"] = fm.estimate(scene, out["u1"], out["u2"], out["lam"]).eta
    if ms is not None:
        row["energy_error"] = ms.energy_error(scene.mesh, out["u1"], out["u2"])
        row["effectivity"] = row["eta"] / row["energy_error"]
    return row, out


def _triple(r):
    return (r.u1, r.u2, r.lam) if hasattr(r, "u1") else (r["u1"], r["u2"], r["lam"])


def configurations(n, a):
    """The (method, nested, path) runs at size n."""
    runs = [("inexact", "auto", "decoupled")]
    if a.only_inexact:  # the issue-15 figure: the default solve alone, in Poisson units
        return runs
    runs.append(("exact-amg", "auto", "decoupled"))
    if n <= a.general_max:
        runs += [("inexact", "auto", "general"), ("exact-amg", "auto", "general")]
    if n <= a.plain_max:
        runs += [("inexact", False, "decoupled"), ("exact-amg", False, "decoupled")]
    if n <= a.exact_max:
        runs.append(("exact", False, "decoupled"))
    if n <= a.exact_general_max:
        runs.append(("exact", False, "general"))
    return runs


def run(sizes, a):
    import fastmem as fm

    fm.warm_up()  # every kernel of a default solve, including those of large meshes only
    warm = fm.Manufactured().scene(fm.Mesh.square(8))  # compile / load the JIT caches
    for method in ("inexact", "exact-amg", "exact"):
        for path in ("decoupled", "general"):
            fm.solve(warm, method=method, path=path, estimate=True)
    rows = []
    naive_ok = True
    for n in sizes:
        mesh = fm.Mesh.square(n)
        unit_info = poisson_unit(mesh, a.repeat)
        unit = unit_info["seconds"]
        progress(
            f"contact_solve: n = {n}: Poisson unit {unit:.4f} s "
            f"({unit_info['iterations']} CG its, rel. res. {unit_info['relative_residual']:.1e})"
        )
        ms = fm.Manufactured()
        scenes = {
            "default": (fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1), None),
            "manufactured": (ms.scene(mesh), ms),
        }
        for name, (scene, man) in scenes.items():
            _prepare(scene)
            runs = configurations(n, a)
            results = {}
            first = len(rows)
            for method, nested, path in runs:
                row, res = run_one(scene, method, nested, path, a.repeat, a.budget, man)
                results[(method, nested, path)] = res
                rows.append(row)
                _finish_row(row, n, name, mesh, unit, unit_info)
            if naive_ok and n <= a.naive_max and not a.only_inexact:
                row, res = run_naive(scene, a.repeat, a.naive_budget, man)
                results[("naive", False, "coupled")] = res
                rows.append(row)
                _finish_row(row, n, name, mesh, unit, unit_info)
                if row["seconds_stats"]["min"] > a.naive_budget:
                    naive_ok = False
                    progress(f"  naive took > {a.naive_budget:.0f} s: not run on larger meshes")
            ref_key = ("exact", False, "decoupled")
            if ref_key not in results:
                ref_key = ("exact-amg", "auto", "decoupled")
            if ref_key not in results:  # --only-inexact: nothing to compare with
                continue
            ref = _triple(results[ref_key])
            for row in rows[first:]:
                key = (row["method"], row["nested"], row["path"])
                u1, u2, lam = _triple(results[key])
                row["reference"] = "{} nested={} {}".format(*ref_key)
                row["max_abs_diff_u_vs_reference"] = float(
                    max(np.abs(u1 - ref[0]).max(), np.abs(u2 - ref[1]).max())
                )
                row["max_abs_diff_lam_vs_reference"] = float(np.abs(lam - ref[2]).max())
                row["max_abs_lam_reference"] = float(np.abs(ref[2]).max())
            _ratios(rows[first:])
    return rows


def _finish_row(row, n, name, mesh, unit, unit_info):
    row.update(n=n, scene=name, vertices=mesh.n_vertices, poisson_s=unit)
    row["poisson_iterations"] = unit_info["iterations"]
    row["poisson_units"] = row["seconds"] / unit
    # the first repetition of this configuration in the process (kernels warmed up on a
    # tiny mesh); with --only-inexact the first solve of the scene in the process
    row["first_poisson_units"] = row["seconds_stats"]["all"][0] / unit
    row["peak_rss_mb"] = peak_rss_mb()
    err = f" err {row['energy_error']:.3e}" if "energy_error" in row else ""
    progress(
        f"  {name:12s} {row['method']:9s} nested={str(row['nested']):5s} "
        f"{row['path'][:9]:9s} steps {row['newton_total']:4d} (finest "
        f"{row['newton_finest']}) inner {row['inner_total']} {row['seconds']:.3f}s = "
        f"{row['poisson_units']:.2f} PU  eta {row['eta']:.3e}" + err
    )


def _ratios(rows):
    """Naive time over each fastmem configuration of the same mesh and scene."""
    naive = [r for r in rows if r["method"] == "naive"]
    if not naive:
        return
    t_naive = naive[0]["seconds"]
    for r in rows:
        if r["method"] != "naive":
            r["naive_over_this"] = t_naive / r["seconds"]
            r["naive_over_this_without_estimate"] = t_naive / r["seconds_without_estimate"]


def main(argv=None):
    p = parser(__doc__)
    p.add_argument("--budget", type=float, default=60.0, help="stop repeating a run after this")
    p.add_argument("--exact-max", type=int, default=512)
    p.add_argument("--exact-general-max", type=int, default=256)
    p.add_argument("--general-max", type=int, default=1024)
    p.add_argument("--plain-max", type=int, default=512)
    p.add_argument("--naive-max", type=int, default=256)
    p.add_argument("--naive-budget", type=float, default=120.0)
    p.add_argument(
        "--only-inexact",
        action="store_true",
        help="only the default solve (inexact, nested, decoupled); writes contact_pu.json",
    )
    args = parse(p, argv)
    sizes = args.sizes or (QUICK_SIZES if args.quick else FULL_SIZES)
    if args.quick and args.repeat == p.get_default("repeat"):
        args.repeat = 1
    payload = {
        "parameters": {
            "sizes": sizes,
            "repeat": args.repeat,
            "budget_s": args.budget,
            "exact_max": args.exact_max,
            "exact_general_max": args.exact_general_max,
            "general_max": args.general_max,
            "plain_max": args.plain_max,
            "naive_max": args.naive_max,
            "naive_budget_s": args.naive_budget,
            "only_inexact": args.only_inexact,
            "quick": args.quick,
        },
        "rows": run(sizes, args),
    }
    finish("contact_pu" if args.only_inexact else "contact_solve", payload, args.quick)


if __name__ == "__main__":
    main()
