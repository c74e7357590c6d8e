r"""Constitutive laws of the liquid–gas model (docs/twophase.md).

van Genuchten–Mualem capillary pressure and relative permeabilities of the
liquid saturation ``S``, with the effective saturation
:math:`S_e = (S - S_{lr}) / (1 - S_{lr} - S_{gr})` clipped to ``[SE_MIN, 1]``
(``m = 1 - 1/n``):

.. math::

    P_c = P_r (S_e^{-1/m} - 1)^{1/n}, \quad
    k_{rl} = \sqrt{S_e}\,(1 - (1 - S_e^{1/m})^m)^2, \quad
    k_{rg} = \sqrt{1 - S_e}\,(1 - S_e^{1/m})^{2m}.

Every function accepts real or complex arrays: the Jacobians of
:mod:`fastmem.twophase.model` are taken by the complex step, exact to
round-off wherever the laws are analytic.  The clip is decided on the real
part (beyond it the derivative is zero).  At ``S_e = 1`` the derivatives of
``P_c`` and ``k_rl`` are infinite; on the last :data:`CHORD` of ``S_e`` both are
replaced by their chords (the model is unchanged for ``S_e <= 1 - CHORD`` and
at ``S_e = 1``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["CHORD", "SE_MIN", "VanGenuchten"]

#: Smallest effective saturation the laws are evaluated at (P_c is infinite at 0).
SE_MIN = 1e-6
#: On ``1 - CHORD < S_e <= 1`` the capillary pressure and the liquid relative
#: permeability are replaced by their chords to the values at ``S_e = 1`` (0 and 1):
#: their derivatives are infinite at ``S_e = 1``, and Newton-min linearised there a
#: cell where gas appears with a zero slope and overshot (docs/twophase.md).
CHORD = 1e-3


def _clip(se):
    """``S_e`` clipped to ``[SE_MIN, 1]`` by its real part (zero derivative outside)."""
    re = np.real(se)
    out = np.where(re > 1.0, 1.0 + 0.0 * se, se)
    return np.where(re <= SE_MIN, SE_MIN + 0.0 * se, out)


class VanGenuchten:
    """The van Genuchten–Mualem laws with parameters ``P_r``, ``n``, ``S_lr``, ``S_gr``."""

    def __init__(self, pr: float, n: float, slr: float, sgr: float = 0.0):
        self.pr = float(pr)
        self.n = float(n)
        self.m = 1.0 - 1.0 / self.n
        self.slr = float(slr)
        self.sgr = float(sgr)

    def effective(self, s):
        """Return the clipped effective saturation of ``s``."""
        return _clip((s - self.slr) / (1.0 - self.slr - self.sgr))

    def _pc(self, se):
        base = se ** (-1.0 / self.m) - 1.0
        return self.pr * base ** (1.0 / self.n)

    def _krl(self, se):
        return np.sqrt(se) * (1.0 - (1.0 - se ** (1.0 / self.m)) ** self.m) ** 2

    def _chorded(self, s, law, at_one):
        """``law(S_e)``, replaced on ``S_e > 1 - CHORD`` by its chord to ``at_one`` at 1."""
        se = self.effective(s)
        top = 1.0 - CHORD
        chord = np.real(se) > top
        inner = np.where(chord, top + 0.0 * se, se)
        value_top = law(top)
        line = at_one + (value_top - at_one) * (1.0 - se) / CHORD  # exact at S_e = 1
        return np.where(chord, line, law(inner))

    def capillary(self, s):
        """Capillary pressure ``P_c(S)``; the chord to ``P_c = 0`` on the last :data:`CHORD`."""
        return self._chorded(s, self._pc, 0.0)

    def k_liquid(self, s):
        """Relative permeability of the liquid; the chord to 1 on the last :data:`CHORD`."""
        return self._chorded(s, self._krl, 1.0)

    def k_gas(self, s):
        """Relative permeability of the gas (0 at ``S_e = 1``)."""
        se = self.effective(s)
        inner = 1.0 - se ** (1.0 / self.m)
        full = np.real(se) >= 1.0
        safe = np.where(full, 1.0 + 0.0 * inner, inner)
        rest = np.where(full, 1.0 + 0.0 * se, 1.0 - se)
        return np.where(full, 0.0 * inner, np.sqrt(rest) * safe ** (2.0 * self.m))
