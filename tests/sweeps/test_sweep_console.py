"""What a user of sweeps sees: a quiet console, bad grids refused up front, pointers to commands.

``fastmem sweep -q`` printed 33 lines of distributed's INFO log under a
``fastmem: INFO:`` prefix, including a dashboard link that answered 404; bad
grid values of a study were found by the workers, under the wrong factory's
name; ``fastmem sweep study/`` failed to read a "study file".  Real Dask, no
mocks of it.  No test asserts on time.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import fastmem as fm
from fastmem.errors import InputTypeError, ParameterError
from fastmem.sweeps import engine, standard_scene, task
from fastmem.sweeps import study as sweeps

distributed = pytest.importorskip("distributed")
pytest.importorskip("pandas")

from fastmem.cli import sweep as sweep_cli  # noqa: E402

WAIT = 180.0
UNREACHABLE = "tcp://127.0.0.1:9"


def cli(argv) -> int:
    parser = argparse.ArgumentParser(prog="fastmem")
    sweep_cli.add_sweep_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


def fastmem_command() -> list:
    """The ``fastmem`` console script of this environment (``python -m fastmem`` without one)."""
    script = Path(sys.executable).with_name("fastmem")
    if script.is_file():
        return [str(script)]
    found = shutil.which("fastmem")
    return [found] if found else [sys.executable, "-m", "fastmem"]


@pytest.fixture
def no_cluster(monkeypatch):
    """Make any attempt of a sweep to start or reach a cluster fail the test."""

    def refuse(*args, **kwargs):
        raise AssertionError("the sweep started a cluster")

    monkeypatch.setattr(sweeps, "_connect", refuse)


# ----------------------------------------------------------------------------- quiet


def test_quiet_command_prints_no_info_line(tmp_path):
    """``fastmem sweep -q study.toml``: no INFO line, no dashboard, on a real LocalCluster."""
    (tmp_path / "study.toml").write_text(
        "[sweep]\nworkers = 1\nnumba_threads = 1\n\n[grid]\nn = 4\nmu2 = [1.0]\n"
    )
    env = {k: v for k, v in os.environ.items() if "LOGGING" not in k.upper()}
    proc = subprocess.run(
        [*fastmem_command(), "sweep", "-q", "study.toml"],
        capture_output=True,
        text=True,
        timeout=WAIT,
        cwd=tmp_path,
        env=env,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "1 runs: 1 done" in proc.stdout
    assert [ln for ln in proc.stderr.splitlines() if "INFO" in ln] == []
    assert "dashboard" not in proc.stderr
    assert "fastmem: INFO" not in proc.stdout + proc.stderr


def test_cluster_has_no_dashboard_and_quiet_workers():
    """The LocalCluster of a sweep: WARNING in this process and in the workers, no :8787."""
    import dask

    if engine._logging_configured(dask):
        pytest.skip("this environment configures distributed's logging (kept by sweeps)")
    log = logging.getLogger("distributed")
    before = log.level
    with engine._connect(None, 1, 1, 1) as (client, _):
        assert log.getEffectiveLevel() == logging.WARNING
        http = client.cluster.scheduler.services["dashboard"]  # the name of its HTTP server
        assert http.port != 8787
        levels = client.run(lambda: logging.getLogger("distributed").getEffectiveLevel())
        assert set(levels.values()) == {logging.WARNING}
    assert log.level == before


def test_user_logging_config_is_kept():
    import dask

    assert not engine._logging_configured(dask)
    with dask.config.set({"logging": {"distributed": "info"}}):
        assert engine._logging_configured(dask)
    log = logging.getLogger("distributed")
    before = log.level
    with engine._quiet_logs(enabled=False):
        assert log.level == before
    with engine._quiet_logs():
        assert log.getEffectiveLevel() >= logging.WARNING
    assert log.level == before


def test_dask_warnings_are_not_printed_as_fastmem_messages(monkeypatch, capsys):
    """Under the command's root handler ("fastmem: LEVEL:"), distributed's records name it."""
    log = logging.getLogger("distributed")
    monkeypatch.setattr(log, "propagate", True)  # as when a root handler existed at its import
    monkeypatch.setattr(log, "handlers", [])
    with sweep_cli._named_dask_records():
        logging.getLogger("distributed.nanny").warning("worker restarted")
    assert "distributed.nanny: WARNING: worker restarted" in capsys.readouterr().err
    assert log.propagate is True
    assert log.handlers == []


# ----------------------------------------------------------------------------- bad grids


@pytest.mark.parametrize(
    ("grid", "match"),
    [
        (
            {"domain": "lshape", "n": [8, 7]},
            r"run 1 \{\"domain\":\"lshape\",\"n\":7\}: n must be even",
        ),
        ({"mu2": [1.0, -2.0], "n": 8}, r"run 1 .*mu2 must be positive and finite, got -2.0"),
        ({"n": [8, 0]}, r"run 1 .*n must be a positive integer, got 0"),
        ({"refine": [0, -1], "n": 4}, r"refine must be an integer >= 0, got -1"),
        ({"g": [-0.5], "n": 4}, r"the run .*g must be >= 0 on the boundary"),
        ({"domain": ["disc"], "n": 4}, r"domain must be 'square' or 'lshape', got 'disc'"),
    ],
    ids=["odd-n-lshape", "negative-mu2", "zero-n", "negative-refine", "negative-g", "domain"],
)
def test_bad_grid_value_refused_before_any_worker_starts(tmp_path, no_cluster, grid, match):
    out = tmp_path / "study"
    with pytest.raises(ParameterError, match=match) as info:
        fm.sweep(standard_scene, grid, out)  # client=None: a LocalCluster would start
    assert str(info.value).startswith("standard_scene() refuses")
    assert "make_scene" not in str(info.value)
    assert not out.exists()


def test_bad_toml_grid_refused_before_any_worker_starts(tmp_path, no_cluster, capsys):
    toml = tmp_path / "bad.toml"
    toml.write_text('[grid]\ndomain = "lshape"\nn = [8, 7, 5, 3, 1]\nmu2 = [1.0, -2.0]\n')
    assert cli(["sweep", str(toml)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fastmem: error: standard_scene() refuses 9 of the 10 runs")
    assert "n must be even for the L-shaped domain, got 7" in err
    assert "mu2 must be positive and finite, got -2.0" in err
    assert "and 6 more" in err
    assert not (tmp_path / "bad").exists()


def sweep_factory(mu2=1.0):
    """A module-level factory (workers import it by name); tests give it a validate hook."""
    return fm.Scene(fm.Mesh.square(4), mu=(1.0, mu2))


def test_validate_hook_of_a_user_factory(tmp_path, no_cluster, monkeypatch):
    def validate(mu2=1.0):
        if mu2 > 1:
            raise ValueError(f"mu2 = {mu2} is too stiff for this study")

    monkeypatch.setattr(sweep_factory, "validate", validate, raising=False)
    with pytest.raises(ParameterError, match=r"sweep_factory\(\) refuses 1 of the 2 runs.*stiff"):
        fm.sweep(sweep_factory, {"mu2": [1.0, 2.0]}, tmp_path / "study")
    monkeypatch.setattr(sweep_factory, "validate", 42)
    with pytest.raises(InputTypeError, match="validate attribute must be a function"):
        fm.sweep(sweep_factory, {"mu2": [1.0, 2.0]}, tmp_path / "study")
    assert not (tmp_path / "study").exists()


def test_failed_run_names_its_factory(job_for):
    """A refusal that only the run finds is recorded under the factory's own name."""
    job = job_for(standard_scene, {"domain": "lshape", "n": 7})
    row = task._run_job(job)
    assert row["status"] == "failed"
    assert row["error"] == (
        "ParameterError in standard_scene: n must be even for the L-shaped domain, got 7"
    )


