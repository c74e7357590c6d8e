"""Parameter sweeps on dask.distributed (fastmem.sweeps, fastmem.cli.sweep): real Dask, no mocks.

One LocalCluster of 2 worker processes (one task thread each) serves the module;
the client-interruption test starts its own (in the killed subprocess).  Workers
import the scene factories of this module by name (``test_sweep``: the tests
folder is on ``sys.path``, which spawned workers inherit).  Slow runs are made
deterministic with gates: the factory waits for a file the test creates, so a
kill always hits a run in flight.  No test asserts on time.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import queue
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numba
import numpy as np
import pytest
from numpy.testing import assert_array_equal

import fastmem as fm
from fastmem.errors import ArchiveError, InputTypeError, ParameterError

distributed = pytest.importorskip("distributed")
pd = pytest.importorskip("pandas")
psutil = pytest.importorskip("psutil")  # a dependency of distributed

from fastmem.cli import sweep as sweep_cli  # noqa: E402
from fastmem.sweeps import study as sweeps  # noqa: E402

HERE = Path(__file__).resolve().parent
GATE_TIMEOUT = 120.0  # a gate that never opens fails its run instead of hanging the test
WAIT = 180.0  # generous limit for anything the tests wait for
UNREACHABLE = "tcp://127.0.0.1:9"  # nothing listens: a sweep that tried to connect would fail

#: 12 scenes at n = 16 (the issue's test): 4 stiffness ratios x 3 gaps.
GRID = {"mu2": [0.5, 1.0, 2.0, 4.0], "g": [0.0, 0.05, 0.1]}


# ----------------------------------------------------------------------------- factories


def make_scene(mu2=1.0, g=0.1, n=16, fail="", gate=""):
    """Scene factory of the tests (module level: workers import it by name)."""
    if fail == "raise":
        raise ValueError(f"factory refused mu2={mu2}")
    if fail == "type":
        return 42
    if gate:
        _wait_for_gate(gate)
    return fm.Scene(fm.Mesh.square(n), mu=(1.0, mu2), f=(-1.0, 1.0), g=g)


def make_obstacle(lower=-0.1, n=16):
    """Obstacle factory of the tests: one membrane under f = -10 above ``lower``."""
    return fm.Obstacle(fm.Mesh.square(n), mu=1.0, f=-10.0, g=0.0, lower=lower)


def _wait_for_gate(gate):
    """Record this process (the tests kill it) and wait until the file ``gate`` exists."""
    with open(gate + ".started", "a") as fh:
        fh.write(f"{os.getpid()}\n")
    deadline = time.monotonic() + GATE_TIMEOUT
    while not os.path.exists(gate):
        if time.monotonic() > deadline:
            raise TimeoutError(f"gate {gate} was never opened")
        time.sleep(0.02)


def _nested_factory():
    def make(mu2=1.0):
        return fm.Scene(fm.Mesh.square(4), mu=(1.0, mu2))

    return make


# ----------------------------------------------------------------------------- helpers


@pytest.fixture(scope="module")
def client():
    """A LocalCluster of 2 worker processes (1 task thread each), shut down after the module."""
    import dask

    keys = [*dask.config.get("distributed.nanny.pre-spawn-environ"), "PYTHONHASHSEED"]
    with (
        sweeps._restored_environ(keys),  # the Nanny sets them in this process
        dask.config.set({"distributed.scheduler.allowed-failures": 3}),
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as c,
    ):
        yield c


def writes(out) -> list:
    """The runs of the archive-write log of a study, one entry per archive written."""
    log = Path(out) / sweeps.WRITE_LOG
    if not log.exists():
        return []
    return [json.loads(line)["run"] for line in log.read_text().splitlines()]


def wait_until(predicate, what, timeout=WAIT):
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


def serial(params, **solve_options):
    """The reference: the same run solved in this process with one Numba thread (as a worker)."""
    old = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        return fm.solve(make_scene(**params), **solve_options)
    finally:
        numba.set_num_threads(old)


def cli(argv) -> int:
    """Run ``fastmem <argv>`` through the parsers of fastmem.cli.sweep (before cli.py wiring)."""
    parser = argparse.ArgumentParser(prog="fastmem")
    sub = parser.add_subparsers(dest="command")
    sweep_cli.add_sweep_parser(sub)
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.fixture(scope="module")
def study(client, tmp_path_factory):
    """The 12-scene sweep, with the index as seen by the progress callback after each run."""
    out = tmp_path_factory.mktemp("sweep") / "study"
    seen = []

    def progress(state):
        if state["event"] == "run":
            index = sweeps.load_sweep(out)
            seen.append((state["done"], state["failed"], int((index.status == "done").sum())))

    table = fm.sweep(make_scene, GRID, out, client=client, progress=progress)
    return out, table, seen


# ----------------------------------------------------------------------------- the sweep


def test_sweep_matches_serial_solves(study):
    out, table, seen = study
    assert len(table) == 12
    assert (table.status == "done").all()
    assert list(zip(table.mu2, table.g, strict=True)) == [
        (m, g) for m in GRID["mu2"] for g in GRID["g"]
    ]
    for row in table.itertuples():
        ref = serial({"mu2": row.mu2, "g": row.g})
        assert row.eta == ref.eta
        assert (row.eta_disc, row.eta_lin, row.eta_alg) == tuple(
            ref.eta_components[k] for k in ("eta_disc", "eta_lin", "eta_alg")
        )
        assert row.contact_fraction == ref.contact_fraction
        assert row.newton_steps == ref.n_newton
        assert row.cg_iterations == sum(lv["inner"] for lv in ref.parameters["solver"]["levels"])
        assert row.converged == ref.converged
        assert row.vertices == 17**2
        archived = fm.load(row.archive)
        for name in ("u1", "u2", "lam", "active"):
            assert_array_equal(getattr(archived, name), getattr(ref, name))
        assert archived.parameters["sweep"]["params"] == {"mu2": row.mu2, "g": row.g}
        assert Path(row.archive).name == sweeps.run_name({"mu2": row.mu2, "g": row.g}) + ".h5"
    # every run written once; the index was rewritten before each progress report
    assert sorted(writes(out)) == sorted(table.run)
    assert [s[0] for s in seen] == list(range(1, 13))
    assert all(done == indexed for done, _, indexed in seen)
    assert not list(out.glob(".*tmp*"))


def test_rerun_solves_nothing(study):
    out, table, _ = study
    before = writes(out)
    # no cluster is reached: every run has a valid archive, nothing is submitted
    again = fm.sweep(make_scene, GRID, out, client=UNREACHABLE)
    assert writes(out) == before
    pd.testing.assert_frame_equal(again, table)  # rows rebuilt from the archives
    pd.testing.assert_frame_equal(fm.load_sweep(out), table)


def test_grown_grid_solves_only_new_runs(study, client, tmp_path):
    out = tmp_path / "study"
    shutil.copytree(study[0], out)
    before = writes(out)
    grid = {"mu2": [*GRID["mu2"], 8.0], "g": GRID["g"]}
    grown = fm.sweep(make_scene, grid, out, client=client)
    new = writes(out)[len(before) :]
    assert sorted(new) == sorted(grown.run[grown.mu2 == 8.0])
    assert len(grown) == 15
    assert (grown.status == "done").all()


def test_failing_run_is_recorded(client, tmp_path):
    out = tmp_path / "study"
    grid = [
        {"mu2": 1.0},
        {"mu2": 2.0, "fail": "raise"},
        {"mu2": 3.0, "fail": "type"},
        {"mu2": 4.0},
    ]
    table = fm.sweep(make_scene, grid, out, client=client)
    assert list(table.status) == ["done", "failed", "failed", "done"]
    assert table.error[1] == "ValueError in make_scene: factory refused mu2=2.0"
    assert "returned int, not a fastmem.Scene" in table.error[2]
    assert table.error[0] == table.error[3] == ""
    assert table.archive[1] == ""
    assert pd.isna(table.eta[1])
    assert pd.isna(table.newton_steps[1])
    assert pd.isna(table.converged[1])
    status = sweeps.sweep_status(out)
    assert (status["done"], status["failed"], status["pending"]) == (2, 2, 0)
    assert status["active"] is None
    assert "ValueError: factory refused mu2=2.0" in status["failures"][0][2]  # the traceback
    # a new sweep tries the failed runs again (they fail again) and solves nothing else
    before = writes(out)
    again = fm.sweep(make_scene, grid, out, client=client)
    assert writes(out) == before
    assert list(again.status) == ["done", "failed", "failed", "done"]


def test_worker_killed_mid_run(client, tmp_path):
    """SIGKILL to the worker process running a run: it is retried elsewhere, nothing twice."""
    out = tmp_path / "study"
    gate = str(tmp_path / "gate")
    grid = [{"mu2": 1.0, "gate": gate}] + [{"mu2": m} for m in (1.5, 2.0, 2.5, 3.0, 3.5)]
    killed = []

    def killer():
        started = Path(gate + ".started")
        try:
            wait_until(lambda: started.exists() and started.read_text().strip(), "gated run")
            pid = int(started.read_text().split()[0])
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

            def gone():
                try:
                    return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
                except psutil.NoSuchProcess:
                    return True

            wait_until(gone, f"worker {pid} to die")
        finally:
            Path(gate).touch()  # the retry may go on

    thread = threading.Thread(target=killer, daemon=True)
    thread.start()
    table = fm.sweep(make_scene, grid, out, client=client)
    thread.join(WAIT)
    assert killed, "the gated run never started"
    assert (table.status == "done").all(), table.error.tolist()
    log = writes(out)
    assert sorted(log) == sorted(table.run)  # every run written exactly once
    pids = [int(p) for p in Path(gate + ".started").read_text().split()]
    assert pids[0] == killed[0]
    assert len(pids) == 2
    assert pids[1] != killed[0]


_CLIENT_SCRIPT = """
import sys

