"""Sweep runs: the grid, run names, constants, and the checks made before a sweep starts.

Part of :mod:`fastmem.sweeps.study` (its docstring has the rules, docs/sweeps.md the
reasons): a grid is expanded into validated parameter dicts, each run is named
by the SHA-256 of its canonical JSON, and the factory and solve options are
checked before anything is created or started.  Needs neither dask nor pandas.
"""

from __future__ import annotations

import hashlib
import inspect
import itertools
import json
import keyword
import math
import numbers
import pickle
import re
import types
from collections.abc import Mapping
from dataclasses import fields

import numpy as np

from ..config import check_count
from ..errors import FastmemError, InputTypeError, ParameterError
from ..pipeline import solve
from ..solver.options import (
    AdaptOptions,
    InnerOptions,
    NewtonOptions,
    RecordOptions,
    SolveOptions,
)

MISSING_DASK = 'fastmem sweeps need dask.distributed and pandas: pip install "fastmem[dask]"'
"""Message of the :class:`ImportError` raised when the ``dask`` extra is missing."""

INDEX_NAME = "sweep-index.h5"
RUNS_DIR = "runs"
WRITE_LOG = "archive-writes.log"
LOCK_NAME = ".sweep.lock"
INDEX_FORMAT = "fastmem-sweep-index"
INDEX_VERSION = 1

_FLOATS = ("eta", "eta_disc", "eta_lin", "eta_alg", "contact_fraction", "seconds")
_INTS = ("newton_steps", "cg_iterations", "vertices", "triangles")
TABLE_COLUMNS = (
    "run",
    "status",
    "converged",
    *_FLOATS[:5],
    *_INTS,
    "seconds",
    "archive",
    "error",
)
"""Columns of the table after the parameters (see :func:`load_sweep`)."""

_TEXTS = ("run", "key", "params", "status", "archive", "error", "traceback")
_RESERVED = frozenset(TABLE_COLUMNS) | {"key", "params", "traceback"}
# keywords of fastmem.solve a sweep cannot pass: per-run objects, not options
_PER_RUN = ("monitor", "level_monitor", "initial", "scene")


def _require_dask():
    """Import dask.distributed or raise ImportError with the installation hint."""
    try:
        import distributed
    except ImportError as exc:
        raise ImportError(MISSING_DASK) from exc
    return distributed


def _require_pandas():
    try:
        import pandas
    except ImportError as exc:
        raise ImportError(MISSING_DASK) from exc
    return pandas


# ----------------------------------------------------------------------------- runs


def _canonical_value(value, where: str):
    """Return a JSON scalar for a parameter value, or raise naming ``where``."""
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        value = float(value)
        if not math.isfinite(value):
            raise ParameterError(f"grid entry {where} = {value!r} is not finite")
        return value
    raise InputTypeError(
        f"grid entry {where} = {value!r:.60} ({type(value).__name__}) is not a number, string, "
        "bool or None: sweep parameters are scalars (build arrays inside the scene factory)"
    )


def _check_name(name) -> str:
    if not isinstance(name, str):
        raise InputTypeError(f"grid parameter names must be strings, got {name!r}")
    if not name.isidentifier() or keyword.iskeyword(name):
        raise ParameterError(
            f"grid parameter name {name!r} is not a Python identifier (it is passed to the "
            "scene factory as a keyword)"
        )
    if name in _RESERVED:
        raise ParameterError(
            f"grid parameter name {name!r} is a column of the sweep table; rename it "
            f"(reserved: {', '.join(sorted(_RESERVED))})"
        )
    return name


def _values(name, value) -> list:
    if isinstance(value, (list, tuple, range, np.ndarray)):
        values = list(np.asarray(value).tolist() if isinstance(value, np.ndarray) else value)
        if not values:
            raise ParameterError(f"grid entry {name!r} has no values")
        return [_canonical_value(v, f"{name}[{i}]") for i, v in enumerate(values)]
    return [_canonical_value(value, repr(name))]  # a fixed value


