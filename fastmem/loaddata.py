r"""Integrals of the loads per triangle, with one evaluation of each callable per mesh.

Three quantities are built from the loads :math:`f_i`:

- the load vector :math:`F_{i,a} = (f_i, \psi_a)` (every solve);
- the moments :math:`\int_K f_i \lambda_j \lambda_k` of the flux reconstruction
  (every flux, :mod:`fastmem.flux`);
- the data oscillation :math:`\eta_{osc,K,i}` (the final bound,
  :mod:`fastmem.estimators`).

For a callable load all three come from its values at the points of one
quadrature rule (degree ``scene.load_degree``).  A user callable may be
expensive, so :func:`integrals` evaluates it once, block by block, and
computes everything asked for from the same values; the results are cached on
the scene.  Whether the moments and the oscillation are wanted is known before
the first evaluation: :func:`expect_estimates` (called by the solver when a
bound will be computed) makes the first call build all three; without it
(``estimate=False`` with the exact solver) only the load vector is built and
nothing is stored per triangle.

Per-vertex (P1) loads need no oscillation; their moments have a closed form,
rebuilt for each flux (nothing stored per triangle).  Constant loads have
neither (the flux kernel integrates them exactly).
"""

from __future__ import annotations

import math

import numpy as np

from .assembly import assemble_load, evaluate_callable
from .kernels import assembly as _k
from .quadrature import quadrature_points, triangle_rule

__all__ = ["callable_integrals", "expect_estimates", "forget", "integrals"]

#: Triangles per block when a callable is evaluated: bounds the (block, n_points)
#: temporaries (coordinates, values, products) to a few tens of MB.
BLOCK = 1 << 17

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


def _moments_block(fw, bary, areas) -> np.ndarray:
    nq = bary.shape[0]
    outer = (bary[:, :, None] * bary[:, None, :]).reshape(nq, 9)
    mom = (fw @ outer) * areas[:, None]
    return mom.reshape(-1, 3, 3)


def _callable(scene, i, f, name, want_all) -> dict:
    out = callable_integrals(scene.mesh, f, scene.load_degree, name, want_all)
    if want_all:
        mu = scene.mu1 if i == 1 else scene.mu2
        out["osc"] = (scene.mesh.diameters / math.pi) * out.pop("osc_norm") / np.sqrt(mu)
    return out


def callable_integrals(mesh, f, degree, name="f", want_all=False) -> dict:
    """One blocked pass of the callable ``f(x, y)`` over the points of the rule of ``degree``.

    Returns ``{"F": load vector}``, with ``want_all`` also ``"moments"`` (M, 3, 3)
    and ``"osc_norm"`` (M,), the norms ``||f - Pi_K f||_K`` of the oscillation.
    The single implementation behind :func:`fastmem.assembly.assemble_load`
    (callables) and :func:`integrals`.
    """
    m = mesh.n_triangles
    bary, w = triangle_rule(degree)
    local = np.empty((m, 3))
    if want_all:
        mom = np.empty((m, 3, 3))
        norm = np.empty(m)  # ||f - Pi_K f||_K
    for start in range(0, m, BLOCK):
        stop = min(start + BLOCK, m)
        x, y = quadrature_points(mesh.vertices, mesh.triangles[start:stop], bary)
        fv = evaluate_callable(f, x, y, name)  # (m_b, nq)
        fw = fv * w
        avg = fw @ bary  # (m_b, 3): (f, phi_j)_K / |K|
        areas = mesh.areas[start:stop]
        local[start:stop] = avg * areas[:, None]
        if want_all:
            mom[start:stop] = _moments_block(fw, bary, areas)
            # L2(K) projection onto P1: M_K^{-1} = (3/|K|) [[3,-1,-1],[-1,3,-1],[-1,-1,3]]
            # => coefficients c = 12 avg - 3 sum(avg); the oscillation is summed as
            # squares of f - Pi_K f at the points (free of cancellation, never negative)
            # (in units of max |f| per triangle: no overflow for data near the float range)
            scale = np.abs(fv).max(axis=1)
            scale[scale == 0.0] = 1.0
            avg_s = avg / scale[:, None]
            coef = 12.0 * avg_s - 3.0 * avg_s.sum(axis=1, keepdims=True)
            diff = fv / scale[:, None] - coef @ bary.T
            norm[start:stop] = scale * np.sqrt(((diff * diff) @ w) * areas)
    vec = _k.gather_vector(local, mesh.patch_ptr, mesh.patch_triangles, mesh.patch_local)
    out = {"F": vec}
    if want_all:
        out["moments"] = mom
        out["osc_norm"] = norm
    return out
