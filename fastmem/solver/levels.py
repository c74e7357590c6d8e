"""Levels of a solve: nested iteration over the coarse chain, then the result.

The outer layer of the pipeline (:func:`fastmem.solve` → :func:`solve_levels`
→ :func:`fastmem.solver.newton.newton_min` → :mod:`fastmem.solver.steps`).  Without an
initial triple, the problem is solved first on the chain of coarser scenes
(:func:`fastmem.solver.nested.coarse_scenes`: coarser versions of the mesh, or
auxiliary coarse meshes for meshes without one), coarsest first, each
solution prolonged as the initial iterate of the next level; every method
does this, ``"exact"`` with a direct solver on every level.  The
intermediate levels only make initial guesses: ``"inexact"`` reconstructs no
flux there and stops by the ``eta_disc`` predicted from the coarser level.
The last level is the scene's own mesh; its triple, with the guaranteed
bound when one is asked for (always for ``"inexact"``), becomes the
:class:`~fastmem.io.result.Result`.
"""

from __future__ import annotations

import logging
import time

from ..config import get_threads
from ..estimators.bound import evaluate
from ..fem.loaddata import expect_estimates
from ..io.result import Result
from ..linalg.gmg import NestedChain, attach_coarse_operator
from ..linalg.sparse import THREADED_ROWS, submatrix
from .history import history_arrays, new_history
from .nested import coarse_scenes, interpolation_matrix, prolong_triple
from .newton import newton_min
from .safeguard import new_safeguard_record

__all__ = ["AUXILIARY", "HINT_SAFETY", "attach_laplacian", "keeps_chain", "solve_levels"]

logger = logging.getLogger(__name__)

#: Factor applied to the eta_disc predicted from coarser levels before the final level: the
#: prediction (eta_disc ~ h) overestimated by 18% on the default scene at n = 512, and an
#: overestimate costs one flux reconstruction more, an underestimate a CG iteration or two.
#: The outer (Newton) candidate test divides it out again (``hint_slack`` of newton_min):
#: there an underestimate costs whole Newton steps (manufactured scene, n = 768: 2 steps).
HINT_SAFETY = 0.7

#: Nested iteration builds auxiliary coarse meshes for meshes without a coarser version.
AUXILIARY = True


#: Decoupled CGs on the levels of nested iteration precondition the sum s by a two-grid
#: cycle over the coarser level (:class:`fastmem.linalg.amg.TwoGridLaplacian`) instead of an
#: AMG setup of their own.
TWO_GRID = True

#: ``multigrid="auto"``: the geometric multigrid on the levels with at least this many
#: interior vertices (those whose products run in the kernel threads), pyamg below: a
#: default ``fastmem run`` (n = 128) then compiles no multigrid kernel (1.4 s of its first
#: run), and below it the two are equally fast.
GEOMETRIC_MIN_UNKNOWNS = THREADED_ROWS


def _two_grid(options, scene) -> bool:
    """Whether the level's linear step gets the interpolation for the two-grid cycle.

    Only the decoupled CG (``path`` "decoupled", or "auto" with constant tensions) uses it.
    """
    no = options.newton
    decoupled = no.path == "decoupled" or (no.path == "auto" and scene.constant_mu)
    return TWO_GRID and no.method in ("inexact", "exact-amg") and decoupled


def _general_cg(options, scene) -> bool:
    """Whether the level's linear step is the general path's CG (:class:`GeneralCG`)."""
    no = options.newton
    general = no.path == "general" or (no.path == "auto" and not scene.constant_mu)
    return no.method in ("inexact", "exact-amg") and general


def _merge_safeguard(records):
    """Sum the per-level safeguard bookkeeping into one record."""
    total = new_safeguard_record()
    for lev, rec in enumerate(records):
        for name in ("uses", "steps", "seconds"):
            total[name] += rec[name]
        total["triggers"] += [f"level {lev}: {t}" for t in rec["triggers"]]
        total["reached_kkt"] += rec["reached_kkt"]
    return total


def _chain(scene, options, init, timings):
    """Return the scenes to solve, coarsest first, ending with ``scene``."""
    nested = options.newton.nested
    if init is not None or nested is False:
        return [scene]
    t0 = time.perf_counter()
    chain = coarse_scenes(scene, auxiliary=AUXILIARY)
    timings["coarsening"] = time.perf_counter() - t0
    if nested is True and not chain:
        logger.warning("nested=True but this mesh has no usable coarser version")
    return chain + [scene]


