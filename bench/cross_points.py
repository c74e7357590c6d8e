"""Cross points and layers of heterogeneous membranes: effectivity and cost (issue 16).

Four sections, written to ``bench/results/cross_points.json``:

* ``kellogg``: eta / exact error on Kellogg's cross-point solution
  (:mod:`fastmem.problems.kellogg`, contrasts 10, 161.45, 1e3, 1e6; uniform n = 16 ... 128;
  exact and inexact solves), with the cross-point correction as it is
  (``glob=True``: global P1 stream functions plus the rings' P2 bubbles) and with
  the rings alone (``glob=False``, the correction before), on the same triples.
* ``checkerboard``: the checkerboard of bench/effectivity.py (mu1 in {1, c} on
  4 x 4 squares, mu2 = 1, g = 0.1), exact solves, n = 16 ... 64 against a solution
  ``--ref-levels`` refinements finer; eta with and without the global part, and
  the bracket of the true effectivity that the reference allows: the true error
  lies in [err_ref, (err_ref^2 + eta_ref^2)^(1/2)] (Galerkin orthogonality for
  nested meshes, exact for linear problems, approximate with contact; eta_ref the
  reference's own bound), so eta / error lies in
  [eta / (err_ref^2 + eta_ref^2)^(1/2), eta / err_ref].
* ``adaptive``: ``fm.solve(scene, tol=...)`` on the two-material L-shape (mu1 = 1
  | c) and the checkerboard, and the effectivity of the final mesh against that
  mesh refined twice uniformly (``eta_ref`` given: the reference's bound).
* ``cost``: seconds of the flux reconstruction and of the correction (rings
  alone, and as it is), and of the reconstruction before issue 16
  (``bench.estimate.BASE_COMMIT``), alternating, medians of ``--repeat`` after a
  first call (the scene's correction setup is built by the solve's own bound).

``--only SECTION`` re-runs one section and keeps the others of the existing file.

    python -m bench.cross_points [--quick] [--repeat 5] [--ref-levels 3]
"""

from __future__ import annotations

import statistics
import time

import numpy as np

from bench._common import finish, keep_sections, parse, progress, section_rows, sectioned_parser
from bench.effectivity import (
    chain_solutions,
    checkerboard,
    energy,
    prolong,
    reference_chain,
    two_materials,
)

KELLOGG_CONTRASTS = (10.0, 161.4476387975881, 1e3, 1e6)
CHECKER = ((1e3, (-1.0, 1.0)), (1e3, (-4.0, 2.0)), (1e6, (-1.0, 1.0)), (1e-3, (-1.0, 1.0)))
ADAPTIVE = (
    ("lshape", 1e-3, (-1.0, 1.0), (3e-2, 1e-2)),
    ("lshape", 1e-6, (-1.0, 1.0), (3e-2, 1e-2)),
    ("lshape", 1e3, (-1.0, 1.0), (1e-2,)),
    ("checkerboard", 1e3, (-1.0, 1.0), (3e-2,)),
    ("checkerboard", 1e-3, (-1.0, 1.0), (3e-2,)),
)


def _eta(scene, r, glob):
    """The bound of result r with the cross-point correction's global part on or off."""
    import fastmem as fm
    import fastmem.estimators.bound as fb
    from fastmem.estimators import flux

    orig = fb.cross_point_correction
    try:
        fb.cross_point_correction = lambda s, a, b, f: flux.cross_point_correction(
            s, a, b, f, glob=glob
        )
        return float(fm.estimate(scene, r.u1, r.u2, r.lam, r1=r.r1, r2=r.r2).eta)
    finally:
        fb.cross_point_correction = orig


def run_kellogg(sizes):
    import fastmem as fm
    from fastmem.problems.kellogg import Kellogg

    rows = []
    for contrast in KELLOGG_CONTRASTS:
        k = Kellogg(contrast)
        for n in sizes:
            mesh = fm.Mesh.square(n)
            scene = k.scene(mesh)
            for method in ("exact", "inexact"):
                r = fm.solve(scene, method=method, estimate=True)
                err = k.energy_error(mesh, r.u1, r.u2)
                rings = _eta(scene, r, False)
                rows.append(
                    {
                        "contrast": contrast,
                        "gamma": k.gamma,
                        "n": n,
                        "method": method,
                        "error": err,
                        "eta": r.eta,
                        "effectivity": r.eta / err,
                        "eta_rings_only": rings,
                        "effectivity_rings_only": rings / err,
                    }
                )
                progress(
                    f"  kellogg R={contrast:g} n={n} {method}: eff {r.eta / err:.3f} "
                    f"(rings only {rings / err:.3f})"
                )
    return rows


