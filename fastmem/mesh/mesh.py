"""Triangular meshes: validation, derived topology, generators, refinement, file I/O.

A :class:`Mesh` holds vertex coordinates ``vertices`` (N, 2) float64 and
triangles ``triangles`` (M, 3) int64, counter-clockwise.  Derived topology
(edges with a global orientation, triangle-to-edge map, boundary, vertex
patches in CSR form) is computed once, on first use, with vectorised sorts:
no Python loop over entities.

Conventions
-----------
* Local edge ``i`` of a triangle is the edge opposite its local vertex ``i``,
  i.e. between local vertices ``(i+1) % 3`` and ``(i+2) % 3``.
* Global edge ``e`` is oriented from ``edges[e, 0]`` to ``edges[e, 1]`` with
  ``edges[e, 0] < edges[e, 1]`` (lower to higher global vertex index).  Both
  triangles sharing an edge see the same orientation, which is what
  H(div)-conforming (Raviart-Thomas) degrees of freedom need.

Validation policy
-----------------
Refused with :class:`~fastmem.errors.MeshError`: wrong shapes, empty arrays,
non-finite coordinates, coordinates outside the supported length range (see
below), indices out of range, triangles repeating a vertex, zero-area
(degenerate) triangles, duplicate vertices (identical coordinates), unused
vertices, edges shared by more than two triangles (non-manifold edges),
boundary vertices where the boundary touches itself (non-manifold vertices),
and folded/overlapping neighbours (two triangles on the same side of their
shared edge).  Clockwise triangles are **re-oriented** with a
:class:`~fastmem.errors.MeshWarning` (pass ``orientation="raise"`` to refuse
them instead): a consistently clockwise mesh is common in files, and after
re-orientation a genuinely tangled mesh is still caught by the fold check.
Several connected components are allowed (each is a domain of its own).

Supported length range: every coordinate must satisfy ``|x| <= 1e50`` and every
triangle diameter ``h_K >= 1e-50``.  The kernels form areas, their squares and
products of gradients; inside this range (far beyond any physical unit system)
none of them under- or overflows float64.

Dtype policy
------------
``vertices``: any real numeric dtype (float16/32/64, longdouble, signed or
unsigned integers), any memory layout (Fortran order, strided views, read-only
arrays, nested lists); converted **once** to a new C-contiguous float64 array
(exact for float16/float32 and for integers up to 2**53; longdouble is
rounded).  ``triangles``: any signed or unsigned integer dtype, any layout;
converted once to C-contiguous int64.  Refused with
:class:`~fastmem.errors.InputTypeError` naming the field: bool, complex,
object, string, datetime and (for triangles) floating-point arrays, even with
integral values (no silent truncation), and anything that is not an array
(None, dicts, ragged lists); masked arrays with masked entries raise
:class:`~fastmem.errors.DataError`.  The mesh never aliases the caller's
arrays, and its own arrays are read-only.

Derived index arrays use the 32-bit index path (at most :data:`INDEX_LIMIT` =
2**31 - 1 vertices and 715,827,882 triangles, refused with
:class:`~fastmem.errors.MeshError` above; the n = 4096 square has 33.5M
triangles): ``edges``, ``triangle_edges``, ``edge_triangles`` and
``patch_triangles`` are int32, ``patch_local`` (0, 1 or 2) is int8, ``patch_ptr``
int64; about 140 bytes per vertex less than int64 throughout.
"""

from __future__ import annotations

import contextlib
import io
import logging
import warnings
from pathlib import Path

import numpy as np

from ..errors import (
    DataError,
    InputTypeError,
    MeshError,
    MeshFileError,
    MeshWarning,
    ParameterError,
    ReadOnlyError,
    checked_keywords,
)
from ..kernels import pool as _par
from ..kernels import topology as _kt
from ..memory import check_memory

__all__ = ["Mesh"]

logger = logging.getLogger(__name__)

# Relative area below which a triangle counts as degenerate: |K| <= tol * h_K^2.
_DEGENERATE_TOL = 1e-13

# Supported length range: |coordinate| <= _MAX_COORD and h_K >= _MIN_DIAMETER.
_MAX_COORD = 1e50
_MIN_DIAMETER = 1e-50

#: Largest vertex count and half-edge count (3 M) of the 32-bit index path: the mesh
#: topology (:mod:`fastmem.kernels.topology`: ``edges`` and the half-edge pass) and the
#: CSR pattern index with int32.  Up to 2**31 - 1 vertices and 715,827,882 triangles;
#: larger meshes are refused with MeshError (the n = 4096 square has 33.5M triangles).
INDEX_LIMIT = 2**31 - 1

