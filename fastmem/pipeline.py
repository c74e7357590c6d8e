r"""The solver's entry point: :func:`solve` validates, groups the options, runs the pipeline.

The pipeline, one loop per layer, each layer knowing only the one below:

0. :mod:`fastmem.adapt.loop` (only with ``tol`` or ``rtol``): the adaptive
   refinement loop, SOLVE -> ESTIMATE -> MARK -> REFINE, calling the levels
   layer once per mesh;
1. :mod:`fastmem.solver.levels`: nested iteration over the chain of coarser meshes
   (every method), then the :class:`~fastmem.io.result.Result`;
2. :mod:`fastmem.solver.newton`: Newton-min on one mesh, one loop for every method
   (active-set update, stopping rule, safeguard, history rows);
3. :mod:`fastmem.solver.steps` and :mod:`fastmem.solver.inexact`: the linear step of one
   active set, solved directly (``"exact"``), by AMG-CG to round-off
   (``"exact-amg"``) or by AMG-CG stopped by the estimators (``"inexact"``);
   the formulations (general reduced SPD system, decoupled sum/gap) are in
   :mod:`fastmem.solver.linear`.

Options are grouped in the frozen dataclasses of :mod:`fastmem.solver.options`; the
history has one schema for every method (:mod:`fastmem.solver.history`).
"""

from __future__ import annotations

import time

from .adapt.loop import solve_to_tolerance
from .adapt.obstacle import solve_obstacle
from .config import blas_limits
from .errors import InputTypeError, ParameterError, checked_keywords
from .fem.loaddata import expect_estimates
from .fem.obstacle import Obstacle
from .fem.scene import Scene
from .io.result import Result, check_nodal, check_triple
from .memory import check_memory
from .solver.history import HISTORY_COLUMNS
from .solver.levels import solve_levels
from .solver.newton import complementarity
from .solver.options import METHODS, SolveOptions

__all__ = ["HISTORY_COLUMNS", "METHODS", "complementarity", "solve"]


