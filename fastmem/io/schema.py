"""What every group and dataset of a result archive means: one table for the writer and the docs.

:mod:`fastmem.io.writer` stores these texts as the ``description``
attribute of each group and dataset (and ``units`` where one applies), so an
archive explains itself to anyone who opens it with h5py or HDFView;
``docs/archive.md`` is checked against the same table by the tests.  The
problem is stated without physical units: lengths are in the unit of the
mesh coordinates, u1, u2 in the unit of g, and times in seconds.
"""

from __future__ import annotations

__all__ = ["DATASETS", "GROUPS", "describe"]

#: Group path -> description.  ``/estimators`` and ``/timings`` keep their attributes
#: for data (estimator totals, seconds per phase), so they carry no description attribute.
GROUPS = {
    "mesh": "the triangle mesh the result lives on",
    "solution": "the returned discrete triple and its residuals, one value per vertex",
    "estimators": "per-triangle error indicators; attributes: eta, its components, diagnostics",
    "history": "one row per estimator check of the solve (columns in the attribute 'columns')",
    "adaptivity": "solve to a tolerance: one row per mesh of the adaptive loop",
    "timings": "attributes: phase name -> wall seconds",
}

_PER_VERTEX = "per vertex, shape (N,)"
_PER_TRIANGLE = "per triangle, shape (M,)"
_ROW = "one value per row"

#: Dataset path -> (description, units or None).
DATASETS = {
    "mesh/vertices": ("vertex coordinates (x, y), shape (N, 2)", "length"),
    "mesh/triangles": ("vertex indices of each triangle, counter-clockwise, shape (M, 3)", None),
    "solution/u1": (
        f"displacement of membrane 1 at the vertices ({_PER_VERTEX}); = g on the boundary",
        "length",
    ),
    "solution/u2": (f"displacement of membrane 2 ({_PER_VERTEX}); 0 on the boundary", "length"),
    "solution/lambda": (
        f"contact pressure lambda_h ({_PER_VERTEX}); 0 on the boundary",
        "force / area",
    ),
    "solution/r1": (
        f"algebraic residual of membrane 1's equation, R1 = F1 - A1 u1 + B lambda "
        f"({_PER_VERTEX}; 0 at boundary vertices): the linear solve's leftover",
        "force",
    ),
    "solution/r2": (
        f"algebraic residual of membrane 2's equation, R2 = F2 - A2 u2 - B lambda "
        f"({_PER_VERTEX}; 0 at boundary vertices)",
        "force",
    ),
    "solution/active": (
        f"contact set of the last Newton-min step, 1 = in contact ({_PER_VERTEX})",
        None,
    ),
    "estimators/eta_F1": (
        f"flux estimator of membrane 1, ||mu1^(1/2) grad u1h + mu1^(-1/2) "
        f"sigma1h||_K ({_PER_TRIANGLE})",
        None,
    ),
    "estimators/eta_F2": (f"flux estimator of membrane 2 ({_PER_TRIANGLE})", None),
    "estimators/eta_osc1": (
        f"data oscillation of membrane 1, h_K / pi ||f1 - Pi f1||_K mu1^(-1/2) ({_PER_TRIANGLE})",
        None,
    ),
    "estimators/eta_osc2": (f"data oscillation of membrane 2 ({_PER_TRIANGLE})", None),
    "estimators/eta_nc": (
        f"non-conformity: energy norm of (u2h - u1h)^+ on K ({_PER_TRIANGLE})",
        None,
    ),
    "estimators/eta_C": (
        f"complementarity term (lambda_h, (u1h - u2h)^+)_K ({_PER_TRIANGLE}); "
        "its sum enters eta squared",
        None,
    ),
}

_HISTORY = {
    "level": "nested-iteration level (0 = coarsest; the last is the scene's mesh)",
    "k": "Newton-min step on that level (1, 2, ...)",
    "inner": "CG iterations of this step so far (0 for method 'exact')",
    "inner_total": "CG iterations of the whole solve so far, all levels",
    "n_active": "size of the active set the step was solved with",
    "n_changed": "vertices whose contact status changes if the next step starts here",
    "comp_norm": "||min(u1 - u2, lambda)|| over interior vertices",
    "res_norm": "||(R1, R2)||, the algebraic residual",
    "eta_disc": "discretisation estimator used by the stopping test (NaN where none exists)",
    "eta_lin": "linearisation estimator",
    "eta_alg": "algebraic estimator",
    "eta": "guaranteed bound of this row's iterate where its flux was reconstructed, else NaN",
    "fresh_disc": "1 when the flux was reconstructed for this row's iterate",
    "seconds": "wall time since the start of the level",
    "safeguard": "1 for rows of the monotone safeguard iteration",
}

_ADAPTIVITY = {
    "level": "mesh number of the adaptive loop (0 = the scene's mesh)",
    "n_vertices": "vertices of the mesh",
    "n_triangles": "triangles of the mesh",
    "eta": "guaranteed bound of the triple solved on this mesh",
    "eta_disc": "discretisation component of eta",
    "eta_lin": "linearisation component of eta",
    "eta_alg": "algebraic component of eta",
    "energy_norm": "|||u_h||| = (sum_i mu_i ||grad u_ih||^2)^(1/2) of the triple",
    "target": "the tolerance eta had to reach: max(tol, rtol * energy_norm)",
    "marked_fraction": "fraction of the triangles marked for refinement (0 on the last mesh)",
    "newton": "Newton-min steps on this mesh",
    "inner": "CG iterations on this mesh",
    "solve_seconds": "wall time of SOLVE and ESTIMATE on this mesh",
    "refine_seconds": "wall time of MARK and REFINE after this mesh, moving the data included",
    "cg_stop": "1 on an intermediate mesh whose CG could stop by its own error estimate "
    "(its eta_alg, and eta with it, can be loose)",
}

for _name, _text in _HISTORY.items():
    DATASETS[f"history/{_name}"] = (f"{_text} ({_ROW})", "s" if _name == "seconds" else None)
for _name, _text in _ADAPTIVITY.items():
    units = "s" if _name.endswith("seconds") else None
    DATASETS[f"adaptivity/{_name}"] = (f"{_text} (one value per mesh)", units)


def describe(path: str) -> tuple[str, str | None]:
    """Return the description and units of the dataset ``path`` (e.g. ``"solution/u1"``).

    Datasets not in the table (estimator maps or history columns added by a
    caller) get a generic description from their group.
    """
    if path in DATASETS:
        return DATASETS[path]
    group = path.split("/", 1)[0]
    generic = {
        "estimators": f"estimator map ({_PER_TRIANGLE})",
        "history": f"history column ({_ROW})",
        "adaptivity": "adaptivity column (one value per mesh)",
    }
    return generic.get(group, "dataset"), None