# Local edge i joins local vertices _EDGE_VERTS[i] (edge opposite local vertex i).
_EDGE_VERTS = np.array([[1, 2], [2, 0], [0, 1]])


def _refuse_masked(value, name) -> None:
    """Masked entries would be read as whatever lies under the mask: refuse them."""
    if isinstance(value, np.ma.MaskedArray) and np.ma.is_masked(value):
        raise DataError(
            f"{name} has {int(np.ma.count_masked(value))} masked entries; fill or remove them"
        )


def _as_vertices(vertices) -> np.ndarray:
    _refuse_masked(vertices, "vertices")
    try:
        arr = np.asarray(vertices)
    except Exception as exc:  # ragged lists and the like
        raise InputTypeError(f"vertices cannot be converted to an array: {exc}") from exc
    if arr.dtype.kind not in "iuf":
        raise InputTypeError(
            f"vertices must be a real numeric array, got dtype {arr.dtype} "
            f"(kind {arr.dtype.kind!r})"
        )
    if arr.ndim != 2 or arr.shape[1] not in (2, 3):
        raise MeshError(f"vertices must have shape (N, 2) (or (N, 3) with z = 0), got {arr.shape}")
    if arr.shape[0] == 0:
        raise MeshError("vertices is empty: a mesh needs at least three vertices")
    with np.errstate(over="ignore"):  # longdouble beyond float64 becomes inf: reported below
        arr = np.array(arr, dtype=np.float64, order="C", copy=True)  # never alias the caller's
    _check_coordinates(arr)
    if arr.shape[1] == 3:
        scale = max(float(np.abs(arr[:, :2]).max(initial=0.0)), 1.0)
        zmax = float(np.abs(arr[:, 2]).max(initial=0.0))
        if zmax > 1e-12 * scale:
            raise MeshError(f"vertices are not planar: max |z| = {zmax:g} (2D meshes only)")
        arr = np.ascontiguousarray(arr[:, :2])
    return arr


def _check_flags(orientation, validate) -> None:
    if not isinstance(orientation, str) or orientation not in ("fix", "raise"):
        raise ParameterError(f"orientation must be 'fix' or 'raise', got {orientation!r}")
    if not isinstance(validate, (bool, np.bool_)):
        raise InputTypeError(f"validate must be True or False, got {validate!r}")


def _check_coordinates(arr: np.ndarray) -> None:
    """Refuse NaN/inf and coordinates beyond ``_MAX_COORD`` (no (N, 2) temporaries)."""
    lo, hi = arr.min(), arr.max()  # NaN propagates; max |x| = max(hi, -lo)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
        raise MeshError(
            f"vertices contain NaN or inf at {bad.size} vertices (first: vertex {bad[0]})"
        )
    big = float(max(hi, -lo))
    if big > _MAX_COORD:
        k = int(np.argmax(np.abs(arr).max(axis=1)))
        raise MeshError(
            f"vertices: coordinate {big:.3g} (vertex {k}) is outside the supported range "
            f"|x| <= {_MAX_COORD:.0e}; rescale the mesh (and the data) to other units"
        )


def _as_triangles(triangles, n_vertices: int) -> np.ndarray:
    _refuse_masked(triangles, "triangles")
    try:
        arr = np.asarray(triangles)
    except Exception as exc:
        raise InputTypeError(f"triangles cannot be converted to an array: {exc}") from exc
    if arr.size == 0 and arr.dtype.kind in "iuf" and arr.ndim <= 2:  # [] is a float array
        raise MeshError("triangles is empty: a mesh needs at least one triangle")
    if arr.dtype.kind not in "iu":
        raise InputTypeError(f"triangles must have an integer dtype, got {arr.dtype}")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise MeshError(f"triangles must have shape (M, 3), got {arr.shape}")
    lo, hi = arr.min(), arr.max()
    if lo < 0 or hi >= n_vertices:
        bad = int(lo) if lo < 0 else int(hi)
        raise MeshError(
            f"triangles reference vertex index {bad}, outside [0, {n_vertices - 1}] "
            f"({n_vertices} vertices)"
        )
    return np.array(arr, dtype=np.int64, order="C", copy=True)  # never alias the caller's


