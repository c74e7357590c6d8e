"""The tests' subprocesses import the fastmem the tests import (tests/conftest.py).

Started from the repository root, ``python -c`` and ``python -m`` put the working
directory first on ``sys.path``: without ``PYTHONSAFEPATH`` they imported the source
tree while the tests import the installed package, and compiled its kernels into a
second Numba cache.  With a non-editable install (CI) the two are different folders.
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest
from fresh import ROOT, bench_env, run_python

import fastmem

pytestmark = pytest.mark.skipif(
    sys.version_info < (3, 11), reason="PYTHONSAFEPATH needs Python 3.11 or newer"
)


def test_a_subprocess_from_the_repository_root_imports_the_same_fastmem():
    assert os.environ.get("PYTHONSAFEPATH") == "1"
    out = subprocess.run(
        [sys.executable, "-c", "import fastmem; print(fastmem.__file__)"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout
    assert Path(out.strip()).resolve() == Path(fastmem.__file__).resolve()
    assert (
        Path(run_python("import fastmem; print(fastmem.__file__)").strip()).resolve()
        == Path(fastmem.__file__).resolve()
    )


def test_bench_env_puts_bench_but_not_the_source_tree_on_the_path():
    script = "import bench, fastmem; print(bench.__file__); print(fastmem.__file__)"
    out = subprocess.run(
        [sys.executable, "-c", script],
        cwd=ROOT,
        env=bench_env(),
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout.split()
    assert Path(out[0]).resolve() == (ROOT / "bench" / "__init__.py").resolve()
    assert Path(out[1]).resolve() == Path(fastmem.__file__).resolve()
