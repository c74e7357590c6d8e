"""Solve to a guaranteed tolerance by adaptive mesh refinement on an L-shaped domain.

Instead of choosing a mesh size, give a tolerance: ``fm.solve(scene,
tol=...)`` refines the mesh where the estimators locate the error (Dörfler
marking, newest-vertex bisection; docs/method.md §9) until the guaranteed
bound η of the returned solution is below ``tol``.  The re-entrant corner
of the L-shape makes the exact solution singular there, which uniform
refinement resolves slowly and adaptive refinement quickly.  The script
prints one row per mesh of ``result.adaptivity`` and saves the final result.

Output: ``lshape_tol.h5`` in ``$FASTMEM_EXAMPLES_OUT`` (default: the current
folder); ``fastmem plot lshape_tol.h5`` draws η against N and the final mesh.
"""

import os
from pathlib import Path

import fastmem as fm


def main() -> None:
    """Solve to tol, print the per-mesh table, save."""
    out = Path(os.environ.get("FASTMEM_EXAMPLES_OUT", "."))
    tol = 5e-3
    scene = fm.Scene(fm.Mesh.lshape(8), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    print(f"solving {scene} to eta <= {tol:g}")
    result = fm.solve(scene, tol=tol)

    table = result.adaptivity  # dict of columns, one row per mesh
    print(f"{'mesh':>4} {'vertices':>9} {'eta':>10} {'eta_disc':>10} {'marked':>7} {'seconds':>8}")
    for i in range(len(table["level"])):
        seconds = table["solve_seconds"][i] + table["refine_seconds"][i]
        print(
            f"{table['level'][i]:4d} {table['n_vertices'][i]:9d} {table['eta'][i]:10.3e} "
            f"{table['eta_disc'][i]:10.3e} {table['marked_fraction'][i]:7.1%} {seconds:8.2f}"
        )
    stop = result.parameters["adaptivity"]["stop_reason"]
    print(f"converged: {result.converged} ({stop}); final {result.mesh}, eta = {result.eta:.4e}")

    path = out / "lshape_tol.h5"
    result.save(path)
    print(f"saved {path}")


if __name__ == "__main__":
    main()
