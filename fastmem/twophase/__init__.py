"""Liquid–gas flow with gas appearance and disappearance (issue 34; docs/twophase.md).

Hydrogen injected into water-saturated rock dissolves until the water holds
no more; then a gas phase appears.  Which cells hold gas is a complementarity
condition, solved by Newton-min (docs/twophase.md).

* :class:`Physics`, :class:`Grid`, :class:`Problem`: the model on a cell graph
  (the 1D column of the benchmark; 2D vertex-centred meshes);
* :func:`benchmark`: the Couplex-Gas / MoMaS hydrogen column;
* :func:`simulate`: backward Euler with Newton-min and the ``exact``,
  ``inexact`` and ``adaptive`` strategies, GMRES with ILU or CPR-AMG;
* :class:`Estimator`: discretisation, linearisation and algebraic estimators.
"""

from .estimators import Estimate, Estimator
from .model import YEAR, Grid, Physics, Problem, mesh_grid
from .newton import STRATEGIES, newton_min
from .run import VISCOSITIES, Run, benchmark, section, simulate

__all__ = [
    "STRATEGIES",
    "VISCOSITIES",
    "YEAR",
    "Estimate",
    "Estimator",
    "Grid",
    "Physics",
    "Problem",
    "Run",
    "benchmark",
    "mesh_grid",
    "newton_min",
    "section",
    "simulate",
]