import fastmem as fm
import test_sweep


def progress(state):
    if state["event"] == "run":
        print("RUN", state["row"]["run"], state["row"]["status"], flush=True)


if __name__ == "__main__":
    out, gate = sys.argv[1], sys.argv[2]
    grid = [{"mu2": m} for m in (1.0, 1.5, 2.0, 2.5)]
    grid += [{"mu2": m, "gate": gate} for m in (3.0, 3.5)]
    fm.sweep(test_sweep.make_scene, grid, out, workers=2, progress=progress)
    print("FINISHED", flush=True)
"""


def _start_client(script, out, gate):
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(HERE), env.get("PYTHONPATH")]))
    return subprocess.Popen(
        [sys.executable, str(script), str(out), gate],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
        cwd=script.parent,
    )


def test_client_killed_and_restarted(tmp_path):
    """The client process (with its LocalCluster) killed mid-sweep; a new one does the rest."""
    out = tmp_path / "study"
    gate = str(tmp_path / "gate")
    script = tmp_path / "client.py"
    script.write_text(_CLIENT_SCRIPT)
    proc = _start_client(script, out, gate)
    lines = queue.Queue()
    reader = threading.Thread(target=lambda: [lines.put(ln) for ln in proc.stdout], daemon=True)
    reader.start()
    done = []
    try:
        deadline = time.monotonic() + WAIT
        while len(done) < 4:
            try:
                line = lines.get(timeout=max(0.1, deadline - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"only {done} finished in {WAIT} s") from None
            assert not line.startswith("RUN") or line.split()[2] == "done", line
            if line.startswith("RUN"):
                done.append(line.split()[1])
        started = Path(gate + ".started")
        wait_until(lambda: started.exists() and len(started.read_text().split()) == 2, "gates")
    finally:
        family = psutil.Process(proc.pid).children(recursive=True)
        proc.kill()  # the client first, then its worker processes, by pid
        for child in family:
            try:
                child.kill()
            except psutil.NoSuchProcess:
                pass
        psutil.wait_procs(family, timeout=60)
        proc.wait(60)
    first = writes(out)
    assert sorted(first) == sorted(done)  # the 4 fast runs, none of the gated ones
    status = sweeps.sweep_status(out)
    assert (status["done"], status["pending"], status["active"]) == (4, 2, None)

    Path(gate).touch()
    proc = _start_client(script, out, gate)
    stdout, _ = proc.communicate(timeout=WAIT)
    assert proc.returncode == 0
    assert "FINISHED" in stdout
    second = [ln.split()[1] for ln in stdout.splitlines() if ln.startswith("RUN")]
    log = writes(out)
    assert log[: len(first)] == first
    assert sorted(log[len(first) :]) == sorted(second)  # only the missing runs
    assert len(second) == 2
    assert not set(second) & set(first)
    table = fm.load_sweep(out)
    assert (table.status == "done").all()
    assert len(table) == 6


def test_run_job_does_not_solve_a_written_run_again(tmp_path, job_for):
    """The worker-side check: a retried task finds the archive its dead worker wrote."""
    params = {"mu2": 2.0, "n": 6}
    name = sweeps.run_name(params)
    job = job_for(make_scene, params)
    first = sweeps._run_job(job)
    second = sweeps._run_job(job)
    assert first.pop("solved") is True
    assert second.pop("solved") is False
    assert first == second
    assert writes(tmp_path) == [name]


# ----------------------------------------------------------------------------- options


def test_methods_and_tolerances(client, tmp_path):
    tol = fm.sweep(
        make_scene, {"mu2": [1.0, 2.0], "n": 8}, tmp_path / "tol", client=client,
        solve_options={"tol": 0.06},
    )  # fmt: skip
    assert (tol.status == "done").all()
    assert tol.converged.all()
    assert (tol.eta <= 0.06).all()
    assert (tol.vertices > 81).all()
    result = fm.load(tol.archive[0])
    assert result.adaptivity is not None
    assert tol.cg_iterations[0] == int(np.sum(result.adaptivity["inner"]))
    exact = fm.sweep(
        make_scene, {"mu2": [1.0], "n": 8}, tmp_path / "exact", client=client,
        solve_options={"method": "exact", "estimate": False},
    )  # fmt: skip
    assert exact.status[0] == "done"
    assert pd.isna(exact.eta[0])
    ref = serial({"mu2": 1.0, "n": 8}, method="exact", estimate=False)
    assert_array_equal(fm.load(exact.archive[0]).u1, ref.u1)


@pytest.mark.parametrize(
    ("factory", "error", "match"),
    [
        (lambda mu2: None, InputTypeError, "is a lambda"),
        (_nested_factory(), InputTypeError, "defined inside a function"),
        (print, InputTypeError, "plain function"),
        (42, InputTypeError, "must be a function"),
    ],
)
def test_unusable_factory_refused_up_front(tmp_path, factory, error, match):
    out = tmp_path / "study"
    with pytest.raises(error, match=match):
        fm.sweep(factory, {"mu2": [1.0]}, out, client=UNREACHABLE)
    assert not out.exists()


@pytest.mark.parametrize(
    ("grid", "error", "match"),
    [
        ({"mu2": []}, ParameterError, "'mu2' has no values"),
        ({"mu2": [1.0, float("nan")]}, ParameterError, r"mu2\[1\] = nan is not finite"),
        ({"mu2": [np.ones(3)]}, InputTypeError, r"mu2\[0\] = array.*not a number"),
        ({"mu 2": [1.0]}, ParameterError, "not a Python identifier"),
        ({"eta": [1.0]}, ParameterError, "column of the sweep table"),
        ({1: [1.0]}, InputTypeError, "names must be strings"),
        ([{"mu2": 1.0}, {"mu2": 1.0}], ParameterError, "runs 0 and 1 have the same parameters"),
        ([{"mu2": 1.0}, 5], InputTypeError, r"grid\[1\] must be a dict"),
        ({"mu3": [1.0]}, ParameterError, "cannot take these parameters"),
        ("mu2", InputTypeError, "grid must be a dict"),
        ([], ParameterError, "no runs"),
    ],
)
def test_bad_grid_refused_up_front(tmp_path, grid, error, match):
    out = tmp_path / "study"
    with pytest.raises(error, match=match):
        fm.sweep(make_scene, grid, out, client=UNREACHABLE)
    assert not out.exists()


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"method": "fast"}, "method"),
        ({"monitor": print}, "per-run object"),
        ({"colour": 1}, "not a keyword of fastmem.solve"),
        ({"workers": 0}, "workers must be a positive integer"),
    ],
)
def test_bad_options_refused_up_front(tmp_path, options, match):
    out = tmp_path / "study"
    kwargs = {"solve_options": options} if "workers" not in options else options
    with pytest.raises(ParameterError, match=match):
        fm.sweep(make_scene, {"mu2": [1.0]}, out, client=UNREACHABLE, **kwargs)
    assert not out.exists()


def test_study_belongs_to_one_spec_and_one_client(study, tmp_path):
    out, _, _ = study
    with pytest.raises(ParameterError, match="was run with solve_options"):
        fm.sweep(make_scene, GRID, out, client=UNREACHABLE, solve_options={"method": "exact"})
    with open(out / sweeps.LOCK_NAME, "a+") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        with pytest.raises(ArchiveError, match="being run by another sweep"):
            fm.sweep(make_scene, GRID, out, client=UNREACHABLE)
        assert sweeps.sweep_status(out)["active"] is not None


def test_index_errors(tmp_path):
    with pytest.raises(ArchiveError, match="not a sweep study"):
        fm.load_sweep(tmp_path)
    (tmp_path / sweeps.INDEX_NAME).write_bytes(b"not hdf5")
    with pytest.raises(ArchiveError, match="cannot read sweep index"):
        fm.load_sweep(tmp_path)


def test_grid_expansion_and_names():
    runs = sweeps.expand_grid({"a": [1, 2], "b": ["x", "y"], "n": 16})
    assert runs == [
        {"a": 1, "b": "x", "n": 16},
        {"a": 1, "b": "y", "n": 16},
        {"a": 2, "b": "x", "n": 16},
        {"a": 2, "b": "y", "n": 16},
    ]
    assert sweeps.expand_grid([{"a": np.float64(0.5)}]) == [{"a": 0.5}]
    assert type(sweeps.expand_grid({"a": np.arange(2)})[1]["a"]) is int
    # stable across processes and machines: SHA-256 of the canonical JSON
    assert sweeps.run_name({"mu2": 0.5, "g": 0.1}) == "g=0.1_mu2=0.5__63bc6e8081c4"
    assert sweeps.run_name({"g": 0.1, "mu2": 0.5}) == sweeps.run_name({"mu2": 0.5, "g": 0.1})
    assert sweeps.run_name({"mu2": 1}) != sweeps.run_name({"mu2": 1.0})


def test_core_works_without_the_dask_extra(tmp_path):
    code = f"""
