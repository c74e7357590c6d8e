r"""Solving to a guaranteed tolerance: the adaptive refinement loop (docs/method.md §9).

``fm.solve(scene, tol=1e-3)`` (or ``rtol=``) runs, from the scene's mesh,

    SOLVE -> ESTIMATE -> MARK -> REFINE

until the guaranteed bound of the returned triple is below the target:

1. **SOLVE** the problem on the current mesh with the pipeline of
   :func:`fastmem.solver.levels.solve_levels` (the first mesh with nested iteration
   over its coarse chain; every later mesh warm-started from the triple of the
   previous one, prolonged exactly: newest-vertex bisection keeps P1
   functions), with the stopping rule of the method (for ``"inexact"``:
   ``eta_alg, eta_lin <= gamma * eta_disc``).  ``eta_alg`` and ``eta_lin``
   are part of the bound checked against the target (``eta <= eta_disc +
   eta_lin + eta_alg``; with the default gamma = 0.1 about 5 % of eta), so
   with ``"inexact"`` a mesh expected to be the last one (its predicted
   ``eta_disc``, ``eta_disc`` of the previous mesh times ``(N_prev /
   N)^(1/2)``, meets the target, or a mesh made by the landing rule below) is
   solved with gamma = :data:`FINAL_GAMMA` (0.01, unless the user's gammas are
   smaller), and a mesh whose ``eta``
   misses the target while ``eta - eta_alg - eta_lin`` meets it is solved on,
   warm-started, with that gamma before any refinement: a tighter solve costs
   a fraction of a level, a refinement a level 1.3 to 1.4 times larger.
   The other meshes' triples only mark and warm-start the next mesh: with
   :data:`INTERMEDIATE_ALG` ``"cg"`` their CGs stop when the CG's own estimate of
   the algebraic error in the energy norm
   (:meth:`fastmem.linalg.amg.PCG.error_estimate`) or the guaranteed
   ``eta_alg`` is below ``gamma_alg max(eta_disc, eta_lin)``.  ``eta_alg``
   is a Friedrichs constant times the norm of the residual: for the warm start
   prolonged from the previous mesh, whose residual lives on the new
   vertices, it exceeds the algebraic error a thousandfold (7.6 against an
   ``eta_disc`` of 2.4e-3 on the L-shape), and the CG spent 11 iterations
   bringing it down, against 3-5 by its own estimate.  Every mesh's bound is
   computed as before; a mesh that misses the target by its ``eta_alg`` is
   the near miss above.  A mesh whose predicted ``eta_disc`` is within
   :data:`NEAR_TARGET` of the target keeps the guaranteed criterion (solved as
   an intermediate one, it would be the near miss, solved twice, with two
   flux reconstructions); so does the last mesh of a loop that stops short
   of the target (``max_levels``, the resolution limit, ...), solved on
   before it is returned.
2. **ESTIMATE**: the bound ``eta`` of the level's final triple, evaluated fresh
   (a flux reconstruction per mesh, none on the intermediate meshes of nested
   iteration), and the per-triangle indicators

   .. math:: \eta_K^2 = \sum_i (\eta_{osc,K,i} + \eta_{F,K,i})^2 + \eta_{nc,K}^2 + \eta_{C,K}

   (:func:`indicators`).  They are the local contributions of ``eta_disc``
   (flux, oscillation, complementarity) and ``eta_lin`` (non-conformity);
   the global terms (``eta_alg`` and the ``lam^-`` part of ``eta_lin``,
   Friedrichs constant times a norm over the whole domain) have no local
   form and are made small by the solver, not by refinement.
3. **STOP** when ``eta <= target`` with ``target = max(tol, rtol * |||u_h|||)``
   (either tolerance may be omitted), where

   .. math:: |||u_h|||^2 = \sum_{i=1,2} \mu_i \|\nabla u_{ih}\|^2

   is the energy norm of the discrete solution (the norm the bound measures
   the error in); or when the next mesh would exceed ``max_vertices``, the
   loop has solved ``max_levels`` meshes, or the next level would end after
   ``time_budget`` seconds (predicted from the last level's time, scaled by
   the number of vertices), or the triangles at the resolution limit
   (diameter at most :data:`RESOLUTION_LIMIT` = 2^-26 of the domain's size;
   they are never marked, since below it round-off swamps the bound) alone
   hold more than the target.  Then ``converged=False`` and the reason is in
   ``result.parameters["adaptivity"]["stop_reason"]``.
4. **MARK** the fewest triangles holding a fraction ``theta`` of
   ``sum eta_K^2`` (Dörfler, :func:`fastmem.mesh.refine.dorfler_mark`, O(M));
   with ``min_growth > 1`` (default 1, off), when their refinement would make
   fewer than ``min_growth`` times the vertices, the largest indicators that
   give that many (:func:`ensure_growth`; the top-k search of the landing rule
   below).  The loop's total work is then about ``min_growth / (min_growth -
   1)`` times the last mesh's, 3 at 1.5 against 3.7-4.3 for Dörfler's own
   1.3-1.4 (L-shape, tol 9.1e-3: 17 meshes and 1.05-1.2 s instead of 23 and
   1.3-1.45 s).  Larger factors do not pay with one round of bisection per
   step: at 1.7 the marked set spreads (57k final vertices instead of 34k), at
   2 it is every triangle; and near an unresolvable singularity (Kellogg)
   even 1.5 spreads it until ``max_vertices``.  Unless the target is predicted
   within reach of that mesh: then **land**.
   The mesh part of the bound (:func:`mesh_part`: ``eta`` without its solver
   terms, which the tight last solve makes small) behaves like ``C N^(-1/2)``,
   so the target is met at about ``N_aim = N (eta_mesh / (LANDING_AIM *
   target))^2`` vertices (:data:`LANDING_AIM` = 0.97: a margin for the scatter
   of ``eta sqrt(N)`` between meshes, a few per cent, and for the solver's
   share).  If ``N_aim`` is below the vertex count of Dörfler's mesh (the
   closure kernel counts it before refining) or below
   :data:`LANDING_MAX_GROWTH` = 4 times ``N``, the largest indicators are
   marked, as many as give about ``N_aim - N`` new vertices (top-k by
   :func:`numpy.argpartition` and a closure count per trial, secant steps on
   k, O(M) each, at most 8 trials).  Dörfler's mesh overshoots the target by
   up to its whole growth (at least ``min_growth``); the landed
   mesh by the margin.  Landing only within Dörfler's mesh cost a mesh more:
   the step that fell short of the target and the small landing step after it
   (L-shape, the eta of uniform n = 2048: 97,596 -> 168,635 vertices, eta 1.1
   times the target, -> 219,377) instead of one step (97,596 -> 223,748), 37 %
   more vertices in all.  ``parameters["adaptivity"]["landings"]`` lists the
   landings (level, vertices aimed at, vertices made).
5. **REFINE** by newest-vertex bisection with conforming closure
   (:func:`fastmem.mesh.refine.refine_marked`), ``bisections`` rounds (default 2:
   the children of the marked triangles are marked again and bisected with their
   own closure, so each marked triangle is cut into four or more; the
   convergence and optimality theory of AFEM allows any fixed number b >= 1 of
   bisections per marked triangle).  Dörfler's set then grows the mesh 1.6-1.9
   times instead of 1.3-1.4 (L-shape), and the loop solves fewer vertices in all
   (tol 3.44e-3: 15 meshes, 513k vertices in all, against 29 meshes, 771k); the
   counts of the minimum growth and of the landing are the first round's closure
   count times the ratio of all rounds to the first measured on the last
   refinement made; the set found is refined, and while it misses by more than
   3 % regula falsi on the exact counts of the sets refined so far picks another
   (at most 3 more; the ratio varies by 10-20 % from set to set).  Later rounds
   do not mark children at the resolution limit.
   Each mesh's multigrid hierarchy is the previous mesh's plus one level
   (:func:`extend_chain`, the ``transfers`` of
   :func:`~fastmem.solver.levels.solve_levels`): the geometric multigrid of
   :mod:`fastmem.linalg.gmg` on meshes with at least
   :data:`~fastmem.solver.levels.GEOMETRIC_MIN_UNKNOWNS` interior vertices, the
   two-grid cycle over the previous mesh below.  The scene moves to the new mesh by
   :func:`refine_scene` (per-triangle mu inherited, per-vertex data
   interpolated, callables evaluated on the new mesh).

Refined meshes keep the numbering of :func:`~fastmem.mesh.refine.refine_marked`
(old vertices first, new ones by bisected edge).  Renumbering them for
locality was measured and does not pay: on a 182k-vertex adapted L-shape
mesh, a Morton-curve order of the vertices (triangles sorted by their first
vertex) made a solve from scratch 1.3x slower (5.4 s against 4.2 s, the
auxiliary coarse meshes 1.0 -> 1.9 s), and the direct factorisations order
by nested dissection from the coordinates anyway (:mod:`fastmem.linalg.direct`).

The result is the last level's, on its mesh, with ``result.adaptivity``: one
row per mesh (:data:`ADAPTIVITY_COLUMNS`), archived under ``/adaptivity``.
Its history holds the rows of every mesh in order; the ``level`` column
counts the meshes (nested-iteration levels of the first mesh, then one per
refinement), and ``parameters["solver"]["levels"]`` has one entry per mesh.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from ..estimators.terms import refinement_indicators
from ..fem.scene import Scene
from ..kernels import nvb as _kn
from ..linalg.sparse import submatrix
from ..mesh.refine import (
    RefinementRounds,
    dorfler_mark,
    next_round,
    refine_marked,
    refinement_edges,
)
from ..solver.levels import attach_laplacian, keeps_chain, solve_levels
from ..solver.nested import NESTED_MIN_VERTICES

__all__ = [
    "ADAPTIVITY_COLUMNS",
    "energy_norm",
    "indicators",
    "prolong_to_refined",
    "refine_scene",
    "resolution_limit",
    "solve_to_tolerance",
]

logger = logging.getLogger(__name__)

#: Columns of ``result.adaptivity``: one row per mesh of the adaptive loop.
ADAPTIVITY_COLUMNS = (
    "level",  # 0 = the scene's mesh
    "n_vertices",
    "n_triangles",
    "eta",  # guaranteed bound of the level's final triple (fresh)
    "eta_disc",
    "eta_lin",
    "eta_alg",
    "energy_norm",  # |||u_h||| of the level's triple
    "target",  # max(tol, rtol * energy_norm)
    "marked_fraction",  # marked / triangles (0 on the last level)
    "newton",  # Newton-min steps on this mesh (nested levels of the first mesh included)
    "inner",  # CG iterations on this mesh (0 for "exact")
    "solve_seconds",  # SOLVE + ESTIMATE
    "refine_seconds",  # MARK + REFINE + moving the scene and the triple
    "cg_stop",  # 1: an intermediate mesh whose CG could stop by its own error estimate
)
_INT_COLUMNS = frozenset({"level", "n_vertices", "n_triangles", "newton", "inner", "cg_stop"})


def indicators(estimate) -> np.ndarray:
    r"""Per-triangle refinement indicators :math:`\eta_K^2` of an estimate (module docstring)."""
    if getattr(estimate, "marking", None) is not None:
        return estimate.marking
    if "eta_K" in estimate.maps:  # an obstacle estimate: the indicators themselves
        return np.asarray(estimate.maps["eta_K"]) ** 2
    return refinement_indicators(estimate.maps)


def energy_norm(scene: Scene, u1, u2) -> float:
    r""":math:`(\sum_i \mu_i \|\nabla u_{ih}\|^2)^{1/2}`, the energy norm of a discrete pair."""
    e = u1 @ (scene.weighted_stiffness(1) @ u1) + u2 @ (scene.weighted_stiffness(2) @ u2)
    return float(np.sqrt(max(e, 0.0)))


def refine_scene(scene: Scene, mesh, refinement) -> Scene:
    """Move the problem to a refined mesh (``refine_marked``'s ``(mesh, refinement)``).

    Constant data and callables are kept (callables are evaluated on the new
    mesh); per-triangle ``mu`` is inherited by the children; per-vertex loads
    are interpolated (exact for P1 data); per-vertex ``g`` is interpolated
    along the bisected boundary edges.
    """

    def nodal(value):
        return value if callable(value) or isinstance(value, float) else refinement.prolong(value)

    def per_triangle(value):
        return value if isinstance(value, float) else refinement.inherit(value)

    g = scene.g
    if not (callable(g) or isinstance(g, float)):
        g = refinement.prolong(scene.boundary_values)
    return Scene(
        mesh,
        mu=(per_triangle(scene.mu1), per_triangle(scene.mu2)),
        f=(nodal(scene.f1), nodal(scene.f2)),
        g=g,
        active_c=scene.active_c,
        load_degree=scene.load_degree,
        parallel_callables=scene.parallel_callables,
    )


def prolong_to_refined(scene: Scene, refinement, triple):
    """Prolong a triple to the refined ``scene`` exactly; boundary values set from its data."""
    u1, u2, lam = (refinement.prolong(x) for x in triple)
    bnd = scene.mesh.boundary_vertices
    u1[bnd] = scene.boundary_values[bnd]
    u2[bnd] = 0.0
    lam[bnd] = 0.0
    return u1, u2, lam


def _level_options(options):
    """Every mesh of the loop needs the bound: ``estimate=True`` for the exact methods."""
    if options.newton.needs_estimate:
        return options
    return replace(options, newton=replace(options.newton, estimate=True))


#: gamma_alg and gamma_lin on a mesh expected to be the last one, and when a level misses
#: the target only by its algebraic and linearisation parts (module docstring); None: off.
FINAL_GAMMA = 0.01

#: What stops the CG on the meshes not expected to be the last one (their triples only
#: mark and warm-start): "cg", the CG's own estimate of the algebraic error
#: (``InnerOptions.alg_estimate``); "bound", the guaranteed eta_alg as on the last mesh.
INTERMEDIATE_ALG = "cg"
#: ... except on a mesh whose predicted eta_disc is within this factor of the target: it
#: may well be the last one, and solved as an intermediate one it would miss the target by
#: its (guaranteed) eta_alg and be solved again, with a second flux reconstruction; such a
#: mesh takes the solver's own criterion.  Consecutive meshes' eta_disc differ by about
#: 1.3 (the growth 1.6-1.9 to the power 1/2), so the mesh before the last stays cheap.
NEAR_TARGET = 1.2


def _intermediate(options):
    """``options`` for a mesh not expected to be the last (:data:`INTERMEDIATE_ALG`)."""
    if options.newton.method != "inexact" or options.inner.alg_estimate == INTERMEDIATE_ALG:
        return options
    return replace(options, inner=replace(options.inner, alg_estimate=INTERMEDIATE_ALG))


def _with_gamma(options, gamma):
    """``options`` with gamma_alg, gamma_lin at most ``gamma``; None if that changes nothing."""
    no, inner = options.newton, options.inner
    if gamma is None or no.method != "inexact" or min(no.gamma_lin, inner.gamma_alg) <= gamma:
        return None
    return replace(
        options,
        newton=replace(options.newton, gamma_lin=min(gamma, options.newton.gamma_lin)),
        inner=replace(
            options.inner, gamma_alg=min(gamma, options.inner.gamma_alg), alg_estimate="bound"
        ),
    )


class _Merged:
    """History rows and level entries of all meshes, renumbered into one sequence."""

    def __init__(self):
        self.history = None
        self.levels = []
        self.factorizations = 0
        self.safeguard = None

    def add(self, result, same_mesh=False):
        h = result.history
        solver = result.parameters["solver"]
        offset = len(self.levels) - (1 if same_mesh else 0)
        if self.history is None:
            self.history = {k: [np.asarray(v)] for k, v in h.items()}
        else:
            inner0 = self.history["inner_total"][-1]
            start = int(inner0[-1]) if inner0.size else 0
            for k, v in h.items():
                v = np.asarray(v)
                if k == "level":
                    v = v + offset
                elif k == "inner_total":
                    v = v + start
                self.history[k].append(v)
        if same_mesh:  # a second solve on the last mesh: one entry, counts summed
            (info,) = solver["levels"]
            prev = self.levels[-1]
            for k, v in info.items():
                if k not in ("level", "n_vertices", "safeguard") and type(v) in (int, float):
                    prev[k] = prev.get(k, 0) + v
            prev["converged"] = info["converged"]
            prev["solves"] = prev.get("solves", 1) + 1
        else:
            for info in solver["levels"]:
                self.levels.append({**info, "level": offset + info["level"]})
        self.factorizations += solver.get("factorizations", 0)
        sg = solver["safeguard"]
        if self.safeguard is None:
            self.safeguard = {k: (list(v) if isinstance(v, list) else v) for k, v in sg.items()}
        else:
            for k in ("uses", "steps", "seconds", "reached_kkt"):
                self.safeguard[k] += sg[k]
            self.safeguard["triggers"] += [f"mesh {offset}+: {t}" for t in sg["triggers"]]

    def history_arrays(self):
        return {k: np.concatenate(v) for k, v in self.history.items()}


def _row(level, scene, result, target, energy, seconds):
    totals = result.estimate.totals
    newton = sum(info["newton"] for info in result.parameters["solver"]["levels"])
    inner = result.history["inner_total"]
    return {
        "level": level,
        "n_vertices": scene.mesh.n_vertices,
        "n_triangles": scene.mesh.n_triangles,
        "eta": float(totals["eta"]),
        "eta_disc": float(totals["eta_disc"]),
        "eta_lin": float(totals["eta_lin"]),
        "eta_alg": float(totals["eta_alg"]),
        "energy_norm": energy,
        "target": target,
        "marked_fraction": 0.0,
        "newton": int(newton),
        "inner": int(inner[-1]) if inner.size else 0,
        "solve_seconds": seconds,
        "refine_seconds": 0.0,
        "cg_stop": 0,
    }


def _table(rows) -> dict:
    return {
        c: np.asarray([r[c] for r in rows], dtype=np.int64 if c in _INT_COLUMNS else np.float64)
        for c in ADAPTIVITY_COLUMNS
    }


#: Landing (module docstring): a refinement predicted to reach the target aims at
#: ``mesh_part(eta) = LANDING_AIM * target`` ...
LANDING_AIM = 0.97
#: ... when the vertices this needs are at most LANDING_MAX_GROWTH times the current ones
#: (or at most Dörfler's next mesh); None: landing off (every mesh from Dörfler marking).
#: Beyond Dörfler's mesh the step is larger and the scatter of eta sqrt(N) with it (the
#: manufactured solution's observed rates alternate between 0.45 and 0.6): such a landing
#: aims at LANDING_FAR_AIM * target ...
LANDING_FAR_AIM = 0.93
#: ... and only where the mesh part of the bound fell at least like N^-LANDING_MIN_RATE
#: over the last refinement (Kellogg's checkerboard, u ~ r^0.1, falls far slower: an aim
#: from the N^(-1/2) law lands short there, several times over).
LANDING_MIN_RATE = 0.4
#: ... from meshes of this many vertices on (below, a Dörfler step costs milliseconds, and
#: on Kellogg's first meshes the rate of a local Dörfler step, 0.4-0.6, says nothing of a
#: landing step spread over the domain: aims from 97 and 265 vertices landed short)
LANDING_FAR_MIN_VERTICES = 1000
#: Measured at ten tolerances (L-shape, f = (-1, -1), 2e-2 to 3e-3; square, f = (-1, 1),
#: 1e-2 to 4e-3): against 1.0 (never beyond Dörfler's mesh) 4 solved one or two meshes
#: fewer and 24-45 % fewer vertices in all, every loop landing at the first try; 3.5 and 5
#: made the same meshes but at one or two tolerances; 6 and 8 landed from coarser meshes,
#: where eta does not follow the N^(-1/2) law yet, and solved more vertices in all at six
#: and seven of the ten.
LANDING_MAX_GROWTH = 4.0
#: The marked set of a landing step has a closure within this fraction of the new vertices
#: aimed at (at most _LANDING_TRIES closure counts).
_LANDING_TOL = 0.01
#: With more than one round of bisection, a marked set whose refinement misses the count
#: aimed at by more than this fraction is searched for once more (:func:`_recount`).
_ROUNDS_TOL = 0.03
_ROUNDS_TRIES = 3
_LANDING_TRIES = 8

#: Triangles whose diameter is at most this fraction of the domain's size (the longer
#: side of its bounding box) are not marked.  Below it the geometry and the nodal
#: residuals lose too many digits for the bound to mean anything: on a checkerboard of
#: contrast 1e3 the loop refined the cross points to diameters of 1e-10 ... 1e-16 (1e-9
#: after 60 meshes, 2 levels per halving), where round-off in the residuals, divided by
#: lumped masses of h^2, made the global term eta_alg grow from 6e-3 to 2e3 while
#: eta_disc kept falling.  2^-26 (1.5e-8) leaves two orders of magnitude to that.
RESOLUTION_LIMIT = 2.0**-26


def mesh_part(totals) -> float:
    r"""Return the bound ``eta`` of an estimate without its solver parts (what refinement controls).

    ``eta`` is the positive root of :math:`x^2 = a x + c` plus :math:`\eta_{nc}`, with
    :math:`a = (\sum_K d_{1,K}^2 + (d_{2,K} + \eta_{nc,K})^2)^{1/2} + |(\eta_{glob,1},
    \eta_{glob,2})|` (docs/method.md §6).  Without the non-conformity and the global terms
    (both vanish as the solver converges) :math:`a_0 = \eta_{disc} - c^{1/2}`; the result is
    the root of :math:`x^2 = a_0 x + c`.  Its local terms all scale alike under refinement
    (c like the squares), so it is homogeneous of degree one in them.
    """
    c = max(float(totals["c"]), 0.0)
    a0 = max(float(totals["eta_disc"]) - np.sqrt(c), 0.0)
    return 0.5 * (a0 + np.sqrt(a0 * a0 + 4.0 * c))


def _landing_vertices(row, target, n_dorfler, rate=None):
    """Vertices of the next mesh for the landing rule, or None (Dörfler's mesh).

    With the mesh part of the bound (:func:`mesh_part`) ~ N^(-1/2) on adapted meshes, the
    target is met at about ``N (eta_mesh / target)^2`` vertices; the rule aims at
    ``LANDING_AIM * target`` (a margin for the solver's share of the last mesh and for the
    scatter of eta sqrt(N) between meshes: a miss costs one more mesh).  Beyond Dörfler's
    mesh (``n_dorfler`` vertices), up to ``LANDING_MAX_GROWTH`` times the vertices, only
    from ``LANDING_FAR_MIN_VERTICES`` vertices on and when the mesh part fell at least
    like ``N^-LANDING_MIN_RATE`` over the last refinement (``rate``; None: unknown), and at
    ``LANDING_FAR_AIM * target``.
    """
    if LANDING_MAX_GROWTH is None or not target > 0.0:
        return None
    n = row["n_vertices"]
    need = n * (row["eta_mesh"] / (LANDING_AIM * target)) ** 2
    if need <= n_dorfler:
        # (eta_disc already at the aim, eta missed it by its solver share: a small step)
        return max(need, n * 1.05)
    if n < LANDING_FAR_MIN_VERTICES or rate is None or not rate >= LANDING_MIN_RATE:
        return None  # not in the N^(-1/2) regime (yet): a Dörfler step
    need = n * (row["eta_mesh"] / (LANDING_FAR_AIM * target)) ** 2
    return need if need <= n * LANDING_MAX_GROWTH else None  # else not yet in reach


def _rate(before, row):
    """Observed rate p of ``eta_mesh ~ N^-p`` from the row ``before`` to ``row``, or None."""
    if before is None or not before["n_vertices"] < row["n_vertices"]:
        return None
    if not (before["eta_mesh"] > 0.0 and row["eta_mesh"] > 0.0):
        return None
    return float(
        -np.log(row["eta_mesh"] / before["eta_mesh"])
        / np.log(row["n_vertices"] / before["n_vertices"])
    )


class _Counter:
    """New vertices of refining a mask of ``mesh`` with ``bisections`` rounds, O(M) each.

    The closure kernel of :func:`~fastmem.mesh.refine.refine_marked` counts the edges
    that the first round bisects, without refining.  With more rounds (whose closures
    depend on the meshes of the rounds before) the count is that number times the ratio
    of all rounds' vertices to the first round's, measured by the last exact count.
    :meth:`exact` counts by making every round but the last (the last one's closure
    is counted on the mesh before it) and keeps those rounds for :meth:`refine`.
    """

    def __init__(self, mesh, bisections=1):
        self.mesh, self.bisections = mesh, bisections
        self.limit = resolution_limit(mesh)  # later rounds do not go below it either
        self.ref = refinement_edges(mesh, None)
        self.ratio = 1.0
        self.made = None  # (mask, rounds but the last: [(mesh, Refinement)], last mask)

    def _closure_count(self, mesh, mask, ref=None) -> int:
        ref = refinement_edges(mesh, None) if ref is None else ref
        return int(
            np.count_nonzero(_kn.closure(mesh.triangle_edges, mesh.edge_triangles, ref, mask))
        )

    def first_round(self, mask) -> int:
        return self._closure_count(self.mesh, mask, self.ref)

    def __call__(self, mask, want=None) -> int:
        n1 = self.first_round(mask)
        return n1 if self.bisections == 1 else int(round(n1 * self.ratio))

    def _rounds_but_last(self, mask):
        if self.made is not None and self.made[0] is mask:
            return self.made[1], self.made[2]
        rounds, cur, m = [], self.mesh, mask
        for _ in range(self.bisections - 1):
            cur, one = refine_marked(cur, m, validate=False)
            rounds.append((cur, one))
            m = next_round(m, cur, one, self.limit)
        self.made = (mask, rounds, m)
        return rounds, m

    def exact(self, mask) -> int:
        """Count the vertices refining ``mask`` adds (the rounds made are kept)."""
        if self.bisections == 1:
            return self.first_round(mask)
        rounds, last = self._rounds_but_last(mask)
        before = rounds[-1][0]
        n = before.n_vertices - self.mesh.n_vertices + self._closure_count(before, last)
        self.ratio = n / max(rounds[0][1].n_new_vertices, 1)
        return n

    def refine(self, mask):
        """``refine_marked(mesh, mask, bisections=...)``, from the kept rounds if any."""
        if self.bisections == 1:
            return refine_marked(self.mesh, mask, validate=False)
        rounds, last = self._rounds_but_last(mask)
        fine, one = refine_marked(rounds[-1][0], last, validate=False)
        return fine, RefinementRounds([r for _, r in rounds] + [one])


def _mark_vertices(mesh, eta2, want, k0, n0, count=None):
    """Mark the k largest indicators whose NVB closure bisects about ``want`` edges.

    ``k0`` triangles (Dörfler's set) gave ``n0`` bisected edges.  Each trial is a top-k
    selection (:func:`numpy.argpartition`, O(M)) and a count (``count``, a
    :class:`_Counter`: the closure kernel of :func:`~fastmem.mesh.refine.refine_marked`
    for one round of bisection, O(M)), at most ``_LANDING_TRIES`` of them: secant steps
    on k inside the bracket found so far.
    """
    m = eta2.size
    count = _Counter(mesh) if count is None else count
    lo, hi = (0, 0), (m, None)
    if n0 <= want:
        lo = (k0, n0)
    else:
        hi = (k0, n0)
    best = None
    k = k0 * want / max(n0, 1)
    for _ in range(_LANDING_TRIES):
        k = int(min(max(round(k), lo[0] + 1), hi[0] - 1 if hi[1] is not None else m))
        mask = _top(eta2, k)
        n_k = count(mask)
        if best is None or abs(n_k - want) < abs(best[1] - want):
            best = (mask, n_k)
        if abs(n_k - want) <= _LANDING_TOL * want or k >= m:
            break
        if n_k < want:
            lo = (k, n_k)
        else:
            hi = (k, n_k)
        if hi[1] is None:  # no upper bracket yet: proportional step from the lower one
            k = k * want / max(n_k, 1)
        elif hi[0] - lo[0] <= 1:
            break
        else:
            k = lo[0] + (want - lo[1]) * (hi[0] - lo[0]) / (hi[1] - lo[1])
    return best[0]


def new_vertices(mesh, marked, bisections=1) -> int:
    """Vertices that refining ``marked`` adds (edges bisected with the NVB closure), O(M)."""
    return _Counter(mesh, bisections).exact(marked)


def _top(eta2, k):
    """Mask of the ``k`` largest indicators (:func:`numpy.argpartition`, O(M))."""
    m = eta2.size
    mask = np.zeros(m, dtype=bool)
    mask[np.argpartition(eta2, m - k)[m - k :]] = True
    return mask


def _recount(mesh, eta2, want, marked, count, known=()):
    """Return ``marked``, or a top set closer to ``want`` when it misses by > 3 %.

    With more than one round of bisection the search counts by a ratio measured on
    another set (:class:`_Counter`), which varies from set to set by 10-20 %.  The set
    found is refined; while its count misses ``want`` by more than :data:`_ROUNDS_TOL`,
    regula falsi on the exact counts of the top sets refined so far (``known``: more
    ``(k, count)`` pairs, Dörfler's set) picks the next size, at most
    :data:`_ROUNDS_TRIES` times; the set closest to ``want`` is returned.
    """
    if count.bisections == 1:
        return marked
    m = eta2.size
    pts = list(known)
    best = None
    mask, k = marked, int(np.count_nonzero(marked))
    for _ in range(_ROUNDS_TRIES + 1):
        n = count.exact(mask)
        pts.append((k, n))
        if best is None or abs(n - want) < abs(best[1] - want):
            best = (mask, n)
        if abs(n - want) <= _ROUNDS_TOL * want:
            break
        lo = max((p for p in pts if p[1] <= want), default=(0, 0))
        hi = min((p for p in pts if p[1] > want), default=None)
        if hi is None:
            step = k * want / max(n, 1)
        elif hi[0] - lo[0] <= 1:
            break
        else:
            step = lo[0] + (want - lo[1]) * (hi[0] - lo[0]) / (hi[1] - lo[1])
        k = int(min(max(round(step), lo[0] + 1), m if hi is None else hi[0] - 1))
        mask = _top(eta2, k)
    return best[0]


def ensure_growth(mesh, eta2, marked, min_growth, bisections=1):
    """Return ``marked``, or the largest indicators giving ``min_growth`` times the vertices.

    The minimum growth of the MARK step (module docstring), for a loop without the
    landing rule (:mod:`fastmem.adapt.obstacle`); ``bisections`` rounds per refinement.
    """
    grow = (min_growth - 1.0) * mesh.n_vertices
    if grow <= 0.0:
        return marked
    count = _Counter(mesh, bisections)
    n0 = count.exact(marked)
    if n0 >= grow:
        return marked
    k0 = int(np.count_nonzero(marked))
    marked = _mark_vertices(mesh, eta2, grow, k0, n0, count)
    return _recount(mesh, eta2, grow, marked, count, [(k0, n0)])


def resolution_limit(mesh) -> float:
    """Smallest diameter of a triangle the adaptive loop still marks (:data:`RESOLUTION_LIMIT`)."""
    x0, x1, y0, y1 = mesh.bounding_box
    return RESOLUTION_LIMIT * max(x1 - x0, y1 - y0)


def _markable(mesh, eta2, target):
    r"""Return the indicators without the triangles at the resolution limit, and a stop reason.

    The loop stops when those triangles alone hold more than the target
    (:math:`(\sum \eta_K^2)^{1/2}` over them: refinement cannot bring the bound below
    it), or when nothing else is left to mark; the reason is None otherwise.
    """
    limit = resolution_limit(mesh)
    small = mesh.diameters <= limit
    if not small.any():
        return eta2, None
    stuck = float(np.sqrt(eta2[small].sum()))
    eta2 = np.where(small, 0.0, eta2)
    where = mesh.vertices[mesh.triangles[np.argmax(np.where(small, mesh.diameters, 0.0))]]
    x, y = where.mean(axis=0)
    what = (
        f"triangles at the resolution limit (diameter <= {limit:.3g}, {RESOLUTION_LIMIT:.3g} "
        f"of the domain; {int(small.sum())} of them, e.g. near ({x:.6g}, {y:.6g})) hold "
        f"{stuck:.4e} of the indicators"
    )
    if stuck > target:
        return eta2, f"{what} > target {target:.4e}: a singularity no mesh can resolve further"
    if not (eta2 > 0.0).any():
        return eta2, f"{what}; nothing else is left to refine"
    return eta2, None


def _next_mesh(scene, result, adapt, row=None, target=None, eta2=None):
    """MARK and REFINE: (marked fraction, new scene, refinement, landing aim or None)."""
    if eta2 is None:
        eta2 = indicators(result.estimate)
    marked = dorfler_mark(eta2, adapt.theta)
    mesh = scene.mesh
    aim = None
    count = _Counter(mesh, adapt.bisections)
    if row is not None:
        k0 = int(np.count_nonzero(marked))
        n0 = count.exact(marked)
        # the minimum growth: Dörfler's set, or the largest indicators that give
        # (min_growth - 1) N new vertices when it gives fewer
        grow = (adapt.min_growth - 1.0) * mesh.n_vertices
        aim = _landing_vertices(row, target, mesh.n_vertices + max(n0, grow), row.get("rate"))
        if aim is not None:
            marked = _mark_vertices(mesh, eta2, aim - mesh.n_vertices, k0, n0, count)
            marked = _recount(mesh, eta2, aim - mesh.n_vertices, marked, count, [(k0, n0)])
        elif n0 < grow:
            marked = _mark_vertices(mesh, eta2, grow, k0, n0, count)
            marked = _recount(mesh, eta2, grow, marked, count, [(k0, n0)])
    # validate=False skips only the duplicate-vertex search (new vertices are midpoints of
    # distinct edges); the edge checks run when the solver first asks for the edges
    fine, refinement = count.refine(marked)
    return float(marked.mean()), fine, refinement, aim


def _stop_before_refining(level, adapt, t_start):
    if level + 1 >= adapt.max_levels:
        return f"max_levels={adapt.max_levels} meshes solved"
    if adapt.time_budget is not None and time.perf_counter() - t_start >= adapt.time_budget:
        return f"time_budget={adapt.time_budget:g} s used"
    return None


def _stop_after_refining(mesh, row, adapt, t_start):
    if mesh.n_vertices > adapt.max_vertices:
        return (
            f"the next mesh would have {mesh.n_vertices} vertices > "
            f"max_vertices={adapt.max_vertices}"
        )
    if adapt.time_budget is not None:
        growth = mesh.n_vertices / row["n_vertices"]
        end = time.perf_counter() - t_start + row["solve_seconds"] * growth
        if end > adapt.time_budget:
            return (
                f"the next level would end after about {end:.1f} s > "
                f"time_budget={adapt.time_budget:g} s"
            )
    return None


def solve_to_tolerance(scene, options, init, timings):
    """Run the adaptive loop (module docstring); return the Result on the final mesh."""
    adapt = options.adapt
    level_options = _level_options(options)
    t_start = time.perf_counter()
    merged, rows = _Merged(), []
    triple, prolonged, hint, landing = init, False, None, False
    # the interior interpolations onto the current mesh, finest first: the multigrid
    # hierarchy of every mesh is the one before plus a level (solve_levels' transfers)
    chain = [] if keeps_chain(level_options, scene) else None
    tight = _with_gamma(level_options, FINAL_GAMMA)  # None: nothing to tighten
    loose = _intermediate(level_options) if tight is not None else level_options
    refine_total = 0.0
    landings = []
    previous = None  # the last refined mesh's row with its eta_mesh (the observed rate)
    level = 0
    while True:
        t0 = time.perf_counter()
        # a mesh whose predicted eta_disc meets the target is probably the last one: solve
        # it tighter (eta_alg, eta_lin are part of the bound the target is checked against)
        expected = None if hint is None else _target(adapt, rows[-1]["energy_norm"])
        last_expected = tight is not None and hint is not None and (landing or hint <= expected)
        near = hint is not None and hint <= NEAR_TARGET * expected
        opts = tight if last_expected else (level_options if near else loose)
        result = solve_levels(
            scene, opts, triple, {}, prolonged=prolonged, disc_hint=hint, transfers=chain
        )
        energy = energy_norm(scene, result.u1, result.u2)
        target = _target(adapt, energy)
        row = _row(level, scene, result, target, energy, time.perf_counter() - t0)
        row["cg_stop"] = int(opts is loose and loose is not level_options)
        merged.add(result)
        if tight is not None and opts is not tight and _near_miss(row, target):
            # missed by the solver's share only: solve on, on this mesh (no refinement)
            result, row, target = _solve_on(scene, tight, result, row, level, t0, chain, adapt)
            merged.add(result, same_mesh=True)
        rows.append(row)
        ok = result.converged
        reached = row["eta"] <= target
        reason = None
        if reached:
            reason = "tolerance reached"
        elif not ok:
            reason = f"the solver did not converge on level {level} ({result.n_newton} steps)"
        else:
            reason = _stop_before_refining(level, adapt, t_start)
        at_limit = False  # the stop is the resolution limit's (its reason names the indicators)
        if reason is None:
            eta2, reason = _markable(scene.mesh, indicators(result.estimate), target)
            at_limit = reason is not None
        if reason is None:
            t1 = time.perf_counter()
            parts = dict(row, eta_mesh=mesh_part(result.estimate.totals))
            parts["rate"] = _rate(previous, parts)
            previous = parts
            fraction, mesh, refinement, aim = _next_mesh(scene, result, adapt, parts, target, eta2)
            landing = aim is not None  # the next mesh is aimed at the target: solve it tight
            if landing:
                landings.append({"level": level, "aim": int(aim), "vertices": mesh.n_vertices})
            reason = _stop_after_refining(mesh, row, adapt, t_start)
            if reason is None:
                new_scene = refine_scene(scene, mesh, refinement)
                last = (result.u1, result.u2, result.lam)
                triple = prolong_to_refined(new_scene, refinement, last)
                if chain is not None:
                    extend_chain(chain, scene.mesh, mesh, refinement)
                    attach_laplacian(level_options, chain[0], scene)
                # eta_disc ~ N^(-1/2) on adapted meshes: the prediction for the next mesh
                hint = row["eta_disc"] * (row["n_vertices"] / mesh.n_vertices) ** 0.5
                scene, prolonged = new_scene, True
                row["marked_fraction"] = fraction
            row["refine_seconds"] = time.perf_counter() - t1
            refine_total += row["refine_seconds"]
        _report(row, adapt)
        if reason is not None:
            break
        # the next solve must not keep this level alive: its mesh (with the topology and
        # patch caches), estimator maps and refinement arrays would be ~1 KB per vertex
        result = mesh = refinement = last = None
        level += 1
    if opts is loose and loose is not level_options and ok and not reached:
        # stopped short of the target on a mesh solved as an intermediate one: the triple
        # returned gets the solver's own criterion, as on every mesh before INTERMEDIATE_ALG
        kept = {k: row[k] for k in ("marked_fraction", "refine_seconds") if k in row}
        result, row, target = _solve_on(scene, level_options, result, row, level, t0, chain, adapt)
        merged.add(result, same_mesh=True)
        rows[-1] = row = {**row, **kept}
        ok = result.converged
        if ok and row["eta"] <= target:
            reached, reason = True, "tolerance reached"
        elif at_limit:  # the message names the returned triple's indicators
            reason = _markable(scene.mesh, indicators(result.estimate), target)[1] or reason
        _report(row, adapt)  # the mesh again, as returned
    timings["refine"] = refine_total
    timings["solve"] = time.perf_counter() - t_start - refine_total
    result.timings = timings
    result = _finish(result, merged, rows, adapt, reached and ok, reason)
    result.parameters["adaptivity"]["landings"] = landings
    return result


def _solve_on(scene, options, result, row, level, t0, chain, adapt):
    """Solve on, on ``result``'s mesh, from its triple with ``options``: (result, row, target).

    The row counts the Newton steps and CG iterations of both solves; its time runs
    from ``t0``, the start of the mesh's first solve.
    """
    result = solve_levels(
        scene,
        options,
        [result.u1, result.u2, result.lam],
        {},
        disc_hint=row["eta_disc"],
        transfers=chain,
    )
    energy = energy_norm(scene, result.u1, result.u2)
    target = _target(adapt, energy)
    again = _row(level, scene, result, target, energy, time.perf_counter() - t0)
    for key in ("newton", "inner"):
        again[key] += row[key]
    return result, again, target


#: The adaptive chain keeps its coarsest level below this many interior vertices: coarser
#: links are dropped (the coarsest level is factored directly, at most
#: :data:`fastmem.linalg.gmg.COARSE_DIRECT` unknowns).
CHAIN_MIN_UNKNOWNS = NESTED_MIN_VERTICES


def extend_chain(chain, old, new, refinement) -> None:
    """Put the interior interpolation from mesh ``old`` to its refinement ``new`` first.

    ``chain``: interior interpolations onto ``old``, finest first (changed in place).  The
    coarsest links go while the level above them has fewer than
    :data:`CHAIN_MIN_UNKNOWNS` interior vertices.
    """
    p = refinement.prolongation_matrix()
    chain.insert(0, submatrix(p, new.interior_vertices, old.interior_vertices))
    while len(chain) > 1 and chain[-1].shape[0] < CHAIN_MIN_UNKNOWNS:
        chain.pop()


def _target(adapt, energy):
    """max(tol, rtol * |||u_h|||), the target of a level whose triple has energy norm ``energy``."""
    return max(adapt.tol or 0.0, (adapt.rtol or 0.0) * energy)


def _near_miss(row, target):
    """Tell whether eta misses the target but eta - eta_alg - eta_lin meets it."""
    return row["eta"] > target and row["eta"] - row["eta_alg"] - row["eta_lin"] <= target


def _report(row, adapt):
    logger.info(
        "adaptive level %d: %d vertices, eta %.4e (target %.4e), marked %.1f%%, %.2f s",
        row["level"],
        row["n_vertices"],
        row["eta"],
        row["target"],
        100 * row["marked_fraction"],
        row["solve_seconds"] + row["refine_seconds"],
    )
    if adapt.level_monitor is not None:
        adapt.level_monitor(dict(row))


def _finish(result, merged, rows, adapt, converged, reason):
    solver = result.parameters["solver"]
    solver["levels"] = merged.levels
    solver["nested_levels"] = len(merged.levels)
    solver["safeguard"] = merged.safeguard
    if "factorizations" in solver:
        solver["factorizations"] = merged.factorizations
    result.parameters["adaptivity"] = {
        "tol": adapt.tol,
        "rtol": adapt.rtol,
        "theta": adapt.theta,
        "min_growth": adapt.min_growth,
        "bisections": adapt.bisections,
        "max_vertices": adapt.max_vertices,
        "max_levels": adapt.max_levels,
        "time_budget": adapt.time_budget,
        "meshes": len(rows),
        "converged": bool(converged),
        "stop_reason": reason,
        "indicators": "eta_K^2 = sum_i (eta_osc,K,i + eta_F,K,i)^2 + eta_nc,K^2 + eta_C,K",
    }
    result.history = merged.history_arrays()
    result.adaptivity = _table(rows)
    result.converged = bool(converged)
    if not converged:
        logger.warning("adaptive refinement stopped before the tolerance: %s", reason)
    return result
