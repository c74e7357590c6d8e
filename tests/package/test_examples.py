"""Run every script of examples/ in a fresh process and check what it printed and wrote.

Each example runs with ``cwd`` and ``FASTMEM_EXAMPLES_OUT`` set to a temporary
folder; it must exit with status 0, and the checks below look at its output
(the printed bound is a positive float, archives load with ``fastmem.load``,
files it announces exist).  An example without a specific check still has to
run cleanly and print something.  The scripts are found next to the tests in
a source checkout; an installed package without its sources skips them.
"""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import fastmem as fm

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
SCRIPTS = sorted(EXAMPLES.glob("*.py")) if EXAMPLES.is_dir() else []
TIMEOUT = 300  # seconds per script, Numba compilation of a cold cache included
ETA = re.compile(r"\beta = ([0-9.]+(?:e[+-]?[0-9]+)?)")


def _run(script: Path, out: Path) -> str:
    env = {**os.environ, "FASTMEM_EXAMPLES_OUT": str(out), "MPLBACKEND": "Agg"}
    proc = subprocess.run(
        [sys.executable, str(script)],
        cwd=out,
        env=env,
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
    )
    assert proc.returncode == 0, (
        f"{script.name} exited with {proc.returncode}\n"
        f"--- stdout\n{proc.stdout}\n--- stderr\n{proc.stderr}"
    )
    assert proc.stdout.strip(), f"{script.name} printed nothing"
    return proc.stdout


def _eta(stdout: str) -> float:
    """The last bound printed as ``eta = <float>``: a positive finite number."""
    found = ETA.findall(stdout)
    assert found, f"no 'eta = <number>' in the output:\n{stdout}"
    eta = float(found[-1])
    assert 0.0 < eta < float("inf")
    return eta


def _check_default_scene(stdout, out):
    eta = _eta(stdout)
    result = fm.load(out / "default_scene.h5")
    assert result.converged
    assert result.mesh.n_vertices == 129 * 129
    assert result.eta == pytest.approx(eta, rel=1e-4)
    comps = {k: float(v) for k, v in re.findall(r"(eta_disc|eta_lin|eta_alg)\s+= (\S+)", stdout)}
    assert set(comps) == {"eta_disc", "eta_lin", "eta_alg"}
    assert eta <= sum(comps.values()) * (1 + 1e-3)


def _check_gmsh_mesh(stdout, out):
    try:
        import gmsh  # noqa: F401
    except ImportError:
        assert "gmsh is not installed" in stdout
        return
    _eta(stdout)
    mesh = fm.Mesh.read(out / "annulus.msh")
    assert f"read {mesh}" in stdout


def _check_heterogeneous_mu(stdout, out):
    _eta(stdout)
    assert "path: general" in stdout
    assert (out / "heterogeneous_mu.vtu").stat().st_size > 0


def _check_read_archive_h5py(stdout, out):
    eta = _eta(stdout)
    result = fm.load(out / "small.h5")
    assert result.eta == pytest.approx(eta, rel=1e-4)
    n, m = result.mesh.n_vertices, result.mesh.n_triangles
    assert f"mesh: {n} vertices, {m} triangles" in stdout
    for name in ("/mesh/vertices", "/solution/u1", "/estimators/", "@format = fastmem-result"):
        assert name in stdout


def _check_solve_to_tolerance(stdout, out):
    eta = _eta(stdout)
    assert eta <= 5e-3
    assert "converged: True" in stdout
    result = fm.load(out / "lshape_tol.h5")
    assert result.eta == pytest.approx(eta, rel=1e-4)
    rows = len(result.adaptivity["level"])
    assert rows > 1
    assert re.search(rf"^\s*{rows - 1}\s+{result.mesh.n_vertices}\s", stdout, re.MULTILINE)


def _check_gallery(stdout, out):
    names = ("single", "adaptive", "heterogeneous", "sweep")
    for name in names:
        png = out / f"{name}.png"
        data = png.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{png} is not a PNG"
        assert 10_000 < len(data) <= 300_000, f"{png}: {len(data)} bytes"
        assert f"{name}.png: {len(data)} bytes" in stdout
    assert not (out / "gallery-work").exists()  # the archives and the study are removed


CHECKS = {
    "default_scene": _check_default_scene,
    "gallery": _check_gallery,
    "gmsh_mesh": _check_gmsh_mesh,
    "heterogeneous_mu": _check_heterogeneous_mu,
    "read_archive_h5py": _check_read_archive_h5py,
    "solve_to_tolerance": _check_solve_to_tolerance,
}

#: Examples that need optional packages: run only where they import.
REQUIRES = {
    "parameter_study": ("dask", "pandas"),
    "gallery": ("matplotlib", "dask", "pandas"),
}


@pytest.mark.skipif(not SCRIPTS, reason=f"no examples folder at {EXAMPLES} (installed package)")
@pytest.mark.parametrize("script", SCRIPTS, ids=[s.stem for s in SCRIPTS])
def test_example(script, tmp_path):
    for module in REQUIRES.get(script.stem, ()):
        pytest.importorskip(module)
    stdout = _run(script, tmp_path)
    check = CHECKS.get(script.stem)
    if check is not None:
        check(stdout, tmp_path)


@pytest.mark.skipif(not SCRIPTS, reason=f"no examples folder at {EXAMPLES} (installed package)")
def test_every_example_is_documented():
    """Each script opens with a docstring that says what it shows."""
    for script in SCRIPTS:
        text = script.read_text(encoding="utf-8")
        assert text.startswith('"""'), f"{script.name} has no module docstring"