def expand_grid(grid) -> list[dict]:
    """Return the runs of a grid as a list of parameter dicts, validated.

    Parameters
    ----------
    grid : dict or list of dict
        A dict ``{name: list of values}`` (its cartesian product, the first
        name varying slowest; a scalar is a fixed value), or a list of dicts,
        one per run.

    Returns
    -------
    list of dict
        One dict per run, values converted to plain Python scalars.

    Raises
    ------
    InputTypeError
        For a grid that is neither, a non-string name or a value that is not a
        number, string, bool or None.
    ParameterError
        For no runs, an empty value list, NaN or inf, a name that is not an
        identifier or is a column of the table, or the same run twice.
    """
    if isinstance(grid, Mapping):
        names = [_check_name(n) for n in grid]
        lists = [_values(n, grid[n]) for n in names]
        runs = [dict(zip(names, combo, strict=True)) for combo in itertools.product(*lists)]
    elif isinstance(grid, (list, tuple)):
        runs = []
        for i, entry in enumerate(grid):
            if not isinstance(entry, Mapping):
                raise InputTypeError(
                    f"grid[{i}] must be a dict of parameters, got {type(entry).__name__}"
                )
            runs.append(
                {_check_name(n): _canonical_value(v, f"grid[{i}][{n!r}]") for n, v in entry.items()}
            )
    else:
        raise InputTypeError(
            f"grid must be a dict of parameter lists or a list of dicts, got {type(grid).__name__}"
        )
    if not runs:
        raise ParameterError("the grid has no runs")
    seen = {}
    for i, params in enumerate(runs):
        key = _canonical(params)
        if key in seen:
            raise ParameterError(f"runs {seen[key]} and {i} have the same parameters {key}")
        seen[key] = i
    return runs


