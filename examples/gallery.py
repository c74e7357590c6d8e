"""Regenerate the figures of docs/gallery.md with the ``fastmem`` command line.

Every figure is made by the commands a user types (``fastmem run``,
``fastmem plot``, ``fastmem sweep``), called in-process through
``fastmem.cli.main.main``:

* ``single.png``: the default scene on a 128 x 128 square (``fastmem run``);
* ``adaptive.png``: the L-shape solved to a tolerance by adaptive refinement,
  beside uniform refinement (``fastmem run --tol``, ``fastmem plot --uniform``);
* ``heterogeneous.png``: a per-triangle tension that jumps across x = 0 (a
  scene built in Python, saved, then ``fastmem plot``);
* ``sweep.png``: a small parameter study (``fastmem sweep`` on a TOML file,
  then ``fastmem plot STUDY --x mu2 --y contact_fraction``).

The images are written at 100 dpi and stored with a 256-colour palette
(Pillow, which matplotlib installs), so that each stays under 300 KB for the
repository.  Needs the ``plot`` and ``dask`` extras.

Usage::

    python examples/gallery.py [FOLDER]

FOLDER defaults to ``$FASTMEM_EXAMPLES_OUT`` or the current folder; the
committed figures are made by ``python examples/gallery.py docs/gallery``.
"""

import os
import shutil
import sys
from pathlib import Path

import numpy as np

import fastmem as fm
from fastmem.cli.main import main as fastmem

MAX_BYTES = 300_000
DPI = "100"


def shrink(png: Path) -> int:
    """Store ``png`` with a 256-colour palette (dithered); return its size in bytes."""
    from PIL import Image

    with Image.open(png) as image:
        rgb = image.convert("RGB")
    palette = rgb.quantize(
        256, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.FLOYDSTEINBERG
    )
    palette.save(png, optimize=True)
    size = png.stat().st_size
    if size > MAX_BYTES:
        raise SystemExit(f"{png} has {size} bytes, more than the gallery's {MAX_BYTES}")
    return size


def run(*argv) -> None:
    """Run one ``fastmem`` command; stop the script if it fails."""
    argv = [str(a) for a in argv]
    print("$ fastmem " + " ".join(argv), flush=True)
    status = fastmem(argv)
    if status != 0:
        raise SystemExit(f"fastmem {argv[0]} exited with status {status}")


def single(out: Path, work: Path) -> Path:
    """Draw the default scene: one solve with the guaranteed bound."""
    archive = work / "single.h5"
    run("run", "--n", 128, "-q", "-o", archive)
    run("plot", archive, "-o", out / "single.png", "--dpi", DPI)
    return out / "single.png"


def adaptive(out: Path, work: Path) -> Path:
    """Draw the L-shape solved to a tolerance, beside the curve of uniform refinement."""
    archive = work / "adaptive.h5"
    run("run", "--domain", "lshape", "--n", 8, "--tol", "5e-3", "-q", "-o", archive)
    uniform = []
    for n in (16, 32, 64, 128):
        path = work / f"uniform-{n}.h5"
        run("run", "--domain", "lshape", "--n", n, "-q", "-o", path)
        uniform.append(path)
    run("plot", archive, "--uniform", *uniform, "-o", out / "adaptive.png", "--dpi", DPI)
    return out / "adaptive.png"


def heterogeneous(out: Path, work: Path) -> Path:
    """Membrane 1 ten times stiffer on the right half (per-triangle mu1)."""
    mesh = fm.Mesh.square(96)
    centroids = mesh.vertices[mesh.triangles].mean(axis=1)
    mu1 = np.where(centroids[:, 0] < 0.0, 1.0, 10.0)
    result = fm.solve(fm.Scene(mesh, mu=(mu1, 1.0), f=(-1.0, 1.0), g=0.1))
    archive = work / "heterogeneous.h5"
    result.save(archive)
    print(f"solved the heterogeneous scene: eta = {result.eta:.4e}")
    run("plot", archive, "-o", out / "heterogeneous.png", "--dpi", DPI)
    return out / "heterogeneous.png"


STUDY = """\
[sweep]
out = "study"

[grid]
n = 32
mu2 = [0.25, 0.5, 1.0, 2.0, 4.0]
g = [0.05, 0.1]
"""


def sweep(out: Path, work: Path) -> Path:
    """Draw a parameter study of the default problem: contact fraction against mu2."""
    toml = work / "study.toml"
    toml.write_text(STUDY)
    run("sweep", "-q", "--workers", 2, toml)
    run("plot", work / "study", "--x", "mu2", "--y", "contact_fraction", "-o", out / "sweep.png")
    return out / "sweep.png"


def main() -> None:
    """Make every figure of the gallery in the folder given (or the examples' output folder)."""
    folder = sys.argv[1] if len(sys.argv) > 1 else os.environ.get("FASTMEM_EXAMPLES_OUT", ".")
    out = Path(folder).resolve()
    out.mkdir(parents=True, exist_ok=True)
    work = out / "gallery-work"
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir()
    try:
        for make in (single, adaptive, heterogeneous, sweep):
            png = make(out, work)
            print(f"{png.name}: {shrink(png)} bytes")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
