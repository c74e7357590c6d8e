"""PETSc side of ``bench.peers``: the ball obstacle problem with SNES VI (ex9-like).

Run by the *PETSc* interpreter (one that imports ``petsc4py``), never by
fastmem's: this file imports neither fastmem nor anything of ``bench``.  It
reads one JSON object (from the file named by its first argument, ``-`` or
nothing for stdin)::

    {"sizes": [64, 128], "variant": "mg", "repeats": 3, "budget": 60,
     "outdir": "/tmp/x", "coarse": 4, "options": {"ksp_rtol": "1e-6"}, "label": "mg"}

and prints one JSON object on the last line of stdout (PETSc's own output,
e.g. with ``-snes_view`` in ``options``, goes before it).

The problem is the ball of docs/obstacle.md §8.1 on (-2, 2)^2: a DMDA of
(n+1) x (n+1) points (n cells per side, h = 4/n), the 5-point Laplacian with
the Dirichlet data u_exact eliminated from the interior rows and the boundary
rows ``4 (u - g)`` (the scaling of PETSc's snes tutorial ex9, which makes
the Jacobian symmetric with diagonal 4), the lower bound psi (the C^1
obstacle of §8.1), upper bound +inf, SNES ``vinewtonrsls``.  The bounds are
given the way ex9 gives them, by a callback (SNESVISetComputeVariableBounds),
so that ``-snes_grid_sequence`` recomputes them on every refined grid;
petsc4py (3.18 and 3.26 checked) wraps only the fixed-vector form, so the
function is reached through ctypes in the PETSc library petsc4py has loaded.

Variants (``variant``):

* ``mg``: ex9's "full-cycle multigrid" run: from a coarse DMDA of
  ``coarse`` cells per side (default 4, ex9's 5 x 5 points; a smaller power
  of two dividing n when 4 does not fit), ``-snes_grid_sequence k`` with
  n = coarse * 2^k, ``-pc_type mg`` (levels from the DMDA hierarchy), KSP
  GMRES (PETSc's default, as ex9 leaves it), default tolerances;
* ``gamg``: directly on the n x n grid from u = 0 (projected onto the bounds),
  ``-pc_type gamg``, KSP GMRES, default tolerances but ``-snes_max_it
  max(50, n)``: the active set grows by about a ring of points per Newton
  step, so the step count grows like n (33 at n = 256, past the default
  limit of 50 at n = 512);
* ``gamg_gs``: the grid sequence of ``mg`` with ``-pc_type gamg``.

For the GAMG variants the KSP gets a fresh GAMG at the first Newton step on
each grid (every Newton step before PETSc 3.19.4); ``"fresh_gamg"``:
``"grid"``, ``"step"`` or ``"off"`` overrides it (the reasons are at
``Callbacks.__init__``).

``options`` (name without the dash -> value string, "" for a flag) are set
on top of the variant's for each solve; e.g. ``{"ksp_type": "cg"}``.
``init_args`` (a list) goes to ``petsc4py.init`` for the whole run, e.g.
``["-log_view"]`` (printed at exit, after the JSON line).

Per n it reports: ``setup_s`` (create the DMDA, its coordinates, the SNES
and its callbacks, SNESSetFromOptions: everything before SNESSolve),
``solve_s`` (SNESSolve, including every grid of a sequence, the Jacobian
assemblies and the PC setups; ``callback_s`` is the part of it spent in
this file's Python callbacks, residual, Jacobian and bounds), each as
min/median/all over ``repeats`` fresh runs (fewer once the runs of a size
add up to ``budget`` seconds; after one untimed warm-up run at n = 16); SNES
iterations (final grid and summed over the sequence), KSP iterations (summed
over the whole solve), the convergence reason, the final residual norm, the
max nodal error against u_exact, the active-point count, and the file of the
solution: ``<outdir>/petsc_<label>_n<n>.npy``, an ((n+1)^2, 3) float64 array
with columns x, y, u, rows in the DMDA's natural ordering (x fastest:
row j*(n+1)+i is the point (-2 + i h, -2 + j h)).

The Jacobian of this problem does not depend on u; the callback assembles it
(vectorised, one MatSetValuesCSR) the first time it sees a matrix and leaves
it as it is on later Newton steps, as a C code could too: Python would
otherwise add a per-step cost that ex9 in C does not have.  The residual is
vectorised NumPy on the serial global vector.  Serial only (one MPI rank).
"""

