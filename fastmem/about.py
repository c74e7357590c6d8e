"""The installed version of fastmem (ground floor: the package root and the archives read it)."""

from __future__ import annotations

import importlib.metadata

__all__ = ["package_version"]


def package_version(default: str) -> str:
    """The version of the installed distribution, or ``default`` in a source tree without one."""
    try:
        return importlib.metadata.version("fastmem")
    except importlib.metadata.PackageNotFoundError:  # pragma: no cover - a bare source tree
        return default
