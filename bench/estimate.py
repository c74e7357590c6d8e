"""Flux reconstruction and estimators in Poisson units.

For each mesh size: one pyamg smoothed-aggregation Poisson solve (setup + CG
to 1e-8, BLAS limited to one thread; ``bench._common.poisson_unit``) as the
unit, then the flux
reconstruction (first evaluation on a fresh mesh object, which builds the
cached topology and vertex colouring, and repeated evaluation) and the whole
estimate, with patches per second.  Numba compilation is done on a tiny mesh
beforehand and is not in any timing.  The estimate is taken at the exact discrete solution up
to ``--solve-max`` and at the Dirichlet lifting beyond.

Side by side (issue 16): the flux reconstruction of the current tree against
that of ``--base`` (default: the commit before the mu-weighted reconstruction),
whose ``fastmem/flux.py`` and ``kernels/flux.py`` are loaded from git into
temporary modules, timed alternately in one process on the same triples:
constant mu (the default scene), a 4 x 4 checkerboard mu1 in {1, 1e-3} with
f = (-4, 2) (per-triangle weights, redistributed contact load) and random
per-triangle mu1 in {1, 1e3} (every patch mixes both: two factorisations).

    python -m bench.estimate [--quick] [--sizes 256 1024 2048] [--base COMMIT] [--results DIR]
"""

import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench._common import finish, parse, parser, peak_rss_mb, poisson_unit, progress, timed

#: Timed runs of the flux and of the estimate add up to at least this (seconds).
MIN_SECONDS = 1.0


def run(sizes, repeat, solve_max):
    import fastmem as fm
    from fastmem.estimators.flux import reconstruct

    fm.estimate(*_lifting(fm.Scene(fm.Mesh.square(8), f=(-1.0, 1.0), g=0.1)))  # JIT caches
    rows = []
    for n in sizes:
        progress(f"estimate: n = {n}")
        mesh = fm.Mesh.square(n)
        scene = fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
        unit_info = poisson_unit(mesh, repeat)
        if n <= solve_max:
            r = fm.solve(scene)
            u1, u2, lam = r.u1, r.u2, r.lam
        else:
            _, u1, u2, lam = _lifting(scene)
        # first evaluation: a fresh mesh object, so its cached topology and colouring are
        # built inside the timing (JIT compilation was done on a tiny mesh above)
        fresh = fm.Scene(fm.Mesh.square(n), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
        t0 = time.perf_counter()
        reconstruct(fresh, u1, u2, lam)
        t_first = time.perf_counter() - t0
        est_first = fm.estimate(fresh, u1, u2, lam)
        del fresh
        # small meshes: repeated until 1 s of runs (the median of 3 runs of 60 ms was noise)
        _, t_flux = timed(lambda: reconstruct(scene, u1, u2, lam), repeat, 0, MIN_SECONDS)
        est, t_est = timed(lambda: fm.estimate(scene, u1, u2, lam), repeat, 0, MIN_SECONDS)
        unit = unit_info["seconds"]
        row = {
            "n": n,
            "vertices": mesh.n_vertices,
            "triangles": mesh.n_triangles,
            "poisson_s": unit_info["total_s"],
            "poisson": unit_info,
            "triple": "exact solution" if n <= solve_max else "Dirichlet lifting",
            "flux_first_s": t_first,
            "flux_repeat_s": t_flux,
            "estimate_s": t_est,
            "patches_per_s": mesh.n_vertices / t_flux["median"],
            "estimate_poisson_units": t_est["median"] / unit,
            "eta": est.eta,
            "eta_first_minus_repeat": abs(est.eta - est_first.eta),
            "peak_rss_mb": peak_rss_mb(),
        }
        rows.append(row)
        progress(
            f"  poisson {unit:.3f}s flux {t_flux['median']:.3f}s "
            f"({row['patches_per_s']:.0f} patches/s) estimate {t_est['median']:.3f}s "
            f"= {row['estimate_poisson_units']:.1f} Poisson units"
        )
    return rows


#: The commit before issue 16 (mu-weighted flux reconstruction).
BASE_COMMIT = "50e810d6a930b7dc32ef37f8e82332eda87a38ae"


#: The flat-layout imports of the base commit's fastmem/flux.py and where those names live now.
_BASE_IMPORTS = {
    "from .assembly import csr_structure": "from fastmem.mesh.pattern import csr_structure",
    "from .errors import DataError": "from fastmem.errors import DataError",
    "from .kernels import flux as _kf": "from fastmem.kernels import flux as _kf",
    "from .linear import residuals": "from fastmem.fem.residual import residuals",
    "from .loaddata import integrals": "from fastmem.fem.loaddata import integrals",
}


def base_reconstruct(commit):
    """``reconstruct`` of ``commit``: its fastmem/flux.py and kernels/flux.py as temporary modules.

    The kernel module is registered as ``fastmem.kernels._flux_base`` (its
    relative imports resolve in the installed package; Numba caches it next to
    the temporary file), the wrapper as ``fastmem._flux_base`` with its kernel
    module replaced by that one.  The wrapper's imports name the flat layout of
    that commit; they are pointed at today's modules (:data:`_BASE_IMPORTS`).
    """
    root = Path(__file__).resolve().parent.parent
    tmp = Path(tempfile.mkdtemp(prefix="fastmem_flux_base_"))
    mods = {}
    for name, path in (
        ("fastmem.kernels._flux_base", "kernels/flux.py"),
        ("fastmem._flux_base", "fastmem/flux.py"),
    ):
        src = subprocess.run(
            ["git", "show", f"{commit}:{path}"],
            cwd=root,
            check=True,
            capture_output=True,
            text=True,
        ).stdout
        for old, new in _BASE_IMPORTS.items():
            src = src.replace(old, new)
        file = tmp / (name.rsplit(".", 1)[1] + ".py")
        file.write_text(src)
        spec = importlib.util.spec_from_file_location(name, file)
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
        mods[name] = mod
    wrapper = mods["fastmem._flux_base"]
    wrapper._kf = mods["fastmem.kernels._flux_base"]
    return wrapper.reconstruct


def _comparison_scenes(mesh):
    import fastmem as fm

    cen = mesh.vertices[mesh.triangles].mean(axis=1)
    blocks = np.floor((cen + 1.0) * 2.0).sum(axis=1) % 2 == 0
    rng = np.random.default_rng(20261123)
    return {
        "constant mu": fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1),
        "checkerboard mu1": fm.Scene(
            mesh, mu=(np.where(blocks, 1.0, 1e-3), 1.0), f=(-4.0, 2.0), g=0.1
        ),
        "random mu1": fm.Scene(
            mesh,
            mu=(np.where(rng.random(mesh.n_triangles) < 0.5, 1.0, 1e3), 1.0),
            f=(-1.0, 1.0),
            g=0.1,
        ),
    }


