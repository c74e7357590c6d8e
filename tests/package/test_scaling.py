"""bench.scaling --merge: a size measured on its own joins the rows of an earlier run."""

import json
import subprocess
import sys
from pathlib import Path

from fresh import bench_env

ROOT = Path(__file__).resolve().parents[2]


def _run(results, *args):
    subprocess.run(
        [sys.executable, "-m", "bench.scaling", "--quick", "--results", str(results), *args],
        cwd=ROOT,
        env=bench_env(),
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    return json.loads((results / "scaling_quick.json").read_text())


def test_merge_keeps_the_other_sizes_and_refits(tmp_path):
    first = _run(tmp_path, "--sizes", "8", "16")
    assert [r["n"] for r in first["rows"]] == [8, 16]
    merged = _run(tmp_path, "--sizes", "24", "16", "--merge")
    assert [r["n"] for r in merged["rows"]] == [8, 16, 24]
    assert merged["parameters"]["merged"] == {"kept": [8], "measured_now": [24, 16]}
    assert merged["rows"][0] == first["rows"][0]  # kept as it was
    assert merged["rows"][1] != first["rows"][1]  # measured again (new timings)
    assert merged["exponents"]["sizes_used"] == [8, 16, 24]
    # without --merge the file holds the sizes of this run only
    alone = _run(tmp_path, "--sizes", "8")
    assert [r["n"] for r in alone["rows"]] == [8]
    assert alone["parameters"]["merged"] is None