import sys
sys.modules["distributed"] = None
sys.modules["pandas"] = None
import fastmem as fm
from fastmem import sweeps
fm.solve(fm.Scene(fm.Mesh.square(4)))
try:
    fm.sweep(sweeps.standard_scene, {{"n": [4]}}, {str(tmp_path / "s")!r})
except ImportError as exc:
    print(exc)
"""
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=WAIT, check=False
    )
    assert proc.returncode == 0, proc.stderr
    assert 'pip install "fastmem[dask]"' in proc.stdout


# ----------------------------------------------------------------------------- command line


def test_cli_sweep_toml_and_status(client, tmp_path, capsys):
    toml = tmp_path / "study.toml"
    toml.write_text(
        f"""
[sweep]
out = "out"
scheduler = "{client.scheduler.address}"

[solve]
method = "inexact"

[grid]
n = 8
mu2 = [1.0, 2.0]
g = [0.0, 0.1]
"""
    )
    assert cli(["sweep", str(toml)]) == 0
    text = capsys.readouterr().out
    assert "finished" in text
    assert "remaining" in text
    assert "ETA" in text
    assert "4 runs: 4 done" in text
    table = fm.load_sweep(tmp_path / "out")
    assert (table.status == "done").all()
    assert set(table.mu2) == {1.0, 2.0}
    assert sweeps.load_sweep(tmp_path / "out").n.tolist() == [8] * 4
    assert cli(["sweep", "--status", str(tmp_path / "out")]) == 0
    status = capsys.readouterr().out
    assert "4 runs" in status
    assert "4 done" in status
    assert "0 failed" in status
    assert "fastmem.sweeps:standard_scene" in status


def test_cli_sweep_errors(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("[grid]\nmu2 = [1.0]\n[solve]\nmethod = 'fast'\n")
    assert cli(["sweep", str(bad)]) == 2
    assert "method" in capsys.readouterr().err
    bad.write_text("[sweep]\nfactory = 'no_such_module:make'\n[grid]\nmu2 = [1.0]\n")
    assert cli(["sweep", str(bad)]) == 2
    assert "no_such_module" in capsys.readouterr().err
    bad.write_text("[sweep]\ncolour = 1\n[grid]\nmu2 = [1.0]\n")
    assert cli(["sweep", str(bad)]) == 2
    assert "colour" in capsys.readouterr().err
    assert cli(["sweep", str(tmp_path / "missing.toml")]) == 2
    assert cli(["sweep", "--status", str(tmp_path)]) == 2
    assert "not a sweep study" in capsys.readouterr().err


def test_plot_sweep(study, tmp_path):
    pytest.importorskip("matplotlib")
    out, table, _ = study
    png = tmp_path / "cf.png"
    fig = sweep_cli.plot_sweep(out, "mu2", "contact_fraction", out=png)
    assert png.stat().st_size > 0
    ax = fig.axes[0]
    assert len(ax.get_lines()) == 3  # one line per gap g
    # words, not column names; the legend names the other parameter that varies
    assert ax.get_xlabel() == r"tension $\mu_2$ of membrane 2"
    assert ax.get_ylabel() == "contact fraction (share of vertices in contact)"
    assert ax.get_title().startswith(r"contact fraction against $\mu_2$ (study ")
    assert all(line.get_label().startswith("g = ") for line in ax.get_lines())
    assert sweep_cli.column_label("my_parameter") == "my parameter"  # a user's factory
    with pytest.raises(ParameterError, match="'colour'.*mu2"):
        sweep_cli.plot_sweep(out, "mu2", "colour")


# ----------------------------------------------------------------------------- wired CLI
# These go through fastmem.cli.main.main: they pass once cli.py calls
# fastmem.cli.sweep.add_sweep_parser and extend_plot_parser (wiring by the lead).


def test_wired_cli_sweep_status(study, capsys):
    from fastmem.cli.main import main

    out, _, _ = study
    assert main(["sweep", "--status", str(out)]) == 0
    assert "done" in capsys.readouterr().out


def test_wired_cli_plot_study(study, tmp_path):
    pytest.importorskip("matplotlib")
    from fastmem.cli.main import main

    out, _, _ = study
    png = tmp_path / "plot.png"
    assert main(["plot", str(out), "--x", "mu2", "--y", "contact_fraction", "-o", str(png)]) == 0
    assert png.stat().st_size > 0


def test_cluster_after_config_block_around_first_distributed_import(tmp_path):
    """dask.config.set around the first import of distributed must not break the next sweep."""
    code = """