import ctypes
import json
import math
import os
import sys
import time

import numpy as np

# ---------------------------------------------------------------- the problem

R0 = 0.9
PSI0 = math.sqrt(1.0 - R0 * R0)
DPSI0 = -R0 / PSI0
AFREE = 0.697965148223374
A_EX = 0.680259411891719
B_EX = 0.471519893402112
LO, HI = -2.0, 2.0


def psi(x, y):
    """The C^1 ball obstacle (docs/obstacle.md §8.1), vectorised."""
    r = np.hypot(x, y)
    inner = np.sqrt(np.maximum(1.0 - r * r, 0.0))
    return np.where(r <= R0, inner, PSI0 + DPSI0 * (r - R0))


def u_exact(x, y):
    r = np.hypot(x, y)
    with np.errstate(divide="ignore"):
        outer = -A_EX * np.log(r) + B_EX
    return np.where(r <= AFREE, psi(x, y), outer)


class Grid:
    """Geometry and constant data of one (m+1) x (m+1) point grid (m cells per side)."""

    _cache = {}

    def __init__(self, npts):
        self.npts = npts
        self.m = npts - 1
        self.h = (HI - LO) / self.m
        t = LO + self.h * np.arange(npts)
        self.x, self.y = np.meshgrid(t, t)  # [j, i]: x varies along axis 1 (fastest)
        self.g = u_exact(self.x, self.y)
        self.psi = psi(self.x, self.y)
        bnd = np.zeros((npts, npts), dtype=bool)
        bnd[0, :] = bnd[-1, :] = bnd[:, 0] = bnd[:, -1] = True
        self.boundary = bnd
        # boundary values of the neighbours of interior points (eliminated data)
        gb = np.where(bnd, self.g, 0.0)
        self.rhs_interior = np.zeros((npts, npts))
        c = self.rhs_interior[1:-1, 1:-1]
        c += gb[1:-1, :-2] + gb[1:-1, 2:] + gb[:-2, 1:-1] + gb[2:, 1:-1]

    @classmethod
    def get(cls, npts):
        g = cls._cache.get(npts)
        if g is None:
            g = cls._cache[npts] = Grid(npts)
        return g

    def csr(self):
        """The Jacobian (ex9's scaling, h_x = h_y) as CSR arrays in natural ordering."""
        p = self.npts
        idx = np.arange(p * p).reshape(p, p)
        rows, cols, vals = [idx.ravel()], [idx.ravel()], [np.full(p * p, 4.0)]
        inner = np.zeros((p, p), dtype=bool)
        inner[1:-1, 1:-1] = True
        for dj, di in ((0, -1), (0, 1), (-1, 0), (1, 0)):
            # interior point (j, i) with an interior neighbour (j+dj, i+di)
            nb = np.zeros((p, p), dtype=bool)
            js = slice(max(0, -dj), p - max(0, dj))
            is_ = slice(max(0, -di), p - max(0, di))
            jn = slice(max(0, dj), p - max(0, -dj))
            in_ = slice(max(0, di), p - max(0, -di))
            nb[js, is_] = inner[js, is_] & inner[jn, in_]
            r = idx[nb]
            rows.append(r)
            cols.append(r + dj * p + di)
            vals.append(np.full(r.size, -1.0))
        rows = np.concatenate(rows)
        cols = np.concatenate(cols)
        vals = np.concatenate(vals)
        order = np.lexsort((cols, rows))
        rows, cols, vals = rows[order], cols[order], vals[order]
        indptr = np.zeros(p * p + 1, dtype=np.int64)
        np.cumsum(np.bincount(rows, minlength=p * p), out=indptr[1:])
        return indptr, cols, vals


