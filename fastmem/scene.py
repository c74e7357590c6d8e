"""The problem statement: mesh, tensions mu1, mu2, loads f1, f2, boundary value g.

A :class:`Scene` is validated on construction and knows which work it needs:
constant data are integrated without quadrature, constant tensions select the
decoupled solver path, and matrices and load vectors are assembled once, on
first use, and cached.
"""

from __future__ import annotations

import logging
import numbers

import numpy as np

from .assembly import DEFAULT_LOAD_DEGREE, assemble_load, assemble_stiffness, evaluate_callable
from .errors import DataError, InputTypeError, ParameterError
from .mesh import Mesh

__all__ = ["Scene"]

logger = logging.getLogger(__name__)


def _is_real_scalar(x) -> bool:
    return (
        isinstance(x, numbers.Real)
        and not isinstance(x, bool)
        or (isinstance(x, np.ndarray) and x.ndim == 0 and x.dtype.kind in "iuf")
    )


def _pair(value, name):
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 2:
        raise InputTypeError(
            f"{name} must be a pair ({name}1, {name}2), got {type(value).__name__} {value!r:.80}"
        )
    return value[0], value[1]


def _check_mu(value, name, n_triangles):
    if _is_real_scalar(value):
        v = float(value)
        if not np.isfinite(v) or v <= 0:
            raise ParameterError(f"{name} must be positive and finite, got {v!r}")
        return v
    if isinstance(value, (np.ndarray, list, tuple)):
        arr = np.asarray(value)
        if arr.dtype.kind not in "iuf":
            raise InputTypeError(f"{name} must be real numbers, got dtype {arr.dtype}")
        arr = np.ascontiguousarray(arr, dtype=np.float64)
        if arr.shape != (n_triangles,):
            raise DataError(
                f"{name} as an array must have one value per triangle, shape ({n_triangles},), "
                f"got {arr.shape}"
            )
        bad = ~(np.isfinite(arr) & (arr > 0))
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ParameterError(
                f"{name} must be positive and finite on every triangle; "
                f"{int(bad.sum())} values are not (first: triangle {k}, value {arr[k]!r})"
            )
        if (arr == arr[0]).all():
            return float(arr[0])
        arr.flags.writeable = False
        return arr
    raise InputTypeError(
        f"{name} must be a positive number or an array of per-triangle values, "
        f"got {type(value).__name__}"
    )


def _check_load(value, name, n_vertices):
    if callable(value):
        return value
    if _is_real_scalar(value):
        v = float(value)
        if not np.isfinite(v):
            raise DataError(f"{name} must be finite, got {v!r}")
        return v
    if isinstance(value, (np.ndarray, list, tuple)):
        arr = np.asarray(value)
        if arr.dtype.kind not in "iuf":
            raise InputTypeError(f"{name} must be real numbers, got dtype {arr.dtype}")
        arr = np.ascontiguousarray(arr, dtype=np.float64)
        if arr.shape != (n_vertices,):
            raise DataError(
                f"{name} as an array must have one value per vertex, shape ({n_vertices},), "
                f"got {arr.shape}"
            )
        if not np.isfinite(arr).all():
            raise DataError(
                f"{name} contains NaN or inf at {int((~np.isfinite(arr)).sum())} vertices"
            )
        arr.flags.writeable = False
        return arr
    raise InputTypeError(
        f"{name} must be a number, an array of per-vertex values or a callable f(x, y), "
        f"got {type(value).__name__}"
    )


def _describe(value):
    if callable(value):
        return {"kind": "callable", "name": getattr(value, "__qualname__", repr(value))}
    if isinstance(value, np.ndarray):
        return {"kind": "array", "size": int(value.size)}
    return {"kind": "constant", "value": value}


