"""The benchmark suite runs in --quick mode and records its correctness checks.

Every benchmark is run once, as ``python -m bench.<name> --quick --results
DIR`` with a temporary DIR (nothing is written into the repository); the
tests check the exit code, the JSON file (machine info, expected keys) and
that the comparisons inside each benchmark found both sides equal.  No test
asserts on wall time.  About 40 s on a 2-core machine.
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from fresh import bench_env

pytest.importorskip("pyamg")

ROOT = Path(__file__).resolve().parents[2]
if not (ROOT / "bench" / "__init__.py").exists():  # pragma: no cover - installed without bench/
    pytest.skip("bench/ is not in this source tree", allow_module_level=True)

#: Every benchmark script in bench/ (not the helpers ``_*.py``, ``report``, ``__main__``).
BENCHMARKS = tuple(
    sorted(
        p.stem
        for p in (ROOT / "bench").glob("*.py")
        if not p.stem.startswith("_") and p.stem != "report"
    )
)

MACHINE_KEYS = {"cores", "numba_threads", "fastmem_threads", "blas_libraries", "versions"}


def _run(args, results):
    env = bench_env()
    env.pop("FASTMEM_BENCH_RESULTS", None)
    return subprocess.run(
        [sys.executable, "-m", *args, "--results", str(results)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    return tmp_path_factory.mktemp("bench-results")


@pytest.fixture(scope="module")
def quick(results):
    """Run a benchmark in --quick mode once per module; return its JSON payload."""
    done = {}

    def get(name):
        if name not in done:
            res = _run([f"bench.{name}", "--quick"], results)
            assert res.returncode == 0, f"bench.{name} failed:\n{res.stderr[-3000:]}"
            path = results / f"{name}_quick.json"
            assert path.exists(), f"bench.{name} wrote no {path.name}"
            assert not (results / f"{name}.json").exists(), "quick run wrote the full result"
            done[name] = json.loads(path.read_text())
        return done[name]

    return get


@pytest.mark.parametrize("name", BENCHMARKS)
def test_quick_run_writes_json(quick, name):
    d = quick(name)
    assert d["benchmark"] == name
    assert d["quick"] is True
    assert MACHINE_KEYS <= set(d["machine"])
    assert d["machine"]["fastmem_threads"]["blas"] >= 1
    assert "parameters" in d
    assert d["rows"], "no rows"


def test_assembly_matches_scikit_fem(quick):
    pytest.importorskip("skfem")
    rows = quick("assembly")["rows"]
    for r in rows:
        assert {"coo_kernel_s", "assemble_stiffness_fused_s", "skfem_s"} <= set(r)
        assert r["max_abs_diff_vs_skfem"] < 1e-12
        assert r["ratio_skfem_over_fastmem"] > 0
        assert r["callable_identical"] is True  # every block size and thread mode: same bits
        assert len(r["callable_load_s"]) == 6


def test_poisson_unit_converges(quick):
    d = quick("poisson_unit")
    for r in d["rows"]:
        assert {"setup_s", "solve_s", "total_s", "iterations", "peak_rss_mb"} <= set(r)
        assert len(r["total_s"]["all"]) >= 3
        assert r["relative_residual"] < 1e-7
        assert r["iterations"] > 0
    assert {"setup", "solve", "total"} <= set(d["exponents"])


def test_exact_solve_paths_agree(quick):
    rows = quick("exact_solve")["rows"]
    general = [r for r in rows if r["path"] == "general"]
    assert general
    for r in general:
        assert r["max_abs_diff_u_vs_decoupled"] < 1e-10
    assert all(r["converged"] for r in rows)


def test_contact_solve_checks(quick):
    rows = quick("contact_solve")["rows"]
    methods = {(r["method"], r["path"]) for r in rows}
    assert {("inexact", "decoupled"), ("inexact", "general"), ("exact", "decoupled")} <= methods
    assert ("naive", "coupled") in methods
    for r in rows:
        assert r["poisson_units"] > 0
        assert r["first_poisson_units"] > 0  # the first solve in the process, beside the median
        assert "max_abs_diff_u_vs_reference" in r
    for r in rows:
        if r["method"] in ("exact", "exact-amg", "naive"):
            # all exact solvers reach the same discrete solution
            assert r["max_abs_diff_u_vs_reference"] < 1e-8, r
    naive = [r for r in rows if r["method"] == "naive"]
    for r in naive:
        assert r["converged"]
        assert not r["cycled"]
        assert r["reference"].startswith("exact ")
        exact = next(
            x
            for x in rows
            if x["n"] == r["n"]
            and x["scene"] == r["scene"]
            and x["method"] == "exact"
            and x["path"] == "decoupled"
        )
        assert r["newton_total"] == exact["newton_total"]
        assert r["max_abs_diff_lam_vs_reference"] < 1e-8 * max(1.0, r["max_abs_lam_reference"])
    for r in rows:
        if "energy_error" in r:
            assert r["eta"] >= r["energy_error"]


def test_estimate_rows(quick):
    for r in quick("estimate")["rows"]:
        assert r["patches_per_s"] > 0
        assert r["eta_first_minus_repeat"] < 1e-12 * max(1.0, r["eta"])
        assert r["poisson"]["relative_residual"] < 1e-7


def test_work_precision_bound_and_errors(quick):
    d = quick("work_precision")
    rows = d["rows"]
    assert {r["method"] for r in rows} == {"exact", "exact-amg", "inexact"}
    for r in rows:
        assert r["bound_holds"]
        assert r["effectivity"] >= 1.0
        # every method reaches the discretisation error of the exact solve
        assert abs(r["error_over_exact_amg_error"] - 1.0) < 0.05
        if r["method"] == "exact":
            assert r["max_abs_diff_u_vs_exact_amg"] < 1e-8
    assert set(d["rates"]) == {"exact", "exact-amg", "inexact"}


def test_scaling_phases(quick):
    d = quick("scaling")
    for r in d["rows"]:
        assert set(d["phases"]) <= set(r["phases"])
        assert r["archive_roundtrip_max_diff"] == 0.0
        assert r["peak_rss_mb"] > 0
        # the Poisson unit measured on the same mesh, the solve expressed in it
        assert r["poisson_s"] > 0
        assert r["solve_poisson_units"] == pytest.approx(
            r["phases"]["solve"]["median"] / r["poisson_s"]
        )
    for ph in d["phases"]:
        assert d["exponents"][ph] is not None
    assert d["exponents"]["poisson_unit"] is not None


def test_threads_results_identical(quick):
    rows = quick("threads")["rows"]
    assert {r["kernel"] for r in rows} >= {"assembly", "flux", "estimate"}
    for r in rows:
        assert r["max_rel_diff"] < 1e-12, r
        assert r["speedup"] > 0


def test_manycore_repeats_alternate_and_agree(tmp_path):
    """--repeat 2: every row has its two solves, medians, the product ceiling, and the
    same eta in every solve (the bits do not depend on the thread count); with
    --adaptive, the adaptive loop's rows likewise (one final mesh, its speed-ups), for
    each --intermediate mode."""
    res = _run(
        ["bench.manycore", "--quick", "--repeat", "2", "--adaptive", "32"]
        + ["--intermediate", "cg", "bound"],
        tmp_path,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    rows = json.loads((tmp_path / "manycore_quick.json").read_text())["rows"]
    solved = [r for r in rows if "solve_s" in r]
    assert {r["threads"] for r in solved} >= {1}
    for r in solved:
        assert len(r["solve_all_s"]) == 2, r
        assert r["solve_median_s"] > 0
        assert r["product_ms"] > 0
        assert "eta_mismatch" not in r, r
        # the solve's CPU split and page faults (getrusage deltas of this solve)
        assert len(r["solve_system_all_s"]) == 2, r
        assert r["solve_system_s"] >= 0, r
        assert r["solve_minor_faults"] >= 0, r
        assert 0 < r["solve_user_s"] + r["solve_system_s"], r
    by_case = {}
    for r in solved:
        by_case.setdefault((r["multigrid"], r["scene"]), set()).add(r["eta"])
    assert all(len(etas) == 1 for etas in by_case.values()), by_case
    # the solve a user meets, timed before the unit, in a row of its own
    user = [r for r in rows if "user_first_s" in r]
    assert len(user) == 1
    assert user[0]["user_first_pu"] == user[0]["user_first_s"] / user[0]["poisson_s"]
    assert "solve_s" not in user[0]
    assert user[0]["user_first_minor_faults"] > 0  # its memory is new to the process
    assert 0 <= user[0]["user_first_system_s"]
    adaptive = [r for r in rows if "adaptive_s" in r]
    assert {r["threads"] for r in adaptive} == {r["threads"] for r in solved}
    assert {r["intermediate"] for r in adaptive} == {"cg", "bound"}
    for r in adaptive:
        assert len(r["adaptive_all_s"]) == 2, r
        assert "eta_mismatch" not in r, r
        assert r["eta"] <= r["tol"], r
        assert "solve_s" not in r
    for mode in ("cg", "bound"):
        finals = {(r["final_vertices"], r["eta"]) for r in adaptive if r["intermediate"] == mode}
        assert len(finals) == 1, adaptive
    # the speed-ups against one thread, on every row (the report's T1/Tk)
    assert all(r["adaptive_speedup_median"] > 0 for r in adaptive)


def test_critical_path_adds_up(quick):
    """The probed solve: the same η, its time split into loops and the rest, spans in range."""
    d = quick("critical_path")
    assert [row["scene"] for row in d["rows"]] == ["default", "estimate"]
    for row in d["rows"]:
        threads = row["threads"]
        assert row["same_eta"], row["scene"]
        assert row["repeats"]
        for rep in row["repeats"]:
            assert rep["parallel_work_s"] + rep["outside_s"] == pytest.approx(rep["serial_s"])
            assert rep["outside_s"] >= 0.0
            # a loop takes at least its work spread evenly, at most its work in one thread
            assert rep["parallel_work_s"] / threads <= rep["span_s"] * (1 + 1e-9)
            assert rep["span_s"] <= rep["parallel_work_s"] * (1 + 1e-9)
            assert 1.0 <= rep["ideal_speedup"] <= threads
            assert rep["loops"] > 0
        for site in row["sites"]:
            assert site["work_s"] / threads <= site["span_s"] * (1 + 1e-9)
            assert site["span_s"] <= site["work_s"] * (1 + 1e-9)
        assert row["outside_top"]
        # the profile's self times are the profiled solve's own time outside the loops
        # (compared with that solve, not with the unprofiled repeats, which run faster)
        assert 0.0 < row["profiled_outside_s"] <= row["profiled_wall_s"]
        top = sum(f["self_s"] for f in row["outside_top"])
        assert top <= row["profiled_outside_s"] * (1 + 1e-6) + 1e-6


def test_report_and_figures(quick, results):
    for name in BENCHMARKS:
        quick(name)
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from bench import report

    vals = report.values(quick=True, folder=results)
    for key in ("assembly_ratio", "poisson_s", "contact_inexact_pu", "naive_pu", "wp_eff_range"):
        assert key in vals
    text = report.fill("{naive_pu} {no_such_value}", vals)
    assert text.endswith("{no_such_value}")
    assert "{naive_pu}" not in text
    res = _run(["bench.report", "--quick"], results)
    assert res.returncode == 0, res.stderr
    assert "## Performance" in res.stdout
    if report._plots_available():
        assert list(results.glob("*_quick.png"))


def test_contact_solve_only_inexact_and_its_report_table(tmp_path):
    """``--only-inexact`` (the issue-15 figure): the default solve alone, in contact_pu."""
    res = _run(["bench.contact_solve", "--quick", "--only-inexact"], tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    assert not (tmp_path / "contact_solve_quick.json").exists()
    d = json.loads((tmp_path / "contact_pu_quick.json").read_text())
    assert d["parameters"]["only_inexact"] is True
    assert {(r["method"], r["nested"], r["path"]) for r in d["rows"]} == {
        ("inexact", "auto", "decoupled")
    }
    assert {r["scene"] for r in d["rows"]} == {"default", "manufactured"}
    for r in d["rows"]:
        assert r["first_poisson_units"] > 0
        assert r["poisson_units"] > 0
        assert "max_abs_diff_u_vs_reference" not in r  # nothing to compare with
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from bench import report

    table = report.values(quick=True, folder=tmp_path)["contact_pu_table"]
    assert table.count("\n") == len(d["rows"]) + 1  # header, rule, one line per row
    assert "| manufactured |" in table


def test_main_runs_one_benchmark(tmp_path):
    res = _run(["bench", "--quick", "--only", "exact_solve"], tmp_path)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "exact_solve_quick.json").exists()
    assert "key numbers" in res.stdout


def test_every_script_is_registered(tmp_path):
    """``python -m bench`` runs every benchmark script there is (none forgotten)."""
    res = _run(["bench", "--list"], tmp_path)
    assert res.returncode == 0, res.stderr
    assert sorted(res.stdout.split()) == list(BENCHMARKS)