def _readonly(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


class Mesh:
    """A conforming triangular mesh of a polygon.

    Parameters
    ----------
    vertices : array_like of shape (N, 2)
        Vertex coordinates (converted once to C-contiguous float64).  Shape
        (N, 3) is accepted when every z coordinate is zero.
    triangles : array_like of int, shape (M, 3)
        Vertex indices of each triangle (any integer dtype, converted to int64).
    orientation : {"fix", "raise"}
        What to do with clockwise triangles: re-orient them with a
        :class:`~fastmem.errors.MeshWarning` (default) or raise MeshError.
    validate : bool
        Run the full validation (duplicate vertices, non-manifold and folded
        edges) immediately.  Built-in generators pass False: their output is
        valid by construction.  The cheap checks (shapes, ranges, areas,
        orientation, unused vertices) always run.

    Raises
    ------
    InputTypeError
        Arrays of a refused dtype (bool, complex, object, strings; floats for
        ``triangles``) or objects that are not arrays.
    MeshError
        Invalid geometry or topology (see the module docstring).

    Notes
    -----
    Dtype policy: ``vertices`` of any real numeric dtype and ``triangles`` of
    any integer dtype (int8 ... uint64), in any memory layout (Fortran order,
    non-contiguous views, read-only), are converted once to new C-contiguous
    float64 / int64 arrays; the mesh gives the same result as for the
    canonical float64 / int64 input of the same values.  Bool, complex,
    object and string arrays are refused with InputTypeError naming the
    field.  Coordinates must lie in ``|x| <= 1e50`` and triangle diameters
    be at least ``1e-50`` (module docstring).

    A Mesh is immutable: its arrays are read-only and assigning a public
    attribute raises :class:`~fastmem.errors.ReadOnlyError`.

    Examples
    --------
    >>> import fastmem as fm
    >>> mesh = fm.Mesh.square(4)
    >>> mesh.n_vertices, mesh.n_triangles, mesh.n_edges
    (25, 32, 56)
    """

    @checked_keywords("fastmem.Mesh")
    def __init__(self, vertices, triangles, *, orientation: str = "fix", validate: bool = True):
        _check_flags(orientation, validate)
        v = _as_vertices(vertices)
        t = _as_triangles(triangles, v.shape[0])
        self._init(v, t, orientation, validate)

    @classmethod
    def _from_owned(cls, vertices, triangles, *, orientation: str = "fix", validate: bool = True):
        """Return a Mesh that owns new arrays: float64 (N, 2) and int64 (M, 3), C order.

        For the generators and :meth:`_compact`, whose arrays are fresh, of the right
        dtypes and in range by construction: no conversion copy (at n = 4096 the copies
        were 1.07 GB of new memory to first-touch, 1.6 s of the 7.5 s ``square``).  The
        coordinates are still checked (finite, in the supported range); every other
        check runs as in :class:`Mesh`.
        """
        if vertices.dtype != np.float64 or triangles.dtype != np.int64:
            raise TypeError("_from_owned needs float64 vertices and int64 triangles")
        v = np.ascontiguousarray(vertices)
        t = np.ascontiguousarray(triangles)
        if v.ndim != 2 or v.shape[1] != 2 or t.ndim != 2 or t.shape[1] != 3:
            raise ValueError("_from_owned needs (N, 2) vertices and (M, 3) triangles")
        _check_flags(orientation, validate)
        _check_coordinates(v)
        mesh = cls.__new__(cls)
        mesh._init(v, t, orientation, validate)
        return mesh

    def _init(self, v, t, orientation, validate):
        self._cache: dict = {}
        self._parent: Mesh | None = None
        self._coarse_recipe = None  # (generator name, args) of a coarser version, if any
        self._grid = None  # (nx, ny, x0, x1, y0, y1): vertices on this grid (generators)

        # the cheap checks in one pass (kernel): counts only, masks formed to report
        used = np.zeros(v.shape[0], dtype=np.uint8)
        area2, h2, bad = _kt.triangle_checks(v, t, _MIN_DIAMETER**2, 2.0 * _DEGENERATE_TOL, used)
        n_rep, n_small, n_degenerate, n_cw = (int(c) for c in bad)
        # Repeated vertex inside one triangle.
        if n_rep:
            rep = (t[:, 0] == t[:, 1]) | (t[:, 1] == t[:, 2]) | (t[:, 0] == t[:, 2])
            k = int(np.flatnonzero(rep)[0])
            raise MeshError(
                f"degenerate triangles: {int(rep.sum())} triangles repeat a vertex "
                f"(first: triangle {k} = {t[k].tolist()})"
            )
        if n_small:
            small = h2 < _MIN_DIAMETER**2
            k = int(np.flatnonzero(small)[0])
            raise MeshError(
                f"triangles too small: {int(small.sum())} triangles have a diameter below "
                f"{_MIN_DIAMETER:.0e} (first: triangle {k} = {t[k].tolist()}, diameter "
                f"{np.sqrt(h2[k]):.3g}); rescale the mesh (and the data) to other units"
            )
        if n_degenerate:
            degenerate = np.abs(area2) <= 2.0 * _DEGENERATE_TOL * h2
            k = int(np.flatnonzero(degenerate)[0])
            raise MeshError(
                f"degenerate triangles: {int(degenerate.sum())} triangles have zero area "
                f"(first: triangle {k} = {t[k].tolist()}, area {0.5 * area2[k]:g})"
            )
        if n_cw:
            cw = area2 < 0
            k = int(np.flatnonzero(cw)[0])
            msg = (
                f"{int(cw.sum())} of {t.shape[0]} triangles are clockwise "
                f"(first: triangle {k} = {t[k].tolist()})"
            )
            if orientation == "raise":
                raise MeshError(f"inverted triangles: {msg}")
            warnings.warn(f"{msg}; re-oriented to counter-clockwise", MeshWarning, stacklevel=3)
            t = t.copy()
            t[cw, 1], t[cw, 2] = t[cw, 2].copy(), t[cw, 1].copy()
            np.abs(area2, out=area2)
        if not used.all():  # marked by triangle_checks: 1 byte per vertex, no bincount
            unused = np.flatnonzero(used == 0)
            raise MeshError(
                f"unused vertices: {unused.size} vertices belong to no triangle "
                f"(first: vertex {unused[0]}); remove them or use Mesh.read, which compacts"
            )
        self.vertices = _readonly(v)
        self.triangles = _readonly(t)
        # in place: the same values as 0.5 * area2 and np.sqrt(h2), no new (M,) arrays
        self._cache["areas"] = _readonly(np.multiply(area2, 0.5, out=area2))
        self._cache["diameters"] = _readonly(np.sqrt(h2, out=h2))
        if validate:
            self._check_duplicate_vertices()
            self._topology()  # runs the edge checks
        self._frozen = True

    def __setattr__(self, name, value):
        if not name.startswith("_") and getattr(self, "_frozen", False):
            raise ReadOnlyError(
                f"Mesh.{name} cannot be assigned: a Mesh is immutable (its topology and "
                "geometry are cached); build a new Mesh"
            )
        object.__setattr__(self, name, value)

    @property
    def parent(self) -> Mesh | None:
        """The mesh this one was refined from by :meth:`refine`, or None."""
        return self._parent

    # ------------------------------------------------------------------ sizes
    @property
    def n_vertices(self) -> int:
        """Number of vertices N."""
        return self.vertices.shape[0]

    @property
    def n_triangles(self) -> int:
        """Number of triangles M."""
        return self.triangles.shape[0]

    @property
    def n_edges(self) -> int:
        """Number of edges E."""
        return self.edges.shape[0]

    def __repr__(self) -> str:
        return f"Mesh(n_vertices={self.n_vertices}, n_triangles={self.n_triangles})"

    # --------------------------------------------------------------- geometry
    @property
    def areas(self) -> np.ndarray:
        """Triangle areas |K|, shape (M,)."""
        return self._cache["areas"]

    @property
    def diameters(self) -> np.ndarray:
        """Triangle diameters h_K (longest edge), shape (M,)."""
        return self._cache["diameters"]

    @property
    def h(self) -> float:
        """Mesh size max_K h_K."""
        return float(self.diameters.max())

    @property
    def bounding_box(self) -> tuple[float, float, float, float]:
        """``(xmin, xmax, ymin, ymax)`` of the vertices (computed once)."""
        if "bounding_box" not in self._cache:
            # column by column: NumPy reduces an (N, 2) array along axis 0 two entries
            # at a time, 20x slower (0.107 s against 0.0056 s at 4.2M vertices)
            x, y = self.vertices[:, 0], self.vertices[:, 1]
            box = (x.min(), x.max(), y.min(), y.max())
            self._cache["bounding_box"] = tuple(float(c) for c in box)
        return self._cache["bounding_box"]

    @property
    def min_height(self) -> float:
        """Smallest triangle height ``min_K 2|K| / h_K`` (computed once)."""
        if "min_height" not in self._cache:
            # in blocks through one small buffer: the same products and quotients as
            # ``np.min(2.0 * areas / diameters)`` without two temporaries of M doubles
            # (0.05-0.12 s of a default solve at n = 2048, most of it their page faults)
            areas, diameters = self.areas, self.diameters
            block = 1 << 16
            buf = np.empty(min(block, areas.size))
            lows = np.empty(-(-areas.size // block))  # each block's minimum (NaN stays NaN)
            for k, start in enumerate(range(0, areas.size, block)):
                part = buf[: min(block, areas.size - start)]
                np.multiply(areas[start : start + block], 2.0, out=part)
                np.divide(part, diameters[start : start + block], out=part)
                lows[k] = part.min()
            self._cache["min_height"] = float(lows.min())
        return self._cache["min_height"]

    @property
    def lumped_mass(self) -> np.ndarray:
        """Lumped P1 mass ``B_a = |omega_a| / 3``, shape (N,)."""
        if "lumped_mass" not in self._cache:
            b = _kt.lumped_mass(self.triangles, self.areas, self.n_vertices)
            self._cache["lumped_mass"] = _readonly(b)
        return self._cache["lumped_mass"]

    @property
    def gradients(self) -> np.ndarray:
        """Gradients of the three P1 hat functions on each triangle, shape (M, 3, 2)."""
        if "gradients" not in self._cache:
            self._cache["gradients"] = _readonly(_p1_gradients(self.vertices, self.triangles))
        return self._cache["gradients"]

    # --------------------------------------------------------------- topology
    def _topology(self) -> dict:
        if "edges" in self._cache:
            return self._cache
        check_index_limit(self.n_vertices, self.n_triangles)
        # the edges are read from the vertex patches (computed once, kept: assembly uses them)
        patches = (self.patch_ptr, self.patch_triangles, self.patch_local)
        self._set_topology(*_kt.edge_topology(self.triangles, self.n_vertices, patches))
        return self._cache

    def _set_topology(self, edges, tri_edges, et, counts, fwd_count) -> None:
        """Check and cache the arrays of :func:`fastmem.kernels.topology.edge_topology`.

        Also the entry point of a topology derived otherwise (a refined mesh's, from its
        parent's: :func:`fastmem.mesh.refine.refine_marked`); the edge checks run the same.
        """
        n = self.n_vertices
        if (counts > 2).any():
            e = int(np.flatnonzero(counts > 2)[0])
            # counts may be saturated (int8 of edge_topology): recount this edge exactly
            lo, hi = self.triangles[:, [1, 2, 0]], self.triangles[:, [2, 0, 1]]
            on_e = (np.minimum(lo, hi) == edges[e, 0]) & (np.maximum(lo, hi) == edges[e, 1])
            raise MeshError(
                f"non-manifold edges: {int((counts > 2).sum())} edges are shared by more than "
                f"two triangles (first: edge ({edges[e, 0]}, {edges[e, 1]}) in "
                f"{int(on_e.sum())} triangles)"
            )
        # the fold check: the two half-edges of an interior edge must run in opposite
        # directions
        two = counts == 2
        folded = two & (fwd_count != 1)
        if folded.any():
            e = int(np.flatnonzero(folded)[0])
            raise MeshError(
                f"folded or overlapping triangles: {int(folded.sum())} interior edges have both "
                f"neighbours on the same side (first: edge {edges[e].tolist()} between triangles "
                f"{et[e].tolist()}); the mesh is tangled or has duplicate triangles"
            )
        boundary_edges = np.flatnonzero(~two)
        # boundary edges per vertex: np.add.at over the few boundary edges, into memory
        # first touched by two threads (np.bincount's calloc'ed output cost 0.2 s at n = 4096)
        bcount = _par.zeros(n, np.int64)
        np.add.at(bcount, edges[boundary_edges].ravel(), 1)
        if ((bcount != 0) & (bcount != 2)).any():
            vtx = int(np.flatnonzero((bcount != 0) & (bcount != 2))[0])
            raise MeshError(
                f"non-manifold vertex {vtx}: it lies on {bcount[vtx]} boundary edges "
                "(the boundary touches itself there; expected 2)"
            )
        self._cache.update(
            edges=_readonly(edges),
            triangle_edges=_readonly(tri_edges.astype(np.int32, copy=False)),
            edge_triangles=_readonly(et.astype(np.int32, copy=False)),
            boundary_edges=_readonly(boundary_edges),
            boundary_vertex_mask=_readonly(bcount > 0),
        )

    @property
    def edges(self) -> np.ndarray:
        """Edges as int32 vertex pairs (E, 2), ``edges[:, 0] < edges[:, 1]`` (global orientation).

        int32 (the 32-bit index path, :data:`INDEX_LIMIT`): 24 instead of 48 bytes per vertex.
        """
        return self._topology()["edges"]

    @property
    def triangle_edges(self) -> np.ndarray:
        """Global edge (int32) of each local edge (M, 3); local edge i is opposite vertex i."""
        return self._topology()["triangle_edges"]

    @property
    def edge_triangles(self) -> np.ndarray:
        """The one or two triangles (int32) of each edge (E, 2); -1 marks a missing neighbour."""
        return self._topology()["edge_triangles"]

    @property
    def boundary_edges(self) -> np.ndarray:
        """Indices of the boundary edges (edges with one triangle)."""
        return self._topology()["boundary_edges"]

    @property
    def boundary_vertex_mask(self) -> np.ndarray:
        """Boolean mask of boundary vertices, shape (N,)."""
        return self._topology()["boundary_vertex_mask"]

    @property
    def boundary_vertices(self) -> np.ndarray:
        """Indices of the boundary vertices (sorted)."""
        if "boundary_vertices" not in self._cache:
            self._cache["boundary_vertices"] = _readonly(np.flatnonzero(self.boundary_vertex_mask))
        return self._cache["boundary_vertices"]

    @property
    def interior_vertices(self) -> np.ndarray:
        """Indices of the interior vertices (sorted)."""
        if "interior_vertices" not in self._cache:
            self._cache["interior_vertices"] = _readonly(np.flatnonzero(~self.boundary_vertex_mask))
        return self._cache["interior_vertices"]

    def _patches(self) -> dict:
        if "patch_ptr" not in self._cache:
            # vertex degrees: counted here (O(M)) rather than kept from __init__ (8 B/vertex)
            ptr = _kt.vertex_patch_ptr(self.triangles, self.n_vertices)
            tris, local = _kt.vertex_patches(self.triangles, ptr)  # a counting sort, O(N + M)
            self._cache.update(
                patch_ptr=_readonly(ptr),
                patch_triangles=_readonly(tris),
                patch_local=_readonly(local),
            )
        return self._cache

    @property
    def patch_ptr(self) -> np.ndarray:
        """CSR pointer of the vertex patches, shape (N + 1,)."""
        return self._patches()["patch_ptr"]

    @property
    def patch_triangles(self) -> np.ndarray:
        """Triangles (int32) of patch a: ``patch_triangles[patch_ptr[a]:patch_ptr[a+1]]``."""
        return self._patches()["patch_triangles"]

    @property
    def patch_local(self) -> np.ndarray:
        """Local index (0, 1, 2; int8) of the patch vertex in each patch triangle (same layout)."""
        return self._patches()["patch_local"]

    def _check_duplicate_vertices(self) -> None:
        v = self.vertices
        order = np.lexsort((v[:, 1], v[:, 0]))
        sv = v[order]
        same = (sv[1:] == sv[:-1]).all(axis=1)
        if same.any():
            i = int(np.flatnonzero(same)[0])
            a, b = sorted((int(order[i]), int(order[i + 1])))
            raise MeshError(
                f"duplicate vertices: {int(same.sum())} vertices repeat the coordinates of "
                f"another (first: vertices {a} and {b} at {v[a].tolist()})"
            )

    # ------------------------------------------------------------- generators
    @classmethod
    def rectangle(
        cls,
        nx: int,
        ny: int | None = None,
        bounds=(0.0, 1.0, 0.0, 1.0),
        diagonal: str = "right",
    ) -> Mesh:
        """Structured mesh of a rectangle with ``nx`` x ``ny`` cells, two triangles per cell.

        Parameters
        ----------
        nx, ny : int
            Cells in x and y (``ny`` defaults to ``nx``).
        bounds : tuple of float
            ``(xmin, xmax, ymin, ymax)``.
        diagonal : {"right", "left", "symmetric"}
            Cell diagonals: "right" from lower-left to upper-right, "left" from
            lower-right to upper-left, "symmetric" pointing towards the centre
            in every quadrant (the mesh then has the rectangle's symmetries
            when nx and ny are even).

        Raises
        ------
        MeshError
            Beyond the 32-bit index path (:data:`INDEX_LIMIT`).
        MemoryLimitError
            When building the mesh alone would exceed the machine's memory (the guard
            of :func:`fastmem.memory.check_memory`; ``FASTMEM_MEMORY_LIMIT`` overrides
            it), before anything is allocated.
        """
        nx = _check_cells("nx", nx)
        ny = nx if ny is None else _check_cells("ny", ny)
        try:
            x0, x1, y0, y1 = (float(b) for b in bounds)
        except (TypeError, ValueError) as exc:
            raise ParameterError(
                f"bounds must be four numbers (xmin, xmax, ymin, ymax), got {bounds!r}"
            ) from exc
        if not (np.isfinite([x0, x1, y0, y1]).all() and x1 > x0 and y1 > y0):
            raise ParameterError(f"bounds must be finite with xmin < xmax, ymin < ymax: {bounds}")
        if diagonal not in ("right", "left", "symmetric"):
            raise ParameterError(
                f"diagonal must be 'right', 'left' or 'symmetric', got {diagonal!r}"
            )
        n_vertices, n_triangles = (nx + 1) * (ny + 1), 2 * nx * ny
        check_memory(n_vertices, n_triangles, method=None)  # before anything is allocated
        check_index_limit(n_vertices, n_triangles)
        xs = np.linspace(x0, x1, nx + 1)
        ys = np.linspace(y0, y1, ny + 1)
        if diagonal == "symmetric":  # exact symmetry of the coordinates too
            xs = 0.5 * (xs - xs[::-1]) + 0.5 * (x0 + x1)
            ys = 0.5 * (ys - ys[::-1]) + 0.5 * (y0 + y1)
        # written in place: no (N,) temporaries of np.tile / np.repeat, and the triangles
        # by a kernel (no (nx ny,) int64 temporaries); both handed to the Mesh without
        # the conversion copies (Mesh._from_owned)
        vertices = _par.zeros((ny + 1, nx + 1, 2), np.float64)  # first touch: two threads
        vertices[:, :, 0] = xs[None, :]
        vertices[:, :, 1] = ys[:, None]
        vertices = vertices.reshape(-1, 2)
        tris = _kt.rectangle_triangles(nx, ny, diagonal)
        mesh = cls._from_owned(vertices, tris, validate=False)
        mesh._grid = (nx, ny, x0, x1, y0, y1)
        if nx % 2 == 0 and ny % 2 == 0 and min(nx, ny) >= 4:
            mesh._coarse_recipe = ("rectangle", (nx // 2, ny // 2, bounds, diagonal))
        return mesh

    @classmethod
    def square(cls, n: int = 64, diagonal: str = "symmetric") -> Mesh:
        """Structured mesh of the square (-1, 1)^2 with n x n cells (2 n^2 triangles).

        With the default ``diagonal="symmetric"`` and even ``n`` the mesh is
        invariant under the eight symmetries of the square.
        """
        n = _check_cells("n", n)
        return cls.rectangle(n, n, (-1.0, 1.0, -1.0, 1.0), diagonal=diagonal)

    @classmethod
    def lshape(cls, n: int = 64) -> Mesh:
        """L-shaped domain (-1, 1)^2 minus [0, 1) x (-1, 0], from an n x n grid (n even).

        The reentrant corner is at the origin.
        """
        n = _check_cells("n", n)
        if n % 2:
            raise ParameterError(f"n must be even for the L-shaped domain, got {n}")
        sq = cls.square(n)
        cen = sq.vertices[sq.triangles].mean(axis=1)
        keep = ~((cen[:, 0] > 0) & (cen[:, 1] < 0))
        mesh = cls._compact(sq.vertices, sq.triangles[keep], validate=False)
        mesh._grid = sq._grid
        if n % 4 == 0 and n >= 8:
            mesh._coarse_recipe = ("lshape", (n // 2,))
        return mesh

    @classmethod
    def _compact(cls, vertices, triangles, **kwargs) -> Mesh:
        used = np.zeros(len(vertices), dtype=bool)
        used[np.asarray(triangles).ravel()] = True
        new_index = np.cumsum(used) - 1
        # fresh float64 / int64 arrays (triangles in range): owned by the new mesh
        v = np.asarray(vertices, dtype=np.float64)[used]
        t = new_index.astype(np.int64, copy=False)[np.asarray(triangles)]
        return cls._from_owned(v, t, **kwargs)

    def coarser(self) -> Mesh | None:
        """Return a coarser mesh of the same domain, for nested iteration, or None.

        The ``parent`` of a refined mesh; for the structured generators with
        an even number of cells (at least 4 per side), the same generator
        with half as many cells.  Other meshes have none.
        """
        if self.parent is not None:
            return self.parent
        recipe = self._coarse_recipe
        if recipe is None:
            return None
        name, args = recipe
        return getattr(type(self), name)(*args)

    def refine(self) -> Mesh:
        """Uniform (red) refinement: every triangle split into four by its edge midpoints.

        Vertex ``N + e`` of the refined mesh is the midpoint of edge ``e``; the
        returned mesh keeps a reference to this one in ``parent``.
        """
        v, t, te = self.vertices, self.triangles, self.triangle_edges
        n = self.n_vertices
        mid = 0.5 * (v[self.edges[:, 0]] + v[self.edges[:, 1]])
        m0, m1, m2 = (te[:, k].astype(np.int64) + n for k in range(3))  # te is int32
        v0, v1, v2 = t[:, 0], t[:, 1], t[:, 2]
        children = np.stack(
            [
                np.stack([v0, m2, m1], 1),
                np.stack([m2, v1, m0], 1),
                np.stack([m1, m0, v2], 1),
                np.stack([m0, m1, m2], 1),
            ],
            axis=1,
        ).reshape(-1, 3)
        fine = type(self)(np.vstack([v, mid]), children, validate=False)
        fine._parent = self
        return fine

    # -------------------------------------------------------------------- I/O
    @classmethod
    def read(cls, path, **kwargs) -> Mesh:
        """Read a 2D triangle mesh with meshio (gmsh .msh, .vtu, .xdmf, ...).

        All linear triangle blocks are merged; 3D coordinates are accepted when
        z = 0.  Vertices that belong to no triangle (e.g. geometry points of a
        gmsh file) are dropped.  Keyword arguments go to :class:`Mesh`.
        """
        import meshio  # lazy: meshio adds 0.05 s to import fastmem

        path = Path(path)
        if not path.exists():
            raise MeshFileError(f"mesh file not found: {path}")
        if path.is_dir():
            raise MeshFileError(f"mesh file {path} is a directory")
        said = io.StringIO()
        try:
            with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
                m = meshio.read(path)
        except (Exception, SystemExit) as exc:  # meshio raises many types, even SystemExit
            detail = " ".join(said.getvalue().split()) or (
                "" if isinstance(exc, SystemExit) else str(exc)
            )
            raise MeshFileError(
                f"cannot read mesh file {path} with meshio ({type(exc).__name__}"
                f"{': ' + detail if detail else ''}); is it a mesh file in a format meshio "
                "knows, with a matching suffix (.msh, .vtu, .xdmf, ...)?"
            ) from exc
        blocks = [c.data for c in m.cells if c.type == "triangle"]
        if not blocks:
            kinds = sorted({c.type for c in m.cells})
            raise MeshError(
                f"mesh file {path} has no linear triangle cells (cell types: {kinds}); "
                "fastmem needs a 2D P1 triangle mesh"
            )
        points = _as_vertices(m.points)
        tris = _as_triangles(np.concatenate(blocks), points.shape[0])
        return cls._compact(points, tris, **kwargs)

    def write(self, path, file_format: str | None = None) -> None:
        """Write the mesh with meshio (format from the suffix unless ``file_format`` is given)."""
        import meshio  # lazy: meshio adds 0.05 s to import fastmem

        meshio.write_points_cells(
            str(path), self.vertices, [("triangle", self.triangles)], file_format=file_format
        )


def check_index_limit(n_vertices: int, n_triangles: int) -> None:
    """Refuse a mesh beyond the 32-bit index path (:data:`INDEX_LIMIT`) with MeshError."""
    if n_vertices > INDEX_LIMIT or 3 * n_triangles > INDEX_LIMIT:
        raise MeshError(
            f"mesh too large for fastmem's 32-bit topology indices: {n_vertices} vertices and "
            f"{n_triangles} triangles ({3 * n_triangles} half-edges); at most {INDEX_LIMIT} "
            f"vertices and {INDEX_LIMIT // 3} triangles are supported"
        )


def _check_cells(name, value) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ParameterError(f"{name} must be a positive integer, got {value!r}")
    if value < 1:
        raise ParameterError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def _p1_gradients(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Gradients of the barycentric coordinates: grad(phi_i) = rot90(edge opposite i) / (2|K|)."""
    p = v[t]
    d = p[:, _EDGE_VERTS[:, 1]] - p[:, _EDGE_VERTS[:, 0]]  # edge i vector, from i+1 to i+2
    area2 = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 2, 0] - p[:, 0, 0]) * (
        p[:, 1, 1] - p[:, 0, 1]
    )
    g = np.empty_like(d)
    g[..., 0] = -d[..., 1]
    g[..., 1] = d[..., 0]
    return g / area2[:, None, None]