def _side(size):
    p = math.isqrt(size)
    if p * p != size:
        raise ValueError(f"vector of size {size} is not a square grid")
    return p


# ---------------------------------------------------------------- PETSc glue


def _petsc_lib():
    """The PETSc shared library already loaded by petsc4py (found in /proc/self/maps)."""
    with open("/proc/self/maps") as fh:
        for line in fh:
            path = line.split()[-1]
            base = os.path.basename(path)
            if base.startswith("libpetsc") and ".so" in base:
                return ctypes.CDLL(path), path
    raise RuntimeError("no libpetsc*.so mapped in this process")


class Callbacks:
    """Residual, Jacobian and bounds callbacks, with iteration counters."""

    def __init__(self, PETSc):
        self.PETSc = PETSc
        self.assembled = {}  # Mat handle -> grid side for which it was assembled
        self.levels = []  # per grid of a sequence: [points per side, snes its, ksp its]
        self.ksp_its = 0
        vi = PETSc.Sys.getVersion()
        # A fresh GAMG (PCSetType none, then gamg) for the KSP of vinewtonrsls:
        # * "step", before every Newton step: needed before PETSc 3.19.4, whose
        #   PCReset_GAMG leaves the old multigrid levels in place, so the setup after
        #   an active-set change fails with "Cannot change local size of Amat after
        #   use" (fixed upstream by "PCGAMG: must call PCReset_MG during
        #   PCReset_GAMG", 3.19.4);
        # * "grid", at the first Newton step on each grid: GAMG keeps the number of
        #   levels of its first setup as its maximum (PCSetUp_GAMG overwrites
        #   Nlevels), and -pc_mg_levels is refused for GAMG, so with
        #   -snes_grid_sequence the 5 x 5 start grid fixes 2 levels for all finer
        #   grids (a coarse solve by LU on 1/7 of the unknowns);
        # * "off": PETSc as it is.
        self.fresh_gamg = "step" if tuple(vi) < (3, 19, 4) else "grid"
        self.last_size = None
        self.gamg_resets = 0
        self.callback_s = 0.0  # seconds spent in the Python callbacks (inside SNESSolve)
        lib, self.lib_path = _petsc_lib()
        self.lib = lib
        vp = ctypes.c_void_p
        self._proto = ctypes.CFUNCTYPE(ctypes.c_int, vp, vp, vp)
        lib.SNESVISetComputeVariableBounds.argtypes = [vp, self._proto]
        lib.SNESVISetComputeVariableBounds.restype = ctypes.c_int
        lib.VecGetLocalSize.argtypes = [vp, ctypes.POINTER(PETSC_INT)]
        lib.VecGetArray.argtypes = [vp, ctypes.POINTER(ctypes.POINTER(ctypes.c_double))]
        lib.VecRestoreArray.argtypes = [vp, ctypes.POINTER(ctypes.POINTER(ctypes.c_double))]
        lib.VecSet.argtypes = [vp, ctypes.c_double]
        self._bounds_c = self._proto(self._bounds)  # keep a reference: PETSc holds the pointer

    # -- bounds (ctypes: called by PETSc with raw SNES, Vec, Vec handles)
    def _bounds(self, snes, xl, xu):
        t0 = time.perf_counter()
        try:
            return self._bounds_inner(xl, xu)
        finally:
            self.callback_s += time.perf_counter() - t0

    def _bounds_inner(self, xl, xu):
        try:
            lib = self.lib
            n = PETSC_INT(0)
            if lib.VecGetLocalSize(xl, ctypes.byref(n)):
                return 1
            ptr = ctypes.POINTER(ctypes.c_double)()
            if lib.VecGetArray(xl, ctypes.byref(ptr)):
                return 1
            arr = np.ctypeslib.as_array(ptr, shape=(n.value,))
            arr[:] = Grid.get(_side(n.value)).psi.ravel()
            if lib.VecRestoreArray(xl, ctypes.byref(ptr)):
                return 1
            return lib.VecSet(xu, float(self.PETSc.INFINITY))
        except Exception as exc:  # an exception must not cross the C frame
            sys.stderr.write(f"bounds callback failed: {exc!r}\n")
            return 1

    def install_bounds(self, snes):
        err = self.lib.SNESVISetComputeVariableBounds(snes.handle, self._bounds_c)
        if err:
            raise RuntimeError(f"SNESVISetComputeVariableBounds returned {err}")

    # -- residual and Jacobian (petsc4py callbacks)
    def residual(self, snes, X, F):
        t0 = time.perf_counter()
        self._residual(X, F)
        self.callback_s += time.perf_counter() - t0

    def _residual(self, X, F):
        u = X.getArray(readonly=True)
        p = _side(u.size)
        grid = Grid.get(p)
        u = u.reshape(p, p)
        f = F.getArray().reshape(p, p)
        f[:, :] = 4.0 * (u - grid.g)  # boundary rows; interior rows overwritten below
        ui = np.where(grid.boundary, 0.0, u)
        f[1:-1, 1:-1] = (
            4.0 * u[1:-1, 1:-1]
            - ui[1:-1, :-2]
            - ui[1:-1, 2:]
            - ui[:-2, 1:-1]
            - ui[2:, 1:-1]
            - grid.rhs_interior[1:-1, 1:-1]
        )

    def jacobian(self, snes, X, J, P):
        t0 = time.perf_counter()
        self._jacobian(snes, X, J, P)
        self.callback_s += time.perf_counter() - t0

    def _jacobian(self, snes, X, J, P):
        size = X.getSize()
        if self.fresh_gamg == "step" or (self.fresh_gamg == "grid" and size != self.last_size):
            pc = snes.getKSP().getPC()
            if pc.getType() == "gamg":
                pc.setType("none")
                pc.setType("gamg")
                pc.setFromOptions()
                self.gamg_resets += 1
        self.last_size = size
        p = _side(X.getSize())
        for mat in {J.handle: J, P.handle: P}.values():
            if self.assembled.get(mat.handle) == p:
                continue
            indptr, cols, vals = Grid.get(p).csr()
            it = self.PETSc.IntType
            mat.setValuesCSR(indptr.astype(it), cols.astype(it), vals)
            mat.assemble()
            self.assembled[mat.handle] = p

    # -- counters
    def snes_monitor(self, snes, its, fnorm):
        if its == 0:
            self.levels.append([snes.getDM().getSizes()[0], 0, 0])
        else:
            self.levels[-1][1] = its

    def ksp_monitor(self, ksp, its, rnorm):
        if its > 0:
            self.ksp_its += 1
            if self.levels:
                self.levels[-1][2] += 1


