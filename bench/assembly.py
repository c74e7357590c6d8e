"""Assembly benchmark: fastmem P1 stiffness/mass/load versus scikit-fem.

Splits fastmem's time into the local-matrix kernel (COO values), the gather
into CSR, the once-per-mesh pattern and position map, and reports Numba
compilation separately (a fresh process with an empty cache, and one with a
warm cache).  Checks that both codes assemble the same matrix.

Callable loads: one pass of the manufactured load ``f1`` (``fastmem.problems.
Manufactured``) over the quadrature points of degree 5, the load vector alone and
with the flux moments and the oscillation
(:func:`fastmem.fem.callables.callable_integrals`), in blocks of 2^17 triangles
(before 2026-12-02), in blocks of 2^13 (the default) and with ``parallel=True``
(``Scene(parallel_callables=True)``); checks that all give the same bits.

    python -m bench.assembly [--quick] [--sizes 256 1024 2048] [--results DIR]
"""

import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from bench._common import finish, parse, parser, peak_rss_mb, progress, timed

_COMPILE_SNIPPET = """
import time
t0 = time.perf_counter()
import fastmem as fm
from fastmem.fem.assembly import assemble_stiffness, assemble_mass, assemble_load
t1 = time.perf_counter()
m = fm.Mesh.square(4)
assemble_stiffness(m); assemble_mass(m); assemble_load(m, lambda x, y: x)
t2 = time.perf_counter()
print(t1 - t0, t2 - t1)
"""


def compile_times():
    """Import and first-call times in fresh processes: empty Numba cache, then warm cache."""
    out = {}
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for label in ("cold_cache", "warm_cache"):
            res = subprocess.run(
                [sys.executable, "-c", _COMPILE_SNIPPET],
                env=env,
                capture_output=True,
                text=True,
                check=True,
            )
            imp, first = map(float, res.stdout.split())
            out[label] = {"import_s": imp, "first_calls_s": first}
    return out


#: (label, block size, parallel) of the callable-load passes
CALLABLE_CASES = (
    ("block_2^17", 1 << 17, False),
    ("block_2^13", 1 << 13, False),
    ("block_2^13_parallel", 1 << 13, True),
)


def callable_loads(mesh, repeat):
    """Seconds of one callable-load pass per case (:data:`CALLABLE_CASES`); same bits?"""
    from fastmem.fem import callables
    from fastmem.problems import Manufactured

    f = Manufactured().f1
    block = callables.BLOCK
    times, first = {}, {}
    identical = True
    try:
        for label, size, parallel in CALLABLE_CASES:
            callables.BLOCK = size
            for want in (False, True):
                out, t = timed(
                    lambda: callables.callable_integrals(mesh, f, 5, "f1", want, parallel),
                    repeat,
                )
                key = f"{label}{'_moments' if want else ''}"
                times[key] = t
                ref = first.setdefault(want, out)
                identical &= all(np.array_equal(out[k], ref[k]) for k in ref)
    finally:
        callables.BLOCK = block
    return {"callable_load_s": times, "callable_identical": bool(identical)}


def run(sizes, repeat):
    from fastmem.kernels import assembly as k
    from fastmem.kernels import sparsity as ks

    import fastmem as fm
    from fastmem.fem.assembly import assemble_stiffness
    from fastmem.mesh.pattern import csr_structure

    try:
        import skfem
        from skfem.models.poisson import laplace
    except ImportError:  # the bench extra is not installed
        skfem = None
    m0 = fm.Mesh.square(4)
    assemble_stiffness(m0)  # JIT warm-up
    rows = []
    for n in sizes:
        progress(f"assembly: n = {n}")
        mesh = fm.Mesh.square(n)
        t0 = time.perf_counter()
        _ = mesh.edges, mesh.patch_ptr
        t_topo = time.perf_counter() - t0
        t0 = time.perf_counter()
        indptr, indices = ks.csr_pattern(mesh.n_vertices, mesh.edges, np.int32)
        t_pattern = time.perf_counter() - t0
        t0 = time.perf_counter()
        offsets = ks.position_map(mesh.triangles, indptr, indices)
        t_map = time.perf_counter() - t0
        csr_structure(mesh)
        one = np.ones(1)
        vals, t_kernel = timed(
            lambda: k.stiffness_local(mesh.vertices, mesh.triangles, one), repeat
        )
        _, t_gather = timed(
            lambda: k.gather_csr(
                vals, indptr, offsets, mesh.patch_ptr, mesh.patch_triangles, mesh.patch_local
            ),
            repeat,
        )
        a, t_total = timed(lambda: assemble_stiffness(mesh), repeat)  # fused kernel
        # scipy's route from the same COO values, for the COO->CSR comparison
        t = mesh.triangles
        rr = np.repeat(t, 3, axis=1).ravel()
        cc = np.tile(t, (1, 3)).ravel()
        import scipy.sparse as sp

        _, t_tocsr = timed(
            lambda: sp.coo_matrix((vals.ravel(), (rr, cc)), shape=a.shape).tocsr(),
            max(1, repeat - 1),
            0,
        )
        row = {
            "n": n,
            "vertices": mesh.n_vertices,
            "triangles": mesh.n_triangles,
            "topology_s": t_topo,
            "pattern_s": t_pattern,
            "position_map_s": t_map,
            "coo_kernel_s": t_kernel,
            "coo_to_csr_gather_s": t_gather,
            "assemble_stiffness_fused_s": t_total,
            "scipy_tocsr_s": t_tocsr,
        }
        if skfem is not None:

            def sk():
                sm = skfem.MeshTri(mesh.vertices.T.copy(), mesh.triangles.T.copy())
                basis = skfem.Basis(sm, skfem.ElementTriP1())
                return laplace.assemble(basis)

            a_sk, t_sk = timed(sk, max(1, repeat - 1), 0)
            row["skfem_s"] = t_sk
            row["max_abs_diff_vs_skfem"] = float(abs(a - a_sk).max())
            row["ratio_skfem_over_fastmem"] = t_sk["median"] / t_total["median"]
            del a_sk
        row.update(callable_loads(mesh, repeat))
        row["peak_rss_mb"] = peak_rss_mb()
        rows.append(row)
        progress(
            f"  coo kernel {t_kernel['median']:.4f}s gather {t_gather['median']:.4f}s "
            f"fused {t_total['median']:.4f}s scipy tocsr {t_tocsr['median']:.4f}s "
            + "callable load "
            + " ".join(f"{k} {v['median']:.3f}s" for k, v in row["callable_load_s"].items())
            + f" (same bits: {row['callable_identical']}) "
            + (
                f"skfem {row['skfem_s']['median']:.3f}s ratio {row['ratio_skfem_over_fastmem']:.1f}"
                if "skfem_s" in row
                else ""
            )
        )
    return rows


def main(argv=None):
    p = parser(__doc__)
    p.add_argument(
        "--no-compile", action="store_true", help="skip the cold/warm-cache compile measurement"
    )
    args = parse(p, argv)
    sizes = args.sizes or ([16, 32] if args.quick else [256, 1024, 2048])
    repeat = 1 if args.quick else args.repeat
    payload = {
        "parameters": {"sizes": sizes, "repeat": repeat, "quick": args.quick},
        "compile": None if args.no_compile else compile_times(),
        "rows": run(sizes, repeat),
    }
    finish("assembly", payload, args.quick)


if __name__ == "__main__":
    main()
