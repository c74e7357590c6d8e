"""Sweep workers and the main script: refuse, before anything starts, what spawned workers break.

Part of :mod:`fastmem.sweeps.study`.  The worker processes of a sweep's
LocalCluster are started by multiprocessing's ``spawn`` method (dask's
``distributed.worker.multiprocessing-method``), and a spawned process first
runs the main script of its parent again, as the module ``__mp_main__``, so
that functions defined in it can be found.  Two kinds of script break this,
and without a check each ended in about 100 lines of tracebacks from every
worker ("Nanny failed to start") that named neither the cause nor the fix,
with a study folder left behind:

* **A script without an ``if __name__ == "__main__":`` guard.**  Every worker
  running it again calls the sweep again, from inside a process that is still
  starting.  :func:`check_main_script` finds the statement of the main script
  that is running (the frame executing its top level) and reads the script's
  source: unless that statement sits in the branch of an ``if __name__ ...``
  test that a re-run as ``__mp_main__`` skips, the sweep is refused.  A worker
  that gets there anyway (a script whose source cannot be read in the parent)
  refuses to start a sweep too, with the same advice.
* **A script read from standard input** (``python - < script.py``): its
  ``__file__`` is ``"<stdin>"``, which a worker cannot run again.  Refused,
  whatever the factory.

Neither applies to an existing cluster (``client=``), to the ``fork`` start
method, to ``python -c`` or an interactive session (nothing to run again), nor
to a package's ``__main__`` module (``python -m pkg``: multiprocessing does not
run those again).
"""

from __future__ import annotations

import ast
import os
import sys
import threading
import tokenize

from ..errors import ParameterError

__all__ = ["check_main_script"]

_GUARD = 'if __name__ == "__main__":'
_FIX = (
    f"put the sweep under `{_GUARD}` (the factory may stay at the top level of the script, "
    "where the workers find it, or live in an importable module); or pass client= the "
    "address of a running cluster (docs/sweeps.md)"
)


def _start_method():
    """Return the start method of LocalCluster workers (dask config; ``spawn`` by default).

    None without the dask extra (the sweep then refuses with its own ImportError).
    """
    try:
        import dask
    except ImportError:
        return None
    return str(dask.config.get("distributed.worker.multiprocessing-method", "spawn"))


def _script_to_rerun():
    """Return ``(main module, path)`` of what a spawned process runs again, or None.

    Mirrors :func:`multiprocessing.spawn.get_preparation_data`: a main module
    with a ``__spec__`` is imported again by name (except ``__main__`` modules of
    packages), else its ``__file__`` is run again; without either nothing is.
    """
    main = sys.modules.get("__main__")
    if main is None:
        return None
    name = getattr(getattr(main, "__spec__", None), "name", None)
    if name is not None:
        if name == "__main__" or name.endswith(".__main__"):
            return None
        path = getattr(main.__spec__, "origin", None)
    else:
        path = getattr(main, "__file__", None)
    if path is None:
        return None
    if os.path.splitext(os.path.basename(path))[0] == "ipython":  # left alone as well
        return None
    return main, path


def _main_thread_frames():
    """Yield the frames of the main thread, innermost first (a module's top level runs there)."""
    if threading.current_thread() is threading.main_thread():
        frame = sys._getframe(1)
    else:  # a sweep started from a thread: the main thread may be running the script
        frame = sys._current_frames().get(threading.main_thread().ident)
    while frame is not None:
        yield frame
        frame = frame.f_back


def _running_statement(namespace: dict):
    """Return the line that the top level of the module ``namespace`` is executing, or None."""
    for frame in _main_thread_frames():
        if frame.f_code.co_name == "<module>" and frame.f_globals is namespace:
            return frame.f_lineno
    return None


def _mp_main_frame():
    """Return ``(file, line)`` of a frame running a module as ``__mp_main__``, or None.

    Such a frame exists only in a process started by ``spawn`` (or ``forkserver``)
    while it runs its parent's main script again, before it starts its work.
    """
    for frame in _main_thread_frames():
        if frame.f_code.co_name == "<module>" and frame.f_globals.get("__name__") == "__mp_main__":
            return frame.f_code.co_filename, frame.f_lineno
    return None


