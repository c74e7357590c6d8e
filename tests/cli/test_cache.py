"""Numba's on-disk cache of fastmem's kernels when the install folder cannot hold it.

Numba writes the cache next to the kernels' source (``fastmem/kernels/__pycache__``)
and, when that folder is not writable (a system-wide or read-only install),
falls back to a user-wide folder (``$XDG_CACHE_HOME/numba`` or ``~/.cache/numba``).
Forcing that fallback with ``NUMBA_CACHE_LOCATOR_CLASSES=UserWideCacheLocator``,
two fresh processes check that the first one compiles into the user folder and
the second one loads from it instead of compiling again.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

SCRIPT = """
import json
import numpy as np
from fastmem.kernels import rows
from fastmem.cli.warmup import _counts
d = rows.row_measures
u1, u2, lam = np.zeros(4), np.zeros(4), np.ones(4)
interior, active = np.arange(4), np.zeros(4, dtype=bool)
changed, total = d(u1, u2, lam, interior, active, 1.0)
assert changed == 4 and total == 0.0
hits, misses = _counts([d])
print(json.dumps({"hits": hits, "misses": misses, "sigs": len(d.signatures)}))
"""


def _run(cache_home) -> dict:
    env = {
        **os.environ,
        "NUMBA_CACHE_LOCATOR_CLASSES": "UserWideCacheLocator",
        "XDG_CACHE_HOME": str(cache_home),
    }
    env.pop("NUMBA_CACHE_DIR", None)
    res = subprocess.run(
        [sys.executable, "-c", SCRIPT],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_user_wide_cache_fallback(tmp_path):
    first = _run(tmp_path)
    assert first["sigs"] >= 1
    assert first["misses"] >= 1  # compiled: nothing cached in the empty user folder yet
    index = list((tmp_path / "numba").rglob("*.nbi"))
    assert index, "no cache index written to the user-wide folder"
    second = _run(tmp_path)
    assert second["misses"] == 0
    assert second["hits"] >= 1  # loaded from the user-wide cache, not compiled again
