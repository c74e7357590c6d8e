"""Floppy membranes: the layer bound's effectivity and cost (:mod:`fastmem.estimators.layers`).

Issue 16.

Four sections, written to ``bench/results/layers.json``:

* ``checkerboard``: mu1 in {1, c} on 4 x 4 squares, mu2 = 1, g = 0.1 (the scene
  of bench/effectivity.py), exact solves, n = 16 ... 64 against a solution
  ``--ref-levels`` refinements finer.  For each triple: the bound as returned
  (the smaller of the layer bound and the standard one), the standard bound
  alone (``fastmem.estimators.layers.LAYER_BOUND = False``), the layer bound without the
  cross-point cut and without the connected squeeze, the reference error and the
  bracket of the true effectivity that the reference allows,
  [eta / (err_ref^2 + eta_ref^2)^(1/2), eta / err_ref] (eta_ref: the
  reference's own bound; Galerkin orthogonality, approximate with contact).
  Note: no reference resolves the floppy layer (width 4.5e-4 for c = 1e-6),
  so err_ref misses its energy and eta / err_ref overstates the effectivity.
* ``lshape``: the two-material L-shape (mu1 = 1 for x < 0, c for x > 0), the
  same columns.
* ``cost``: seconds of the whole bound (``fastmem.estimators.bound.estimate``): the
  standard bound alone, with the layer bound but without the cross-point cut,
  without the connected squeeze (``CONNECTED_BAND = False``) and as shipped, on
  the same triple: first call on a fresh scene (with its
  factorisations) and median of ``--repeat`` alternating calls.

* ``adaptive_reference``: the floppy rows (checkerboard and L-shape, c = 1e-6,
  f = (-1, 1)) against a reference that resolves the layer: ``fm.solve(scene,
  tol=...)`` started from the coarse mesh itself, so the coarse P1 solution is
  exactly a function of the adapted mesh (located there, no interpolation
  error); bracket [eta / (err_ref^2 + eta_ref^2)^(1/2), eta / err_ref] as above.
  On the checkerboard the loop stops at the open cross point (-0.5, -0.5), a
  singularity r^0.0013 (contrast 1e6) that no mesh resolves, so eta_ref stays
  near 0.016 there.

``--only SECTION`` re-runs one section and keeps the others of the existing file.

    python -m bench.layers [--quick] [--repeat 5] [--ref-levels 3]
"""

from __future__ import annotations

import math
import statistics
import time

from bench._common import finish, keep_sections, parse, progress, section_rows, sectioned_parser
from bench.effectivity import (
    chain_solutions,
    checkerboard,
    error_vs_reference,
    reference_chain,
    two_materials,
)

CHECKER = tuple((c, f) for c in (1e-6, 1e-3, 1e3, 1e6) for f in ((-1.0, 1.0), (-4.0, 2.0)))
LSHAPE = (1e-6, 1e-3)


def _bounds(scene, r):
    """(eta as returned, standard eta, eta without the cross-point cut, eta without the
    connected squeeze, layer used)."""
    import fastmem.estimators.layers as fl
    from fastmem.estimators.bound import estimate

    est = estimate(scene, r.u1, r.u2, r.lam)
    try:
        fl.LAYER_BOUND = False
        plain = estimate(scene, r.u1, r.u2, r.lam)
        fl.LAYER_BOUND, fl.CUT_CROSS_POINTS = True, False
        uncut = estimate(scene, r.u1, r.u2, r.lam)
        fl.CUT_CROSS_POINTS, fl.CONNECTED_BAND = True, False
        per_triangle = estimate(scene, r.u1, r.u2, r.lam)
    finally:
        fl.LAYER_BOUND, fl.CUT_CROSS_POINTS, fl.CONNECTED_BAND = True, True, True
    used = bool(est.totals.get("layer_bound", 0.0))
    etas = (est, plain, uncut, per_triangle)
    return (*(e.totals["eta"] for e in etas), used)


