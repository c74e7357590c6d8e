"""Effectivity eta / |||u - u_h||| for heterogeneous and extreme tensions (issue 16).

Three families:

* ``checkerboard``: the square (-1, 1)^2, mu1 a 4 x 4 checkerboard of 1 and c
  per triangle, mu2 = 1, g = 0.1, loads f = (-1, 1) and (-4, 2); c = 1e3, 1e-3,
  1e6, 1e-6; n = 16 ... 128; exact and inexact solves.
* ``lshape``: ``Mesh.lshape(n)``, two materials (mu1 = 1 for x < 0, c for
  x > 0), mu2 = 1, f = (-1, 1), g = 0.1.
* ``manufactured``: the constant-mu family of docs/method.md §7 (exact solution
  known), mu from (1, 1) to (1e-6, 1e6).

For the first two the true error is taken against a discrete solution on the
mesh refined ``--ref-levels`` times (default 3) beyond the finest mesh of the
row (every coarse mesh is a uniform refinement ancestor of it, so the coarse
P1 function is prolonged exactly): ``err_ref = |||u_ref - u_h|||``.  Two
statements of its uncertainty: if the error decreases like h^s, the true
error lies within ``err_ref * (1 +- 2^(-s L))`` for L levels finer (the
measured order s of ``err_ref`` over the row is reported with that factor);
guaranteed, it lies in ``[err_ref - eta_ref, err_ref + eta_ref]`` with
``eta_ref`` the bound of the reference solution (so ``eta / (err_ref +
eta_ref)`` is a guaranteed lower bound of the effectivity).  At checkerboard
cross points the solution is singular like r^alpha with alpha small for high
contrast (Kellogg): the error then decays like h^alpha and the reference
misses most of it, which the order s and ``eta_ref`` show.

    python -m bench.effectivity [--quick] [--sizes 16 32 64 128] [--ref-levels 3]

``--glued effectivity`` / ``--glued cost`` (issue 16, the glued contact load of
fastmem.estimators.flux.glued_contact_load)
instead measures, on the same triples, the bound with the glued contact load
(what fastmem.estimate computes) and with the projected redistribution it
replaced (``eta_projected``): the manufactured family for the five tensions of
GLUED_MU at n = 16, 32, 64 and the checkerboard c = 1e3, 1e-3 at n = 16, 32;
and the flux reconstruction's patches/s of both, alternating in one process.
The results go to the key ``glued_contact_load`` of the existing
bench/results/effectivity.json (the other keys are kept).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from bench._common import finish, parse, parser, progress

CONTRASTS = (1e3, 1e-3, 1e6, 1e-6)
LOADS = ((-1.0, 1.0), (-4.0, 2.0))
MANUFACTURED_MU = (
    (1.0, 1.0),
    (1.0, 1e-3),
    (1e-3, 1.0),
    (1.0, 1e-6),
    (1e-6, 1.0),
    (1e-3, 1e3),
    (1e3, 1e-3),
    (1e-6, 1e6),
    (1e6, 1e-6),
)


GLUED_MU = ((1.0, 1.0), (1.0, 1e-6), (1e-6, 1.0), (1e-6, 1e6), (1e6, 1e-6))


def checkerboard(mesh, c, blocks=4):
    """Per-triangle values 1 and c on a blocks x blocks checkerboard of the bounding box."""
    x0, x1, y0, y1 = mesh.bounding_box
    lo = np.array([x0, y0])
    size = np.array([x1 - x0, y1 - y0])
    cells = np.floor((mesh.vertices[mesh.triangles].mean(axis=1) - lo) / size * blocks)
    return np.where(cells.sum(axis=1) % 2 == 0, 1.0, c)


def two_materials(mesh, c):
    """Per-triangle values 1 for x < 0 and c for x > 0 (by centroid)."""
    cen = mesh.vertices[mesh.triangles].mean(axis=1)
    return np.where(cen[:, 0] < 0.0, 1.0, c)


def prolong(mesh, u):
    """Exact P1 prolongation to ``mesh.refine()`` (vertex N + e is the midpoint of edge e)."""
    e = mesh.edges
    return np.concatenate([u, 0.5 * (u[e[:, 0]] + u[e[:, 1]])])


def energy(fine, mu, e1, e2):
    """``(sum_i (mu_i grad e_i, grad e_i))^(1/2)`` on the fine mesh (per-triangle mu)."""
    from fastmem.fem.assembly import assemble_stiffness

    out = 0.0
    for m, e in zip(mu, (e1, e2), strict=True):
        a = assemble_stiffness(fine, m)
        out += float(e @ (a @ e))
    return float(np.sqrt(max(out, 0.0)))


def reference_chain(make, mu_of, c, f, sizes, levels, method="exact-amg"):
    """Meshes ``make(sizes[0])`` refined up to ``levels`` beyond ``sizes[-1]``, and the
    reference result on the finest: ``(chain, ref_scene, ref)`` (mu1 = mu_of(mesh, c), mu2 = 1,
    g = 0.1)."""
    import fastmem as fm

    chain = [make(sizes[0])]
    for _ in range(int(round(np.log2(sizes[-1] / sizes[0]))) + levels):
        chain.append(chain[-1].refine())
    fine = chain[-1]
    ref_scene = fm.Scene(fine, mu=(mu_of(fine, c), 1.0), f=f, g=0.1)
    return chain, ref_scene, fm.solve(ref_scene, method=method, estimate=True)


def error_vs_reference(chain, k, u1, u2, ref_scene, ref):
    """Energy error of (u1, u2) on ``chain[k]`` against the reference on ``chain[-1]``."""
    for m in chain[k:-1]:
        u1, u2 = prolong(m, u1), prolong(m, u2)
    return energy(chain[-1], (ref_scene.mu1, 1.0), ref.u1 - u1, ref.u2 - u2)


def chain_solutions(chain, ref_scene, ref, sizes, mu_of, c, f, estimate=False):
    """Yield ``(n, scene, r, err_ref, hi)`` on the meshes of ``chain`` at ``sizes``.

    r: the exact solve of the scene (mu1 = mu_of(mesh, c), mu2 = 1, g = 0.1);
    err_ref: its energy error against ``ref``; hi: ``(err_ref^2 + eta_ref^2)^(1/2)``,
    the upper end of the true error that the reference allows.
    """
    import fastmem as fm

    for n in sizes:
        k = int(round(np.log2(n / sizes[0])))
        mesh = chain[k]
        scene = fm.Scene(mesh, mu=(mu_of(mesh, c), 1.0), f=f, g=0.1)
        r = fm.solve(scene, method="exact", estimate=estimate)
        err = error_vs_reference(chain, k, r.u1, r.u2, ref_scene, ref)
        yield n, scene, r, err, float(np.hypot(err, ref.eta))


def eta_projected(scene, r):
    """The bound of result r with the projected redistribution (before the glued load).

    fastmem.estimators.bound.evaluate as it was before the glued contact load: the flux of
    ``reconstruct``'s default (``redistribute=True``), the cross-point
    correction, and the plain c and data oscillation.
    """
    from fastmem.estimators.bound import flux_terms
    from fastmem.estimators.flux import cross_point_correction, reconstruct
    from fastmem.estimators.terms import combine, global_terms, local_terms

    lam = np.where(scene.mesh.boundary_vertex_mask, 0.0, r.lam)
    fl = reconstruct(scene, r.u1, r.u2, lam, r.r1, r.r2)
    fl = cross_point_correction(scene, r.u1, r.u2, fl)
    f1, f2 = flux_terms(scene, r.u1, r.u2, fl)
    loc = local_terms(scene, r.u1, r.u2, lam)
    glob = global_terms(scene, r.u1, r.u2, lam, r.r1, r.r2)
    return float(combine(f1, f2, loc, glob)["totals"]["eta"])


def _reference_row(name, base, sizes, ref_levels, mu_of, f, methods, cache=None, projected=False):
    """Solve on the chain base.refine()^k, error against ref_levels beyond the finest."""
    import fastmem as fm

    levels = int(round(np.log2(sizes[-1] / sizes[0])))
    chain = [base]
    for _ in range(levels + ref_levels):
        chain.append(chain[-1].refine())
    fine = chain[-1]
    t0 = time.perf_counter()
    ref_scene = fm.Scene(fine, mu=mu_of(fine), f=f, g=0.1)
    key = f"{name}_{mu_of(base)[0].min():g}_{mu_of(base)[0].max():g}_{f[0]:g}_{f[1]:g}"
    path = None if cache is None else Path(cache) / f"{key}_{fine.n_vertices}.npz"
    if path is not None and path.exists():
        data = np.load(path)
        ref_u1, ref_u2, eta_ref = data["u1"], data["u2"], float(data["eta"])
    else:
        # AMG-CG to a tight tolerance inside an exact Newton-min: 1.5x faster than
        # direct solves at 1M vertices, algebraic error far below the coarse errors
        ref = fm.solve(ref_scene, method="exact-amg", estimate=True)
        ref_u1, ref_u2, eta_ref = ref.u1, ref.u2, float(ref.eta)
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez(path, u1=ref_u1, u2=ref_u2, eta=eta_ref)
    t_ref = time.perf_counter() - t0
    mu_fine = ref_scene.mu1, ref_scene.mu2
    rows = []
    for n in sizes:
        k = int(round(np.log2(n / sizes[0])))
        mesh = chain[k]
        scene = fm.Scene(mesh, mu=mu_of(mesh), f=f, g=0.1)
        for method in methods:
            r = fm.solve(scene, method=method, estimate=True)
            u1, u2 = r.u1, r.u2
            for m in chain[k:-1]:
                u1, u2 = prolong(m, u1), prolong(m, u2)
            err = energy(fine, mu_fine, ref_u1 - u1, ref_u2 - u2)
            t = r.estimate.totals
            maps = r.estimate.maps
            extra = {}
            if projected:
                eta_p = eta_projected(scene, r)
                extra = {"eta_projected": eta_p, "effectivity_projected": eta_p / err}
            rows.append(
                {
                    "family": name,
                    "n": n,
                    "method": method,
                    "eta": r.eta,
                    "err_ref": err,
                    "effectivity": r.eta / err,
                    **extra,
                    # |||u - u_h||| lies in [err_ref - eta_ref, err_ref + eta_ref] (the
                    # reference's own guaranteed bound; the current estimator's)
                    "eta_ref": eta_ref,
                    "effectivity_guaranteed_min": r.eta / (err + eta_ref),
                    "eta_F": float(
                        np.sqrt((maps["eta_F1"] ** 2).sum() + (maps["eta_F2"] ** 2).sum())
                    ),
                    "sqrt_c": float(np.sqrt(t["c"])),
                    "eta_glob": float(np.hypot(t["eta_glob1"], t["eta_glob2"])),
                    "eta_nc": t["eta_nc"],
                }
            )
            progress(
                f"  {name} n={n:4d} {method:8s} eta={r.eta:.4e} err={err:.4e} eff={r.eta / err:.3f}"
            )
    for method in methods:
        sub = [r for r in rows if r["method"] == method]
        if len(sub) >= 2:
            slope = np.polyfit(
                np.log([r["n"] for r in sub]), np.log([r["err_ref"] for r in sub]), 1
            )
            order = float(-slope[0])
            for r in sub:
                # levels between the row's mesh and the reference
                lv = ref_levels + levels - int(round(np.log2(r["n"] / sizes[0])))
                r["order"] = order
                r["uncertainty"] = float(2.0 ** (-order * lv)) if order > 0 else None
    return rows, {"ref_vertices": fine.n_vertices, "ref_seconds": t_ref, "eta_ref": eta_ref}


def _refined_chain_mesh(kind, n0):
    import fastmem as fm

    return fm.Mesh.square(n0) if kind == "square" else fm.Mesh.lshape(n0)


def run_family(
    name, kind, sizes, ref_levels, contrasts, loads, mu_fn, methods, cache=None, projected=False
):
    """Rows of one family: every contrast c and load f, meshes of ``kind`` (square, lshape)."""
    out = []
    for c in contrasts:
        for f in loads:
            progress(f"{name} c={c:g} f={f}")
            rows, info = _reference_row(
                name,
                _refined_chain_mesh(kind, sizes[0]),
                sizes,
                ref_levels,
                lambda m, c=c: (mu_fn(m, c), 1.0),
                f,
                methods,
                cache,
                projected,
            )
            for r in rows:
                r.update({"c": c, "f": list(f)})
            out.append({"c": c, "f": list(f), "rows": rows, **info})
    return out


def run_manufactured(sizes, mus, methods, projected=False):
    import fastmem as fm

    rows = []
    for mu in mus:
        ms = fm.Manufactured(mu=mu)
        for n in sizes:
            mesh = fm.Mesh.square(n)
            for method in methods:
                scene = ms.scene(mesh)
                r = fm.solve(scene, method=method, estimate=True)
                err = ms.energy_error(mesh, r.u1, r.u2)
                extra = {}
                if projected:
                    eta_p = eta_projected(scene, r)
                    t = r.estimate.totals
                    m = r.estimate.maps
                    extra = {
                        "eta_projected": eta_p,
                        "effectivity_projected": eta_p / err,
                        "eta_F1": float(np.sqrt((m["eta_F1"] ** 2).sum())),
                        "eta_F2": float(np.sqrt((m["eta_F2"] ** 2).sum())),
                        "eta_osc1": float(np.sqrt((m["eta_osc1"] ** 2).sum())),
                        "eta_osc2": float(np.sqrt((m["eta_osc2"] ** 2).sum())),
                        "sqrt_c": float(np.sqrt(t["c"])),
                    }
                rows.append(
                    {
                        "family": "manufactured",
                        "mu": list(mu),
                        "n": n,
                        "method": method,
                        "eta": r.eta,
                        "err": err,
                        "effectivity": r.eta / err,
                        **extra,
                    }
                )
                progress(f"  manufactured mu={mu} n={n} {method}: eff={r.eta / err:.3f}")
    return rows


def flux_cost(n, repeats):
    """Patches/s of the bound's flux: glued contact load vs projected redistribution.

    Same triples, one process, alternating repetitions (median): constant equal
    tensions (the default scene), constant unequal tensions with constant loads,
    and the manufactured (1e-6, 1e6) case (callable loads), all at ``Mesh.square(n)``.
    """
    import fastmem as fm
    from fastmem.estimators.flux import reconstruct

    mesh = fm.Mesh.square(n)
    scenes = {
        "constant (1, 1), f = (-1, 1)": fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1),
        "constant (1, 10), f = (-1, 1)": fm.Scene(mesh, mu=(1.0, 10.0), f=(-1.0, 1.0), g=0.1),
        "manufactured (1e-6, 1e6)": fm.Manufactured(mu=(1e-6, 1e6)).scene(mesh),
    }
    out = []
    for label, scene in scenes.items():
        r = fm.solve(scene, method="exact", estimate=True)
        lam = np.where(mesh.boundary_vertex_mask, 0.0, r.lam)
        args = (scene, r.u1, r.u2, lam, r.r1, r.r2)
        times = {"glued": [], "projected": []}
        for mode in ("glued", "projected"):  # warm both (Numba, load moments)
            reconstruct(*args, redistribute="glued" if mode == "glued" else True)
        for _ in range(repeats):
            for mode in ("glued", "projected"):
                t0 = time.perf_counter()
                reconstruct(*args, redistribute="glued" if mode == "glued" else True)
                times[mode].append(time.perf_counter() - t0)
        med = {k: float(np.median(v)) for k, v in times.items()}
        row = {
            "scene": label,
            "n": n,
            "patches": mesh.n_vertices,
            "repeats": repeats,
            "seconds": times,
            "patches_per_second_glued": mesh.n_vertices / med["glued"],
            "patches_per_second_projected": mesh.n_vertices / med["projected"],
            "time_glued_over_projected": med["glued"] / med["projected"],
        }
        progress(
            f"  flux cost {label}: glued {row['patches_per_second_glued']:.0f} patches/s, "
            f"projected {row['patches_per_second_projected']:.0f}, "
            f"ratio {row['time_glued_over_projected']:.3f}"
        )
        out.append(row)
    return out


def run_glued(args):
    """The ``--glued`` section: before/after on the same triples, merged into the JSON."""
    import json
    import os

    from bench._common import machine_info, result_name, results_dir

    t0 = time.perf_counter()
    methods = ("exact", "inexact")
    section = {
        "note": "eta: the bound with the glued contact load "
        "(fastmem.estimators.flux.glued_contact_load); "
        "eta_projected: the same triple with the projected redistribution it replaced; "
        "flux_cost: fastmem.estimators.flux.reconstruct with redistribute='glued' (the bound's) vs "
        "redistribute=True, alternating, exclusive CPU lock",
    }
    if args.glued == "cost":
        section["flux_cost"] = flux_cost(64 if args.quick else 512, 1 if args.quick else 5)
    else:
        section["manufactured"] = run_manufactured([16, 32, 64], GLUED_MU, methods, projected=True)
    if args.glued == "effectivity" and not args.quick:
        section["checkerboard"] = run_family(
            "checkerboard",
            "square",
            [16, 32],
            args.ref_levels,
            (1e3, 1e-3),
            LOADS,
            checkerboard,
            methods,
            args.cache,
            projected=True,
        )
    section[f"seconds_{args.glued}"] = time.perf_counter() - t0
    path = results_dir() / f"{result_name('effectivity', args.quick)}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    data = json.loads(path.read_text()) if path.exists() else {"benchmark": "effectivity"}
    data["glued_contact_load"] = {
        **data.get("glued_contact_load", {}),
        "machine": machine_info(),
        **section,
    }
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)
    progress(f"wrote {path} (key glued_contact_load)")


def main(argv=None):
    p = parser(__doc__, repeat=1)
    p.add_argument("--ref-levels", type=int, default=3)
    p.add_argument("--manufactured-sizes", type=int, nargs="*", default=None)
    p.add_argument("--only", choices=("checkerboard", "lshape", "manufactured"), default=None)
    p.add_argument("--cache", default=None, help="folder for the reference solutions (reused)")
    p.add_argument(
        "--glued",
        choices=("effectivity", "cost"),
        default=None,
        help="the glued contact load section only: effectivities, or the flux cost",
    )
    args = parse(p, argv)
    if args.glued:
        run_glued(args)
        return
    sizes = args.sizes or ([8, 16] if args.quick else [16, 32, 64, 128])
    msizes = args.manufactured_sizes or ([16] if args.quick else [32, 64, 128])
    levels = 1 if args.quick else args.ref_levels
    methods = ("exact", "inexact")
    t0 = time.perf_counter()
    payload = {
        "parameters": {
            "reference_method": "exact-amg",
            "sizes": sizes,
            "manufactured_sizes": msizes,
            "ref_levels": levels,
            "quick": args.quick,
        }
    }
    if args.only in (None, "checkerboard"):
        contrasts = CONTRASTS[:2] if args.quick else CONTRASTS
        payload["checkerboard"] = run_family(
            "checkerboard",
            "square",
            sizes,
            levels,
            contrasts,
            LOADS,
            checkerboard,
            methods,
            args.cache,
        )
    if args.only in (None, "lshape"):
        payload["lshape"] = run_family(
            "lshape",
            "lshape",
            sizes,
            levels,
            CONTRASTS,
            ((-1.0, 1.0),),
            two_materials,
            methods,
            args.cache,
        )
    if args.only in (None, "manufactured"):
        payload["manufactured"] = run_manufactured(msizes, MANUFACTURED_MU, methods)
    # every row of every family in one list (the families keep theirs, with references)
    payload["rows"] = [
        r for fam in ("checkerboard", "lshape") for b in payload.get(fam, []) for r in b["rows"]
    ]
    payload["rows"] += payload.get("manufactured", [])
    payload["seconds"] = time.perf_counter() - t0
    finish("effectivity", payload, args.quick)


if __name__ == "__main__":
    main()
