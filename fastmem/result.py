"""The result of a solve: the final triple, its residuals, history and timings."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Estimate", "Result", "check_triple"]

logger = logging.getLogger(__name__)


def check_triple(mesh, triple, prefix=""):
    """Validate a nodal triple ``(u1, u2, lam)``; return three C-contiguous float64 copies.

    Raises InputTypeError for non-real dtypes and DataError for wrong shapes
    or non-finite values, naming the array (``prefix`` + name).
    """
    from .errors import DataError, InputTypeError

    if not isinstance(triple, (tuple, list)) or len(triple) != 3:
        raise InputTypeError(f"{prefix}(u1, u2, lam) must be a triple of nodal arrays")
    n = mesh.n_vertices
    out = []
    for name, a in zip(("u1", "u2", "lam"), triple, strict=True):
        arr = np.asarray(a)
        if arr.dtype.kind not in "iuf":
            raise InputTypeError(f"{prefix}{name} must be real numbers, got dtype {arr.dtype}")
        if arr.shape != (n,):
            raise DataError(
                f"{prefix}{name} must have one value per vertex, shape ({n},), got {arr.shape}"
            )
        arr = np.array(arr, dtype=np.float64, order="C", copy=True)
        if not np.isfinite(arr).all():
            raise DataError(f"{prefix}{name} contains NaN or inf")
        out.append(arr)
    return out


@dataclass
class Estimate:
    """A posteriori error estimate of a triple (filled by the estimator module).

    Attributes
    ----------
    totals : dict of str to float
        Global values, at least ``eta``, ``eta_disc``, ``eta_lin``, ``eta_alg``.
    maps : dict of str to ndarray of shape (M,)
        Per-triangle indicator maps (e.g. ``eta_F1``, ``eta_C``), kept for adaptivity.
    """

    totals: dict = field(default_factory=dict)
    maps: dict = field(default_factory=dict)

    @property
    def eta(self) -> float:
        """The guaranteed upper bound of the energy error."""
        return float(self.totals["eta"])


@dataclass
class Result:
    """Solution of a two-membrane contact problem with its provenance.

    Attributes
    ----------
    mesh : fastmem.Mesh
        The mesh the problem was solved on.
    u1, u2, lam : ndarray of shape (N,)
        Nodal values of the two membranes and of the contact pressure
        (``u1 = g``, ``u2 = 0``, ``lam = 0`` on boundary vertices).
    r1, r2 : ndarray of shape (N,)
        Algebraic residual vectors of the returned triple (MATH.md section 2),
        zero at boundary vertices.
    active : ndarray of bool, shape (N,)
        The contact (active) set of the last Newton-min step.
    history : dict of str to ndarray
        One column per recorded quantity, one row per Newton step (or estimator
        evaluation).
    timings : dict of str to float
        Seconds per phase (``assembly``, ``solve``, ...).
    parameters : dict
        JSON-serialisable description of the scene and solver settings.
    converged : bool
        True when every stopping criterion of the method was met.
    n_newton : int
        Number of Newton-min steps taken.
    method, path : str
        Solver method (``"exact"``, ...) and linear-step path (``"general"`` or
        ``"decoupled"``).
    estimate : Estimate or None
        The a posteriori estimate, when one was asked for (always for
        ``method="inexact"``).
    iterates : list of tuple or None
        With ``solve(..., keep_iterates=True)``: the triple ``(u1, u2, lam)``
        of every history row (not archived).
    """

    mesh: object
    u1: np.ndarray
    u2: np.ndarray
    lam: np.ndarray
    r1: np.ndarray
    r2: np.ndarray
    active: np.ndarray
    history: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    parameters: dict = field(default_factory=dict)
    converged: bool = False
    n_newton: int = 0
    method: str = ""
    path: str = ""
    estimate: Estimate | None = None
    iterates: list | None = None

    @property
    def gap(self) -> np.ndarray:
        """Nodal gap ``u1 - u2``."""
        return self.u1 - self.u2

    @property
    def contact_fraction(self) -> float:
        """Area fraction of the domain in contact: ``sum(B_a, a active) / |Omega|``."""
        b = self.mesh.lumped_mass
        return float(b[self.active].sum() / b.sum())

    @property
    def eta(self) -> float | None:
        """The guaranteed error bound, or None without an estimate."""
        return None if self.estimate is None else self.estimate.eta

    @property
    def eta_components(self) -> dict | None:
        """``{"eta_disc", "eta_lin", "eta_alg"}`` of the estimate, or None."""
        if self.estimate is None:
            return None
        return {k: v for k, v in self.estimate.totals.items() if k != "eta"}

    def save(self, path) -> None:
        """Write the result to an HDF5 archive atomically (see :func:`fastmem.archive.save`)."""
        from .archive import save

        save(self, path)

    def export(self, path) -> None:
        """Write mesh and nodal fields to a VTU/XDMF file through meshio."""
        from .archive import export

        export(self, path)