def _table(family, cases, sizes, ref_levels):
    import fastmem as fm

    make = fm.Mesh.square if family == "checkerboard" else fm.Mesh.lshape
    mu_of = checkerboard if family == "checkerboard" else two_materials
    rows = []
    for c, f in cases:
        # direct solve: with mu = 1e-6 an iterative reference's own bound is its algebraic
        # error times 1e3 (eta_alg), which would make the bracket useless
        chain, ref_scene, ref = reference_chain(make, mu_of, c, f, sizes, ref_levels, "exact")
        fine = chain[-1]
        for n, scene, r, err, hi in chain_solutions(chain, ref_scene, ref, sizes, mu_of, c, f):
            eta, plain, uncut, per_triangle, used = _bounds(scene, r)
            # the default (inexact) solve of the same scene against the same reference
            ri = fm.solve(scene, estimate=True)
            level = round(math.log2(n / sizes[0]))  # chain[level] is the mesh of size n
            err_i = error_vs_reference(chain, level, ri.u1, ri.u2, ref_scene, ref)
            rows.append(
                {
                    "family": family,
                    "c": c,
                    "f": list(f),
                    "n": n,
                    "ref_vertices": fine.n_vertices,
                    "err_ref": err,
                    "eta_ref": float(ref.eta),
                    "eta": eta,
                    "eta_standard": plain,
                    "eta_without_cut": uncut,
                    "eta_without_connected_squeeze": per_triangle,
                    "layer_bound_used": used,
                    "effectivity_vs_ref": eta / err,
                    "inexact_eta": float(ri.eta),
                    "inexact_err_ref": err_i,
                    "inexact_effectivity_vs_ref": float(ri.eta) / err_i,
                    "effectivity_bracket": [eta / hi, eta / err],
                    "standard_effectivity_vs_ref": plain / err,
                }
            )
            progress(
                f"  {family} c={c:g} f={f} n={n}: eta/err_ref {eta / err:.3f} (standard "
                f"{plain / err:.3f}, no cut {uncut / err:.3f}, per-triangle squeeze "
                f"{per_triangle / err:.3f}; inexact {ri.eta / err_i:.3f}), bracket "
                f"[{eta / hi:.3f}, {eta / err:.3f}]"
            )
    return rows


#: the bound's variants timed by the cost section: (LAYER_BOUND, CUT_CROSS_POINTS,
#: CONNECTED_BAND)
VARIANTS = {
    "standard": (False, True, True),
    "layer_without_cut": (True, False, True),
    "layer_without_connected_squeeze": (True, True, False),
    "layer": (True, True, True),
}


def run_cost(sizes, repeat):
    import fastmem as fm
    import fastmem.estimators.layers as fl
    from fastmem.estimators.bound import estimate

    rows = []
    for c, f in ((1e-6, (-1.0, 1.0)), (1e-3, (-1.0, 1.0)), (1e-3, (-4.0, 2.0))):
        for n in sizes:
            mesh = fm.Mesh.square(n)
            scene = fm.Scene(mesh, mu=(checkerboard(mesh, c), 1.0), f=f, g=0.1)
            r = fm.solve(scene, method="exact-amg", estimate=False)

            def run(name, scene=scene, r=r):
                fl.LAYER_BOUND, fl.CUT_CROSS_POINTS, fl.CONNECTED_BAND = VARIANTS[name]
                try:
                    t = time.perf_counter()
                    eta = estimate(scene, r.u1, r.u2, r.lam).eta
                    return time.perf_counter() - t, eta
                finally:
                    fl.LAYER_BOUND, fl.CUT_CROSS_POINTS, fl.CONNECTED_BAND = True, True, True

            # first calls, each on a fresh scene: every variant builds what it caches there
            # (its factorisations); then alternating repetitions on one scene
            first, eta = {}, {}
            for name in VARIANTS:
                fresh = fm.Scene(mesh, mu=(checkerboard(mesh, c), 1.0), f=f, g=0.1)
                first[name], eta[name] = run(name, fresh)
            times = {name: [] for name in VARIANTS}
            for _ in range(repeat):
                for name in VARIANTS:
                    times[name].append(run(name)[0])
            med = {k: statistics.median(v) for k, v in times.items()}
            rows.append(
                {
                    "scene": f"checkerboard {c:g}, f = {f}",
                    "n": n,
                    "vertices": mesh.n_vertices,
                    "eta": eta,
                    "first_seconds": first,
                    "median_seconds": med,
                    "bound_with_layer_over_standard": med["layer"] / med["standard"],
                    "layer_without_cut_over_standard": med["layer_without_cut"] / med["standard"],
                    "layer_over_layer_without_connected_squeeze": med["layer"]
                    / med["layer_without_connected_squeeze"],
                }
            )
            progress(
                f"  cost c={c:g} f={f} n={n}: standard {med['standard']:.3f} s, layer without "
                f"cut {med['layer_without_cut']:.3f} s, without the connected squeeze "
                f"{med['layer_without_connected_squeeze']:.3f} s, layer {med['layer']:.3f} s "
                f"(first {first['layer']:.3f} s); eta {eta}"
            )
    return rows


