"""Direct factorisation: fill-reducing orderings on meshes of one size but different numberings.

The matrices the exact solver factors -- the interior P1 Laplacian ``A_II``
(the decoupled step) and the reduced system ``P^T K P`` of the general step
(mu = (1, 1)) with an empty and with a realistic active set -- on four meshes
of the square with (nearly) the same vertices: ``Mesh.square(n)``
("structured"), ``Mesh.square(16)`` refined until it has n cells per side
("refined", numbered level by level), the structured mesh under a random
permutation of its vertices ("permuted") and a gmsh mesh of element size
~2/n ("gmsh", skipped without the gmsh package).  The realistic active set
is the contact set of the default scene (f = (-1, 1), g = 0.1) solved on
``Mesh.square(32)``, transferred to every mesh by nearest vertex.

Orderings: ``nested-dissection`` (:func:`fastmem.linalg.direct.factorize` with the
vertex of every unknown), ``nested-dissection-graph`` (the same without
coordinates), ``rcm+MMD`` (reverse Cuthill-McKee renumbering, then SuperLU's
MMD_AT_PLUS_A), and on the given numbering SuperLU's ``MMD_AT_PLUS_A`` (the
former ``fastmem.solver.linear`` default; only up to ``--mmd-max`` cells per side:
it takes 2-60 s at n = 128 on badly numbered meshes) and ``COLAMD`` (up to
``--colamd-max``).  Every candidate gets the same matrix, explicit zeros
dropped.  Rows: mesh x n x system x ordering with seconds (ordering plus
factorisation, min/median/max over ``--repeat`` runs), solve seconds, fill
(nnz(L) + nnz(U)), the relative residual of one solve, and the ratios of
seconds and fill to the structured mesh (same n, system and ordering).

    python -m bench.direct_ordering [--quick] [--sizes 128 256 512] [--mmd-max 128]
"""

import time

import numpy as np

from bench import _gmsh
from bench._common import finish, parse, parser, peak_rss_mb, progress, summary, timed_budget

FULL_SIZES = [128, 256, 512]
QUICK_SIZES = [32]
SEED = 20261123
KINDS = ("structured", "refined", "permuted", "gmsh")
SYSTEMS = ("laplacian", "reduced-empty", "reduced-active")
ORDERINGS = ("nested-dissection", "nested-dissection-graph", "rcm+MMD", "MMD_AT_PLUS_A", "COLAMD")


# ------------------------------------------------------------------ meshes and matrices


def gmsh_square(n):
    """gmsh mesh of (-1, 1)^2 with about (n + 1)^2 vertices (None without the gmsh package)."""
    # an equilateral mesh of element size 2.14 / n has ~ the vertices of Mesh.square(n)
    return _gmsh.mesh("square", lambda occ: occ.addRectangle(-1.0, -1.0, 0.0, 2.0, 2.0), 2.14 / n)


def meshes(n):
    """{kind: Mesh} of the square with n cells per side (n = 16 * 2^k for "refined")."""
    import fastmem as fm

    out = {"structured": fm.Mesh.square(n)}
    if n >= 16 and (n // 16) & (n // 16 - 1) == 0 and n % 16 == 0:
        m = fm.Mesh.square(16)
        while m.n_vertices < (n + 1) ** 2:
            m = m.refine()
        out["refined"] = m
    base = out["structured"]
    p = np.random.default_rng(SEED).permutation(base.n_vertices)
    inv = np.empty_like(p)
    inv[p] = np.arange(p.size)
    out["permuted"] = fm.Mesh(base.vertices[p], inv[base.triangles])
    g = gmsh_square(n)
    if g is not None:
        out["gmsh"] = g
    return out


def reference_contact():
    """(KD-tree of the vertices, contact mask) of the default scene on Mesh.square(32)."""
    from scipy.spatial import cKDTree

    import fastmem as fm

    mesh = fm.Mesh.square(32)
    r = fm.solve(
        fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1), method="exact", estimate=False
    )
    return cKDTree(mesh.vertices), r.lam > 0


def systems(mesh, reference):
    """{system: (matrix, coordinates per unknown)} of the solver's factorisations on ``mesh``."""
    import fastmem as fm
    from fastmem.solver.linear import GeneralStep

    step = GeneralStep(fm.Scene(mesh, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1))
    xy = mesh.vertices[mesh.interior_vertices]
    tree, contact = reference
    out = {"laplacian": (step.a1_ii, xy)}  # mu1 = 1: the interior Laplacian
    for name, active in (
        ("reduced-empty", np.zeros(len(xy), dtype=bool)),
        ("reduced-active", contact[tree.query(xy)[1]]),
    ):
        p = step.prolongation(active)
        out[name] = (p.T @ step.k_ii @ p, np.vstack([xy, xy[~active]]))
    for name, (a, c) in out.items():
        a = a.tocsr()
        a.eliminate_zeros()
        out[name] = (a, c)
    return out


# ------------------------------------------------------------------ candidates