def _multigrid(options, sc, transfers):
    """Choose the linear step's multigrid for level scene ``sc`` from the chain ``transfers``.

    ``transfers``: interior interpolations onto ``sc``'s mesh from the meshes before it,
    finest first (with ``multigrid="algebraic"`` only the link from the level below, for
    the two-grid cycle).  Returns ``(prolongation, used)``: what :func:`newton_min` takes as
    ``prolongation`` and the name recorded in the level's info.
    """
    multigrid = options.inner.multigrid
    if not transfers:
        return None, None
    geometric = multigrid == "geometric" or (
        multigrid == "auto" and sc.mesh.interior_vertices.size >= GEOMETRIC_MIN_UNKNOWNS
    )
    if _two_grid(options, sc):
        if geometric:
            # the decoupled CGs' geometric multigrid over the whole chain
            # (fastmem.linalg.gmg.NestedMG)
            return [NestedChain(transfers)], "geometric"
        # the decoupled CG's two-grid cycle for s (fastmem.linalg.amg.TwoGridLaplacian),
        # handed over as a list that newton_min empties: the step's two-grid
        # cycle is then its only owner and can free it (TwoGridLaplacian.release)
        return [transfers[0]], "two-grid"
    if _general_cg(options, sc) and geometric:
        # the general path's CG: the chain's block interpolations (GeneralCG)
        return [NestedChain(transfers)], "geometric"
    return None, None


def attach_laplacian(options, link, coarse) -> None:
    """Attach ``coarse``'s interior Laplacian to ``link``, the interpolation from its mesh.

    Only for the decoupled CGs, whose geometric multigrid coarsens the interior
    Laplacian: on a nested pair it is the Galerkin product that the chain would
    otherwise form (:func:`fastmem.linalg.gmg.attach_coarse_operator`, which checks
    it before use).  ``coarse``: the scene of the link's coarse mesh.
    """
    if _two_grid(options, coarse) and options.inner.multigrid != "algebraic":
        ii = coarse.mesh.interior_vertices
        attach_coarse_operator(link, submatrix(coarse.stiffness, ii, ii))


def keeps_chain(options, scene) -> bool:
    """Whether the levels of ``scene``'s solve build multigrid on a chain of interpolations."""
    return options.inner.multigrid != "algebraic" and (
        _two_grid(options, scene) or _general_cg(options, scene)
    )


