"""Two-phase scene files: TOML with a unit on every dimensional value.

A scene file describes a column or a section, its rock and fluids, the
injection and the time stepping.  Every dimensional value is a number in SI
units or a string ``"value unit"``; the unit is checked against the
quantity's dimension before anything is computed, so ``permeability = "5e-20
m"`` is refused, naming the field, the unit's dimension and the one expected.
Example (the benchmark)::

    [scene]
    kind = "column"            # or "section"
    length = "200 m"
    cells = 1000

    [physics]
    porosity = 0.15
    permeability = "5e-20 m2"
    mu_l = "1e-3 Pa s"
    mu_g = "9e-6 Pa s"
    henry = "7.65e-6 mol/(Pa m3)"
    diffusion = "3e-9 m2/s"

    [injection]
    rate = "5.57e-6 kg/m2/year"

    [time]
    dt = "5000 year"
    end = "5e5 year"

Units: m, cm, mm, km; s, min, h, day, year (365.25 days); kg, g; mol; K;
Pa, kPa, MPa, GPa, bar; darcy, mD; cP; products with spaces or ``*``,
powers as ``m2``, ``m^2`` or ``s-1``, quotients with ``/`` (every factor
after a ``/`` divides; parentheses group a denominator).
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from ..errors import ParameterError
from .model import YEAR, Physics
from .run import benchmark, section

try:
    import tomllib
except ImportError:  # Python 3.10
    try:
        import tomli as tomllib
    except ImportError:
        tomllib = None

__all__ = ["UNITS", "load_scene", "quantity"]

# dimensions: exponents of (m, kg, s, mol, K)
_M, _KG, _S, _MOL, _K = np.eye(5, dtype=int)
_PA = _KG - _M - 2 * _S

#: The units a scene file may use: name -> (factor to SI, dimension exponents).
UNITS = {
    "m": (1.0, _M),
    "cm": (1e-2, _M),
    "mm": (1e-3, _M),
    "km": (1e3, _M),
    "s": (1.0, _S),
    "min": (60.0, _S),
    "h": (3600.0, _S),
    "day": (86400.0, _S),
    "year": (YEAR, _S),
    "kg": (1.0, _KG),
    "g": (1e-3, _KG),
    "mol": (1.0, _MOL),
    "K": (1.0, _K),
    "Pa": (1.0, _PA),
    "kPa": (1e3, _PA),
    "MPa": (1e6, _PA),
    "GPa": (1e9, _PA),
    "bar": (1e5, _PA),
    "darcy": (9.869233e-13, 2 * _M),
    "mD": (9.869233e-16, 2 * _M),
    "cP": (1e-3, _PA + _S),
}

_NAMES = ("m", "kg", "s", "mol", "K")

#: Expected dimension of every field (fields not listed are dimensionless numbers).
DIMENSIONS = {
    "scene.length": _M,
    "scene.height": _M,
    "scene.stretch": _M,
    "physics.permeability": 2 * _M,
    "physics.mu_l": _PA + _S,
    "physics.mu_g": _PA + _S,
    "physics.rho_w": _KG - 3 * _M,
    "physics.molar_w": _KG - _MOL,
    "physics.molar_h": _KG - _MOL,
    "physics.diffusion": 2 * _M - _S,
    "physics.henry": _MOL - _PA - 3 * _M,
    "physics.temperature": _K,
    "physics.pr": _PA,
    "boundary.pressure": _PA,
    "initial.pressure": _PA,
    "injection.rate": _KG - 2 * _M - _S,
    "injection.stop": _S,
    "time.dt": _S,
    "time.end": _S,
}


def _dimension_text(dims) -> str:
    parts = [f"{n}^{int(e)}" if e != 1 else n for n, e in zip(_NAMES, dims, strict=True) if e]
    return " ".join(parts) or "dimensionless"


def _parse_unit(text: str, field: str):
    """``(factor, dimension)`` of a unit expression."""
    factor, dims = 1.0, np.zeros(5, dtype=int)
    spaced = re.sub(r"\(([^)]*)\)", lambda m: m.group(1).replace(" ", " /"), text)
    tokens = re.findall(r"/|[A-Za-z]+(?:\^?-?\d+)?", spaced.replace("*", " ").replace(".", " "))
    sign = 1
    for tok in tokens:
        if tok == "/":
            sign = -1
            continue
        m = re.fullmatch(r"([A-Za-z]+)\^?(-?\d+)?", tok)
        name, power = m.group(1), int(m.group(2) or 1)
        if name not in UNITS:
            raise ParameterError(
                f"{field}: unknown unit {name!r} in {text!r}; known: {', '.join(UNITS)}"
            )
        f, d = UNITS[name]
        factor *= f ** (sign * power)
        dims = dims + sign * power * d
    return factor, dims


def quantity(value, field: str):
    """Return ``value`` (a number in SI, or ``"value unit"``) in SI, checking its dimension."""
    expected = DIMENSIONS.get(field)
    if isinstance(value, bool):
        raise ParameterError(f"{field} must be a number, got {value!r}")
    if isinstance(value, (int, float)):
        return float(value)
    if isinstance(value, list):
        return [quantity(v, field) for v in value]
    if not isinstance(value, str):
        raise ParameterError(f"{field} must be a number or a 'value unit' string, got {value!r}")
    head, _, unit = value.strip().partition(" ")
    try:
        number = float(head)
    except ValueError:
        raise ParameterError(f"{field}: {value!r} does not start with a number") from None
    factor, dims = _parse_unit(unit.strip(), field) if unit.strip() else (1.0, np.zeros(5, int))
    want = np.zeros(5, dtype=int) if expected is None else expected
    if not np.array_equal(dims, want):
        raise ParameterError(
            f"{field} = {value!r}: the unit has dimension {_dimension_text(dims)}, expected "
            f"{_dimension_text(want)}"
        )
    return number * factor


_ALLOWED = {
    "scene": {"kind", "length", "cells", "nx", "ny", "height", "stretch"},
    "physics": set(Physics.__dataclass_fields__),
    "boundary": {"saturation", "pressure", "chi"},
    "initial": {"saturation", "pressure", "chi"},
    "injection": {"rate", "stop"},
    "time": {"dt", "end"},
    "solver": {"strategy", "linear_solver", "gamma_alg", "gamma_lin", "nu", "complementarity"},
}


def load_scene(path):
    """Read a scene file; return ``(problem, options)`` for :func:`~fastmem.twophase.simulate`.

    ``options`` holds ``dt``, ``t_end`` (s) and the ``[solver]`` table.
    Raises :class:`~fastmem.errors.ParameterError` for an unknown table or
    key, a missing value, a value of the wrong dimension, or data the model
    refuses (all before any computation).
    """
    if tomllib is None:  # pragma: no cover - Python 3.10 without tomli
        raise ParameterError("scene files need Python >= 3.11 (tomllib) or: pip install tomli")
    p = Path(path)
    if not p.is_file():
        raise ParameterError(f"no such scene file: {str(path)!r}")
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ParameterError(f"{p.name} is not valid TOML: {exc}") from exc
    for table, body in data.items():
        if table not in _ALLOWED or not isinstance(body, dict):
            raise ParameterError(f"{p.name}: unknown table [{table}]; known: {', '.join(_ALLOWED)}")
        for key in body:
            if key not in _ALLOWED[table]:
                known = ", ".join(sorted(_ALLOWED[table]))
                raise ParameterError(f"{p.name}: unknown key {table}.{key}; known: {known}")
    scene = data.get("scene", {})

    def get(table, key, default=None):
        value = data.get(table, {}).get(key, default)
        if value is None:
            raise ParameterError(f"{p.name}: {table}.{key} is missing")
        return quantity(value, f"{table}.{key}")

    physics = Physics(
        **{k: quantity(v, f"physics.{k}") for k, v in data.get("physics", {}).items()}
    )
    rate = get("injection", "rate")
    stop = data.get("injection", {}).get("stop")
    stop_years = None if stop is None else quantity(stop, "injection.stop") / YEAR
    state = {
        side: (
            get(side, "saturation", 1.0),
            get(side, "pressure", 1e6),
            get(side, "chi", 0.0),
        )
        for side in ("boundary", "initial")
    }
    kind = scene.get("kind", "column")
    common = {
        "physics": physics,
        "injection": rate * YEAR,
        "stop_injection": stop_years,
        "boundary": state["boundary"],
        "initial": state["initial"],
        "length": get("scene", "length", 200.0),
    }
    complementarity = data.get("solver", {}).get("complementarity", "min")
    if kind == "column":
        problem = benchmark(
            n_cells=int(scene.get("cells", 1000)), complementarity=complementarity, **common
        )
    elif kind == "section":
        problem = section(
            int(scene.get("nx", 500)),
            int(scene.get("ny", 50)),
            height=get("scene", "height", 20.0),
            stretch=tuple(get("scene", "stretch", [9.0, 11.0])),
            complementarity=complementarity,
            **common,
        )
    else:
        raise ParameterError(f"{p.name}: scene.kind must be 'column' or 'section', got {kind!r}")
    problem.scene["name"] = p.stem
    problem.scene["file"] = str(p)
    solver = {k: v for k, v in data.get("solver", {}).items() if k != "complementarity"}
    options = {
        "dt": get("time", "dt", 5000 * YEAR),
        "t_end": get("time", "end", 5e5 * YEAR),
        **solver,
    }
    if not (math.isfinite(options["dt"]) and options["dt"] > 0):
        raise ParameterError(f"{p.name}: time.dt must be positive, got {options['dt']!r} s")
    return problem, options
