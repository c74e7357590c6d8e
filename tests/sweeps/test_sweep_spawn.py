"""Sweeps and the main script (fastmem.sweeps.spawn): real scripts in real subprocesses.

LocalCluster workers are spawned and run the main script again.  A script
without an ``if __name__ == "__main__":`` guard, or one read from standard
input, used to end in about 100 lines of tracebacks from every worker and a
study folder left behind; each is now one ParameterError, raised before the
study folder or any process exists.  No test asserts on time.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from fastmem.errors import ParameterError
from fastmem.sweeps import spawn

pytest.importorskip("distributed")
pytest.importorskip("pandas")

WAIT = 180.0
GUARD = 'if __name__ == "__main__":'

FACTORY = """
import fastmem as fm


def make_scene(mu2, n=4):
    return fm.Scene(fm.Mesh.square(n), mu=(1.0, mu2), f=(-1.0, 1.0), g=0.1)
"""


def environ() -> dict:
    """This environment without a user's choice of distributed's logging."""
    return {k: v for k, v in os.environ.items() if "LOGGING" not in k.upper()}


def python(tmp_path, *args, stdin=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, *args],
        input=stdin,
        capture_output=True,
        text=True,
        timeout=WAIT,
        cwd=tmp_path,
        env=environ(),
        check=False,
    )


def one_clear_error(proc, *phrases) -> None:
    """One traceback, ending in a ParameterError that says all of ``phrases``."""
    err = proc.stderr
    assert proc.returncode == 1, err[-3000:]
    assert err.count("Traceback (most recent call last)") == 1, err[-3000:]
    last = err.strip().splitlines()[-1]
    assert last.startswith("fastmem.errors.ParameterError: "), last
    for phrase in phrases:
        assert phrase in last, last
    assert "Nanny" not in err


# ----------------------------------------------------------------------------- scripts


SWEEP = 'fm.sweep(make_scene, {"mu2": [1.0]}, "study", workers=1, numba_threads=1)'

THREAD = f"""
import threading

errors = []


def main():
    try:
        {SWEEP}
    except Exception as exc:
        errors.append(exc)


thread = threading.Thread(target=main)
thread.start()
thread.join()
raise errors[0]
"""


@pytest.mark.parametrize(
    ("body", "running"),
    [
        (f"table = {SWEEP}\n", "table = "),
        (f"def main():\n    {SWEEP}\n\n\nmain()\n", "main()"),
        (THREAD, "thread.join()"),
    ],
    ids=["top-level-call", "main-without-guard", "from-a-thread"],
)
def test_script_without_guard_gives_one_clear_error(tmp_path, body, running):
    source = FACTORY + "\n\n" + body
    line = next(i for i, text in enumerate(source.splitlines(), 1) if text.startswith(running))
    script = tmp_path / "noguard.py"
    script.write_text(source)
    proc = python(tmp_path, str(script))
    one_clear_error(proc, f"line {line} of the script {script}", GUARD, "client=")
    assert not (tmp_path / "study").exists()


def test_script_read_from_stdin_gives_one_clear_error(tmp_path):
    script = FACTORY + f"\n\n{GUARD}\n    {SWEEP}\n"
    proc = python(tmp_path, "-", stdin=script)
    one_clear_error(proc, "read from standard input", "python script.py", GUARD)
    assert not (tmp_path / "study").exists()


def test_script_with_guard_sweeps_quietly(tmp_path):
    """The guarded script works, and distributed's INFO log stays off (root logger at INFO)."""
    script = tmp_path / "study.py"
    script.write_text(
        FACTORY
        + textwrap.dedent(
            f"""

            {GUARD}
                import logging

                logging.basicConfig(level=logging.INFO, format="%(name)s %(levelname)s %(message)s")
                table = {SWEEP}
                print("status", *table.status)
            """
        )
    )
    proc = python(tmp_path, str(script))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "status done" in proc.stdout
    assert (tmp_path / "study" / "sweep-index.h5").is_file()
    chatter = [ln for ln in proc.stderr.splitlines() if ln.startswith("distributed")]
    assert chatter == []


def test_spawned_process_refuses_to_start_a_sweep(tmp_path):
    """The fallback in the worker: a re-run of a guard-less script stops at the sweep."""
    script = tmp_path / "child.py"
    script.write_text(
        textwrap.dedent(
            f"""
            import multiprocessing

            import fastmem as fm
            from fastmem.sweeps import standard_scene

            if __name__ == "__mp_main__":  # what a guard-less script does in a spawned process
                fm.sweep(standard_scene, {{"n": [4]}}, "study", client="tcp://127.0.0.1:9")


            def noop():
                pass


            {GUARD}
                process = multiprocessing.get_context("spawn").Process(target=noop)
                process.start()
                process.join()
                print("exitcode", process.exitcode)
            """
        )
    )
    proc = python(tmp_path, str(script))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "exitcode 1" in proc.stdout
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("fastmem.errors.ParameterError: "), proc.stderr[-3000:]
    assert f"runs the main script {script} again (line 8)" in last
    assert GUARD in last
    assert not (tmp_path / "study").exists()


# ----------------------------------------------------------------------------- the guard


@pytest.mark.parametrize(
    ("source", "skipped"),
    [
        ("x = 1\nrun()\n", False),
        ('if __name__ == "__main__":\n    x = 1\n    run()\n', True),
        ('if "__main__" == __name__:\n    run()\n', True),
        ('if __name__ == "__main__": run()\n', True),
        ('if __name__ != "__main__":\n    pass\nelse:\n    run()\n', True),
        ('if __name__ != "__main__":\n    x = 1\n    run()\n', False),
        ('if __name__ == "__main__":\n    pass\nelse:\n    run()\n', False),
        ('if __name__ == "__mp_main__":\n    run()\n', False),
        ("if True:\n    x = 1\n    run()\n", False),
        ('try:\n    if __name__ == "__main__":\n        run()\nfinally:\n    pass\n', True),
        ('if __name__ in ("__main__",):\n    run()\n', True),  # not evaluated: trusted
        ("def f(:\n    run()\n", True),  # unreadable: nothing refused
    ],
)
def test_rerun_skips(source, skipped):
    line = next(i for i, text in enumerate(source.splitlines(), 1) if "run()" in text)
    assert spawn._rerun_skips(source, line) is skipped


def test_existing_cluster_fork_and_interactive_sessions_pass(monkeypatch):
    """No LocalCluster (client given), forked workers, nothing to run again: no refusal."""
    main = sys.modules["__main__"]
    monkeypatch.setattr(main, "__spec__", None)
    monkeypatch.setattr(main, "__file__", "<stdin>", raising=False)
    spawn.check_main_script("tcp://127.0.0.1:9")  # an existing cluster spawns nothing
    with pytest.raises(ParameterError, match="read from standard input"):
        spawn.check_main_script(None)
    import dask

    with dask.config.set({"distributed.worker.multiprocessing-method": "fork"}):
        spawn.check_main_script(None)  # forked workers run nothing again
    monkeypatch.delattr(main, "__file__")  # python -c, an interactive session
    spawn.check_main_script(None)