# ----------------------------------------------------------------------------- pointers


def _study(folder: Path) -> None:
    folder.mkdir()
    spec = {"factory": "fastmem.sweeps:standard_scene", "solve_options": {}}
    sweeps._write_index(folder, spec, [], {"running": 0, "active": False})


def test_sweep_of_a_study_folder_points_at_the_commands(tmp_path, capsys):
    study = tmp_path / "study"
    _study(study)
    (tmp_path / "study.toml").write_text("[grid]\nn = [4]\n")  # out: its stem
    (tmp_path / "other.toml").write_text('[sweep]\nout = "elsewhere"\n[grid]\nn = [4]\n')
    for target in (study, study / sweeps.INDEX_NAME):
        assert cli(["sweep", str(target)]) == 2
        err = capsys.readouterr().err
        assert f"fastmem sweep --status {study}`" in err
        assert f"fastmem plot {study} --x PARAMETER --y COLUMN`" in err
        assert f"`fastmem sweep {tmp_path / 'study.toml'}` completes its missing runs" in err
        assert "other.toml" not in err
        assert "TOML" not in err  # not "is not valid TOML"
    assert cli(["sweep", "--status", str(tmp_path / "study.toml")]) == 2
    assert f"`fastmem sweep --status {study}`" in capsys.readouterr().err


def test_sweep_of_other_folders_and_files_points_at_the_commands(tmp_path, capsys):
    assert cli(["sweep", str(tmp_path)]) == 2
    assert "is a folder, not a study file" in capsys.readouterr().err
    (tmp_path / "mine.toml").write_text("[grid]\nn = [4]\n")
    assert cli(["sweep", str(tmp_path)]) == 2
    assert f"`fastmem sweep {tmp_path / 'mine.toml'}`" in capsys.readouterr().err
    archive = tmp_path / "run.h5"
    archive.write_bytes(b"")
    assert cli(["sweep", str(archive)]) == 2
    assert f"`fastmem info {archive}`" in capsys.readouterr().err