def solve_levels(
    scene, options, init, timings, prolonged=False, disc_hint=None, transfers=None
) -> Result:
    """Nested iteration over the coarse chain, then Newton-min on ``scene``: the Result.

    ``prolonged``: ``init`` was prolonged from a coarser mesh (the adaptive loop of
    :mod:`fastmem.adapt.loop`), so its first active set is chosen as on the levels of nested
    iteration (:func:`fastmem.solver.nested.warm_active_set`); ``disc_hint`` is then the
    eta_disc predicted for ``scene`` (used like the prediction from a coarser level).

    ``transfers``: a list of the interior interpolations onto ``scene``'s mesh from the
    meshes it was refined from, finest first (the adaptive loop's chain).  The first
    level's multigrid is built on it, as a nested level's is on the coarse chain; the
    interpolations of nested iteration are added to it in place, so that afterwards it
    is the chain of ``scene``'s mesh.  None: a chain of this solve's own.
    """
    levels = _chain(scene, options, init, timings)
    # the coarser Laplacians are attached to the chain only where a geometric multigrid
    # may use them: a level of this solve that takes it, or a chain handed in (the
    # adaptive loop's, whose later meshes grow); a default run (n = 128) takes none
    attach = transfers is not None or options.inner.multigrid == "geometric"
    attach = attach or levels[-1].mesh.interior_vertices.size >= GEOMETRIC_MIN_UNKNOWNS
    # interior interpolations of the chain so far, finest first
    transfers = [] if transfers is None else transfers
    rows = new_history()
    infos, iterates = [], []
    triple, out = init, None
    t_solve = time.perf_counter()
    for lev, sc in enumerate(levels):
        t0 = time.perf_counter()
        hint, slack = (disc_hint if lev == 0 else None), 1.0
        prolongation, used = None, None
        if lev == 0 and init is not None:
            # the adaptive loop's chain (or none): the first level's multigrid
            prolongation, used = _multigrid(options, sc, transfers)
        if lev > 0:
            coarse = levels[lev - 1]
            mat = interpolation_matrix(coarse.mesh, sc.mesh)
            triple = prolong_triple(sc, coarse, triple, mat)
            if _two_grid(options, sc) or _general_cg(options, sc):
                ii, ic = sc.mesh.interior_vertices, coarse.mesh.interior_vertices
                link = submatrix(mat, ii, ic)
                if keeps_chain(options, sc):
                    # this level's interpolation joins those of the coarser levels, with
                    # the coarser Laplacian that its multigrid's coarse operator is
                    if attach:
                        attach_laplacian(options, link, coarse)
                    transfers.insert(0, link)
                    prolongation, used = _multigrid(options, sc, transfers)
                else:  # "algebraic": the decoupled CG's two-grid cycle only
                    prolongation, used = _multigrid(options, sc, [link])
                del link
            del mat, coarse
            h_ratio = sc.mesh.diameters.max() / levels[lev - 1].mesh.diameters.max()
            hint = None if out.eta_disc is None else out.eta_disc * h_ratio
            # the coarser scene (mesh topology, matrices: a third of the fine level's
            # memory over the chain) is done with: free it before the finer level's solve
            levels[lev - 1] = None
        # intermediate levels only make initial guesses: no flux there (see newton_min)
        certify = lev == 0 or lev == len(levels) - 1
        if certify and options.newton.needs_estimate:
            expect_estimates(sc)  # before the step's load vectors: one pass over the data
        if certify and hint is not None:
            # a hint above the true value triggers a flux too early (a wasted one) ...
            hint *= HINT_SAFETY
            # ... but the outer test must not miss a stop that the true value allows
            slack = 1.0 / HINT_SAFETY
        # handed over as a list: newton_min empties it, so the initial triple is freed
        # with the first step's warm start instead of living through the whole level
        triple = None if triple is None else list(triple)
        out = newton_min(
            sc,
            options,
            triple,
            level=lev,
            rows=rows,
            certify=certify,
            disc_hint=hint,
            hint_slack=slack,
            prolonged=lev > 0 or prolonged,
            prolongation=prolongation,
        )
        del prolongation
        triple = (out.last.u1, out.last.u2, out.last.lam)
        iterates.extend(out.iterates)
        info = {
            "level": lev,
            "n_vertices": sc.mesh.n_vertices,
            "newton": out.n_newton,
            "inner": out.inner,
            "converged": out.converged,
            "seconds": time.perf_counter() - t0,
            # the decoupled CGs' preconditioner from the chain: "geometric" (NestedMG),
            # "two-grid" (TwoGridLaplacian for s) or None (pyamg's setups only)
            "multigrid": used,
            **out.stats,
        }
        infos.append(info)
        logger.info(
            "level %d (%d vertices): %d Newton steps, %d inner iterations, %.2fs",
            lev,
            sc.mesh.n_vertices,
            out.n_newton,
            out.inner,
            info["seconds"],
        )
    timings["solve"] = time.perf_counter() - t_solve
    return _result(scene, options, out, rows, infos, iterates, timings)


def _result(scene, options, out, rows, infos, iterates, timings) -> Result:
    last = out.last
    est = last.estimate
    if est is None and options.newton.needs_estimate:
        t0 = time.perf_counter()
        est = evaluate(scene, last.u1, last.u2, last.lam, last.r1, last.r2, last.local, last.glob)
        timings["estimate"] = time.perf_counter() - t0
    no, inner = options.newton, options.inner
    params = scene.parameters()
    params["solver"] = {
        "method": no.method,
        "path": out.path,
        "max_newton": no.max_newton,
        "gamma_alg": inner.gamma_alg,
        "gamma_lin": no.gamma_lin,
        "max_inner": inner.max_inner,
        "check_every": inner.check_every,
        "amg_reuse": inner.amg_reuse,
        "multigrid": inner.multigrid,
        "amg_options": {k: repr(v) for k, v in inner.amg_options.items()},
        "nested_levels": len(infos),
        "levels": infos,
        "stop_reason": out.reason,
        "safeguard": _merge_safeguard([info["safeguard"] for info in infos]),
        "threads": get_threads(),
    }
    if "factorizations" in out.stats:  # direct steps
        params["solver"]["factorizations"] = sum(info["factorizations"] for info in infos)
        params["solver"]["relative_residual"] = out.stats["relative_residual"]
    result = Result(
        mesh=scene.mesh,
        u1=last.u1,
        u2=last.u2,
        lam=last.lam,
        r1=last.r1,
        r2=last.r2,
        active=out.active,
        history=history_arrays(rows),
        timings=timings,
        parameters=params,
        converged=out.converged,
        n_newton=out.n_newton,
        method=no.method,
        path=out.path,
        estimate=est,
    )
    if options.record.keep_iterates:
        result.iterates = iterates
    return result
