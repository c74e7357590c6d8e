r"""Adaptive refinement: Dörfler marking and newest-vertex bisection (docs/method.md §9).

:func:`refine_marked` refines a mesh by newest-vertex bisection (NVB) with
conforming closure; :func:`dorfler_mark` selects the triangles to refine.

Refinement edges
----------------
Every triangle has a refinement edge; its opposite vertex is the triangle's
newest vertex.  A mesh returned by :func:`refine_marked` stores them in its
vertex order: each triangle lists its newest vertex first, so the refinement
edge is local edge 0 (between ``triangles[k, 1]`` and ``triangles[k, 2]``;
counter-clockwise order is kept), and refining it again continues NVB.  Any
other mesh (a generator's, one read from a file, or one rebuilt from the
arrays of a refined mesh) gets by default the longest edge of each triangle,
ties going to the edge with the lowest global edge index (so the choice does
not depend on the order of the vertices inside a triangle); pass
``refinement_edge=0`` to keep the NVB labels of a mesh rebuilt from arrays.
Any initial labelling gives a conforming mesh and finitely many similarity
classes (at most four per initial triangle, so the minimum angle stays
bounded below); the closure bound of Binev-Dahmen-DeVore / Stevenson holds
for any initial labelling too (Karkulik, Pavlicek, Praetorius 2013).

Algorithm (three O(M) passes, :mod:`fastmem.kernels.nvb`)
----------------------------------------------------------
1. Closure: the refinement edges of the marked triangles are marked; then
   every triangle with a marked edge gets its refinement edge marked, until
   nothing changes.  A work queue over newly marked edges reaches the fixed
   point in O(M + E), however far the closure propagates.
2. New vertices: the midpoint of each marked edge, numbered after the old
   vertices (old vertices keep their indices) in the order of the edges.
3. Split: each triangle is cut into 1, 2, 3 or 4 children by the standard
   NVB patterns (its refinement edge bisected, plus none, one or both of the
   other edges, which are the refinement edges of the two halves).  Children
   of a triangle are contiguous and in the order of their parents.

The new mesh is built by the :class:`~fastmem.mesh.mesh.Mesh` constructor with
``orientation="raise"`` (a clockwise child would be a bug, never re-oriented)
and the full validation by default.

Transfer
--------
P1 functions are prolonged exactly: :meth:`Refinement.prolong` copies the old
values and averages the two ends of the bisected edge at each new vertex,

.. math:: u_{new}[N_{old} + i] = (u_{old}[a_i] + u_{old}[b_i]) / 2,

which is also what boundary data given per vertex (or constant) need on new
boundary vertices (:attr:`Refinement.new_boundary`).  Per-triangle data are
inherited by the children (:meth:`Refinement.inherit`).

Dörfler marking
---------------
:func:`dorfler_mark` returns a set of minimal cardinality: the largest
indicators, as few as needed.  It finds them by quickselect on sums: split
the candidates at their median with :func:`numpy.argpartition` (O(n)); if
the upper half holds enough, continue in it, else take it whole and continue
in the lower half with the remaining amount.  The candidates halve at each
step, so the cost is O(M) (about two partitions of the whole array) instead
of the O(M log M) of a full sort; the last few hundred candidates are sorted.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import DataError, InputTypeError, ParameterError
from ..kernels import nvb as _kn
from ..kernels import topology as _kt_topology
from .mesh import Mesh, check_index_limit

__all__ = ["Refinement", "RefinementRounds", "dorfler_mark", "refine_marked", "refinement_edges"]

logger = logging.getLogger(__name__)

#: Called, when set, before :func:`refine_marked` first runs its kernels (then
#: cleared): :func:`fastmem.warm_up` sets it to wait for a helper process that
#: compiles them into Numba's cache meanwhile (:func:`precompile`).
compile_gate = None

# Key in Mesh._cache: True when each triangle lists its newest vertex first.
_NVB_KEY = "nvb_ordered"

# Dörfler marking sorts the candidates once fewer than this many are left.
_SORT_BELOW = 256


def _readonly(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class Refinement:
    """How a mesh refined by :func:`refine_marked` relates to the mesh it came from.

    Attributes
    ----------
    n_old_vertices : int
        N_old; old vertices keep their indices, new vertex ``i`` is ``N_old + i``.
    n_old_triangles : int
        M_old.
    parent_edges : int64 (K, 2)
        End points ``(a, b)``, ``a < b``, of the old edge bisected by new vertex ``i``.
    bisected_edges : int64 (K,)
        The index of that edge in the old mesh's ``edges``.
    parent_triangle : int64 (M_new,)
        The old triangle each new triangle lies in.
    new_boundary : bool (K,)
        New vertex ``i`` is the midpoint of a boundary edge.
    """

    n_old_vertices: int
    n_old_triangles: int
    parent_edges: np.ndarray
    bisected_edges: np.ndarray
    parent_triangle: np.ndarray
    new_boundary: np.ndarray

    @property
    def n_new_vertices(self) -> int:
        """K, the number of vertices added (one per bisected edge)."""
        return self.parent_edges.shape[0]

    @property
    def new_boundary_vertices(self) -> np.ndarray:
        """Indices in the new mesh of the new vertices on the boundary (sorted)."""
        return self.n_old_vertices + np.flatnonzero(self.new_boundary)

    @property
    def n_children(self) -> np.ndarray:
        """Number of children (1 to 4) of each old triangle, shape (M_old,)."""
        return np.bincount(self.parent_triangle, minlength=self.n_old_triangles)

    def prolong(self, values) -> np.ndarray:
        """Values at the new vertices of a P1 function given at the old ones (exact).

        Parameters
        ----------
        values : array_like, shape (N_old,) or (N_old, ...)
            Nodal values on the old mesh (any trailing shape).

        Returns
        -------
        ndarray, shape (N_new, ...)
            Old values unchanged, the mean of the two edge ends at new vertices
            (float64 for integer input, else the input's floating dtype).
        """
        u = np.asarray(values)
        if u.ndim == 0 or u.shape[0] != self.n_old_vertices:
            raise DataError(
                f"values must have shape ({self.n_old_vertices}, ...) (one per old vertex), "
                f"got {u.shape}"
            )
        if u.dtype.kind not in "fc":
            u = u.astype(np.float64)
        a, b = self.parent_edges[:, 0], self.parent_edges[:, 1]
        out = np.empty((self.n_old_vertices + a.size,) + u.shape[1:], dtype=u.dtype)
        out[: self.n_old_vertices] = u
        np.add(u[a], u[b], out=out[self.n_old_vertices :])
        out[self.n_old_vertices :] *= 0.5
        return out

    def prolongation_matrix(self):
        """Return the prolongation as a sparse matrix (N_new, N_old): ``P @ u == prolong(u)``."""
        n, k = self.n_old_vertices, self.n_new_vertices
        rows = np.concatenate([np.arange(n), np.repeat(np.arange(n, n + k), 2)])
        cols = np.concatenate([np.arange(n), self.parent_edges.ravel()])
        vals = np.concatenate([np.ones(n), np.full(2 * k, 0.5)])
        return sp.csr_matrix((vals, (rows, cols)), shape=(n + k, n))

    def inherit(self, values) -> np.ndarray:
        """Per-triangle data of the old mesh on the new one: each child takes its parent's value.

        Parameters
        ----------
        values : array_like, shape (M_old, ...)
        """
        w = np.asarray(values)
        if w.ndim == 0 or w.shape[0] != self.n_old_triangles:
            raise DataError(
                f"values must have shape ({self.n_old_triangles}, ...) (one per old "
                f"triangle), got {w.shape}"
            )
        return w[self.parent_triangle]


class RefinementRounds:
    """Rounds of :func:`refine_marked` one after another, seen as one refinement.

    What ``refine_marked(..., bisections=b)`` returns for ``b > 1``: the same
    transfers as :class:`Refinement` (:meth:`prolong`, :meth:`inherit`,
    :meth:`prolongation_matrix`, ``parent_triangle``) from the first mesh to
    the last; ``rounds`` holds the :class:`Refinement` of each round.  A
    vertex of a later round is the midpoint of an edge of the round before,
    so its weights on the first mesh are 3/4, 1/4 or 1/2, 1/4, 1/4.
    """

    def __init__(self, rounds):
        self.rounds = tuple(rounds)
        parent = self.rounds[0].parent_triangle
        for r in self.rounds[1:]:
            parent = parent[r.parent_triangle]
        self.parent_triangle = _readonly(parent)

    @property
    def n_old_vertices(self) -> int:
        """N_old, the vertices of the first mesh (they keep their indices)."""
        return self.rounds[0].n_old_vertices

    @property
    def n_old_triangles(self) -> int:
        """M_old, the triangles of the first mesh."""
        return self.rounds[0].n_old_triangles

    @property
    def n_new_vertices(self) -> int:
        """Vertices added by all rounds together."""
        return sum(r.n_new_vertices for r in self.rounds)

    @property
    def n_children(self) -> np.ndarray:
        """Number of descendants of each old triangle, shape (M_old,)."""
        return np.bincount(self.parent_triangle, minlength=self.n_old_triangles)

    def prolong(self, values) -> np.ndarray:
        """Values on the last mesh of a P1 function given on the first one (exact)."""
        for r in self.rounds:
            values = r.prolong(values)
        return values

    def prolongation_matrix(self):
        """Return the prolongation as a sparse matrix (N_new, N_old): ``P @ u == prolong(u)``."""
        p = self.rounds[0].prolongation_matrix()
        for r in self.rounds[1:]:
            p = (r.prolongation_matrix() @ p).tocsr()
        return p

    def inherit(self, values) -> np.ndarray:
        """Per-triangle data of the first mesh on the last: each descendant takes its value."""
        for r in self.rounds:
            values = r.inherit(values)
        return values


def next_round(marked, fine: Mesh, refinement, min_diameter: float = 0.0) -> np.ndarray:
    """Return the marks of the next round of ``refine_marked(..., bisections=)``.

    The children (on ``fine``, made by ``refinement``) of the triangles ``marked``
    in the round before, except those of diameter at most ``min_diameter``.
    """
    mask = marked[refinement.parent_triangle]
    if min_diameter > 0.0:
        mask &= fine.diameters > min_diameter
    return mask


def _as_marked(marked, m: int) -> np.ndarray:
    """Bool mask (M,) from a mask or an index array; refuses anything else."""
    try:
        arr = np.asarray(marked)
    except Exception as exc:
        raise InputTypeError(f"marked cannot be converted to an array: {exc}") from exc
    if arr.size == 0 and arr.ndim == 1:
        return np.zeros(m, dtype=bool)
    if arr.ndim != 1:
        raise DataError(f"marked must be one-dimensional (mask or indices), got shape {arr.shape}")
    if arr.dtype == bool:
        if arr.size != m:
            raise DataError(f"marked is a mask of {arr.size} entries, the mesh has {m} triangles")
        return np.ascontiguousarray(arr)
    if arr.dtype.kind not in "iu":
        raise InputTypeError(
            f"marked must be a bool mask or an integer index array, got dtype {arr.dtype}"
        )
    lo, hi = int(arr.min()), int(arr.max())
    if lo < 0 or hi >= m:
        bad = lo if lo < 0 else hi
        raise DataError(f"marked contains triangle index {bad}, outside [0, {m - 1}]")
    mask = np.zeros(m, dtype=bool)
    mask[arr] = True
    return mask


def refinement_edges(mesh: Mesh, refinement_edge) -> np.ndarray:
    """Local refinement edge of each triangle, int8 (M,)."""
    m = mesh.n_triangles
    if refinement_edge is None:
        if mesh._cache.get(_NVB_KEY, False):
            return np.zeros(m, dtype=np.int8)
        refinement_edge = "longest"
    if isinstance(refinement_edge, str):
        if refinement_edge != "longest":
            raise ParameterError(
                f"refinement_edge must be None, 'longest' or local edge indices, "
                f"got {refinement_edge!r}"
            )
        return _kn.longest_edge(mesh.vertices, mesh.triangles, mesh.triangle_edges)
    arr = np.asarray(refinement_edge)
    if arr.dtype.kind not in "iu":
        raise InputTypeError(
            f"refinement_edge must be integers (local edge 0, 1 or 2), got dtype {arr.dtype}"
        )
    if arr.ndim == 0:
        arr = np.full(m, arr)
    if arr.shape != (m,):
        raise DataError(f"refinement_edge must have shape ({m},), got {arr.shape}")
    bad = (arr < 0) | (arr > 2)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"refinement_edge must be 0, 1 or 2 (local edges), got {arr[k]} at triangle {k}"
        )
    return arr.astype(np.int8)


def refine_marked(
    mesh: Mesh,
    marked,
    refinement_edge=None,
    *,
    validate: bool = True,
    bisections: int = 1,
    min_diameter: float = 0.0,
):
    """Refine the marked triangles by newest-vertex bisection with conforming closure.

    This is a convenience wrapper around the Numba kernels of
    :mod:`fastmem.kernels.nvb` (closure, then the split); see the module
    docstring for the algorithm and the conventions.

    Parameters
    ----------
    mesh : Mesh
    marked : array_like of bool, shape (M,), or of int
        The triangles to refine, as a mask or as indices.  Each is bisected at
        least once across its refinement edge; others only as the closure needs.
    refinement_edge : None, "longest", int or array_like of int, shape (M,)
        Local index (0, 1, 2; local edge ``i`` is opposite local vertex ``i``)
        of each triangle's refinement edge.  None: local edge 0 for a mesh
        returned by this function (its stored NVB labels), else "longest"
        (longest edge, ties to the lowest global edge index).
    validate : bool
        Run the full :class:`~fastmem.mesh.mesh.Mesh` validation on the new mesh
        (duplicate vertices, edge checks; default).  False skips what is valid
        by construction, as :meth:`Mesh.refine` does; the cheap checks
        (areas, orientation, unused vertices) always run.
    bisections : int
        Rounds of refinement (default 1).  In each round after the first, the
        children of the triangles marked in the round before are marked, so a
        marked triangle is bisected at least ``bisections`` times (2: into four
        or more), as the adaptive loop's ``bisections`` option asks.
    min_diameter : float
        With ``bisections > 1``: children with at most this diameter are not
        marked again (the adaptive loop's resolution limit).

    Returns
    -------
    new_mesh : Mesh
        Old vertices first (same indices), then the new midpoints; every
        triangle lists its newest vertex first (refinement edge = local edge 0).
        Its ``parent`` is None (the parent transfers of :mod:`fastmem.solver.nested`
        assume red refinement): move data with ``transfer``.
    transfer : Refinement or RefinementRounds
        Parent edges of the new vertices, parent triangles of the new
        triangles, new boundary vertices; :meth:`Refinement.prolong`.  With
        ``bisections > 1`` a :class:`RefinementRounds` over the rounds.

    Examples
    --------
    >>> import fastmem as fm
    >>> from fastmem.mesh.refine import refine_marked
    >>> mesh = fm.Mesh.square(2)
    >>> fine, transfer = refine_marked(mesh, [0])
    >>> fine.n_triangles, transfer.n_new_vertices
    (10, 1)
    """
    if not isinstance(mesh, Mesh):
        raise InputTypeError(f"mesh must be a fastmem Mesh, got {type(mesh).__name__}")
    if not isinstance(validate, (bool, np.bool_)):
        raise InputTypeError(f"validate must be True or False, got {validate!r}")
    mask = _as_marked(marked, mesh.n_triangles)
    if isinstance(bisections, (bool, np.bool_)) or not isinstance(bisections, (int, np.integer)):
        raise InputTypeError(f"bisections must be an integer >= 1, got {bisections!r}")
    if bisections < 1:
        raise ParameterError(f"bisections must be >= 1, got {bisections}")
    if bisections > 1:
        rounds = []
        for k in range(int(bisections)):
            mesh, one = refine_marked(
                mesh, mask, refinement_edge if k == 0 else None, validate=validate
            )
            rounds.append(one)
            mask = next_round(mask, mesh, one, min_diameter)
        return mesh, RefinementRounds(rounds)
    global compile_gate
    if compile_gate is not None:
        gate, compile_gate = compile_gate, None
        gate()
    ref = refinement_edges(mesh, refinement_edge)
    edges, tri_edges = mesh.edges, mesh.triangle_edges
    bisected = np.flatnonzero(_kn.closure(tri_edges, mesh.edge_triangles, ref, mask))
    n = mesh.n_vertices
    edge_vertex = np.full(edges.shape[0], -1, dtype=np.int64)
    edge_vertex[bisected] = np.arange(n, n + bisected.size)
    children, parent = _kn.bisect(mesh.triangles, tri_edges, ref, edge_vertex)
    parent_edges = edges[bisected].astype(np.int64)  # mesh.edges is int32
    v = mesh.vertices
    vertices = np.empty((n + bisected.size, 2))
    vertices[:n] = v
    np.add(v[parent_edges[:, 0]], v[parent_edges[:, 1]], out=vertices[n:])
    vertices[n:] *= 0.5
    fine = Mesh(vertices, children, orientation="raise", validate=False)
    if validate:  # from scratch: the duplicate-vertex search and the edge checks
        fine._check_duplicate_vertices()
        fine._topology()
    else:  # derived from the parent's edges (the same arrays); the edge checks still run
        check_index_limit(fine.n_vertices, fine.n_triangles)
        fine._set_topology(
            *_kt_topology.refined_edge_topology(
                children,
                parent,
                mesh.n_triangles,
                edges,
                mesh.edge_triangles,
                edge_vertex,
                n,
                vertices.shape[0],
            )
        )
    fine._cache[_NVB_KEY] = True
    transfer = Refinement(
        n_old_vertices=n,
        n_old_triangles=mesh.n_triangles,
        parent_edges=_readonly(parent_edges),
        bisected_edges=_readonly(bisected),
        parent_triangle=_readonly(parent),
        new_boundary=_readonly(mesh.edge_triangles[bisected, 1] < 0),
    )
    logger.debug(
        "NVB: %d marked -> %d bisected edges, %d -> %d triangles",
        int(mask.sum()),
        bisected.size,
        mesh.n_triangles,
        fine.n_triangles,
    )
    return fine, transfer


def precompile() -> None:
    """Compile (or load) the bisection kernels with the types of an adaptive loop.

    Two rounds of marked refinement of a tiny L-shape (longest-edge labels, then
    the stored ones), without validation as :func:`fastmem.solve` refines.
    """
    mesh = Mesh.lshape(2)
    marked = np.zeros(mesh.n_triangles, dtype=bool)
    marked[0] = True
    refine_marked(mesh, marked, validate=False, bisections=2)


def _check_theta(theta) -> float:
    if isinstance(theta, (bool, np.bool_)) or not isinstance(
        theta, (int, float, np.integer, np.floating)
    ):
        raise ParameterError(f"theta must be a real number in (0, 1], got {theta!r}")
    t = float(theta)
    if not (0.0 < t <= 1.0):  # also refuses NaN
        raise ParameterError(f"theta must be in (0, 1], got {theta!r}")
    return t


def _as_indicators(indicators_squared) -> np.ndarray:
    try:
        eta2 = np.asarray(indicators_squared)
    except Exception as exc:
        raise InputTypeError(f"indicators_squared cannot be converted to an array: {exc}") from exc
    if eta2.dtype.kind not in "iuf":
        raise InputTypeError(f"indicators_squared must be real numbers, got dtype {eta2.dtype}")
    if eta2.ndim != 1:
        raise DataError(f"indicators_squared must have shape (M,), got {eta2.shape}")
    eta2 = np.asarray(eta2, dtype=np.float64)
    bad = ~(eta2 >= 0.0)  # NaN too
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"indicators_squared must be non-negative numbers: {int(bad.sum())} are negative "
            f"or NaN (first: entry {k} = {float(eta2[k])!r})"
        )
    if np.isinf(eta2).any():
        k = int(np.flatnonzero(np.isinf(eta2))[0])
        raise DataError(f"indicators_squared must be finite (entry {k} = {float(eta2[k])!r})")
    return eta2


def _largest_with_sum(values: np.ndarray, need: float) -> np.ndarray:
    """Return the indices of the fewest largest entries of ``values`` summing to ``need``."""
    idx = np.arange(values.size)
    vals = values
    taken = []
    while vals.size > _SORT_BELOW:
        cut = vals.size - vals.size // 2
        part = np.argpartition(vals, cut)  # part[cut:]: the vals.size // 2 largest
        upper = part[cut:]
        s = float(vals[upper].sum())
        if s >= need:  # the answer lies in the upper half
            idx, vals = idx[upper], vals[upper]
        else:  # all of the upper half, and more from the lower one
            taken.append(idx[upper])
            need -= s
            lower = part[:cut]
            idx, vals = idx[lower], vals[lower]
    order = np.argsort(vals, kind="stable")[::-1]
    csum = np.cumsum(vals[order])
    k = min(int(np.searchsorted(csum, need)) + 1, order.size)  # first k with csum >= need
    taken.append(idx[order[:k]])
    return np.concatenate(taken)


def dorfler_mark(indicators_squared, theta: float = 0.5) -> np.ndarray:
    r"""Dörfler (bulk) marking: the fewest triangles holding a fraction theta of the estimate.

    Returns a set :math:`\mathcal M` of minimal cardinality with

    .. math:: \sum_{K \in \mathcal M} \eta_K^2 \ge \theta \sum_K \eta_K^2,

    namely the largest indicators (among equal ones, any).  Selection by
    quickselect on sums with :func:`numpy.argpartition`, O(M) (module
    docstring); no full sort.  Minimal up to rounding: the sums are checked
    once more as written above, and in the rare case that rounding leaves the
    selected set short of the bound the next largest indicators are added
    (at most a few).

    Parameters
    ----------
    indicators_squared : array_like of float, shape (M,)
        :math:`\eta_K^2`, finite and non-negative.
    theta : float
        Bulk parameter in (0, 1].  ``theta = 1`` marks every triangle with a
        positive indicator.  Zero indicators are never marked, for any theta
        (they add nothing to the sum); all zero: nothing is marked.

    Returns
    -------
    bool (M,)
        The marked triangles.

    Raises
    ------
    ParameterError
        theta NaN, not a real number, <= 0 or > 1.
    DataError
        Negative, NaN or infinite indicators, or not of shape (M,).
    InputTypeError
        Indicators that are not real numbers.

    Examples
    --------
    >>> from fastmem.mesh.refine import dorfler_mark
    >>> dorfler_mark([4.0, 1.0, 3.0, 2.0], theta=0.5).tolist()
    [True, False, True, False]
    """
    t = _check_theta(theta)
    eta2 = _as_indicators(indicators_squared)
    mask = eta2 > 0.0
    if t == 1.0 or not mask.any():
        return mask
    with np.errstate(over="ignore"):
        total = float(eta2.sum())
    if not math.isfinite(total):  # overflow of the sum: rescale (the set does not change)
        eta2 = eta2 / eta2.max()
        total = float(eta2.sum())
    target = t * total
    mask = np.zeros(eta2.size, dtype=bool)
    mask[_largest_with_sum(eta2, target)] = True
    while float(eta2[mask].sum()) < target:  # rounding: add the next largest
        rest = np.where(mask, -1.0, eta2)
        k = int(np.argmax(rest))
        if rest[k] <= 0.0:
            break
        mask[k] = True
    return mask
