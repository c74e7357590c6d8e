"""Mesh a disk with a hole in gmsh, read the .msh file with fastmem and solve on it.

Shows how to bring a mesh from a mesh generator: the gmsh Python API (the
``gmsh`` wheel from PyPI, used headless here) builds an annulus, writes it as
a ``.msh`` file into the output folder, and :meth:`fastmem.Mesh.read` reads it
(any 2D triangle mesh that meshio reads works the same way; geometry points
and line elements of the file are dropped).  The default data are solved on
it with the guaranteed error bound.

Output: ``annulus.msh`` in ``$FASTMEM_EXAMPLES_OUT`` (default: the current
folder).  Without gmsh installed (``pip install gmsh``) the script says so
and exits successfully.
"""

import os
import sys
from pathlib import Path

import fastmem as fm


def build_annulus(path: Path, h: float = 0.06) -> None:
    """Write a triangle mesh of the annulus 0.3 < r < 1 with element size ``h`` to ``path``."""
    import gmsh

    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)  # no log on stdout
        gmsh.model.add("annulus")
        outer = gmsh.model.occ.addDisk(0.0, 0.0, 0.0, 1.0, 1.0)
        inner = gmsh.model.occ.addDisk(0.0, 0.0, 0.0, 0.3, 0.3)
        gmsh.model.occ.cut([(2, outer)], [(2, inner)])
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMin", h)
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.model.mesh.generate(2)
        gmsh.write(str(path))
    finally:
        gmsh.finalize()


def main() -> None:
    """Mesh, read, solve, print."""
    try:
        import gmsh  # noqa: F401
    except ImportError:
        print("gmsh is not installed (pip install gmsh): nothing to do")
        sys.exit(0)
    out = Path(os.environ.get("FASTMEM_EXAMPLES_OUT", "."))
    msh = out / "annulus.msh"
    build_annulus(msh)
    print(f"gmsh wrote {msh}")

    mesh = fm.Mesh.read(msh)
    print(f"read {mesh}: {mesh.boundary_vertices.size} boundary vertices, h = {mesh.h:.3f}")

    # g = 0.1 on the outer and the inner circle: the membranes are held apart on both
    scene = fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    result = fm.solve(scene)
    print(f"Newton-min steps: {result.n_newton}, converged: {result.converged}")
    print(f"contact fraction: {result.contact_fraction:.3f}")
    print(f"eta = {result.eta:.4e}")


if __name__ == "__main__":
    main()
