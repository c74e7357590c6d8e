"""Sub-steps of the scaling benchmark's ``mesh`` phase, in a fresh process per size.

    python -m bench.mesh_phase_profile [--quick] [--state asis|cold|warm] [--sizes 1024 2048 4096]

Each size runs in its own subprocess (first repetition, which pays the first-touch
page faults of new memory, as bench.scaling's first repetition does); the kernels are
loaded on a tiny mesh first.  Every wrapped function reports wall time, user and
system CPU time and minor page faults (resource.getrusage of the process).

``--state`` controls the memory the fresh process gets.  On this machine (a
Firecracker VM with virtio-balloon free page reporting) guest memory freed for a
few seconds is handed back to the host, and touching it again costs ~2 s per GB
of system time (host faults) instead of ~0.07 s per GB for memory freed just
before: the phase's time depends on what ran before it.  ``asis``: no control
(as bench.scaling's workers); ``cold``: the worker first touches and holds
256 MB blocks until two in a row are slow (it has eaten the recently freed,
still host-backed memory), so the phase gets memory that must be faulted in
from the host; ``warm``: a helper process touches and frees 6 GB just before
the worker, so the phase gets host-backed memory.
"""

import json
import math
import resource
import subprocess
import sys
import time

STEPS = []


def _usage():
    r = resource.getrusage(resource.RUSAGE_SELF)
    return time.perf_counter(), r.ru_utime, r.ru_stime, r.ru_minflt


def _wrap(owner, name, label):
    f = getattr(owner, name)

    def wrapped(*a, **k):
        u0 = _usage()
        depth = len(_STACK)
        _STACK.append(label)
        try:
            return f(*a, **k)
        finally:
            _STACK.pop()
            u1 = _usage()
            STEPS.append((depth, label, *(b - a_ for a_, b in zip(u0, u1, strict=False))))

    setattr(owner, name, wrapped)


_STACK = []


def _hwm():
    """Peak resident memory of the process (VmHWM), MB."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM"):
                return int(line.split()[1]) / 1024
    return 0.0


def _eat_warm_memory():
    """Touch and keep 256 MB blocks until two in a row take > 0.15 s (cold memory)."""
    import numpy as np

    keep, slow = [], 0
    while slow < 2 and len(keep) < 24:  # at most 6 GB (more would add memory pressure)
        t0 = time.perf_counter()
        keep.append(np.ones(2**25))
        slow = slow + 1 if time.perf_counter() - t0 > 0.15 else 0
    return keep


def worker(n, state="asis"):
    import numpy as np

    ballast = _eat_warm_memory() if state == "cold" else []  # held during the phase

    from fastmem.kernels import assembly as ka
    from fastmem.kernels import topology as kt

    import fastmem as fm
    from fastmem.mesh import mesh as fmesh

    m = fm.Mesh.square(8)
    _ = m.edges, m.triangle_edges, m.patch_ptr, m.interior_vertices
    for owner, name, label in [
        (fmesh, "_as_vertices", "init: _as_vertices"),
        (fmesh, "_as_triangles", "init: _as_triangles"),
        (ka, "area2_and_diameter2", "init: area2_and_diameter2"),
        (kt, "rectangle_triangles", "rectangle_triangles"),
        (kt, "triangle_checks", "init: triangle_checks"),
        (np, "bincount", "np.bincount"),
        (fm.Mesh, "__init__", "Mesh.__init__"),
        (fm.Mesh, "_init", "Mesh._init"),
        (kt, "edge_topology", "edge_topology"),
        (kt, "_sort_half_edges", "  _sort_half_edges"),
        (kt, "_number_edges", "  _number_edges"),  # serial before this branch only
        (fm.Mesh, "_set_topology", "  _set_topology"),
        (kt, "vertex_patches", "vertex_patches"),
        (kt, "_fill_patches", "  _fill_patches"),
    ]:
        if name == "_number_edges" and hasattr(kt, "_count_edges"):
            continue  # runs in threads here: timed within edge_topology
        if hasattr(owner, name):
            _wrap(owner, name, label)
    rows = []
    hwm0 = _hwm()

    def step(label, fn):
        STEPS.clear()
        u0 = _usage()
        out = fn()
        u1 = _usage()
        rows.append(
            [label, *(b - a for a, b in zip(u0, u1, strict=False)), _hwm() - hwm0, list(STEPS)]
        )
        return out

    import gc

    gc.collect()
    t0 = time.perf_counter()
    mesh = step("Mesh.square", lambda: fm.Mesh.square(n))
    step("edges", lambda: mesh.edges)
    step("triangle_edges", lambda: mesh.triangle_edges)
    step("patch_ptr", lambda: mesh.patch_ptr)
    step("interior_vertices", lambda: mesh.interior_vertices)
    total = time.perf_counter() - t0
    print(json.dumps({"n": n, "total": total, "rows": rows, "ballast_blocks": len(ballast)}))


def measure(sizes, state="asis"):
    """One fresh worker process per size; returns their rows."""
    out = []
    for n in sizes:
        if state == "warm":
            subprocess.run(
                [sys.executable, "-c", "import numpy as np; a = np.ones(6 * 2**27)"], check=True
            )
        p = subprocess.run(
            [sys.executable, __file__, "--worker", str(n), state], capture_output=True, text=True
        )
        if p.returncode:
            sys.exit(p.stderr)
        out.append(json.loads(p.stdout.strip().splitlines()[-1]))
    return out


def show(out):
    """Print the sub-steps of every size and the pairwise exponents."""
    for r in out:
        print(f"n = {r['n']}: phase {r['total']:.3f} s (ballast {r['ballast_blocks']} x 256 MB)")
        print(
            f"  {'step':34s} {'wall':>7s} {'user':>7s} {'sys':>7s} {'minflt':>9s} {'+HWM MB':>8s}"
        )
        for label, w, u, s, f, hwm, sub in r["rows"]:
            print(f"  {label:34s} {w:7.3f} {u:7.3f} {s:7.3f} {f:9d} {hwm:8.0f}")
            for depth, sl, sw, su, ss, sf in sub:
                print(f"    {'  ' * depth}{sl:30s} {sw:7.3f} {su:7.3f} {ss:7.3f} {sf:9d}")
    for a, b in zip(out, out[1:], strict=False):
        na, nb = (a["n"] + 1) ** 2, (b["n"] + 1) ** 2
        print(
            f"exponent {a['n']}->{b['n']}: "
            f"{math.log(b['total'] / a['total']) / math.log(nb / na):.3f}"
        )


def main(argv=None):
    from bench._common import finish, parse, parser

    p = parser(__doc__, repeat=1)
    p.add_argument("--state", choices=("asis", "cold", "warm"), default="asis")
    args = parse(p, argv)
    sizes = args.sizes or ([16, 32] if args.quick else [1024, 2048, 4096])
    state = "asis" if args.quick else args.state
    out = measure(sizes, state)
    show(out)
    pairs = []
    for a, b in zip(out, out[1:], strict=False):
        na, nb = (a["n"] + 1) ** 2, (b["n"] + 1) ** 2
        pairs.append([a["n"], b["n"], math.log(b["total"] / a["total"]) / math.log(nb / na)])
    payload = {"parameters": {"sizes": sizes, "state": state}, "rows": out, "exponents": pairs}
    finish("mesh_phase_profile", payload, args.quick)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        worker(int(sys.argv[2]), sys.argv[3])
    else:
        main()
