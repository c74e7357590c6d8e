"""Peak resident memory per phase of the pipeline, for the default scene on the n x n square.

The whole pipeline (mesh -> scene -> solve with the bound -> archive) runs in a
fresh subprocess per size.  Phases are marked by wrapping the functions that
do them (found by identity in every ``fastmem`` module, so ``from x import f``
names are wrapped too):

* ``mesh``: ``Mesh.square`` and its topology (edges, patches, boundary);
* ``assembly``: stiffness, mass and load vectors;
* ``coarse chain``: the nested-iteration chain of coarser meshes and scenes;
* ``amg setup``: pyamg smoothed-aggregation hierarchies;
* ``newton``: the Newton-min loops (CG, linear steps, cheap estimators),
  outside the AMG setups and flux reconstructions they call;
* ``flux/estimators``: flux reconstructions and estimators (inside the
  solver's stopping tests and the final bound);
* ``archive``: ``result.save``.

The peak of each phase is exact, not sampled: at every phase boundary the
process's high-water mark (``VmHWM``) is read and reset (``echo 5 >
/proc/self/clear_refs``, Linux >= 4.0), so each segment's peak is charged to
the innermost phase active during it.  Reported per phase: the peak RSS
while in it (GB) and in bytes per vertex of the mesh; the overall peak and
the RSS of the retained objects (mesh, scene, result) at the end.

The inexact step frees its matrices and hierarchies during the flux
reconstructions only under memory pressure (``fastmem.solver.inexact.SPILL =
"auto"``); ``--spill on`` / ``off`` forces it, to measure what it saves on sizes
that fit without it.

    python -m bench.memory [--quick] [--sizes 1024 2048] [--spill auto|on|off]
"""

from __future__ import annotations

import argparse
import functools
import gc
import sys
import tempfile
import time
from pathlib import Path

from bench._common import emit_worker_result, finish, parse, parser, progress, run_worker

FULL_SIZES = [1024, 2048]
QUICK_SIZES = [32, 64]
PHASES = (
    "mesh",
    "assembly",
    "coarse chain",
    "amg setup",
    "newton",
    "flux/estimators",
    "archive",
)


def _status_kb(key: str) -> int:
    with open("/proc/self/status", encoding="ascii") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1])
    raise RuntimeError(f"{key} not in /proc/self/status")


class PhaseMemory:
    """Charge the peak RSS of every segment between phase boundaries to the innermost phase."""

    def __init__(self):
        self.stack = ["other"]
        self.peak = {}
        self._reset()

    @staticmethod
    def _reset():
        with open("/proc/self/clear_refs", "w", encoding="ascii") as fh:
            fh.write("5")

    def boundary(self):
        hwm = _status_kb("VmHWM") * 1024
        phase = self.stack[-1]
        self.peak[phase] = max(self.peak.get(phase, 0), hwm)
        self._reset()

    def enter(self, phase):
        self.boundary()
        self.stack.append(phase)

    def leave(self):
        self.boundary()
        self.stack.pop()

    def wrap(self, phase, fn):
        @functools.wraps(fn)
        def wrapped(*args, **kwargs):
            self.enter(phase)
            try:
                return fn(*args, **kwargs)
            finally:
                self.leave()

        return wrapped


def _install(tracker):
    """Wrap the phase functions wherever a fastmem module holds them."""
    import fastmem.estimators.bound
    import fastmem.estimators.flux
    import fastmem.fem.assembly
    import fastmem.io.writer
    import fastmem.linalg.amg
    import fastmem.solver.levels
    import fastmem.solver.newton

    targets = [
        (fastmem.fem.assembly, "assemble_stiffness", "assembly"),
        (fastmem.fem.assembly, "assemble_mass", "assembly"),
        (fastmem.fem.assembly, "assemble_load", "assembly"),
        (fastmem.solver.levels, "_chain", "coarse chain"),
        (fastmem.solver.newton, "newton_min", "newton"),
        (fastmem.estimators.flux, "reconstruct", "flux/estimators"),
        (fastmem.estimators.bound, "flux_terms", "flux/estimators"),
        (fastmem.estimators.bound, "evaluate", "flux/estimators"),
        (fastmem.io.writer, "write_archive", "archive"),
    ]
    wrapped = 0
    for module, name, phase in targets:
        original = getattr(module, name, None)
        if original is None:
            continue
        new = tracker.wrap(phase, original)
        for mod in list(sys.modules.values()):
            if getattr(mod, "__name__", "").startswith("fastmem") and mod is not None:
                for attr, value in list(vars(mod).items()):
                    if value is original:
                        setattr(mod, attr, new)
                        wrapped += 1
    cls = fastmem.linalg.amg.AMGPreconditioner
    cls.__init__ = tracker.wrap("amg setup", cls.__init__)
    return wrapped + 1


