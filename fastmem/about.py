"""The installed version of fastmem (ground floor: the package root and the archives read it)."""

from __future__ import annotations

import importlib.metadata

__all__ = ["package_version"]


def package_version(default: str) -> str:
    """Return the installed distribution's version, or ``default`` in a bare source tree."""
    try:
        return importlib.metadata.version("fastmem")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - a bare source tree
        return default