@checked_keywords("fastmem.solve")
def solve(
    scene: Scene,
    method: str = "inexact",
    path: str = "auto",
    *,
    max_newton: int = 1000,
    initial=None,
    monitor=None,
    blas_threads: int | None = None,
    estimate: bool = True,
    gamma_alg: float = 0.1,
    gamma_lin: float = 0.1,
    max_inner: int = 500,
    check_every: int = 1,
    amg_options: dict | None = None,
    amg_reuse: float = 0.05,
    multigrid: str = "auto",
    nested: bool | str = "auto",
    full_history: bool = False,
    keep_iterates: bool = False,
    safeguard: bool = True,
    tol: float | None = None,
    rtol: float | None = None,
    theta: float | None = None,
    min_growth: float | None = None,
    bisections: int | None = None,
    max_vertices: int | None = None,
    max_levels: int | None = None,
    time_budget: float | None = None,
    level_monitor=None,
    memory_limit=None,
) -> Result:
    """Solve the discrete two-membrane contact problem with Newton-min.

    Parameters
    ----------
    scene : Scene
        The problem.
    method : {"inexact", "exact-amg", "exact"}
        ``"inexact"`` (default): AMG-preconditioned CG inner solves stopped
        by the estimators (docs/method.md §6, :mod:`fastmem.solver.inexact`): the
        inner iteration stops when ``eta_alg <= gamma_alg * max(eta_disc,
        eta_lin)``, Newton-min when also ``eta_lin <= gamma_lin * eta_disc``.
        ``"exact-amg"``: the same loop with inner solves to relative residual
        1e-12, stopping when the active set repeats (the exact baseline for
        large meshes).  ``"exact"``: every step solved by a sparse direct
        solver (:mod:`fastmem.linalg.direct`; small meshes).
    path : {"auto", "general", "decoupled"}
        Linear-step formulation; "auto" takes "decoupled" for constant mu.
    max_newton : int
        Maximum number of Newton-min steps per level.  Reaching it returns
        a Result with ``converged=False`` and logs a warning.
    initial : tuple (u1, u2, lam) of ndarray, optional
        Initial iterate; its active set starts the iteration (and it is the
        warm start of the AMG methods).  Default: see ``nested``.
    monitor : callable, optional
        Called with each history row (a dict with the columns of
        :data:`fastmem.solver.history.HISTORY_COLUMNS`) as soon as it is recorded.
    blas_threads : int, optional
        BLAS threads during the solve (default :func:`fastmem.get_threads`).
    estimate : bool
        Attach the guaranteed a posteriori error bound of the returned triple
        (:func:`fastmem.estimate`; ``result.eta``), for every method by
        default.  ``estimate=False`` skips the flux reconstruction for
        ``"exact"`` and ``"exact-amg"`` (``result.eta`` is then None);
        ``"inexact"`` computes the bound anyway (its stopping test needs it)
        and always attaches it.
    gamma_alg, gamma_lin : float
        Stopping parameters of ``"inexact"`` (default 0.1 each).
    max_inner : int
        Maximum CG iterations per Newton step (``"inexact"``; ``"exact-amg"``
        allows ten times as many).
    check_every : int
        Evaluate the cheap estimators every ``check_every`` CG iterations.
    amg_options : dict, optional
        Options of :func:`pyamg.smoothed_aggregation_solver` (plus ``cycle``);
        default :data:`fastmem.linalg.amg.AMG_DEFAULTS` (pyamg's defaults, V-cycles).
    amg_reuse : float
        Decoupled path: keep the gap system's AMG setup (its prolongators)
        while the active set differs from the one it was built for in at most
        this fraction of the interior vertices; its coarse operators are
        updated to every new active set (Galerkin products,
        :meth:`fastmem.linalg.amg.AMGPreconditioner.update`).  0: a new setup whenever
        the active set changed.
    multigrid : {"auto", "geometric", "algebraic"}
        Preconditioner of the CGs on the levels of nested iteration (``"inexact"``
        and ``"exact-amg"``).  ``"auto"`` (default): ``"geometric"`` on the
        levels with at least 32,768 interior vertices, ``"algebraic"`` below
        (there both are as fast, and a small solve compiles no multigrid
        kernel).  ``"geometric"``: V(1,1) cycles over the chain of nested
        meshes, whose interpolations are known, with Galerkin coarse operators
        formed in the kernel threads and hybrid Gauss-Seidel sweeps
        (:class:`fastmem.linalg.gmg.NestedMG`; the gap system's coarse spaces
        truncated to the inactive vertices, the general path's built on the
        chain's block interpolations); a mesh without a chain keeps pyamg.
        ``"algebraic"``: pyamg's smoothed aggregation (``amg_options``) on every
        level, as before issue 33.
    nested : bool or "auto"
        Without ``initial`` (every method): solve on the chain of coarser meshes
        (:meth:`Mesh.coarser`, down to about 1000 vertices) and prolong each
        solution as the initial iterate of the next level.  A mesh without a
        coarser version (read from a file, built from arrays) gets auxiliary
        coarse meshes from subsets of its vertices (:mod:`fastmem.mesh.coarsen`).
        "auto": when a coarser mesh exists or can be built and the data can
        move to it; otherwise the iteration starts from the unconstrained
        problem.  ``False``: always the unconstrained start.
    full_history : bool
        Reconstruct the flux at every history row, so that every row carries
        the guaranteed bound ``eta`` (costly; for studies and tests).
    keep_iterates : bool
        Keep the triple of every history row in ``result.iterates``.
    safeguard : bool
        When Newton-min cycles (an active set comes back) or stalls (no new
        smallest ``||min(gap, lam)||`` in
        :data:`fastmem.solver.safeguard.STALL_STEPS` steps), switch
        to the monotone feasible active-set iteration of
        :mod:`fastmem.solver.safeguard` (exact face solves, energy decreasing at
        every step) until it reaches the KKT point or its working set
        settles, then resume Newton-min.  Uses are booked in
        ``result.parameters["solver"]["safeguard"]`` and in the history
        column ``safeguard``.  ``False``: cycling raises
        :class:`~fastmem.errors.CyclingError`.
    tol, rtol : float, optional
        Solve to a guaranteed tolerance by adaptive mesh refinement
        (:mod:`fastmem.adapt.loop`): refine the scene's mesh until the guaranteed
        bound of the returned triple satisfies ``eta <= tol`` or ``eta <= rtol
        * |||u_h|||`` (either suffices), ``|||u_h|||^2 = sum_i mu_i ||grad
        u_ih||^2`` the energy norm of the discrete solution.  The result is on
        the final mesh, with ``result.adaptivity`` (one row per mesh) and
        ``result.parameters["adaptivity"]`` (settings, ``stop_reason``).
        Without either, the scene's mesh is solved as it is.
    theta : float
        Dörfler marking fraction in (0, 1] (default 0.5): each refinement
        marks the fewest triangles holding ``theta`` of ``sum_K eta_K^2``.
    min_growth : float
        Each refinement makes at least ``min_growth`` times the vertices of the
        mesh it refines (in [1, 4], above 2 with ``bisections`` >= 2; default
        1: Dörfler's mesh as it is, 1.3-1.4 times the vertices at
        ``theta=0.5``): when Dörfler's set falls short,
        the next largest indicators are marked too.  Fewer, larger meshes keep
        the loop's total work a smaller multiple of the last mesh's (about
        ``min_growth / (min_growth - 1)`` times it).  On the L-shape
        (``f=(-1, -1)``, ``tol=9.1e-3``) 1.5 took 17 meshes and 1.05-1.2 s
        against 23 meshes and 1.3-1.45 s (2026-12-01, 2 cores); 1.7 made 57k
        vertices instead of 34k, and 2 refines every triangle (one round of
        bisection at most doubles the vertices).  Not the default: near a
        singularity that no mesh resolves (the Kellogg problem) the extra
        marking spreads over the domain and the loop runs to ``max_vertices``
        instead of stopping at the resolution limit.
    bisections : int
        Rounds of newest-vertex bisection per refinement (1, 2 or 3; default
        2): from the second round on the children of the marked triangles are
        marked again, so every marked triangle is bisected at least this many
        times (each into four or more with 2).  Each step then grows the mesh
        more (``min_growth`` up to ``2**bisections``), so the loop makes fewer
        meshes and solves fewer vertices in all: on the L-shape
        (``f=(-1, -1)``, ``tol=3.44e-3``) 15 meshes and 513k vertices in all
        against 29 meshes and 771k with one round (2026-12-02, 2 cores).
    max_vertices : int
        Stop (``converged=False``) instead of solving a mesh with more
        vertices (default :data:`fastmem.solver.options.MAX_VERTICES`, 5M;
        with ``method="exact"`` at most and by default 1M).
    max_levels : int
        Stop after solving this many meshes (default 100).
    time_budget : float
        Seconds: stop when the next level would end after this time
        (predicted from the last level's time per vertex).
    level_monitor : callable, optional
        Called with each row of ``result.adaptivity`` (a dict) when its mesh is done
        (``cg_stop`` 1: an intermediate mesh whose CG could stop by its own error
        estimate, so that its ``eta_alg`` and ``eta`` can be loose bounds,
        :mod:`fastmem.adapt.loop`).  A loop that stops short of the target solves its
        last mesh on and calls it again with that mesh's new row.
    memory_limit : int, str, False or None
        The memory guard (:func:`fastmem.memory.check_memory`): before any work the
        peak memory of the solve is estimated from the mesh size, the method and
        ``estimate``, and a solve that cannot fit is refused with
        :class:`~fastmem.memory.MemoryLimitError` naming the estimate and the limit.
        None (default): the limit is the environment variable ``FASTMEM_MEMORY_LIMIT``
        if set (bytes, or with a K/M/G/T suffix; 0, off or none disable the check),
        else the machine's physical memory (or its cgroup limit).  A number (bytes)
        or a string like ``"40G"`` sets it; ``False`` or 0 disables the check.  With
        ``tol``/``rtol`` only the initial mesh is checked.  The same limit decides when
        the inexact step frees its matrices during flux reconstructions (spilling,
        :func:`fastmem.solver.inexact.memory_pressure`; results are identical either way).

    Returns
    -------
    Result
        ``result.history`` has the same columns for every method, one row
        per estimator check (:mod:`fastmem.solver.history`);
        ``result.parameters["solver"]["levels"]`` one entry per level.

    Notes
    -----
    The keywords are grouped into the frozen option objects of
    :mod:`fastmem.solver.options` (validated there) and handed down the pipeline:
    :func:`fastmem.solver.levels.solve_levels` (nested iteration) →
    :func:`fastmem.solver.newton.newton_min` (one Newton-min loop for every method)
    → the linear steps of :mod:`fastmem.solver.steps`.

    Raises
    ------
    ParameterError
        An option out of range, or an unknown keyword (the message names the
        closest valid one and lists them all).
    CyclingError
        With ``safeguard=False``: when an active set repeats an earlier one.
    MemoryLimitError
        The estimated peak memory exceeds the limit (see ``memory_limit``).
    """
    if isinstance(scene, Obstacle):
        if path != "auto":
            raise ParameterError(
                f"path={path!r} is an option of the two-membrane Scene only; an Obstacle has "
                "one formulation (leave path out)"
            )
        for name, value, default in (
            ("full_history", full_history, False),
            ("keep_iterates", keep_iterates, False),
            ("safeguard", safeguard, True),
        ):
            if value is not default:
                raise ParameterError(
                    f"{name}={value!r} is an option of the two-membrane Scene only; an "
                    f"Obstacle does not take it (leave {name} out)"
                )
    elif not isinstance(scene, Scene):
        raise InputTypeError(
            f"scene must be a fastmem.Scene or fastmem.Obstacle, got {type(scene).__name__}"
        )
    options = SolveOptions.from_keywords(
        method=method,
        path=path,
        max_newton=max_newton,
        gamma_lin=gamma_lin,
        safeguard=safeguard,
        nested=nested,
        estimate=estimate,
        gamma_alg=gamma_alg,
        max_inner=max_inner,
        check_every=check_every,
        amg_reuse=amg_reuse,
        amg_options=amg_options,
        multigrid=multigrid,
        memory_limit=memory_limit,
        monitor=monitor,
        full_history=full_history,
        keep_iterates=keep_iterates,
        tol=tol,
        rtol=rtol,
        theta=theta,
        min_growth=min_growth,
        bisections=bisections,
        max_vertices=max_vertices,
        max_levels=max_levels,
        time_budget=time_budget,
        level_monitor=level_monitor,
    )
    if isinstance(scene, Obstacle):
        return _solve_obstacle(scene, options, initial, blas_threads, memory_limit)
    if path == "decoupled" and not scene.constant_mu:
        raise ParameterError(
            "path='decoupled' needs constant mu1 and mu2; this scene has per-triangle "
            "values (use path='general' or 'auto')"
        )
    adapt = options.adapt
    if adapt is not None and scene.mesh.n_vertices > adapt.max_vertices:
        raise ParameterError(
            f"max_vertices={adapt.max_vertices} is smaller than the initial mesh "
            f"({scene.mesh.n_vertices} vertices)"
        )
    mesh = scene.mesh
    check_memory(
        mesh.n_vertices,
        mesh.n_triangles,
        options.newton.method,
        options.newton.needs_estimate,
        memory_limit,
    )
    init = None if initial is None else check_triple(scene.mesh, initial, prefix="initial ")
    timings = {}
    t_start = time.perf_counter()
    with blas_limits(blas_threads):
        t0 = time.perf_counter()
        if options.newton.needs_estimate:  # one evaluation of callable loads for all uses
            expect_estimates(scene)
        # assembled (and cached on the scene) here, but not held by this frame: the
        # inexact step may free them during a flux reconstruction (AdaptiveStep.spill)
        _ = scene.loads, scene.weighted_stiffness(1), scene.weighted_stiffness(2)
        del _
        timings["assembly"] = time.perf_counter() - t0
        if adapt is None:
            result = solve_levels(scene, options, init, timings)
        else:
            result = solve_to_tolerance(scene, options, init, timings)
    timings["total"] = time.perf_counter() - t_start
    return result


