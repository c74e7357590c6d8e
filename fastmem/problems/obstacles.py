"""The obstacle family's reference problems as ready-made :class:`~fastmem.Obstacle` scenes.

========== ================================================ ===============================
name       problem                                          exact solution
========== ================================================ ===============================
``ball``   PETSc ex9/ex34 (Bueler): f = 0 on (-2, 2)²,       yes: :mod:`.ball`
           the C¹ spherical cap, g from the solution
``step41`` deal.II step-41: f = -10 on (-1, 1)², stairs      no (a finer reference)
``twosided`` the manufactured two-sided case of              yes: :mod:`.twosided`
           docs/obstacle.md §8.3
========== ================================================ ===============================

:func:`reference_obstacle` builds one by name on the structured ``n x n``
mesh (the ``"symmetric"`` diagonal pattern: it has the domain's symmetries),
:func:`exact_error` measures the energy error of a result against the exact
solution where there is one.
"""

from __future__ import annotations

from ..errors import ParameterError, closest_name
from ..fem.obstacle import Obstacle
from ..mesh.mesh import Mesh
from .ball import DOMAIN as BALL_DOMAIN
from .ball import BallObstacle, ball_energy_error, ball_solution
from .step41 import step41
from .twosided import TwoSided

__all__ = ["REFERENCE_OBSTACLES", "ball", "exact_error", "reference_obstacle", "twosided"]


def ball(n: int = 64, mesh: Mesh | None = None) -> Obstacle:
    """Build the ball problem (docs/obstacle.md §8.1) on ``n x n`` cells of (-2, 2)²."""
    if mesh is None:
        lo, hi = BALL_DOMAIN
        mesh = Mesh.rectangle(n, n, bounds=(lo, hi, lo, hi), diagonal="symmetric")
    return Obstacle(mesh, mu=1.0, f=0.0, g=ball_solution, lower=BallObstacle())


def twosided(n: int = 64, mesh: Mesh | None = None, **parameters) -> Obstacle:
    """Build the manufactured two-sided case (§8.3) on ``n x n`` cells of (-1, 1)² (or ``mesh``).

    ``parameters`` go to :class:`~fastmem.problems.twosided.TwoSided`.
    """
    case = TwoSided(**parameters)
    if mesh is None:
        mesh = Mesh.rectangle(n, n, bounds=(-1.0, 1.0, -1.0, 1.0), diagonal="symmetric")
    # the load is vectorised NumPy without state: it may run in all threads
    return Obstacle(
        mesh,
        mu=case.mu,
        f=case.load,
        g=0.0,
        lower=case.lower,
        upper=case.upper,
        parallel_callables=True,
    )


#: name -> factory(n) of the shipped reference problems
REFERENCE_OBSTACLES = {"ball": ball, "step41": step41, "twosided": twosided}


def reference_obstacle(name: str, n: int = 64) -> Obstacle:
    """Build a reference problem by name (:data:`REFERENCE_OBSTACLES`) on ``n x n`` cells."""
    if name not in REFERENCE_OBSTACLES:
        hint = closest_name(name, REFERENCE_OBSTACLES)
        raise ParameterError(
            f"unknown reference obstacle problem {name!r}"
            + (f"; did you mean {hint!r}?" if hint else "")
            + f" (known: {', '.join(REFERENCE_OBSTACLES)})"
        )
    return REFERENCE_OBSTACLES[name](n)


def exact_error(problem: Obstacle, u_h, mesh: Mesh | None = None) -> float | None:
    """``|||u - u_h|||`` against the exact solution of a reference problem, None without one.

    ``mesh``: the mesh of ``u_h`` when it is not the problem's (a solve to a tolerance).
    """
    mesh = problem.mesh if mesh is None else mesh
    lower = problem.lower
    if isinstance(lower, BallObstacle):
        return ball_energy_error(mesh, u_h)
    case = getattr(lower, "_problem", None)
    if isinstance(case, TwoSided):
        return case.energy_error(mesh, u_h)
    return None
