"""A parameter study on Dask: the contact area against the stiffness ratio and the gap.

Twelve scenes, four tensions μ2 of membrane 2 (μ1 = 1) times three boundary
values g of membrane 1, on a 32 × 32 mesh, solved by ``fm.sweep`` on a
LocalCluster of two worker processes, each result kept as its own archive.
The study is resumable: the script sweeps a second time at the end and that
sweep solves nothing (every run has a valid archive).  Needs the dask extra
(``pip install "fastmem[dask]"``); matplotlib draws the contact fraction
against μ2 if it is installed.

The factory ``make_scene`` is a module-level function: the workers import it
by name.  The ``if __name__ == "__main__"`` guard is required, because the
worker processes start by importing this script.

Output in ``$FASTMEM_EXAMPLES_OUT`` (default: the current folder): the study
folder ``parameter_study/`` (``sweep-index.h5``, ``runs/*.h5``) and
``parameter_study/contact_fraction-vs-mu2.png``.
"""

import os
from pathlib import Path

import fastmem as fm


def make_scene(mu2, g, n=32):
    """One scene of the study: the default loads, tension μ2 and boundary value g."""
    return fm.Scene(fm.Mesh.square(n), mu=(1.0, mu2), f=(-1.0, 1.0), g=g)


def main() -> None:
    """Sweep, print the table, sweep again (nothing to do), plot."""
    out = Path(os.environ.get("FASTMEM_EXAMPLES_OUT", ".")) / "parameter_study"
    grid = {"mu2": [0.25, 1.0, 4.0, 16.0], "g": [0.0, 0.05, 0.1]}

    table = fm.sweep(make_scene, grid, out, workers=2)  # a LocalCluster of 2 processes
    columns = ["mu2", "g", "status", "contact_fraction", "eta", "newton_steps", "seconds"]
    print(table[columns].to_string(index=False))
    print(f"largest bound: eta = {table.eta.max():.4e}")

    before = len((out / "archive-writes.log").read_text().splitlines())
    again = fm.sweep(make_scene, grid, out, workers=2)
    after = len((out / "archive-writes.log").read_text().splitlines())
    print(f"second sweep: {(again.status == 'done').sum()} runs done, {after - before} solved")

    try:
        from fastmem.cli.sweep import plot_sweep

        png = out / "contact_fraction-vs-mu2.png"
        plot_sweep(out, "mu2", "contact_fraction", out=png)
        print(f"wrote {png}")
    except ImportError:
        print("matplotlib is not installed: no plot")


if __name__ == "__main__":
    main()