#: (family, c, f, tolerance of the adaptive reference)
ADAPTIVE_REFERENCE = (
    ("checkerboard", 1e-6, (-1.0, 1.0), 7e-3),
    ("lshape", 1e-6, (-1.0, 1.0), 2e-3),
)


def run_adaptive_reference(sizes, quick=False):
    import numpy as np

    import fastmem as fm
    from bench.effectivity import energy
    from fastmem.estimators.bound import estimate
    from fastmem.mesh.coarsen import locate

    rows = []
    for family, c, f, tol in ADAPTIVE_REFERENCE:
        tol = max(tol, 0.05) if quick else tol  # --quick: a smoke run
        make = fm.Mesh.square if family == "checkerboard" else fm.Mesh.lshape
        mu_of = checkerboard if family == "checkerboard" else two_materials
        for n in sizes:
            mesh = make(n)
            scene = fm.Scene(mesh, mu=(mu_of(mesh, c), 1.0), f=f, g=0.1)
            r = fm.solve(scene, method="exact")
            eta = estimate(scene, r.u1, r.u2, r.lam).eta
            t = time.perf_counter()
            ref = fm.solve(scene, tol=tol)
            seconds = time.perf_counter() - t
            fine = ref.mesh
            tri, bary = locate(mesh, fine.vertices)  # nested: exact values of the coarse P1
            if np.any(tri < 0):
                raise RuntimeError("adapted mesh not inside the coarse one")
            u1, u2 = ((u[mesh.triangles[tri]] * bary).sum(axis=1) for u in (r.u1, r.u2))
            err = energy(fine, (mu_of(fine, c), 1.0), ref.u1 - u1, ref.u2 - u2)
            hi = float(np.hypot(err, ref.eta))
            rows.append(
                {
                    "family": family,
                    "c": c,
                    "f": list(f),
                    "n": n,
                    "eta": eta,
                    "ref_tol": tol,
                    "ref_vertices": fine.n_vertices,
                    "ref_converged": bool(ref.converged),
                    "ref_stop_reason": ref.parameters["adaptivity"]["stop_reason"],
                    "ref_seconds": seconds,
                    "err_ref": err,
                    "eta_ref": float(ref.eta),
                    "effectivity_bracket": [eta / hi, eta / err],
                }
            )
            progress(
                f"  adaptive reference {family} c={c:g} n={n}: eta {eta:.4g}, err_ref {err:.4g}, "
                f"eta_ref {ref.eta:.3g} ({fine.n_vertices} vertices, {seconds:.0f} s), "
                f"bracket [{eta / hi:.3f}, {eta / err:.3f}]"
            )
    return rows


def main(argv=None):
    sections = ("checkerboard", "lshape", "cost", "adaptive_reference")
    p = sectioned_parser(__doc__, sections)
    args = parse(p, argv)
    t0 = time.perf_counter()
    sizes = args.sizes or ([8] if args.quick else [16, 32, 64])
    levels = 1 if args.quick else args.ref_levels
    payload = {"parameters": {"sizes": sizes, "ref_levels": levels, "quick": args.quick}}
    payload = keep_sections("layers", args.only, args.quick, payload)
    if args.only in (None, "checkerboard"):
        cases = CHECKER[:1] if args.quick else CHECKER
        payload["checkerboard"] = _table("checkerboard", cases, sizes, levels)
    if args.only in (None, "lshape"):
        cases = [(c, (-1.0, 1.0)) for c in (LSHAPE[:1] if args.quick else LSHAPE)]
        payload["lshape"] = _table("lshape", cases, sizes, levels)
    if args.only in (None, "cost"):
        repeat = 1 if args.quick else args.repeat
        payload["cost"] = run_cost([16] if args.quick else [256, 512], repeat)
    if args.only in (None, "adaptive_reference"):
        payload["adaptive_reference"] = run_adaptive_reference(
            [8] if args.quick else sizes, args.quick
        )
    payload["rows"] = section_rows(payload, sections)
    payload["seconds"] = time.perf_counter() - t0
    finish("layers", payload, args.quick)


if __name__ == "__main__":
    main()
