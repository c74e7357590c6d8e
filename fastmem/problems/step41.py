r"""The stair obstacle of deal.II's step-41 tutorial (docs/obstacle.md §5.5, §8.2).

Ω = (-1, 1)², f = -10, μ = 1, u = 0 on ∂Ω, u ≥ ψ with the stairs

.. math::

    \psi(x) = -0.2 \ (x < -0.5),\quad -0.4 \ (-0.5 \le x < 0),\quad
    -0.6 \ (0 \le x < 0.5),\quad -0.8 \ (x \ge 0.5).

The obstacle is discontinuous, so only case (i) of the bound applies: the
discrete obstacle must be a P1 *majorant* of ψ.  :class:`StairObstacle`
provides it (``nodal_values``: at every vertex the largest value of ψ on
the triangles around it, i.e. the upper step on a jump line) and the values
of ψ on every triangle for the complementarity term (``triangle_values``:
the value almost everywhere on a triangle inside one step, the smallest
value on a triangle that straddles a jump, which bounds the term from
above).  On the structured meshes of (-1, 1)² with a multiple of 4 cells per
side every triangle lies inside one step.

deal.II evaluates ψ pointwise and takes the lower step on the jump lines;
its active set is therefore not the same set of vertices (docs/obstacle.md
§8.2).
"""

from __future__ import annotations

import numpy as np

from ..fem.obstacle import Obstacle
from ..mesh.mesh import Mesh

__all__ = ["JUMPS", "LEVELS", "StairObstacle", "step41"]

#: Jump lines x = -0.5, 0, 0.5 and the four step heights, left to right.
JUMPS = (-0.5, 0.0, 0.5)
LEVELS = (-0.2, -0.4, -0.6, -0.8)


def _stairs(x, right_closed: bool):
    """ψ with the value of the step on the right (True) or left (False) at a jump."""
    x = np.asarray(x, dtype=np.float64)
    idx = np.searchsorted(np.asarray(JUMPS), x, side="right" if right_closed else "left")
    return np.asarray(LEVELS)[idx]


class StairObstacle:
    """The step-41 stairs as an obstacle: ``__call__``, ``nodal_values``, ``triangle_values``."""

    def __call__(self, x, y):
        """ψ(x, y) pointwise (the lower step on a jump line, as deal.II evaluates it)."""
        return _stairs(x, right_closed=True) + 0.0 * np.asarray(y)

    def triangle_values(self, mesh: Mesh) -> np.ndarray:
        """Return the essential infimum of ψ on every triangle (M,)."""
        xs = mesh.vertices[mesh.triangles, 0]
        return _stairs(xs.max(axis=1), right_closed=False)

    def _triangle_sup(self, mesh: Mesh) -> np.ndarray:
        xs = mesh.vertices[mesh.triangles, 0]
        return _stairs(xs.min(axis=1), right_closed=True)

    def nodal_values(self, mesh: Mesh) -> np.ndarray:
        """At every vertex the largest essential supremum of ψ on its triangles (N,)."""
        out = np.full(mesh.n_vertices, -np.inf)
        sup = self._triangle_sup(mesh)
        for k in range(3):  # three corners: a fixed loop, vectorised over triangles
            np.maximum.at(out, mesh.triangles[:, k], sup)
        return out

    def __repr__(self) -> str:
        return "StairObstacle()"


def step41(n: int = 128, mesh: Mesh | None = None) -> Obstacle:
    """Build the step-41 problem on the structured ``n x n`` mesh of (-1, 1)² (or on ``mesh``)."""
    if mesh is None:
        mesh = Mesh.square(n)
    return Obstacle(mesh, mu=1.0, f=-10.0, g=0.0, lower=StairObstacle())