def _superlu(a, spec, perm=None):
    """Factor ``A[perm][:, perm]`` (or A) with SuperLU's column ordering ``spec``; a solver."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    b = sp.csc_matrix(a if perm is None else a[perm][:, perm])
    lu = spla.splu(b, permc_spec=spec)
    fill = lu.L.nnz + lu.U.nnz
    if perm is None:
        return lu.solve, fill

    def solve(rhs):
        x = np.empty_like(rhs)
        x[perm] = lu.solve(rhs[perm])
        return x

    return solve, fill


def factor(ordering, a, coords):
    """(solve function, fill) of one candidate ordering."""
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    from fastmem.linalg.direct import factorize

    if ordering in ("nested-dissection", "nested-dissection-graph"):
        lu = factorize(a, coords if ordering == "nested-dissection" else None)
        return lu.solve, lu.fill
    if ordering == "rcm+MMD":
        return _superlu(a, "MMD_AT_PLUS_A", reverse_cuthill_mckee(a, symmetric_mode=True))
    return _superlu(a, ordering)


def measure(ordering, a, coords, repeat, budget):
    """Timing row of one candidate on one matrix."""
    (solve, fill), t = timed_budget(lambda: factor(ordering, a, coords), repeat, budget)
    rhs = np.random.default_rng(SEED).standard_normal(a.shape[0])
    solves = []
    for _ in range(max(1, len(t["all"]))):
        t0 = time.perf_counter()
        x = solve(rhs)
        solves.append(time.perf_counter() - t0)
    res = float(np.linalg.norm(a @ x - rhs) / np.linalg.norm(rhs))
    return {
        "seconds": t,
        "solve_s": summary(solves),
        "fill": int(fill),
        "fill_per_unknown": fill / a.shape[0],
        "relative_residual": res,
    }


def run(sizes, repeat, budget, mmd_max, colamd_max):
    from fastmem.linalg.direct import factorize

    factorize(2.0 * np.eye(4), np.zeros((4, 2)))  # load the JIT cache
    reference = reference_contact()
    rows = []
    for n in sizes:
        for kind, mesh in meshes(n).items():
            for system, (a, coords) in systems(mesh, reference).items():
                for ordering in ORDERINGS:
                    if (ordering == "MMD_AT_PLUS_A" and n > mmd_max) or (
                        ordering == "COLAMD" and n > colamd_max
                    ):
                        continue
                    row = {
                        "n": n,
                        "mesh": kind,
                        "vertices": mesh.n_vertices,
                        "system": system,
                        "unknowns": a.shape[0],
                        "nnz": int(a.nnz),
                        "ordering": ordering,
                        **measure(ordering, a, coords, repeat, budget),
                        "peak_rss_mb": peak_rss_mb(),
                    }
                    rows.append(row)
                    progress(
                        f"direct_ordering: n={n:4d} {kind:10s} {system:14s} {ordering:23s} "
                        f"N={a.shape[0]:7d} {row['seconds']['median']:8.3f} s "
                        f"solve {row['solve_s']['median']:.4f} s fill {row['fill']:10d}"
                    )
    add_ratios(rows)
    return rows


def add_ratios(rows):
    """Add seconds and fill over those of the structured mesh (same n, system, ordering)."""
    ref = {(r["n"], r["system"], r["ordering"]): r for r in rows if r["mesh"] == "structured"}
    for r in rows:
        s = ref.get((r["n"], r["system"], r["ordering"]))
        if s is not None:
            r["seconds_over_structured"] = r["seconds"]["median"] / s["seconds"]["median"]
            r["fill_over_structured"] = r["fill"] / s["fill"]


def spread(rows):
    """Per n, system and ordering: max/min of seconds and fill over the mesh kinds."""
    out = []
    keys = sorted({(r["n"], r["system"], r["ordering"]) for r in rows})
    for n, system, ordering in keys:
        sub = [r for r in rows if (r["n"], r["system"], r["ordering"]) == (n, system, ordering)]
        if len(sub) < 2:
            continue
        sec = [r["seconds"]["median"] for r in sub]
        fill = [r["fill"] for r in sub]
        out.append(
            {
                "n": n,
                "system": system,
                "ordering": ordering,
                "meshes": [r["mesh"] for r in sub],
                "max_seconds": max(sec),
                "seconds_spread": max(sec) / min(sec),
                "fill_spread": max(fill) / min(fill),
            }
        )
    return out


def table(rows):
    """Plain-text table of the rows (for the log and the commit message)."""
    lines = [
        f"{'n':>4} {'system':14} {'ordering':23} {'mesh':10} {'N':>7} {'seconds':>8} "
        f"{'solve':>7} {'fill':>10} {'s/struct':>8} {'fill/str':>8}"
    ]
    for r in sorted(rows, key=lambda r: (r["n"], r["system"], r["ordering"], r["mesh"])):
        lines.append(
            f"{r['n']:4d} {r['system']:14} {r['ordering']:23} {r['mesh']:10} {r['unknowns']:7d} "
            f"{r['seconds']['median']:8.3f} {r['solve_s']['median']:7.4f} {r['fill']:10d} "
            f"{r.get('seconds_over_structured', float('nan')):8.2f} "
            f"{r.get('fill_over_structured', float('nan')):8.2f}"
        )
    return "\n".join(lines)


def main(argv=None):
    p = parser(__doc__)
    p.add_argument("--mmd-max", type=int, default=128, help="largest n for MMD_AT_PLUS_A as given")
    p.add_argument("--colamd-max", type=int, default=256, help="largest n for COLAMD")
    p.add_argument("--budget", type=float, default=60.0, help="stop repeating a run after this")
    args = parse(p, argv)
    sizes = args.sizes or (QUICK_SIZES if args.quick else FULL_SIZES)
    rows = run(sizes, args.repeat, args.budget, args.mmd_max, args.colamd_max)
    progress(table(rows))
    payload = {
        "parameters": {
            "sizes": sizes,
            "repeat": args.repeat,
            "budget_s": args.budget,
            "mmd_max": args.mmd_max,
            "colamd_max": args.colamd_max,
            "quick": args.quick,
            "seed": SEED,
            "kinds": list(KINDS),
            "systems": list(SYSTEMS),
            "orderings": list(ORDERINGS),
        },
        "rows": rows,
        "spread": spread(rows),
    }
    finish("direct_ordering", payload, args.quick)


if __name__ == "__main__":
    main()
