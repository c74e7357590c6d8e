"""Nothing solved twice across clients (fastmem.sweeps.claims): real Dask, no mocks.

The scenario of issue 17 that dask alone does not cover: on an EXTERNAL cluster
the client process dies while a run is executing on a worker; dask cannot
interrupt the task thread, the worker keeps running it, and the scheduler gives
the same run of a restarted sweep to another worker.  The run's claim file
makes the new task wait for the orphan's archive instead of solving again.
The factory of tests/test_sweep.py records every call (its gate's ``.started``
file): one line per solve.  No test asserts on time.
"""

from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

import fastmem as fm

distributed = pytest.importorskip("distributed")
pytest.importorskip("pandas")
pytest.importorskip("psutil")  # fastmem.sweep_claims: is the owner process alive?

from test_sweep import WAIT, wait_until  # noqa: E402  (the tests folder is on sys.path)

from fastmem.sweeps import claims as sweep_claims  # noqa: E402
from fastmem.sweeps import study as sweeps  # noqa: E402

HERE = Path(__file__).resolve().parent

_CLIENT = """
import sys

import fastmem as fm
import test_sweep


def progress(state):
    if state["event"] == "run":
        print("RUN", state["row"]["run"], state["row"]["status"], flush=True)


if __name__ == "__main__":
    address, out, gate = sys.argv[1:4]
    grid = [{"mu2": 1.0, "gate": gate}, {"mu2": 1.5}, {"mu2": 2.0}]
    fm.sweep(test_sweep.make_scene, grid, out, client=address, progress=progress)
    print("FINISHED", flush=True)
"""


def writes(out) -> list:
    log = Path(out) / sweeps.WRITE_LOG
    return [json.loads(ln) for ln in log.read_text().splitlines()] if log.exists() else []


def start_client(script, address, out, gate):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(HERE), env.get("PYTHONPATH")]))
    return subprocess.Popen(
        [sys.executable, str(script), address, str(out), gate],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
        cwd=script.parent,
    )


@pytest.fixture
def cluster():
    """An external cluster: a LocalCluster of 2 workers, 1 task thread each (queuing on)."""
    import dask

    keys = [*dask.config.get("distributed.nanny.pre-spawn-environ"), "PYTHONHASHSEED"]
    config = {"distributed.scheduler.worker-saturation": 1.0}
    with (
        sweeps._restored_environ(keys),
        dask.config.set(config),
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as c,
    ):
        yield c


def test_orphan_of_killed_client_is_not_solved_again(cluster, tmp_path):
    """Client killed while a run executes on worker A; restarted: the run is solved once."""
    c = cluster
    address = c.scheduler.address
    out = tmp_path / "study"
    gate = str(tmp_path / "gate")
    started = Path(gate + ".started")
    script = tmp_path / "client.py"
    script.write_text(_CLIENT)
    gated = sweeps.run_name({"mu2": 1.0, "gate": gate})

    proc = start_client(script, address, out, gate)
    lines = queue.Queue()
    threading.Thread(target=lambda: [lines.put(ln) for ln in proc.stdout], daemon=True).start()
    done = []
    try:
        while len(done) < 2:  # the two fast runs, on the other worker
            line = lines.get(timeout=WAIT)
            if line.startswith("RUN"):
                done.append(line.split()[1])
        wait_until(lambda: started.exists() and started.read_text().strip(), "the gated run")
    finally:
        proc.kill()  # the client only: the cluster and the orphaned task live on
        proc.wait(60)
    orphan_pid = int(started.read_text().split()[0])
    pids = c.run(os.getpid)
    worker_a = next(w for w, pid in pids.items() if pid == orphan_pid)
    worker_b = next(w for w in pids if w != worker_a)
    # worker A looks busy to the scheduler (a task pinned to it, queued behind the orphan),
    # so the restarted sweep's task for the gated run goes to the idle worker B
    blocker = c.submit(time.sleep, 0, workers=[worker_a], pure=False)
    wait_until(lambda: blocker.key in c.processing()[worker_a], "the blocker on worker A")

    proc = start_client(script, address, out, gate)
    try:

        def on_b():
            return any(k.startswith("fastmem-run-") for k in c.processing()[worker_b])

        wait_until(on_b, "the restarted sweep's task on worker B")
        # without the claim it would make the scene now (a second line in .started)
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline and len(started.read_text().split()) < 2:
            time.sleep(0.05)
        assert started.read_text().split() == [str(orphan_pid)], "the run was started twice"
    finally:
        Path(gate).touch()  # the orphan finishes and writes the archive
    stdout, _ = proc.communicate(timeout=WAIT)
    blocker.result(timeout=WAIT)
    assert proc.returncode == 0
    assert "FINISHED" in stdout
    assert f"RUN {gated} done" in stdout
    assert started.read_text().split() == [str(orphan_pid)]  # the factory ran once
    log = writes(out)
    assert sorted(e["run"] for e in log) == sorted([gated, *done])  # each archive written once
    assert next(e["pid"] for e in log if e["run"] == gated) == orphan_pid
    table = fm.load_sweep(out)
    assert (table.status == "done").all()
    claims = out / sweep_claims.CLAIMS_DIR
    assert (claims / f"{gated}.1").exists()
    assert not (claims / f"{gated}.2").exists()
    assert json.loads((claims / f"{gated}.1").read_text())["pid"] == orphan_pid


# ----------------------------------------------------------------------------- the protocol


def _claim_file(folder, name, generation, **owner):
    folder.mkdir(parents=True, exist_ok=True)
    ident = sweep_claims._identity() | owner
    (folder / f"{name}.{generation}").write_text(json.dumps(ident))
    return ident


def test_claim_of_a_dead_process_is_taken_over_at_once(tmp_path):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    _claim_file(tmp_path, "run", 1, pid=dead.pid, start=None)
    state, claim = sweep_claims.acquire(tmp_path, "run", lambda: None, lease=3600.0)
    try:
        assert state == "claimed"
        assert claim.generation == 2
        assert not claim.superseded()
    finally:
        claim.release()
    assert json.loads((tmp_path / "run.2").read_text())["released"] is True


def test_claim_of_another_machine_is_taken_over_after_its_lease(tmp_path):
    _claim_file(tmp_path, "run", 1, host="elsewhere.invalid", pid=1)
    state, claim = sweep_claims.acquire(tmp_path, "run", lambda: None, lease=0.5)
    claim.release()
    assert (state, claim.generation) == ("claimed", 2)


def test_live_claim_is_waited_for(tmp_path):
    """A second task waits for a live owner, then finds its archive; a newer one supersedes."""
    archive = []
    state, owner = sweep_claims.acquire(tmp_path, "run", lambda: archive, lease=3600.0)
    assert state == "claimed"
    got = []
    waiter = threading.Thread(
        target=lambda: got.append(sweep_claims.acquire(tmp_path, "run", lambda: archive)),
        daemon=True,
    )
    waiter.start()
    waiter.join(1.0)
    assert waiter.is_alive()  # the owner lives and has not released: still waiting
    archive.append("written")
    owner.release()
    waiter.join(WAIT)
    assert got == [("done", ["written"])]
    assert not (tmp_path / "run.2").exists()
    # an owner whose run was taken over sees it before writing
    _claim_file(tmp_path, "run", 2, host="elsewhere.invalid")
    assert owner.superseded()