PETSC_INT = ctypes.c_int32  # replaced in main() by the library's PetscInt


# ---------------------------------------------------------------- one solve


VARIANTS = ("mg", "gamg", "gamg_gs")


def coarse_plan(n, coarse):
    """(coarse cells m0, refinements k) with m0 * 2^k == n; m0 <= coarse, as large as possible."""
    m0, k = n, 0
    while m0 % 2 == 0 and m0 > coarse:
        m0 //= 2
        k += 1
    return m0, k


def variant_options(variant, n, coarse):
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; known: {VARIANTS}")
    opts = {"snes_type": "vinewtonrsls"}
    if variant in ("mg", "gamg_gs"):
        m0, k = coarse_plan(n, coarse)
        opts["snes_grid_sequence"] = str(k)
    else:
        m0, k = n, 0
        # from u = 0 the active set grows by about one ring of points per Newton
        # step: n/4 + 1 steps at n = 256 already, past SNES's default limit of 50
        opts["snes_max_it"] = str(max(50, n))
    opts["pc_type"] = "mg" if variant == "mg" else "gamg"
    return opts, m0, k


def solve_once(PETSc, cb, n, variant, coarse, extra):
    opts, m0, k = variant_options(variant, n, coarse)
    opts.update(extra)
    db = PETSc.Options()
    for key, val in opts.items():
        db.setValue(key, val)
    try:
        t0 = time.perf_counter()
        da = PETSc.DMDA().create(
            dim=2,
            dof=1,
            sizes=(m0 + 1, m0 + 1),
            stencil_type=PETSc.DMDA.StencilType.STAR,
            stencil_width=1,
            boundary_type=(PETSc.DM.BoundaryType.NONE, PETSc.DM.BoundaryType.NONE),
            comm=PETSc.COMM_WORLD,
        )
        da.setUp()
        da.setUniformCoordinates(LO, HI, LO, HI)
        snes = PETSc.SNES().create(comm=PETSc.COMM_WORLD)
        snes.setDM(da)
        snes.setType("vinewtonrsls")
        cb.install_bounds(snes)
        snes.setFunction(cb.residual, None)
        snes.setJacobian(cb.jacobian, None, None)
        snes.setMonitor(cb.snes_monitor)
        snes.getKSP().setMonitor(cb.ksp_monitor)
        snes.setFromOptions()
        u = da.createGlobalVec()
        u.set(0.0)
        cb.levels, cb.ksp_its, cb.assembled, cb.gamg_resets = [], 0, {}, 0
        cb.last_size = None
        cb.callback_s = 0.0
        t1 = time.perf_counter()
        snes.solve(None, u)
        t2 = time.perf_counter()
    finally:
        for key in opts:
            db.delValue(key)
    da_f = snes.getDM()
    x = snes.getSolution()
    p = da_f.getSizes()[0]
    if p != n + 1:
        raise RuntimeError(f"final grid has {p} points per side, expected {n + 1}")
    grid = Grid.get(p)
    uh = x.getArray(readonly=True).reshape(p, p).copy()
    # the DMDA's own coordinates, to hand over the geometry it really used
    c = da_f.getCoordinates()
    if c is not None:
        xy = c.getArray(readonly=True).reshape(p, p, 2).copy()
    else:
        xy = np.stack([grid.x, grid.y], axis=-1)
    coord_dev = float(max(np.abs(xy[..., 0] - grid.x).max(), np.abs(xy[..., 1] - grid.y).max()))
    err = float(np.abs(uh - grid.g).max())
    active = int(np.count_nonzero(uh <= grid.psi + 1e-12))
    row = {
        "setup_s": t1 - t0,
        "solve_s": t2 - t1,
        "callback_s": cb.callback_s,
        "coarse_cells": m0,
        "grid_sequence": k,
        "levels": [{"points": lv[0], "snes_its": lv[1], "ksp_its": lv[2]} for lv in cb.levels],
        "snes_its": snes.getIterationNumber(),
        "snes_its_total": int(sum(lv[1] for lv in cb.levels)),
        "ksp_its_total": cb.ksp_its,
        "converged_reason": int(snes.getConvergedReason()),
        "converged": int(snes.getConvergedReason()) > 0,
        "residual_norm": float(snes.getFunctionNorm()),
        "max_error": err,
        "active_points": active,
        "coordinate_deviation": coord_dev,
        "fresh_gamg": cb.fresh_gamg,
        "gamg_resets": cb.gamg_resets,
        "ksp_type": snes.getKSP().getType(),
        "pc_type": snes.getKSP().getPC().getType(),
        "options": opts,
    }
    solution = np.column_stack([xy[..., 0].ravel(), xy[..., 1].ravel(), uh.ravel()])
    snes.destroy()
    da.destroy()
    return row, solution


