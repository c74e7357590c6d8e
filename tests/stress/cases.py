"""The stress matrix: hard cases for the solver and the guaranteed bound.

Each :class:`Case` builds a scene for a mode (``"fast"``: small meshes, the
default test run; ``"full"``: bigger meshes, ``FASTMEM_STRESS=full``), knows
its exact solution when one exists (the manufactured family of docs/method.md
section 7 on ``(-1, 1)^2``), and states what must hold besides the generic
checks of :mod:`tests.stress.checks` (an :class:`Expect`).

The table is plain data: add a row to add a case.  Names are stable (they are
test ids and report rows).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

import fastmem as fm

from . import meshes

#: Solver variants: name -> (method, extra keyword arguments of fastmem.solve).
VARIANTS = {
    "exact": ("exact", {}),
    "inexact": ("inexact", {}),
    "exact-amg": ("exact-amg", {}),
    "exact-noguard": ("exact", {"safeguard": False}),
    "inexact-noguard": ("inexact", {"safeguard": False}),
}

#: Mesh size parameter per mode (cells per side of the structured meshes).
SIZES = {"fast": 32, "full": 128}


@dataclass(frozen=True)
class Expect:
    """What a case must show besides the generic checks.

    Attributes
    ----------
    must_converge : bool
        True: the solver must return ``converged=True``.  False: raising a
        documented :class:`fastmem.errors.ConvergenceError` (e.g. CyclingError)
        is an accepted outcome too (meshes without the M-matrix property,
        where docs/method.md §3.1 allows Newton-min to cycle).  Returning
        ``converged=False`` without an error is never accepted.
    n_active : {None, "none", "one", "all"}
        Size of the final contact set (checked for converged exact-solve results).
    non_m_matrix : bool
        The stiffness matrix must have positive off-diagonal entries (checked
        on the mesh, so that the case really is what its name says).
    min_aspect : float or None
        Smallest acceptable value of the largest element aspect ratio.
    scale : float or None
        The scene is the case's ``scale = 1`` scene with all data scaled by
        this factor: the solution, lambda and eta must scale with it.
    needs_gmsh : bool
        Skip (with the reason) when the gmsh python package is unavailable.
    """

    must_converge: bool = True
    n_active: str | None = None
    non_m_matrix: bool = False
    min_aspect: float | None = None
    scale: float | None = None
    needs_gmsh: bool = False


@dataclass(frozen=True)
class Built:
    """A case instantiated for one mode."""

    scene: fm.Scene
    exact: fm.Manufactured | None = None
    reference: Callable[[], Built] | None = None  # the scale = 1 version (scaled cases)
    solve_options: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Case:
    """One row of the stress matrix."""

    name: str
    group: str
    description: str
    build: Callable[[str], Built]
    expect: Expect = Expect()
    amg_fast: bool = False  # run "exact-amg" in the fast mode too
    fast: bool = True  # part of the fast subset at all

    def variants(self, mode: str) -> list[str]:
        """Solver variants run for this case in ``mode``."""
        out = ["exact", "inexact"]
        if mode == "full" or self.amg_fast:
            out.append("exact-amg")
        if self.expect.non_m_matrix:  # cycling is the question: also without the safeguard
            out.append("exact-noguard")
            if mode == "full":
                out.append("inexact-noguard")
        return out


# ------------------------------------------------------------------------------ builders


def _n(mode):
    return SIZES[mode]


def mms(mesh_fn=None, path=None, **params):
    """Builder of a manufactured case (parameters of :class:`fastmem.Manufactured`)."""

    def build(mode):
        n = _n(mode)
        mesh = meshes.square(n) if mesh_fn is None else mesh_fn(n)
        exact = fm.Manufactured(**params)
        opts = {} if path is None else {"path": path}
        return Built(exact.scene(mesh), exact, solve_options=opts)

    return build


def default(mesh_fn=None, mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1):
    """Builder of a default-like scene (docs/method.md §8) with some data changed."""

    def build(mode):
        n = _n(mode)
        mesh = meshes.square(n) if mesh_fn is None else mesh_fn(n)
        return Built(fm.Scene(mesh, mu=mu, f=f, g=g))

    return build


def scaled_default(s):
    """Default scene with f and g multiplied by ``s``: the solution is ``s`` times the default."""

    def build(mode):
        return Built(
            fm.Scene(meshes.square(_n(mode)), f=(-s, s), g=0.1 * s),
            reference=lambda: default()(mode),
        )

    return build


def scaled_mms(s):
    """Manufactured family with ``g, beta, s0`` times ``s`` (kappa kept): u, lambda times ``s``."""

    def build(mode):
        exact = fm.Manufactured(g=0.1 * s, beta=0.25 * s, s0=s, kappa=1.0)
        return Built(
            exact.scene(meshes.square(_n(mode))),
            exact,
            reference=lambda: mms()(mode),
        )

    return build


def single_point_mms(mode):
    """Manufactured contact set ``{b >= 1 - h^2/4}``: a disk of radius ~h/2 around the origin.

    The only mesh vertex inside is the origin (n even); lambda = (-q)^+ is tiny.
    """
    n = _n(mode)
    h = 2.0 / n
    g = 0.1
    exact = fm.Manufactured(g=g, beta=g / (1.0 - h * h / 4.0))
    return Built(exact.scene(meshes.square(n)), exact)


def hat_load(mode):
    """f1 = -a psi_c (a hat at the centre vertex c), f2 = 0, g = 0.1: contact at c only.

    The amplitude ``a`` is chosen between the two values that make the
    unconstrained gap vanish at c and at its highest neighbour (geometric
    mean), computed here with an independent scipy solve.
    """
    import scipy.sparse.linalg as spla

    n = _n(mode)
    mesh = meshes.square(n)
    g = 0.1
    centre = int(np.argmin(np.linalg.norm(mesh.vertices, axis=1)))
    hat = np.zeros(mesh.n_vertices)
    hat[centre] = 1.0
    unit = fm.Scene(mesh, f=(hat, 0.0), g=0.0)
    ii = mesh.interior_vertices
    a_ii = unit.stiffness[ii][:, ii].tocsc()
    v = np.zeros(mesh.n_vertices)
    v[ii] = spla.spsolve(a_ii, unit.loads[0][ii])  # response of the gap to -f1: u1 = v
    nb = mesh.triangles[(mesh.triangles == centre).any(axis=1)].ravel()
    nb = np.unique(nb[nb != centre])
    a_lo, a_hi = g / v[centre], g / v[nb].max()  # gap = g - a v
    amp = np.sqrt(a_lo * a_hi)
    return Built(fm.Scene(mesh, f=(-amp * hat, 0.0), g=g))


def _jump_f1(x, y):
    return np.where(y > 0.37 * x + 0.123, -4.0, -0.5)


def _jump_f2(x, y):
    return np.where(y > 0.37 * x + 0.123, 1.0, 3.0)


def _osc_f1(x, y):
    return -1.0 - 2.0 * np.sin(50.0 * np.pi * x) * np.cos(30.0 * np.pi * y)


def _osc_f2(x, y):
    return 1.0 + np.sin(50.0 * np.pi * (x + y))


def mu_per_triangle(mode):
    """mu1 jumps 1e-3 / 1e3 across the line x = 0.3 y + 0.11 (general path), mu2 = 1."""
    mesh = meshes.square(_n(mode))
    c = mesh.vertices[mesh.triangles].mean(axis=1)
    mu1 = np.where(c[:, 0] > 0.3 * c[:, 1] + 0.11, 1e3, 1e-3)
    return Built(fm.Scene(mesh, mu=(mu1, 1.0), f=(-1.0, 1.0), g=0.1))


def mu_opposite_jump(mode):
    """mu1 = 1e6 | 1e-6 and mu2 = 1e-6 | 1e6 across x = 0.3 y + 0.11 (contrast 1e12).

    32 x 32 cells (fast) or 64 x 64 (full), whatever the mode's size: both show
    the AMG-CG failures of known.py (at 16 x 16 and 128 x 128 the inexact run returns).
    """
    mesh = meshes.square({"fast": 32, "full": 64}[mode])
    c = mesh.vertices[mesh.triangles].mean(axis=1)
    right = c[:, 0] > 0.3 * c[:, 1] + 0.11
    mu1 = np.where(right, 1e6, 1e-6)
    mu2 = np.where(right, 1e-6, 1e6)
    return Built(fm.Scene(mesh, mu=(mu1, mu2), f=(-1.0, 1.0), g=0.1))


def mu_checkerboard(mode):
    """mu1 = 1e4 | 1e-4 and mu2 = 1e-4 | 1e4 on a 4 x 4 checkerboard (opposite contrasts).

    With per-triangle mu the obstacle problem of the gap has the matrix
    (A1^-1 + A2^-1)^-1, which need not be an M-matrix even on a structured mesh.
    """
    mesh = meshes.square(_n(mode))
    c = mesh.vertices[mesh.triangles].mean(axis=1)
    black = (np.floor((c[:, 0] + 1) * 2) + np.floor((c[:, 1] + 1) * 2)) % 2 == 0
    mu1 = np.where(black, 1e4, 1e-4)
    mu2 = np.where(black, 1e-4, 1e4)
    return Built(fm.Scene(mesh, mu=(mu1, mu2), f=(-1.0, 1.0), g=0.1))


def initial_all_active(mode):
    """Default scene started from a triple whose active set is every interior vertex."""
    mesh = meshes.square(_n(mode))
    scene = fm.Scene(mesh, f=(-1.0, 1.0), g=0.1)
    u1 = scene.boundary_values.copy()
    lam = np.where(mesh.boundary_vertex_mask, 0.0, 1.0)
    return Built(scene, solve_options={"initial": (u1, u1.copy(), lam)})


def initial_random(mode):
    """Manufactured case on a perturbed mesh, started from a random (seeded) triple."""
    mesh = meshes.perturbed(_n(mode))
    exact = fm.Manufactured()
    rng = np.random.default_rng(meshes.SEED)
    n = mesh.n_vertices
    init = (rng.normal(size=n) * 0.1, rng.normal(size=n) * 0.1, rng.normal(size=n))
    return Built(exact.scene(mesh), exact, solve_options={"initial": init})


def _gmsh_square(n):
    return meshes.gmsh_mesh("square", 0.25 / n, 4.0 / n)


def _gmsh_disk(n):
    return meshes.gmsh_mesh("disk", 0.25 / n, 4.0 / n)


# ------------------------------------------------------------------------------ the table

_MU_VALUES = [
    (1e-6, 1.0),
    (1.0, 1e-6),
    (1e-3, 1e3),
    (1e3, 1e-3),
    (1e6, 1.0),
    (1.0, 1e6),
    (1e-6, 1e6),
    (1e6, 1e-6),
    (1e-6, 1e-6),
    (1e6, 1e6),
]


def _num(x):
    """Short number for case names: 1e-06 -> 1e-6, 1e+06 -> 1e6."""
    return f"{x:g}".replace("e-0", "e-").replace("e+0", "e").replace("e+", "e")


def _mu_name(mu):
    return f"{_num(mu[0])},{_num(mu[1])}"


NON_M = Expect(non_m_matrix=True, must_converge=False)

CASES: list[Case] = []

# --- tension ratios ----------------------------------------------------------
for _mu in _MU_VALUES:
    CASES.append(
        Case(
            f"mms-mu={_mu_name(_mu)}",
            "mu",
            f"manufactured solution, mu = {_mu}",
            mms(mu=_mu),
            amg_fast=_mu in ((1e-6, 1e6), (1e6, 1e-6)),
        )
    )
for _mu in [(1e-6, 1e-6), (1e6, 1e6), (1e-6, 1e6), (1e6, 1e-6), (1e-3, 1e3)]:
    CASES.append(
        Case(
            f"default-mu={_mu_name(_mu)}",
            "mu",
            f"default scene, mu = {_mu}",
            default(mu=_mu),
        )
    )
CASES += [
    Case(
        "mms-mu=1e-6,1e6-general",
        "mu",
        "manufactured, mu = (1e-6, 1e6), reduced SPD (general) path forced",
        mms(path="general", mu=(1e-6, 1e6)),
    ),
    Case(
        "default-mu-per-triangle-jump",
        "mu",
        "mu1 = 1e-3 | 1e3 across a line not aligned with the mesh (general path)",
        mu_per_triangle,
        amg_fast=True,
    ),
]

CASES.append(
    Case(
        "default-mu-opposite-jump-1e6",
        "mu",
        "per-triangle mu1 = 1e6 | 1e-6, mu2 = 1e-6 | 1e6 across a line (general path)",
        mu_opposite_jump,
        amg_fast=True,
    )
)
CASES.append(
    Case(
        "default-mu-checkerboard-opposite",
        "mu",
        "per-triangle mu1 = 1e4 | 1e-4, mu2 = 1e-4 | 1e4 on a checkerboard (general path)",
        mu_checkerboard,
        amg_fast=True,
    )
)

# --- boundary value g ------------------------------------------------------------
for _g in (1e-8, 1e-4, 1e3):
    CASES.append(
        Case(
            f"default-g={_num(_g)}",
            "g",
            f"default scene with g = {_g:g}" + (" (no contact)" if _g > 1 else ""),
            default(g=_g),
            expect=Expect(n_active="none") if _g > 1 else Expect(),
        )
    )
for _g in (1e-8, 1e3):
    CASES.append(
        Case(
            f"mms-g={_num(_g)}",
            "g",
            f"manufactured, g = {_g:g}, beta = 2.5 g (contact set b >= 0.4 kept)",
            mms(g=_g, beta=2.5 * _g),
        )
    )

# --- data scaling ----------------------------------------------------------------
for _s in (1e-8, 1e-4, 1e4, 1e8):
    CASES.append(
        Case(
            f"default-scale={_num(_s)}",
            "scale",
            f"default scene, f and g times {_s:g} (solution times {_s:g})",
            scaled_default(_s),
            expect=Expect(scale=_s),
            amg_fast=_s in (1e-8, 1e8),
        )
    )
for _s in (1e-8, 1e8):
    CASES.append(
        Case(
            f"mms-scale={_num(_s)}",
            "scale",
            f"manufactured, g, beta, s0 times {_s:g} (solution times {_s:g})",
            scaled_mms(_s),
            expect=Expect(scale=_s),
        )
    )
CASES += [
    Case(
        "default-f=1e-8",
        "scale",
        "default scene with f times 1e-8, g = 0.1 (no contact)",
        default(f=(-1e-8, 1e-8)),
        expect=Expect(n_active="none"),
    ),
    Case(
        "default-f=1e8",
        "scale",
        "default scene with f times 1e8, g = 0.1 (contact at every interior vertex)",
        default(f=(-1e8, 1e8)),
        expect=Expect(n_active="all"),
    ),
]

# --- meshes ----------------------------------------------------------------------
CASES += [
    Case(
        "mms-graded-p3",
        "mesh",
        "manufactured on a graded tensor mesh t -> -1 + 2 ((t+1)/2)^3",
        mms(mesh_fn=lambda n: meshes.graded(n, 3)),
        expect=Expect(min_aspect=500.0),
        amg_fast=True,
    ),
    Case(
        "mms-boundary-layer-1e3",
        "mesh",
        "manufactured, y graded towards y = +-1, boundary cells of aspect ratio 1e3",
        mms(mesh_fn=lambda n: meshes.boundary_layer(n, 1e3)),
        expect=Expect(min_aspect=0.99e3),
    ),
    Case(
        "default-rectangle-1000x1",
        "mesh",
        "default data on [0, 1000] x [0, 1], n x n cells (aspect ratio 1e3)",
        default(mesh_fn=meshes.stretched_rectangle),
        expect=Expect(min_aspect=1e3),
        amg_fast=True,
    ),
    Case(
        "default-square-scaled-1000x1",
        "mesh",
        "default data on the square mesh scaled by (1000, 1)",
        default(mesh_fn=lambda n: meshes.scaled(meshes.square(n), 1000.0, 1.0)),
        expect=Expect(min_aspect=1e3),
    ),
    Case(
        "default-square-scaled-1x1000",
        "mesh",
        "default data on the square mesh scaled by (1, 1000) (tall domain)",
        default(mesh_fn=lambda n: meshes.scaled(meshes.square(n), 1.0, 1000.0)),
        expect=Expect(min_aspect=1e3),
    ),
    Case(
        "mms-criss-cross-8:1",
        "mesh",
        "manufactured on a criss-cross mesh of 8:1 cells (obtuse angles ~166 deg)",
        mms(mesh_fn=lambda n: meshes.criss_cross(2 * n, n // 4)),
        expect=NON_M,
        amg_fast=True,
    ),
    Case(
        "mms-anti-delaunay",
        "mesh",
        "manufactured on shifted rows split along the longer diagonal (obtuse)",
        mms(mesh_fn=meshes.anti_delaunay),
        expect=NON_M,
    ),
    Case(
        "mms-perturbed",
        "mesh",
        "manufactured on a randomly perturbed mesh (0.24 cells per coordinate)",
        mms(mesh_fn=meshes.perturbed),
        expect=NON_M,
        amg_fast=True,
    ),
    Case(
        "default-perturbed-strong-load",
        "mesh",
        "f = (-4, 4), g = 0.05 on a randomly perturbed mesh (large contact set)",
        default(mesh_fn=meshes.perturbed, f=(-4.0, 4.0), g=0.05),
        expect=NON_M,
    ),
    Case(
        "default-anti-delaunay-strong-load",
        "mesh",
        "f = (-4, 4), g = 0.05 on the anti-Delaunay mesh",
        default(mesh_fn=meshes.anti_delaunay, f=(-4.0, 4.0), g=0.05),
        expect=NON_M,
    ),
    Case(
        "default-criss-cross-crawl",
        "mesh",
        "f = (-0.5, 0.5) on a criss-cross mesh of 8n x 4 cells (aspect 32 fast, 128 full):"
        " Newton-min moves the contact front about one cell per step",
        default(mesh_fn=lambda n: meshes.criss_cross(8 * n, 4), f=(-0.5, 0.5)),
        expect=NON_M,
        amg_fast=True,
    ),
    Case(
        "mms-gmsh-square",
        "mesh",
        "manufactured on a gmsh square mesh, sizes h/4 (corner, centre) to 4h",
        mms(mesh_fn=_gmsh_square),
        expect=Expect(needs_gmsh=True),
        amg_fast=True,
    ),
    Case(
        "default-gmsh-disk",
        "mesh",
        "default data on a gmsh unit disk, sizes h/4 (near (0.5, 0)) to 4h",
        default(mesh_fn=_gmsh_disk),
        expect=Expect(needs_gmsh=True),
    ),
]

# --- degenerate contact -----------------------------------------------------------
CASES += [
    Case(
        "mms-kappa=0",
        "contact",
        "manufactured, kappa = 0: lambda = 0 on a contact set of positive measure",
        mms(kappa=0.0),
        amg_fast=True,
    ),
    Case(
        "mms-kappa=0-refined-contact",
        "contact",
        "manufactured, kappa = 0, beta = 1 (contact set b >= 0.1, most of the domain)",
        mms(kappa=0.0, beta=1.0),
    ),
    Case(
        "mms-single-point",
        "contact",
        "manufactured contact set = disk of radius h/2 around the origin vertex",
        single_point_mms,
    ),
    Case(
        "default-hat-load-one-vertex",
        "contact",
        "f1 = -a hat(centre), f2 = 0: the discrete contact set is one vertex",
        hat_load,
        expect=Expect(n_active="one"),
        amg_fast=True,
    ),
    Case(
        "default-contact-everywhere",
        "contact",
        "g = 0, f = (-1, 1): contact at every interior vertex",
        default(g=0.0),
        expect=Expect(n_active="all"),
        amg_fast=True,
    ),
    Case(
        "default-contact-everywhere-g=1e-8",
        "contact",
        "g = 1e-8, f = (-10, 10)",
        default(g=1e-8, f=(-10.0, 10.0)),
    ),
]

CASES += [
    Case(
        "default-initial-all-active",
        "contact",
        "default scene, initial iterate with every interior vertex active",
        initial_all_active,
        amg_fast=True,
    ),
    Case(
        "mms-perturbed-initial-random",
        "contact",
        "manufactured on a perturbed mesh, random initial triple (random initial active set)",
        initial_random,
        expect=NON_M,
        amg_fast=True,
    ),
]

CASES += [
    Case(
        "default-zero-data",
        "contact",
        "f = (0, 0), g = 0: the solution is zero, eta must be 0 (no 0/0 anywhere)",
        default(f=(0.0, 0.0), g=0.0),
        amg_fast=True,
    ),
    Case(
        "default-f=0",
        "contact",
        "f = (0, 0), g = 0.1: u1 = g, u2 = 0, no contact; the P1 solution is exact",
        default(f=(0.0, 0.0)),
        expect=Expect(n_active="none"),
    ),
    Case(
        "default-no-interior-vertex",
        "domain",
        "Mesh.square(1): two triangles, no interior vertex (empty systems)",
        default(mesh_fn=lambda n: fm.Mesh.square(1)),
        expect=Expect(n_active="none"),
        amg_fast=True,
    ),
    Case(
        "mms-one-interior-vertex",
        "domain",
        "manufactured on Mesh.square(2): a single interior vertex",
        mms(mesh_fn=lambda n: fm.Mesh.square(2)),
        amg_fast=True,
    ),
]

# --- data --------------------------------------------------------------------------
CASES += [
    Case(
        "default-f-jump-oblique",
        "data",
        "piecewise constant f1, f2 jumping across y = 0.37 x + 0.123",
        default(f=(_jump_f1, _jump_f2)),
        amg_fast=True,
    ),
    Case(
        "default-f-oscillating",
        "data",
        "f1 = -1 - 2 sin(50 pi x) cos(30 pi y), f2 = 1 + sin(50 pi (x + y))",
        default(f=(_osc_f1, _osc_f2)),
    ),
    Case(
        "mms-discontinuous-lambda",
        "data",
        "manufactured with lambda = kappa 1_{q<0} (f jumps across the free boundary)",
        mms(discontinuous=True),
    ),
]

# --- domain ------------------------------------------------------------------------
CASES += [
    Case(
        "default-lshape",
        "domain",
        "default data on the L-shaped domain (reentrant corner)",
        default(mesh_fn=meshes.lshape),
        amg_fast=True,
    ),
    Case(
        "default-lshape-mu=1e-3,1e3",
        "domain",
        "L-shaped domain, mu = (1e-3, 1e3), f = (-1, 1), g = 0.1",
        default(mesh_fn=meshes.lshape, mu=(1e-3, 1e3)),
    ),
]

CASES_BY_NAME = {c.name: c for c in CASES}
assert len(CASES_BY_NAME) == len(CASES), "case names must be unique"


def matrix(mode: str) -> list[tuple[Case, str]]:
    """All (case, variant) pairs of a mode."""
    return [(c, v) for c in CASES if mode == "full" or c.fast for v in c.variants(mode)]