SPILL_MODES = {"auto": "auto", "on": True, "off": False}


def worker(n: int, spill: str = "auto") -> dict:
    import fastmem as fm
    import fastmem.solver.inexact
    from fastmem.memory import estimate_memory

    fastmem.solver.inexact.SPILL = SPILL_MODES[spill]

    fm.warm_up("inexact")  # kernels compiled or loaded before anything is measured
    gc.collect()
    tracker = PhaseMemory()
    _install(tracker)
    base = _status_kb("VmRSS") * 1024
    t0 = time.perf_counter()
    tracker.enter("mesh")
    mesh = fm.Mesh.square(n)
    _ = mesh.edges, mesh.triangle_edges, mesh.patch_ptr, mesh.interior_vertices
    _ = mesh.lumped_mass, mesh.boundary_vertex_mask
    tracker.leave()
    scene = fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    result = fm.solve(scene)
    with tempfile.TemporaryDirectory() as folder:
        result.save(Path(folder) / "run.h5")
    tracker.boundary()
    seconds = time.perf_counter() - t0
    retained = _status_kb("VmRSS") * 1024
    nv = mesh.n_vertices
    peaks = {p: tracker.peak.get(p, 0) for p in (*PHASES, "other")}
    return {
        "n": n,
        "spill": spill,
        "spilled": [lv.get("spill") for lv in result.parameters["solver"]["levels"]],
        "n_vertices": nv,
        "n_triangles": mesh.n_triangles,
        "seconds": seconds,
        "eta": result.eta,
        "rss_start_bytes": base,
        "rss_end_bytes": retained,
        "peak_bytes": peaks,
        "peak_bytes_per_vertex": {p: v / nv for p, v in peaks.items()},
        "overall_peak_bytes": max(peaks.values()),
        # the memory guard's estimate (fastmem.memory.estimate_memory) for this run
        "guard_estimate_bytes": estimate_memory(nv, mesh.n_triangles, "inexact", True),
    }


def main(argv=None):
    p = parser(__doc__)
    p.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument(
        "--spill",
        choices=sorted(SPILL_MODES),
        default="auto",
        help="spilling of the inexact step: auto (under memory pressure, default), on, off",
    )
    args = parse(p, argv)
    if args.worker is not None:
        emit_worker_result(worker(args.worker, args.spill))
        return 0
    sizes = args.sizes or (QUICK_SIZES if args.quick else FULL_SIZES)
    rows = []
    for n in sizes:
        progress(f"memory: n = {n}")
        row = run_worker("bench.memory", ["--worker", str(n), "--spill", args.spill])
        rows.append(row)
        gb = {k: f"{v / 1e9:.2f}" for k, v in row["peak_bytes"].items()}
        progress(f"  N = {row['n_vertices']}: peak {row['overall_peak_bytes'] / 1e9:.2f} GB; {gb}")
    payload = {
        "benchmark": "memory",
        "description": __doc__.split("\n\n")[0],
        "parameters": {
            "sizes": sizes,
            "scene": {"mu": [1.0, 1.0], "f": [-1.0, 1.0], "g": 0.1},
            "method": "inexact",
            "estimate": True,
            "spill": args.spill,
        },
        "phases": list(PHASES),
        "rows": rows,
    }
    finish("memory", payload, args.quick)
    return 0


if __name__ == "__main__":
    sys.exit(main())