def _summary(times):
    s = sorted(times)
    mid = len(s) // 2
    med = s[mid] if len(s) % 2 else 0.5 * (s[mid - 1] + s[mid])
    return {"min": s[0], "median": med, "all": list(times)}


def main(argv):
    src = argv[1] if len(argv) > 1 else "-"
    cfg = json.load(sys.stdin) if src == "-" else json.loads(open(src).read())

    import petsc4py

    # "init_args": PETSc command-line arguments for the whole run, e.g. ["-log_view"]
    petsc4py.init([sys.argv[0], *map(str, cfg.get("init_args", []))])
    from petsc4py import PETSc

    global PETSC_INT
    PETSC_INT = ctypes.c_int64 if np.dtype(PETSc.IntType).itemsize == 8 else ctypes.c_int32
    if PETSc.COMM_WORLD.getSize() != 1:
        raise SystemExit("_petsc_ball.py runs on one MPI rank only")

    sizes = [int(s) for s in cfg["sizes"]]
    variant = cfg.get("variant", "mg")
    repeats = max(1, int(cfg.get("repeats", 1)))
    coarse = int(cfg.get("coarse", 4))
    budget = float(cfg.get("budget", float("inf")))  # stop repeating a size past this
    extra = {str(k): str(v) for k, v in (cfg.get("options") or {}).items()}
    label = cfg.get("label", variant)
    outdir = cfg.get("outdir")
    if outdir:
        os.makedirs(outdir, exist_ok=True)

    cb = Callbacks(PETSc)
    if cfg.get("fresh_gamg") is not None:  # "step", "grid" or "off" (see Callbacks)
        cb.fresh_gamg = str(cfg["fresh_gamg"])
    # warm-up: first calls into PETSc and NumPy paths, not timed
    solve_once(PETSc, cb, 16, variant, coarse, extra)

    rows = []
    for n in sizes:
        setups, solves, callbacks, row, sol = [], [], [], None, None
        for _ in range(repeats):
            Grid._cache.clear()  # every run computes its own grid data (inside the timings)
            row, sol = solve_once(PETSc, cb, n, variant, coarse, extra)
            setups.append(row["setup_s"])
            solves.append(row["solve_s"])
            callbacks.append(row["callback_s"])
            if sum(setups) + sum(solves) > budget:
                break
        row = {"n": n, **row}
        row["callback_s"] = _summary(callbacks)
        row["setup_s"] = _summary(setups)
        row["solve_s"] = _summary(solves)
        row["seconds"] = row["setup_s"]["median"] + row["solve_s"]["median"]
        if outdir:
            path = os.path.join(outdir, f"petsc_{label}_n{n}.npy")
            np.save(path, sol)
            row["solution_file"] = path
        rows.append(row)
        sys.stderr.write(
            f"petsc {label} n={n}: solve {row['solve_s']['median']:.3f}s "
            f"setup {row['setup_s']['median']:.4f}s snes {row['snes_its']}/{row['snes_its_total']} "
            f"ksp {row['ksp_its_total']} max err {row['max_error']:.3e}\n"
        )
        sys.stderr.flush()

    vi = PETSc.Sys.getVersionInfo()
    out = {
        "variant": variant,
        "label": label,
        "petsc_version": "{major}.{minor}.{subminor}".format(**vi),
        "petsc4py_version": petsc4py.__version__,
        "petsc_library": cb.lib_path,
        "numpy_version": np.__version__,
        "python": sys.version.split()[0],
        "executable": sys.executable,
        "repeats": repeats,
        "rows": rows,
    }
    sys.stdout.write(json.dumps(out) + "\n")
    sys.stdout.flush()


if __name__ == "__main__":
    main(sys.argv)