def _solve_obstacle(problem, options, initial, blas_threads, memory_limit):
    """:func:`solve` for an :class:`~fastmem.fem.obstacle.Obstacle` (validated options)."""
    adapt = options.adapt
    if adapt is not None and problem.mesh.n_vertices > adapt.max_vertices:
        raise ParameterError(
            f"max_vertices={adapt.max_vertices} is smaller than the initial mesh "
            f"({problem.mesh.n_vertices} vertices)"
        )
    mesh = problem.mesh
    check_memory(
        mesh.n_vertices,
        mesh.n_triangles,
        options.newton.method,
        options.newton.needs_estimate,
        memory_limit,
    )
    init = None
    if initial is not None:
        if not isinstance(initial, (tuple, list)) or len(initial) != 2:
            raise InputTypeError("initial must be a pair (u, lam) of nodal arrays for an Obstacle")
        init = [
            check_nodal(mesh, a, "initial " + n) for n, a in zip(("u", "lam"), initial, strict=True)
        ]
    opts = {
        "method": options.newton.method,
        "max_newton": options.newton.max_newton,
        "gamma_lin": options.newton.gamma_lin,
        "nested": options.newton.nested,
        "estimate": options.newton.needs_estimate,
        "gamma_alg": options.inner.gamma_alg,
        "max_inner": options.inner.max_inner * (10 if options.newton.method == "exact-amg" else 1),
        "check_every": options.inner.check_every,
        "amg_reuse": options.inner.amg_reuse,
        "amg_options": dict(options.inner.amg_options),
        "monitor": options.record.monitor,
        "adapt": None,
    }
    if adapt is not None:
        opts["adapt"] = {
            "tol": adapt.tol,
            "rtol": adapt.rtol,
            "theta": adapt.theta,
            "min_growth": adapt.min_growth,
            "bisections": adapt.bisections,
            "max_vertices": adapt.max_vertices,
            "max_levels": adapt.max_levels,
            "time_budget": adapt.time_budget,
            "level_monitor": adapt.level_monitor,
        }
    with blas_limits(blas_threads):
        if opts["estimate"]:
            expect_estimates(problem)
        return solve_obstacle(problem, opts, init)