def _canonical(params: dict) -> str:
    return json.dumps(params, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _key(params: dict) -> str:
    return hashlib.sha256(_canonical(params).encode("utf-8")).hexdigest()


def run_name(params: dict) -> str:
    """File stem of a run: readable ``name=value`` fields and 12 hex digits of its hash.

    Parameters
    ----------
    params : dict
        The run's parameters (plain scalars, as returned by :func:`expand_grid`).

    Returns
    -------
    str
        E.g. ``"g=0.1_mu2=0.5__3f0c5e2b9a41"``: the fields sorted by name,
        characters other than letters, digits and ``._+-=`` replaced by ``-``,
        at most 80 characters of them; the suffix is the start of the SHA-256
        of the canonical JSON of ``params``, which identifies the run.
    """
    fields = "_".join(f"{k}={params[k]}" for k in sorted(params))
    readable = re.sub(r"[^A-Za-z0-9._+=-]", "-", fields)[:80]
    return f"{readable}__{_key(params)[:12]}"


# ----------------------------------------------------------------------------- checks


def _factory_name(make_scene) -> str:
    """Check that the factory is a picklable module-level function; return ``module:name``."""
    if not callable(make_scene):
        raise InputTypeError(f"make_scene must be a function, got {type(make_scene).__name__}")
    desc = getattr(make_scene, "__qualname__", repr(make_scene))
    hint = (
        "workers on other machines import it by name: define it with def at the top level "
        "of a module (or of the script)"
    )
    if not isinstance(make_scene, types.FunctionType):
        raise InputTypeError(
            f"make_scene must be a plain function, got {type(make_scene).__name__} {desc}; {hint}"
        )
    if make_scene.__name__ == "<lambda>":
        raise InputTypeError(f"make_scene {desc} is a lambda; {hint}")
    if "<locals>" in make_scene.__qualname__:
        raise InputTypeError(f"make_scene {desc} is defined inside a function; {hint}")
    try:
        back = pickle.loads(pickle.dumps(make_scene))
    except Exception as exc:
        raise InputTypeError(
            f"make_scene {desc} cannot be pickled by name ({exc}); {hint}"
        ) from exc
    if back is not make_scene:
        raise InputTypeError(
            f"make_scene {desc}: its name {make_scene.__module__}.{make_scene.__qualname__} "
            f"refers to another object; {hint}"
        )
    return f"{make_scene.__module__}:{make_scene.__qualname__}"


def _check_signature(make_scene, runs) -> None:
    try:
        sig = inspect.signature(make_scene)
    except (TypeError, ValueError):  # pragma: no cover - builtins without a signature
        return
    for i, params in enumerate(runs):
        try:
            sig.bind(**params)
        except TypeError as exc:
            raise ParameterError(
                f"run {i} {_canonical(params)}: {make_scene.__qualname__}() cannot take these "
                f"parameters: {exc}"
            ) from None


def _check_runs(make_scene, runs, shown: int = 3) -> None:
    """Check every run with the factory's own checks, ``make_scene.validate``, if it has them.

    A factory may carry a ``validate`` attribute: a function taking the same
    keywords that raises for values the factory would refuse, without building
    anything large (:func:`fastmem.sweeps.standard_scene` has one).  All runs
    are checked; the error names the factory, how many runs it refuses and the
    first ``shown`` of them with their reasons.  Its type is that of the first
    refusal (:class:`ParameterError` or :class:`InputTypeError` for a plain
    ``ValueError`` or ``TypeError``).
    """
    validate = getattr(make_scene, "validate", None)
    if validate is None:
        return
    name = f"{make_scene.__qualname__}()"
    if not callable(validate):
        raise InputTypeError(
            f"make_scene {make_scene.__qualname__}: its validate attribute must be a function "
            f"taking the run's parameters, got {type(validate).__name__}"
        )
    refused = []
    for i, params in enumerate(runs):
        try:
            validate(**params)
        except (ValueError, TypeError) as exc:
            refused.append((i, params, exc))
    if not refused:
        return
    first = refused[0][2]
    if isinstance(first, FastmemError):
        error = type(first)
    else:
        error = InputTypeError if isinstance(first, TypeError) else ParameterError
    lines = "; ".join(f"run {i} {_canonical(p)}: {exc}" for i, p, exc in refused[:shown])
    more = f"; and {len(refused) - shown} more" if len(refused) > shown else ""
    count = "the run" if len(runs) == 1 else f"{len(refused)} of the {len(runs)} runs"
    raise error(
        f"{name} refuses {count} of this grid (nothing has been started or written; fix "
        f"the grid): {lines}{more}"
    )


def _check_solve_options(solve_options) -> dict:
    """Validate the keywords of :func:`fastmem.solve` once, before anything starts."""
    if solve_options is None:
        return {}
    if not isinstance(solve_options, Mapping):
        raise InputTypeError(
            f"solve_options must be a dict of fastmem.solve keywords, "
            f"got {type(solve_options).__name__}"
        )
    options = dict(solve_options)
    sig = inspect.signature(solve).parameters
    for name in options:
        if name in _PER_RUN:
            raise ParameterError(
                f"solve_options[{name!r}] cannot be used in a sweep (a per-run object, "
                "not an option)"
            )
        if name not in sig:
            raise ParameterError(
                f"solve_options[{name!r}] is not a keyword of fastmem.solve "
                f"(known: {', '.join(n for n in sig if n not in _PER_RUN)})"
            )
    try:
        json.dumps(options, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"solve_options must be JSON values ({exc})") from exc
    # the keywords fm.solve groups into option objects are checked by those objects;
    # the others (blas_threads, ...) are handled by fm.solve itself
    grouped = {
        f.name
        for cls in (NewtonOptions, InnerOptions, RecordOptions, AdaptOptions)
        for f in fields(cls)
    }
    keywords = {n: v for n, v in options.items() if n in grouped}
    SolveOptions.from_keywords(**keywords)  # raises ParameterError naming the option
    if options.get("blas_threads") is not None:

        check_count("solve_options['blas_threads']", options["blas_threads"])
    return options


def _positive(name, value, allow_none=True):
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise InputTypeError(f"{name} must be a positive integer, got {value!r}")
    if value < 1:
        raise ParameterError(f"{name} must be a positive integer, got {value!r}")
    return int(value)
