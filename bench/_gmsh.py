"""gmsh meshes for the benchmarks (None when the gmsh package is not installed)."""


def mesh(name, add_geometry, size):
    """Frontal-Delaunay mesh of element size ``size`` of the geometry ``add_geometry(occ)`` adds.

    ``add_geometry`` receives ``gmsh.model.occ``; the mesh goes through a
    ``.msh`` file and :meth:`fastmem.Mesh.read`, as a user's would.  Returns
    None without the gmsh package.
    """
    try:
        import gmsh
    except ImportError:
        return None
    import os
    import tempfile

    import fastmem as fm

    gmsh.initialize(["-noenv"], readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add(name)
        add_geometry(gmsh.model.occ)
        gmsh.model.occ.synchronize()
        gmsh.option.setNumber("Mesh.MeshSizeMin", size)
        gmsh.option.setNumber("Mesh.MeshSizeMax", size)
        gmsh.option.setNumber("Mesh.Algorithm", 6)
        gmsh.option.setNumber("Mesh.RandomSeed", 1.0)
        gmsh.model.mesh.generate(2)
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, f"{name}.msh")
            gmsh.write(path)
            return fm.Mesh.read(path)
    finally:
        gmsh.finalize()
