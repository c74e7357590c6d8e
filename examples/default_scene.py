"""Solve the default scene and look at the guaranteed error bound and its parts.

The default scene of ``fastmem run`` (docs/method.md §8): two membranes over
the square (-1, 1)², tensions μ1 = μ2 = 1, loads f1 = -1 (membrane 1 pushed
down) and f2 = 1 (membrane 2 pushed up), membrane 1 held at g = 0.1 on the
boundary, on a 128 × 128 structured mesh.  The default solver (adaptive
inexact Newton-min) returns the discrete solution with a guaranteed upper
bound η of its energy error, which is printed with its three components and
saved, with everything else, in an HDF5 archive.

Output: ``default_scene.h5`` in ``$FASTMEM_EXAMPLES_OUT`` (default: the
current folder).
"""

import os
from pathlib import Path

import fastmem as fm


def main() -> None:
    """Solve, print, save."""
    out = Path(os.environ.get("FASTMEM_EXAMPLES_OUT", "."))
    mesh = fm.Mesh.square(128)
    scene = fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    print(f"solving {scene}")
    result = fm.solve(scene)  # method="inexact": AMG-CG stopped by the estimators

    levels = result.parameters["solver"]["levels"]  # nested iteration: coarsest mesh first
    steps = sum(level["newton"] for level in levels)
    print(f"converged: {result.converged}; Newton-min steps: {result.n_newton} on this mesh,")
    first = levels[0]["n_vertices"]
    print(f"  {steps} in all over {len(levels)} nested meshes (the first with {first} vertices)")
    print(f"contact fraction: {result.contact_fraction:.4f} of the domain")
    print(f"max gap u1 - u2: {result.gap.max():.4e}, max pressure: {result.lam.max():.4e}")
    print(f"eta = {result.eta:.4e}   (guaranteed: energy error <= eta)")
    totals = result.estimate.totals
    for name in ("eta_disc", "eta_lin", "eta_alg"):
        print(f"  {name:8s} = {totals[name]:.4e}")
    # the components bound parts of the error; eta <= their sum, and eta may be
    # smaller than eta_disc alone (docs/method.md §6)
    parts = totals["eta_disc"] + totals["eta_lin"] + totals["eta_alg"]
    print(f"  sum      = {parts:.4e} >= eta")

    path = out / "default_scene.h5"
    result.save(path)
    print(f"saved {path}")


if __name__ == "__main__":
    main()
