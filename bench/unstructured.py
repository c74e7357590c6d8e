"""Nested iteration on meshes that did not come from refinement: auxiliary coarse meshes.

For meshes without a coarser version (a randomly perturbed square mesh, a
gmsh mesh of the unit disk when the gmsh package is installed), the inexact
solve with ``nested="auto"`` (auxiliary coarse meshes from subsets of the
vertices, :mod:`fastmem.mesh.coarsen`) against ``nested=False`` (Newton-min from
the unconstrained solution), on the default scene (docs/method.md §8) and,
on the square, the default manufactured solution (section 7).  Per run:
Newton steps per level and on the finest mesh, CG iterations, time (median
of ``--repeat``), time in Poisson units (``bench._common.poisson_unit`` on
the same mesh), the time spent building the coarse meshes, the bound eta
and, for the manufactured scene, the true energy error.  Each repetition
starts from a new scene on the same fine mesh: loads evaluated and coarse
meshes built again; the fine mesh's topology and sparsity pattern are built
once, before the timings (as in ``bench.contact_solve``).

    python -m bench.unstructured [--quick] [--sizes 256 512 1024]
"""

import numpy as np

from bench import _gmsh
from bench._common import finish, parse, parser, peak_rss_mb, poisson_unit, progress, timed_budget

FULL_SIZES = [256, 512, 1024]
QUICK_SIZES = [24]
SEED = 20261121


def jittered_square(n):
    """Mesh.square(n) with every interior vertex moved by up to 0.2 h at random (no recipe)."""
    import fastmem as fm

    base = fm.Mesh.square(n, diagonal="right")
    pts = base.vertices.copy()
    inner = base.interior_vertices
    shift = np.random.default_rng(SEED).uniform(-0.2, 0.2, (inner.size, 2))
    pts[inner] += shift * (2.0 / n)
    return fm.Mesh(pts, base.triangles)


def disk(n):
    """gmsh mesh of the unit disk with element size 2/n (None without the gmsh package)."""
    return _gmsh.mesh("disk", lambda occ: occ.addDisk(0.0, 0.0, 0.0, 1.0, 1.0), 2.0 / n)


def scenes(n):
    """(name, mesh, scene factory, Manufactured or None) of every case at size n."""
    import fastmem as fm

    sq = jittered_square(n)
    out = [
        ("square-default", sq, lambda m: fm.Scene(m, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1), None),
        ("square-manufactured", sq, lambda m: fm.Manufactured().scene(m), fm.Manufactured()),
    ]
    dm = disk(n)
    if dm is not None:
        out.append(
            ("disk-default", dm, lambda m: fm.Scene(m, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1), None)
        )
    return out


def run(sizes, repeat, budget):
    import fastmem as fm

    fm.solve(fm.Manufactured().scene(jittered_square(8)), estimate=True)  # JIT caches
    rows = []
    for n in sizes:
        for name, mesh, make, ms in scenes(n):
            _ = mesh.edges, mesh.triangle_edges, mesh.patch_ptr
            unit = poisson_unit(mesh, repeat)["seconds"]
            for nested in ("auto", False):
                r, t = timed_budget(lambda: fm.solve(make(mesh), nested=nested), repeat, budget)  # noqa: B023
                levels = r.parameters["solver"]["levels"]
                row = {
                    "n": n,
                    "scene": name,
                    "vertices": mesh.n_vertices,
                    "nested": nested,
                    "converged": bool(r.converged),
                    "newton_per_level": [lv["newton"] for lv in levels],
                    "level_vertices": [lv["n_vertices"] for lv in levels],
                    "newton_finest": r.n_newton,
                    "newton_total": int(sum(lv["newton"] for lv in levels)),
                    "inner_total": int(r.history["inner_total"][-1]),
                    "seconds": t["median"],
                    "seconds_stats": t,
                    "coarsening_seconds": r.timings.get("coarsening", 0.0),
                    "poisson_unit_s": unit,
                    "pu": t["median"] / unit,
                    "eta": r.eta,
                    "peak_rss_mb": peak_rss_mb(),
                }
                if ms is not None:
                    row["energy_error"] = ms.energy_error(mesh, r.u1, r.u2)
                    row["effectivity"] = r.eta / row["energy_error"]
                rows.append(row)
                progress(
                    f"unstructured: {name:19s} N={mesh.n_vertices:8d} nested={nested!s:5s} "
                    f"steps {row['newton_per_level']} {row['seconds']:.2f} s = {row['pu']:.2f} PU "
                    f"(coarsening {row['coarsening_seconds']:.2f} s) eta {r.eta:.3e}"
                )
            auto, cold = rows[-2], rows[-1]
            auto["speedup_vs_unconstrained_start"] = cold["seconds"] / auto["seconds"]
    return rows


def main(argv=None):
    p = parser(__doc__, repeat=1)
    p.add_argument("--budget", type=float, default=60.0, help="stop repeating a run after this")
    args = parse(p, argv)
    sizes = args.sizes or (QUICK_SIZES if args.quick else FULL_SIZES)
    payload = {
        "parameters": {"sizes": sizes, "repeat": args.repeat, "quick": args.quick, "seed": SEED},
        "rows": run(sizes, args.repeat, args.budget),
    }
    finish("unstructured", payload, args.quick)


if __name__ == "__main__":
    main()