def run_checkerboard(sizes, levels):
    import fastmem as fm

    rows = []
    for c, f in CHECKER:
        chain, ref_scene, ref = reference_chain(fm.Mesh.square, checkerboard, c, f, sizes, levels)
        fine = chain[-1]
        sols = chain_solutions(chain, ref_scene, ref, sizes, checkerboard, c, f, estimate=True)
        for n, scene, r, err, hi in sols:
            rings = _eta(scene, r, False)
            rows.append(
                {
                    "c": c,
                    "f": list(f),
                    "n": n,
                    "ref_vertices": fine.n_vertices,
                    "err_ref": err,
                    "eta_ref": float(ref.eta),
                    "eta": r.eta,
                    "eta_rings_only": rings,
                    "effectivity_vs_ref": r.eta / err,
                    "effectivity_bracket": [r.eta / hi, r.eta / err],
                    "effectivity_rings_only_vs_ref": rings / err,
                }
            )
            progress(
                f"  checkerboard c={c:g} f={f} n={n}: eta/err_ref {r.eta / err:.3f} "
                f"(rings only {rings / err:.3f}), bracket [{r.eta / hi:.3f}, {r.eta / err:.3f}]"
            )
    return rows


def run_adaptive(ref_levels=2):
    import fastmem as fm

    rows = []
    for family, c, f, tols in ADAPTIVE:
        mu_of = checkerboard if family == "checkerboard" else two_materials
        base = fm.Mesh.square(8) if family == "checkerboard" else fm.Mesh.lshape(8)
        for tol in tols:
            t0 = time.perf_counter()
            scene = fm.Scene(base, mu=(mu_of(base, c), 1.0), f=f, g=0.1)
            r = fm.solve(scene, tol=tol, max_levels=100)
            seconds = time.perf_counter() - t0
            chain = [r.mesh]
            for _ in range(ref_levels):
                chain.append(chain[-1].refine())
            fine = chain[-1]
            ref_scene = fm.Scene(fine, mu=(mu_of(fine, c), 1.0), f=f, g=0.1)
            ref = fm.solve(ref_scene, method="exact-amg", estimate=True)
            u1, u2 = r.u1, r.u2
            for m in chain[:-1]:
                u1, u2 = prolong(m, u1), prolong(m, u2)
            err = energy(fine, (ref_scene.mu1, 1.0), ref.u1 - u1, ref.u2 - u2)
            hi = float(np.hypot(err, ref.eta))
            rows.append(
                {
                    "family": family,
                    "c": c,
                    "f": list(f),
                    "tol": tol,
                    "converged": bool(r.converged),
                    "stop_reason": r.parameters["adaptivity"]["stop_reason"],
                    "vertices": r.mesh.n_vertices,
                    "meshes": len(r.adaptivity["level"]),
                    "h_min": float(r.mesh.diameters.min()),
                    "seconds": seconds,
                    "eta": r.eta,
                    "err_ref": err,
                    "eta_ref": float(ref.eta),
                    "effectivity_vs_ref": r.eta / err,
                    "effectivity_bracket": [r.eta / hi, r.eta / err],
                }
            )
            progress(
                f"  adaptive {family} c={c:g} tol={tol:g}: {r.mesh.n_vertices} vertices, "
                f"eta {r.eta:.3e}, eta/err_ref {r.eta / err:.3f} (eta_ref {ref.eta:.2e})"
            )
    return rows