def compare(sizes, repeat, commit):
    """patches/s of the current and the base reconstruction, alternating, same process."""
    import fastmem as fm
    from fastmem.estimators.flux import reconstruct
    from fastmem.fem.residual import residuals

    old = base_reconstruct(commit)
    tiny = fm.Scene(fm.Mesh.square(8), mu=(np.full(128, 2.0), 1.0), f=(-1.0, 1.0), g=0.1)
    for fn in (old, reconstruct):  # JIT caches
        fn(*_lifting(tiny))
        fn(*_lifting(fm.Scene(tiny.mesh, f=(-1.0, 1.0), g=0.1)))
    rows = []
    for n in sizes:
        mesh = fm.Mesh.square(n)
        for name, scene in _comparison_scenes(mesh).items():
            r = fm.solve(scene, method="exact")
            args = (scene, r.u1, r.u2, r.lam, *residuals(scene, r.u1, r.u2, r.lam))
            times = {"new": [], "base": []}
            for fn in (reconstruct, old):
                fn(*args)
            for _ in range(max(repeat, 3)):
                for key, fn in (("new", reconstruct), ("base", old)):
                    t0 = time.perf_counter()
                    fn(*args)
                    times[key].append(time.perf_counter() - t0)
            med = {k: float(np.median(v)) for k, v in times.items()}
            row = {
                "n": n,
                "vertices": mesh.n_vertices,
                "mu": name,
                "seconds_new": times["new"],
                "seconds_base": times["base"],
                "patches_per_s_new": mesh.n_vertices / med["new"],
                "patches_per_s_base": mesh.n_vertices / med["base"],
                "time_ratio_new_over_base": med["new"] / med["base"],
            }
            rows.append(row)
            progress(
                f"  n={n} {name:16s} new {row['patches_per_s_new']:.0f} patches/s, base "
                f"{row['patches_per_s_base']:.0f} patches/s: time ratio "
                f"{row['time_ratio_new_over_base']:.3f}"
            )
    return {"base_commit": commit, "rows": rows}


def _lifting(scene):
    """The Dirichlet lifting (u1 = g on the boundary, zero elsewhere) as a triple."""
    n = scene.mesh.n_vertices
    return scene, scene.boundary_values.copy(), np.zeros(n), np.zeros(n)


def main(argv=None):
    p = parser(__doc__)
    p.add_argument("--solve-max", type=int, default=512)
    p.add_argument("--base", default=BASE_COMMIT, help="commit of the side-by-side reconstruction")
    p.add_argument("--compare-sizes", type=int, nargs="*", default=None)
    args = parse(p, argv)
    sizes = args.sizes or ([16, 32] if args.quick else [256, 1024, 2048])
    compare_sizes = args.compare_sizes or ([16] if args.quick else [256, 512])
    repeat = 1 if args.quick else args.repeat
    payload = {
        "parameters": {
            "sizes": sizes,
            "repeat": repeat,
            "solve_max": args.solve_max,
            "quick": args.quick,
            "compare_sizes": compare_sizes,
        },
        "rows": run(sizes, repeat, args.solve_max),
        "comparison": compare(compare_sizes, repeat, args.base),
    }
    finish("estimate", payload, args.quick)


if __name__ == "__main__":
    main()
