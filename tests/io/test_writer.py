"""Temporary files of interrupted writes (fastmem.io.writer.remove_stale_temporaries).

A write goes to ``.NAME.tmp-HOST-PID-RANDOM`` beside the target and is renamed
when complete.  A writer killed on the way leaves that file; the next write of
the same target removes it when its writer is gone (or, when the writer cannot
be checked, when it is older than ``STALE_AFTER``), and never touches the file
of a writer that still runs or of another target.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("h5py")

import fastmem as fm  # noqa: E402
from fastmem.io import writer  # noqa: E402

POSIX_ONLY = pytest.mark.skipif(os.name != "posix", reason="the process check needs POSIX")


@pytest.fixture(scope="module")
def result():
    scene = fm.Scene(fm.Mesh.square(4), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1)
    return fm.solve(scene, method="exact")


def dead_pid() -> int:
    """The id of a process that has exited (and been reaped)."""
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def temporary(folder, target: str, host: str | None, pid: int | None, *, age: float = 0.0):
    """Create a leftover temporary file by the writer's naming pattern, ``age`` seconds old."""
    owner = "" if pid is None else f"{host}-{pid}-"
    path = folder / f".{target}.tmp-{owner}k3x9_q2z"
    path.write_bytes(b"half an archive")
    if age:
        stamp = time.time() - age
        os.utime(path, (stamp, stamp))
    return path


@POSIX_ONLY
def test_leftover_of_a_dead_writer_is_removed_by_the_next_save(tmp_path, result):
    path = tmp_path / "run.h5"
    result.save(path)
    stale = temporary(tmp_path, "run.h5", writer._host(), dead_pid())
    result.save(path)
    assert not stale.exists()
    assert sorted(os.listdir(tmp_path)) == ["run.h5"]
    assert np.array_equal(fm.load(path).u1, result.u1)


@POSIX_ONLY
def test_running_writers_and_other_targets_are_left_alone(tmp_path, result):
    host, gone = writer._host(), dead_pid()
    keep = [
        temporary(tmp_path, "run.h5", host, os.getppid()),  # a running writer on this host
        temporary(tmp_path, "run.h5", host, os.getpid()),  # this process
        temporary(tmp_path, "run.h5", "otherhost", gone),  # cannot be checked, recent
        temporary(tmp_path, "run.h5", None, None),  # an older fastmem's name, recent
        temporary(tmp_path, "other.h5", host, gone),  # another target
    ]
    foreign = tmp_path / ".run.h5.tmp-notours"  # not the pattern: somebody else's
    foreign.write_text("x")
    result.save(tmp_path / "run.h5")
    assert all(p.exists() for p in keep), [p.name for p in keep if not p.exists()]
    assert foreign.exists()


def test_unverifiable_leftovers_go_after_the_age_limit(tmp_path, result):
    old = writer.STALE_AFTER + 60.0
    stale = [
        temporary(tmp_path, "run.h5", "otherhost", 12345, age=old),
        temporary(tmp_path, "run.h5", None, None, age=old),
    ]
    removed = writer.remove_stale_temporaries(tmp_path / "run.h5")
    assert sorted(removed) == sorted(stale)
    assert not any(p.exists() for p in stale)


@POSIX_ONLY
def test_leftover_folder_of_an_xdmf_export_is_removed(tmp_path, result):
    pytest.importorskip("meshio")
    folder = tmp_path / f".run.xdmf.tmp-{writer._host()}-{dead_pid()}-a1b2c3d4"
    folder.mkdir()
    (folder / "run.xdmf.h5").write_bytes(b"half")
    result.export(tmp_path / "run.xdmf")
    assert not folder.exists()
    assert sorted(os.listdir(tmp_path)) == ["run.xdmf", "run.xdmf.h5"]


#: Saves an archive over ARGV[1] and stops for good just before the rename.
_HANGING_WRITER = """
import sys, time
import fastmem as fm
from fastmem.io import writer

def hang(path):
    print("writing", flush=True)
    time.sleep(600)

writer._write_integrity_header = hang
fm.load(sys.argv[1]).save(sys.argv[1])
"""


@POSIX_ONLY
def test_kill_9_during_an_overwrite_then_save_again(tmp_path, result):
    """A writer killed mid-write leaves its temporary file; the next save removes it."""
    path = tmp_path / "run.h5"
    result.save(path)
    before = path.read_bytes()
    proc = subprocess.Popen(
        [sys.executable, "-c", _HANGING_WRITER, str(path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout.readline().strip() == "writing"
    finally:
        proc.kill()  # SIGKILL: no cleanup runs
        proc.wait(timeout=60)
        proc.stdout.close()
    leftovers = [p for p in os.listdir(tmp_path) if p != "run.h5"]
    assert len(leftovers) == 1, leftovers
    assert leftovers[0].startswith(".run.h5.tmp-"), leftovers
    assert f"-{proc.pid}-" in leftovers[0]
    assert path.read_bytes() == before  # the old archive untouched
    result.save(path)
    assert sorted(os.listdir(tmp_path)) == ["run.h5"]
    back = fm.load(path)
    assert np.array_equal(back.u1, result.u1)
    assert back.n_newton == result.n_newton