import dask
with dask.config.set({"distributed.comm.timeouts.connect": "20s"}):
    import distributed
assert "distributed" not in dask.config.config  # the pitfall: the section is gone
from fastmem.sweeps.engine import _connect
with _connect(None, 1, 1, 1) as (client, threads):
    assert client.submit(sum, [40, 2]).result() == 42
assert dask.config.get("distributed.comm.timeouts.connect") == "30s"  # defaults back
print("cluster ok")
"""
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=180, cwd=tmp_path
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert "cluster ok" in out.stdout


def test_sweep_of_an_obstacle_factory(client, tmp_path):
    grid = {"lower": [-0.2, -0.1, -0.05]}
    out = tmp_path / "obstacles"
    table = fm.sweep(make_obstacle, grid, out, client=client, solve_options={"method": "exact"})
    assert (table.status == "done").all()
    for row in table.itertuples():
        ref = fm.solve(make_obstacle(lower=row.lower), method="exact")
        got = fm.load(row.archive)
        assert type(got).__name__ == "ObstacleResult"
        assert_array_equal(got.u, ref.u)
        assert row.eta == ref.eta
        assert row.contact_fraction == ref.contact_fraction
    # a higher obstacle touches more of the membrane
    fractions = table.sort_values("lower").contact_fraction.to_numpy()
    assert np.all(np.diff(fractions) > 0)
