"""Sweep claims: a run is solved by one task at a time, also across clients.

Part of :mod:`fastmem.sweeps.study` (docs/sweeps.md, "Nothing twice").  dask does not
guarantee it: a task already executing when its client goes away cannot be
interrupted; the worker keeps running it ("cancelled" in its state machine)
while the scheduler, which has forgotten it, hands the same run of a restarted
sweep to another worker.  So before making its scene a task claims the run in
the study's ``claims/`` folder:

* ``claims/<run>.<generation>`` (generation 1, 2, ...) holds the JSON identity
  of its owner (host, boot id, pid, process start time, dask worker).  A claim
  file is created complete (written to a temporary file, then ``os.link``-ed
  to its name, which fails if the name exists), and claim files are never
  deleted, so generation numbers are never reused: the owner of a run is the
  owner of its highest generation, and of two tasks creating the same
  generation exactly one succeeds.
* While it solves, the owner touches its file every :data:`HEARTBEAT` seconds
  (a daemon thread); when it is done (archive written or failure recorded) it
  replaces the file atomically by a copy marked ``released``.
* A task that finds a run claimed by a live owner waits: when the claim is
  released it loads the archive (``solved`` false in its row), or claims the
  next generation if there is no valid archive (the owner failed).
* A claim is stale, and the next generation may be created, when its owner is
  on this machine (same host name and boot id) and its process is gone (or a
  zombie, or another process with its pid): at once; otherwise when its file
  has not been touched for ``lease`` seconds as seen by the waiting task
  (:data:`LEASE`, measured with the waiter's own clock, so clock skew between
  machines does not matter).
* Before writing its archive the owner checks that no newer generation exists;
  if one does (its heartbeat stalled beyond the lease), it waits like any other
  task instead of writing: the archive is written once.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import threading
import time
import uuid
from pathlib import Path

CLAIMS_DIR = "claims"
HEARTBEAT = 5.0
"""Seconds between two touches of a claim file by its owner."""
LEASE = 60.0
"""Seconds without a touch after which a claim of another machine is stale."""
POLL = 0.2
"""Seconds between two looks at a claim held by another task."""

try:
    import psutil
except ImportError:  # pragma: no cover - a dependency of distributed
    psutil = None


def _boot_id() -> str:
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return ""


def _start_time(pid: int):
    """Start time of process ``pid`` (None if unknown); None raises nothing."""
    if psutil is None:
        return None
    try:
        return psutil.Process(pid).create_time()
    except psutil.Error:
        return None


def _identity() -> dict:
    worker = ""
    with contextlib.suppress(Exception):
        from distributed import get_worker

        worker = get_worker().address
    return {
        "host": socket.gethostname(),
        "boot_id": _boot_id(),
        "pid": os.getpid(),
        "start": _start_time(os.getpid()),
        "worker": worker,
        "token": uuid.uuid4().hex,
        "time": time.time(),
    }


def _process_alive(owner: dict) -> bool | None:
    """Whether the owner's process lives (this machine only; None when unknown)."""
    if owner.get("host") != socket.gethostname() or owner.get("boot_id") != _boot_id():
        return None
    if psutil is None or not isinstance(owner.get("pid"), int):
        return None
    try:
        proc = psutil.Process(owner["pid"])
        if proc.status() == psutil.STATUS_ZOMBIE:
            return False
        return owner.get("start") is None or proc.create_time() == owner["start"]
    except psutil.Error:
        return False


def _path(folder: Path, name: str, generation: int) -> Path:
    return folder / f"{name}.{generation}"


def _top(folder: Path, name: str) -> int:
    """Return the highest generation of ``name`` (0: never claimed; generations are contiguous)."""
    generation = 0
    while _path(folder, name, generation + 1).exists():
        generation += 1
    return generation


def _write_new(path: Path, data: dict) -> bool:
    """Create ``path`` with ``data``, complete at once; False if it exists already."""
    tmp = path.with_name(f".{path.name}.{data['token']}.tmp")
    tmp.write_text(json.dumps(data), encoding="utf-8")
    try:
        os.link(tmp, path)
    except FileExistsError:
        return False
    finally:
        tmp.unlink()
    return True


def _read(path: Path) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


class Claim:
    """A claim held by this task: heartbeat while alive, released at the end."""

    def __init__(self, folder: Path, name: str, generation: int, identity: dict):
        self.folder, self.name, self.generation = folder, name, generation
        self.path = _path(folder, name, generation)
        self.identity = identity
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._beat, name=f"fastmem-claim-{name[-12:]}", daemon=True
        )
        self._thread.start()

    def _beat(self) -> None:
        while not self._stop.wait(HEARTBEAT):
            with contextlib.suppress(OSError):
                os.utime(self.path)

    def superseded(self) -> bool:
        """Whether another task has taken the run over (a newer generation exists)."""
        return _path(self.folder, self.name, self.generation + 1).exists()

    def release(self) -> None:
        """Stop the heartbeat and mark the claim released (atomic replace)."""
        self._stop.set()
        self._thread.join()
        data = dict(self.identity, released=True, released_at=time.time())
        tmp = self.path.with_name(f".{self.path.name}.{self.identity['token']}.rel")
        with contextlib.suppress(OSError):
            tmp.write_text(json.dumps(data), encoding="utf-8")
            os.replace(tmp, self.path)


def acquire(folder: Path, name: str, done, lease: float = LEASE):
    """Claim run ``name`` or wait for its owner; return ``("claimed", Claim)`` or ``("done", x)``.

    ``done()`` returns a true value (e.g. the loaded result) when the run has a
    valid archive; it is called before each claim attempt and after an owner
    released the run, never while a live owner holds it.
    """
    folder.mkdir(parents=True, exist_ok=True)
    identity = _identity()
    seen = {}  # generation -> (mtime_ns, monotonic time since which it is unchanged)
    while True:
        generation = _top(folder, name)
        if generation:
            path = _path(folder, name, generation)
            owner = _read(path)
            if not owner.get("released") and not _stale(path, owner, generation, seen, lease):
                time.sleep(POLL)
                continue
        result = done()
        if result:
            return "done", result
        mine = dict(identity, generation=generation + 1, time=time.time())
        if _write_new(_path(folder, name, generation + 1), mine):
            return "claimed", Claim(folder, name, generation + 1, mine)


def _stale(path: Path, owner: dict, generation: int, seen: dict, lease: float) -> bool:
    alive = _process_alive(owner)
    if alive is not None:
        return not alive
    try:
        mtime = path.stat().st_mtime_ns
    except OSError:
        return False  # being replaced (released): look again
    now = time.monotonic()
    last = seen.get(generation)
    if last is None or last[0] != mtime:
        seen[generation] = (mtime, now)
        return False
    return now - last[1] >= lease
