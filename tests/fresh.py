"""Run Python in a fresh process (empty in-process kernel state), for the warm-up tests."""

import ast
import atexit
import functools
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_python(script: str, env: dict | None = None) -> str:
    """Run ``script`` with this interpreter in a new process; return its stdout.

    The process must exit with 0 (its stderr is the assertion message otherwise).
    ``env``: variables added to this process's environment.
    """
    res = subprocess.run(
        [sys.executable, "-c", script],
        env=None if env is None else {**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    return res.stdout


def compiled_after(warm_up: str, work: str) -> list[str]:
    """The kernels that ``work`` compiles (finds in no cache) after ``warm_up``, in a new process.

    Both are lines of Python run after ``import fastmem as fm``; ``work`` may assert.
    """
    script = "\n".join(
        [
            "import fastmem as fm",
            "from fastmem.cli import warmup",
            warm_up,
            "ds = warmup._dispatchers()",
            "before = {d: sum(d.stats.cache_misses.values()) for d in ds}",
            work,
            "print([d.__name__ for d in ds if sum(d.stats.cache_misses.values()) != before[d]])",
        ]
    )
    return ast.literal_eval(run_python(script).strip().splitlines()[-1])


@functools.cache
def _bench_folder() -> str:
    """A folder holding only a link to the repository's bench/ (the repository if none)."""
    folder = Path(tempfile.mkdtemp(prefix="fastmem-bench-path-"))
    atexit.register(shutil.rmtree, folder, True)
    try:
        (folder / "bench").symlink_to(ROOT / "bench", target_is_directory=True)
    except OSError:  # pragma: no cover - no symbolic links here
        return str(ROOT)
    return str(folder)


def bench_env() -> dict:
    """The environment for ``python -m bench...`` in a subprocess: bench/ on its path.

    Only bench/ is put on PYTHONPATH, through a folder that links to it: with the
    repository itself there the benchmarks imported the source tree's fastmem, whose
    kernels compile into a Numba cache of their own (a second cold compile of every
    kernel in a fresh clone); so they import the installed fastmem, as the tests and
    their other subprocesses do (tests/conftest.py).
    """
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [_bench_folder(), env.get("PYTHONPATH")]))
    return env
