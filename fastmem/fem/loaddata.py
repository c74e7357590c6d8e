r"""Integrals of the loads per triangle, with one evaluation of each callable per mesh.

Three quantities are built from the loads :math:`f_i`:

- the load vector :math:`F_{i,a} = (f_i, \psi_a)` (every solve);
- the moments :math:`\int_K f_i \lambda_j \lambda_k` of the flux reconstruction
  (every flux, :mod:`fastmem.estimators.flux`);
- the data oscillation :math:`\eta_{osc,K,i}` (the final bound,
  :mod:`fastmem.estimators.terms`).

For a callable load all three come from its values at the points of one
quadrature rule (degree ``scene.load_degree``).  A user callable may be
expensive, so :func:`integrals` evaluates it once, block by block, and
computes everything asked for from the same values; the results are cached on
the scene.  The pass itself is :func:`fastmem.fem.callables.callable_integrals`
(re-exported here), which :func:`fastmem.fem.assembly.assemble_load` uses too.
Whether the moments and the oscillation are wanted is known before the first
evaluation: :func:`expect_estimates` (called by the solver when a bound will
be computed) makes the first call build all three; without it
(``estimate=False`` with the exact solver) only the load vector is built and
nothing is stored per triangle.

Per-vertex (P1) loads need no oscillation; their moments have a closed form,
rebuilt for each flux (nothing stored per triangle).  Constant loads have
neither (the flux kernel integrates them exactly).
"""

from __future__ import annotations

import math

import numpy as np

from .assembly import assemble_load
from .callables import callable_integrals

__all__ = ["callable_integrals", "expect_estimates", "forget", "integrals"]

_WANT = "loads_for_estimates"


def expect_estimates(scene) -> None:
    """Declare that fluxes and the bound will be computed on ``scene``.

    The first evaluation of a callable load then also builds its flux
    moments and oscillation (one pass instead of three).  Harmless if the
    loads were already evaluated: the missing parts are built on demand.
    """
    scene._cache[_WANT] = True


def integrals(scene, i: int, *, moments: bool) -> dict:
    """Return the integrals of the load ``f_i`` (``i`` in {1, 2}), cached where worth it.

    Parameters
    ----------
    scene : Scene
    i : int
        Membrane.
    moments : bool
        Also return the flux moments and the oscillation (built now if they
        were not, together with the load vector).

    Returns
    -------
    dict
        ``"F"``: load vector (N,); with ``moments``: ``"moments"`` of shape
        (M, 3, 3) or None (constant load) and ``"osc"`` of shape (M,) (zeros
        for constant and P1 loads).  For a callable everything is cached on
        the scene (the moments take 72 bytes per triangle: 0.6 GB per load at
        8.4 million triangles, against evaluating the callable again); for a
        P1 load the moments have a closed form and are rebuilt per call.
    """
    key = f"load_integrals{i}"
    cache = scene._cache
    have = cache.get(key)
    name = f"f{i}"
    f = scene.f1 if i == 1 else scene.f2
    kind = scene.data_kind(name)
    if kind != "callable":
        if have is None:
            have = cache[key] = {"F": assemble_load(scene.mesh, f, name=name)}
        if not moments:
            return have
        m = scene.mesh.n_triangles
        mom = None if kind == "constant" else _p1_moments(scene.mesh, f)
        return {"F": have["F"], "moments": mom, "osc": np.zeros(m)}
    if have is not None and (not moments or "moments" in have):
        return have
    out = _callable(scene, i, f, name, moments or bool(cache.get(_WANT, False)))
    if have is not None:  # keep the load vector already handed out (same values)
        out["F"] = have["F"]
    cache[key] = out
    return out


def forget(scene) -> None:
    """Drop the cached load integrals of ``scene`` (benchmarks: time a fresh evaluation)."""
    for i in (1, 2):
        scene._cache.pop(f"load_integrals{i}", None)
    scene._cache.pop("F", None)


def _p1_moments(mesh, f) -> np.ndarray:
    """Exact moments of a P1 load ``f = sum_k f_k lambda_k``.

    ``int_K lambda_i lambda_j lambda_k = 2 |K| a! b! c! / (a + b + c + 2)!`` gives
    ``int_K f lambda_i lambda_j = |K| / 60 (1 + [i = j]) (f_1 + f_2 + f_3 + f_i + f_j)``.
    """
    ft = np.asarray(f, dtype=np.float64)[mesh.triangles]  # (M, 3)
    mom = ft.sum(axis=1)[:, None, None] + ft[:, :, None] + ft[:, None, :]
    mom[:, [0, 1, 2], [0, 1, 2]] *= 2.0
    mom *= (mesh.areas / 60.0)[:, None, None]
    return mom


def _callable(scene, i, f, name, want_all) -> dict:
    out = callable_integrals(
        scene.mesh, f, scene.load_degree, name, want_all, parallel=scene.parallel_callables
    )
    if want_all:
        mu = scene.mu1 if i == 1 else scene.mu2
        out["osc"] = (scene.mesh.diameters / math.pi) * out.pop("osc_norm") / np.sqrt(mu)
    return out
