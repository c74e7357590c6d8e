"""The history of a solve: one schema for every method, one row per estimator check.

A row is recorded for every iterate the Newton layer judges: after every
linear step of the methods ``"exact"`` and ``"exact-amg"``, at every
estimator check inside the CG iterations of ``"inexact"``, and after every
face solve of the safeguard.  ``result.history`` holds one 1-D array per
column (archived under ``/history``, shown by ``fastmem info`` and
``fastmem plot``), with the same columns for every method:

==============  =======  ====================================================================
column          dtype    meaning
==============  =======  ====================================================================
level           int      nested-iteration level (0 = coarsest; the last level is the mesh
                         of the scene)
k               int      Newton-min step on that level (1, 2, ...)
inner           int      CG iterations of this step so far (0 for ``"exact"``)
inner_total     int      CG iterations of the whole solve so far, all levels, including the
                         sum ``s`` of the decoupled path and safeguard face solves
n_active        int      size of the active set the step was solved with
n_changed       int      vertices whose membership changes if the next step starts from this
                         iterate (0: the active set has settled)
comp_norm       float    ``||min(u1 - u2, lam)||`` over interior vertices
res_norm        float    ``||(R1, R2)||``, the algebraic residual (docs/method.md §2)
eta_disc        float    eta_disc used by the stopping test: fresh when ``fresh_disc`` is 1,
                         else the last fresh value of the level or the value predicted from
                         the coarser level; NaN where none exists (``"exact"`` and
                         ``"exact-amg"`` without ``full_history``)
eta_lin         float    linearisation estimator (docs/method.md §6), every row
eta_alg         float    algebraic estimator (docs/method.md §6), every row
eta             float    the guaranteed bound of this row's iterate where a flux was
                         reconstructed (``fresh_disc`` is 1); NaN elsewhere
fresh_disc      int      1 when the flux was reconstructed for this row's iterate
seconds         float    wall time since the start of the level
safeguard       int      1 for rows of the monotone safeguard (:mod:`fastmem.solver.safeguard`)
==============  =======  ====================================================================

Only ``eta_disc`` and ``eta`` may hold NaN, and only where the table says
so; every other column is finite on every row.
"""

from __future__ import annotations

import numpy as np

__all__ = ["ADAPTIVE_HISTORY_COLUMNS", "HISTORY_COLUMNS", "history_arrays"]

#: Columns of ``result.history`` for every method (see the module docstring).
HISTORY_COLUMNS = (
    "level",
    "k",
    "inner",
    "inner_total",
    "n_active",
    "n_changed",
    "comp_norm",
    "res_norm",
    "eta_disc",
    "eta_lin",
    "eta_alg",
    "eta",
    "fresh_disc",
    "seconds",
    "safeguard",
)

#: Former name of the columns of the AMG methods: now the one schema of every method.
ADAPTIVE_HISTORY_COLUMNS = HISTORY_COLUMNS

_FLOAT_COLUMNS = frozenset(
    {"comp_norm", "res_norm", "eta_disc", "eta_lin", "eta_alg", "eta", "seconds"}
)


def new_history() -> dict:
    """Empty columns, to be filled row by row."""
    return {name: [] for name in HISTORY_COLUMNS}


def history_arrays(rows: dict) -> dict:
    """Row lists to arrays: float64 for norms, estimators and times, int64 otherwise."""
    return {
        name: np.asarray(rows[name], dtype=np.float64 if name in _FLOAT_COLUMNS else np.int64)
        for name in HISTORY_COLUMNS
    }
