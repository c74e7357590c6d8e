"""Read a fastmem archive with plain h5py, without fastmem.

A result saved by ``result.save(path)`` (or ``fastmem run -o path``) is an
ordinary HDF5 file: any HDF5 tool reads it (h5py, h5dump, HDFView, MATLAB,
Julia...).  This script solves a small problem, saves it, then walks the file
with h5py: every group and dataset with its shape, dtype and attributes,
and reads the mesh and the solution u1 back as NumPy arrays.  Only the first
part uses fastmem; the second would work on a machine without it.

The file starts with a 512-byte user block that holds fastmem's checksum
header; HDF5 skips it by itself.  Change an archive only through fastmem
(load, modify a copy, save): an edit made with h5py breaks the checksum, and
``fastmem.load`` then refuses the file.

Output: ``small.h5`` in ``$FASTMEM_EXAMPLES_OUT`` (default: the current folder).
"""

import json
import os
from pathlib import Path

import h5py
import numpy as np


def make_archive(path: Path) -> None:
    """Solve a small default scene with fastmem and save it to ``path``."""
    import fastmem as fm

    scene = fm.Scene(fm.Mesh.square(32), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    fm.solve(scene).save(path)
    print(f"fastmem saved {path}")


def show(name: str, obj) -> None:
    """Print one group or dataset of the file and its attributes (a visititems callback)."""
    if isinstance(obj, h5py.Dataset):
        print(f"  /{name}  dataset {obj.shape} {obj.dtype}")
    else:
        print(f"  /{name}/  group")
    for key, value in obj.attrs.items():
        text = str(value)
        print(f"      @{key} = {text[:70] + '...' if len(text) > 70 else text}")


def main() -> None:
    """Write an archive, then list and read it with h5py."""
    out = Path(os.environ.get("FASTMEM_EXAMPLES_OUT", "."))
    path = out / "small.h5"
    make_archive(path)

    # from here on: h5py and NumPy only
    with h5py.File(path, "r") as f:
        print(f"root attributes of {path.name}:")
        for key, value in f.attrs.items():
            if key != "scene":
                print(f"  @{key} = {value}")
        scene = json.loads(f.attrs["scene"])  # the scene and solver settings, as JSON
        print(f"  @scene = JSON with keys {sorted(scene)}")
        print("contents:")
        f.visititems(show)

        vertices = f["mesh/vertices"][()]  # (N, 2) float64
        triangles = f["mesh/triangles"][()]  # (M, 3) int64, counter-clockwise
        u1 = f["solution/u1"][()]  # (N,), nodal values of membrane 1
        lam = f["solution/lambda"][()]  # (N,), nodal contact pressure
        eta = f["estimators"].attrs["eta"] if "estimators" in f else None

    print(f"mesh: {vertices.shape[0]} vertices, {triangles.shape[0]} triangles")
    centre = np.argmin(np.hypot(vertices[:, 0], vertices[:, 1]))
    print(f"u1 at the vertex {vertices[centre].tolist()}: {u1[centre]:.6f}")
    print(f"u1 in [{u1.min():.4f}, {u1.max():.4f}], lambda max {lam.max():.4f}")
    print(f"eta = {eta:.4e}" if eta is not None else "no estimate in this archive")


if __name__ == "__main__":
    main()
