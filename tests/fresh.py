"""Run Python in a fresh process (empty in-process kernel state), for the warm-up tests."""

import ast
import subprocess
import sys


def run_python(script: str) -> str:
    """Run ``script`` with this interpreter in a new process; return its stdout.

    The process must exit with 0 (its stderr is the assertion message otherwise).
    """
    res = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=600, check=False
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