def _child_enters(test: ast.expr):
    """Whether a re-run as ``__mp_main__`` takes the ``if`` branch of ``test``.

    True or False for ``__name__ == "..."`` and ``__name__ != "..."`` (either
    order); ``"unknown"`` for another test that reads ``__name__``; None for a
    test that does not read it.
    """
    names = [n for n in ast.walk(test) if isinstance(n, ast.Name) and n.id == "__name__"]
    if not names:
        return None
    if isinstance(test, ast.Compare) and len(test.ops) == 1:
        sides = [test.left, test.comparators[0]]
        consts = [s.value for s in sides if isinstance(s, ast.Constant)]
        if len(consts) == 1 and isinstance(consts[0], str) and names[0] in sides:
            if isinstance(test.ops[0], ast.Eq):
                return consts[0] == "__mp_main__"
            if isinstance(test.ops[0], ast.NotEq):
                return consts[0] != "__mp_main__"
    return "unknown"


def _within(body: list, line: int) -> bool:
    return bool(body) and body[0].lineno <= line <= body[-1].end_lineno


def _rerun_skips(source: str, line: int) -> bool:
    """Return whether running ``source`` as ``__mp_main__`` skips the statement at ``line``.

    Any ``if`` around the line whose test reads ``__name__`` in a way this does
    not evaluate counts as a guard (the check refuses only what it is sure of).
    """
    try:
        tree = ast.parse(source)
    except (SyntaxError, ValueError):
        return True
    for node in ast.walk(tree):
        if not isinstance(node, ast.If) or not node.lineno <= line <= node.end_lineno:
            continue
        enters = _child_enters(node.test)
        if enters is None:
            continue
        if enters == "unknown":
            return True
        in_body, in_else = _within(node.body, line), _within(node.orelse, line)
        if (in_body and not enters) or (in_else and enters):
            return True
    return False


def _read(path: str):
    try:
        with tokenize.open(path) as fh:
            return fh.read()
    except (OSError, SyntaxError, UnicodeDecodeError):
        return None


def check_main_script(client) -> None:
    """Refuse a sweep that the worker processes of its LocalCluster could not start.

    Called by :func:`fastmem.sweeps.study.sweep` before the study folder is
    created or any process is started (the module docstring has the cases).

    Parameters
    ----------
    client : None, str or distributed.Client
        The ``client`` argument of the sweep: only ``None`` (a new LocalCluster)
        spawns processes that run the main script again.

    Raises
    ------
    ParameterError
        For a sweep started by the top level of a script without an
        ``if __name__ == "__main__":`` guard (in the parent, or in a worker
        running that script again), or by a script read from standard input.
    """
    rerun = _mp_main_frame()  # only while a spawned process prepares (runs the script again)
    if rerun is not None:
        path, line = rerun
        raise ParameterError(
            f"fm.sweep was called while this process, started with the 'spawn' method, runs "
            f"the main script {path} again (line {line}): the sweep there is not under "
            f"`{_GUARD}`, so every worker process would start it again. Fix: {_FIX}"
        )
    if client is not None or _start_method() not in ("spawn", "forkserver"):
        return  # no processes of ours, or forked ones (they run nothing again)
    found = _script_to_rerun()
    if found is None:
        return
    main, path = found
    if path.startswith("<") or not os.path.exists(os.path.abspath(path)):
        what = "was read from standard input" if path == "<stdin>" else f"is not a file ({path})"
        raise ParameterError(
            f"the main script {what}, and the worker processes of a LocalCluster start by "
            "running the main script again: they cannot. Nothing was started or written. "
            "Fix: save the script to a file and run `python script.py`, with the factory at "
            f"its top level (or in an importable module) and the sweep under `{_GUARD}`; or "
            "pass client= the address of a running cluster (docs/sweeps.md)"
        )
    line = _running_statement(vars(main))
    if line is None:  # the script's top level is not running: a re-run does not get here
        return
    source = _read(path)
    if source is None or _rerun_skips(source, line):
        return
    raise ParameterError(
        f"fm.sweep was called by line {line} of the script {path}, outside an `{_GUARD}` "
        "block: the worker processes of a LocalCluster start by running the main script "
        "again, so each would start the sweep again. Nothing was started or written. "
        f"Fix: {_FIX}"
    )