class Scene:
    """A two-membrane contact problem on a mesh (MATH.md section 1).

    Parameters
    ----------
    mesh : Mesh
    mu : pair of (float or ndarray of shape (M,))
        Tensions mu1, mu2 > 0: constants, or one value per triangle (then the
        general solver path is used).
    f : pair of (float, ndarray of shape (N,), or callable)
        Loads f1, f2: constants, nodal values of P1 functions, or callables
        ``f(x, y)`` evaluated on arrays.
    g : float, ndarray of shape (N,), or callable
        Boundary value of membrane 1, ``g >= 0``: a constant, nodal values (only
        boundary vertices are read) or a callable evaluated at boundary
        vertices.  The a posteriori bound is exact when g is constant or
        piecewise linear on boundary edges.
    active_c : float
        Constant c > 0 of the active-set rule ``lambda_a > c * gap_a``.
    load_degree : int
        Quadrature degree for callable loads (default 5).

    Examples
    --------
    >>> import fastmem as fm
    >>> scene = fm.Scene(fm.Mesh.square(8), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    >>> scene.constant_mu
    True
    """

    def __init__(
        self,
        mesh: Mesh,
        mu=(1.0, 1.0),
        f=(0.0, 0.0),
        g=0.0,
        *,
        active_c: float = 1.0,
        load_degree: int = DEFAULT_LOAD_DEGREE,
    ):
        if not isinstance(mesh, Mesh):
            raise InputTypeError(f"mesh must be a fastmem.Mesh, got {type(mesh).__name__}")
        self.mesh = mesh
        mu1, mu2 = _pair(mu, "mu")
        self.mu1 = _check_mu(mu1, "mu1", mesh.n_triangles)
        self.mu2 = _check_mu(mu2, "mu2", mesh.n_triangles)
        f1, f2 = _pair(f, "f")
        self.f1 = _check_load(f1, "f1", mesh.n_vertices)
        self.f2 = _check_load(f2, "f2", mesh.n_vertices)
        self.g = self._check_g(g)
        if not _is_real_scalar(active_c) or not (np.isfinite(active_c) and active_c > 0):
            raise ParameterError(f"active_c must be positive and finite, got {active_c!r}")
        self.active_c = float(active_c)
        if isinstance(load_degree, bool) or not isinstance(load_degree, (int, np.integer)):
            raise ParameterError(f"load_degree must be an integer, got {load_degree!r}")
        if not 1 <= load_degree <= 30:
            raise ParameterError(f"load_degree must be in [1, 30], got {load_degree}")
        self.load_degree = int(load_degree)
        self._cache: dict = {}

    def _check_g(self, g):
        mesh = self.mesh
        bnd = mesh.boundary_vertices
        if callable(g):
            vals = evaluate_callable(g, mesh.vertices[bnd, 0], mesh.vertices[bnd, 1], "g")
        elif _is_real_scalar(g):
            vals = np.full(bnd.size, float(g))
            if not np.isfinite(vals[0]):
                raise DataError(f"g must be finite, got {float(g)!r}")
        elif isinstance(g, (np.ndarray, list, tuple)):
            arr = np.asarray(g)
            if arr.dtype.kind not in "iuf":
                raise InputTypeError(f"g must be real numbers, got dtype {arr.dtype}")
            if arr.shape != (mesh.n_vertices,):
                raise DataError(
                    f"g as an array must have one value per vertex, shape ({mesh.n_vertices},), "
                    f"got {arr.shape}"
                )
            vals = arr[bnd].astype(np.float64)
            if not np.isfinite(vals).all():
                raise DataError("g contains NaN or inf at boundary vertices")
        else:
            raise InputTypeError(
                f"g must be a number, an array or a callable g(x, y), got {type(g).__name__}"
            )
        if (vals < 0).any():
            k = int(np.argmin(vals))
            raise ParameterError(
                f"g must be >= 0 on the boundary (membrane 1 above membrane 2 there), "
                f"got {vals[k]!r} at vertex {int(bnd[k])}"
            )
        return g if callable(g) or not _is_real_scalar(g) else float(g)

    # ----------------------------------------------------------------- derived
    @property
    def constant_mu(self) -> bool:
        """True when both tensions are constants (the decoupled path applies)."""
        return isinstance(self.mu1, float) and isinstance(self.mu2, float)

    @property
    def mu_max(self) -> tuple[float, float]:
        """Largest value of mu1 and of mu2 (for scaling)."""
        return float(np.max(self.mu1)), float(np.max(self.mu2))

    @property
    def stiffness(self):
        """Plain P1 stiffness matrix A (coefficient 1), CSR, assembled once."""
        if "A" not in self._cache:
            self._cache["A"] = assemble_stiffness(self.mesh)
        return self._cache["A"]

    def weighted_stiffness(self, i: int):
        """``mu_i A`` for membrane i in {1, 2} (per-triangle mu supported), CSR, cached."""
        key = f"A{i}"
        if key not in self._cache:
            mu = self.mu1 if i == 1 else self.mu2
            if isinstance(mu, float):
                self._cache[key] = self.stiffness * mu
            else:
                self._cache[key] = assemble_stiffness(self.mesh, mu)
        return self._cache[key]

    @property
    def loads(self) -> tuple[np.ndarray, np.ndarray]:
        """Load vectors ``(F1, F2)`` with ``F_i,a = (f_i, psi_a)``, assembled once."""
        if "F" not in self._cache:
            self._cache["F"] = tuple(
                assemble_load(self.mesh, f, self.load_degree, name)
                for f, name in ((self.f1, "f1"), (self.f2, "f2"))
            )
        return self._cache["F"]

    @property
    def boundary_values(self) -> np.ndarray:
        """Nodal vector of g on boundary vertices (zero elsewhere), shape (N,)."""
        if "gB" not in self._cache:
            mesh = self.mesh
            out = np.zeros(mesh.n_vertices)
            bnd = mesh.boundary_vertices
            if callable(self.g):
                out[bnd] = evaluate_callable(
                    self.g, mesh.vertices[bnd, 0], mesh.vertices[bnd, 1], "g"
                )
            elif isinstance(self.g, float):
                out[bnd] = self.g
            else:
                out[bnd] = np.asarray(self.g, dtype=np.float64)[bnd]
            out.flags.writeable = False
            self._cache["gB"] = out
        return self._cache["gB"]

    def data_kind(self, name: str) -> str:
        """Kind of a datum ``"f1"``, ``"f2"`` or ``"g"``: constant, array or callable."""
        return _describe(getattr(self, name))["kind"]

    def parameters(self) -> dict:
        """JSON-serialisable description of the scene."""

        def mu_desc(mu):
            return (
                mu
                if isinstance(mu, float)
                else {"kind": "per-triangle", "min": float(mu.min()), "max": float(mu.max())}
            )

        return {
            "n_vertices": self.mesh.n_vertices,
            "n_triangles": self.mesh.n_triangles,
            "mu1": mu_desc(self.mu1),
            "mu2": mu_desc(self.mu2),
            "f1": _describe(self.f1),
            "f2": _describe(self.f2),
            "g": _describe(self.g),
            "active_c": self.active_c,
            "load_degree": self.load_degree,
        }

    def __repr__(self) -> str:
        p = self.parameters()
        f1, f2, g = (p[k].get("value", p[k]["kind"]) for k in ("f1", "f2", "g"))
        return f"Scene({self.mesh!r}, mu=({p['mu1']}, {p['mu2']}), f=({f1}, {f2}), g={g})"