def run_cost(sizes, repeat):
    import fastmem as fm
    from bench.estimate import BASE_COMMIT, base_reconstruct
    from fastmem.estimators import flux
    from fastmem.problems.kellogg import Kellogg

    old = base_reconstruct(BASE_COMMIT)
    rows = []
    scenes = (
        (
            "checkerboard 1e3, f = (-1, 1)",
            lambda m: fm.Scene(m, mu=(checkerboard(m, 1e3), 1.0), f=(-1.0, 1.0), g=0.1),
        ),
        (
            "checkerboard 1e-3, f = (-4, 2)",
            lambda m: fm.Scene(m, mu=(checkerboard(m, 1e-3), 1.0), f=(-4.0, 2.0), g=0.1),
        ),
        ("kellogg 1e3", lambda m: Kellogg(1e3).scene(m)),
    )
    for name, make in scenes:
        for n in sizes:
            mesh = fm.Mesh.square(n)
            scene = make(mesh)
            r = fm.solve(scene, method="exact-amg")
            lam = np.where(mesh.boundary_vertex_mask, 0.0, r.lam)

            def rec(scene=scene, r=r, lam=lam):
                return flux.reconstruct(scene, r.u1, r.u2, lam, r.r1, r.r2, redistribute="glued")

            def base(scene=scene, r=r, lam=lam):
                return old(scene, r.u1, r.u2, lam, r.r1, r.r2)

            first = {}
            t = time.perf_counter()
            fl = rec()
            first["reconstruct"] = time.perf_counter() - t
            base()
            for key, glob in (("rings", False), ("joint", True)):
                t = time.perf_counter()
                flux.cross_point_correction(scene, r.u1, r.u2, fl, glob=glob)
                first[key] = time.perf_counter() - t
            times = {"reconstruct": [], "rings": [], "joint": [], "base": []}
            for _ in range(repeat):
                t = time.perf_counter()
                base()
                times["base"].append(time.perf_counter() - t)
                t = time.perf_counter()
                fl = rec()
                times["reconstruct"].append(time.perf_counter() - t)
                for key, glob in (("rings", False), ("joint", True)):
                    t = time.perf_counter()
                    flux.cross_point_correction(scene, r.u1, r.u2, fl, glob=glob)
                    times[key].append(time.perf_counter() - t)
            med = {k: statistics.median(v) for k, v in times.items()}
            rows.append(
                {
                    "scene": name,
                    "n": n,
                    "vertices": mesh.n_vertices,
                    "first_seconds": first,
                    "median_seconds": med,
                    "flux_with_joint_over_rings": (med["reconstruct"] + med["joint"])
                    / (med["reconstruct"] + med["rings"]),
                    # the bound's flux now (glued load, weighted patches, correction) against
                    # the reconstruction before issue 16 (bench.estimate.BASE_COMMIT)
                    "bound_flux_over_base": (med["reconstruct"] + med["joint"]) / med["base"],
                }
            )
            progress(
                f"  cost {name} n={n}: reconstruct {med['reconstruct']:.3f} s, rings "
                f"{med['rings']:.3f} s, joint {med['joint']:.3f} s (first {first['joint']:.3f} s), "
                f"before issue 16 {med['base']:.3f} s"
            )
    return rows


def main(argv=None):
    p = sectioned_parser(__doc__, ("kellogg", "checkerboard", "adaptive", "cost"))
    args = parse(p, argv)
    t0 = time.perf_counter()
    sizes = args.sizes or ([8, 16] if args.quick else [16, 32, 64, 128])
    payload = {"parameters": {"sizes": sizes, "ref_levels": args.ref_levels, "quick": args.quick}}
    payload = keep_sections("cross_points", args.only, args.quick, payload)
    if args.only in (None, "kellogg"):
        payload["kellogg"] = run_kellogg(sizes)
    if args.only in (None, "checkerboard"):
        csizes = [s for s in sizes if s <= 64] or sizes
        payload["checkerboard"] = run_checkerboard(csizes, 1 if args.quick else args.ref_levels)
    if args.only in (None, "adaptive") and not args.quick:
        payload["adaptive"] = run_adaptive()
    if args.only in (None, "cost"):
        payload["cost"] = run_cost([32] if args.quick else [256, 512], args.repeat)
    payload["rows"] = section_rows(payload, ("kellogg", "checkerboard", "adaptive", "cost"))
    payload["seconds"] = time.perf_counter() - t0
    finish("cross_points", payload, args.quick)


if __name__ == "__main__":
    main()
