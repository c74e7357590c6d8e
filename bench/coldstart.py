"""Cold start: the first ``fastmem run`` with an empty Numba cache, the second one, and
the compile time of every kernel.

A fresh install has no compiled kernels; Numba compiles each one on its first
call and caches it on disk (``cache=True``).  This benchmark points Numba at
an empty cache folder (``NUMBA_CACHE_DIR``) and measures, each in a fresh
process:

* ``cold``: ``fastmem run --no-save`` (the README's first command without the
  install) with the empty cache: wall time of the whole process (the flux
  kernel compiles in a helper process meanwhile, :mod:`fastmem.cli.warmup`);
* ``cold_no_helper``: the same with ``FASTMEM_COMPILE_HELPER=0`` and another
  empty cache (everything compiles in the one process: the baseline of the
  helper, measured in the same run);
* ``warm``: the same command again, with the cache the first one filled;
* ``import``: ``python -c "import fastmem"`` (the floor of any run);
* for every run also its user + system CPU seconds (``RUSAGE_CHILDREN``: the
  process and the helper it waited for), steadier than wall time on a shared
  machine;
* per kernel: the compile time of every kernel specialisation compiled by the
  cold run (Numba's ``numba:compile`` events; times of nested compilations are
  included in their caller's and listed as well).

``--quick`` checks the machinery in seconds: ``fastmem run --n 8`` with the
cache as it is (no empty cache), and the compile events of one small kernel.

    python -m bench.coldstart [--quick] [--repeat 3]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

from bench._common import emit_worker_result, finish, parse, parser, progress, summary

COMMAND = ["-m", "fastmem", "run", "--no-save"]
QUICK_COMMAND = [*COMMAND, "--n", "8"]


def _cpu_children() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _timed(args, env) -> tuple[float, float, str]:
    """Wall seconds, user+sys CPU seconds (the process and its waited-for helper), stdout."""
    c0 = _cpu_children()
    t0 = time.perf_counter()
    res = subprocess.run(
        [sys.executable, *args], env=env, stdout=subprocess.PIPE, text=True, check=False
    )
    seconds = time.perf_counter() - t0
    cpu = _cpu_children() - c0
    if res.returncode not in (0, 1):
        raise RuntimeError(f"{' '.join(args)} failed with exit code {res.returncode}")
    return seconds, cpu, res.stdout


def compile_worker(quick: bool) -> dict:
    """Run the default scene with Numba's compile events recorded (empty cache expected).

    ``quick``: call one small kernel instead (checks the event bookkeeping).
    """
    import numpy as np
    from fastmem.kernels import rows as _rows
    from numba.core import event

    import fastmem as fm

    with event.install_recorder("numba:compile") as rec:
        t0 = time.perf_counter()
        if quick:
            z = np.zeros(3)
            _rows.row_measures(z, z, z, np.arange(3), np.zeros(3, dtype=bool), 1.0)
        else:
            fm.solve(fm.Scene(fm.Mesh.square(128), mu=(1.0, 1.0), f=(-1.0, 1.0), g=0.1))
        seconds = time.perf_counter() - t0
    starts, rows = {}, []
    for ts, ev in rec.buffer:
        d = ev.data["dispatcher"]
        key = (id(d), str(ev.data["args"]))
        if ev.is_start:
            starts[key] = ts
        elif key in starts:
            name = f"{d.py_func.__module__}.{d.py_func.__name__}"
            rows.append({"kernel": name, "args": str(ev.data["args"]), "seconds": ts - starts[key]})
    rows.sort(key=lambda r: -r["seconds"])
    return {"solve_seconds": seconds, "compiles": rows}


def main(argv=None):
    p = parser(__doc__, repeat=3)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parse(p, argv)
    if args.worker:
        emit_worker_result(compile_worker(args.quick))
        return 0
    repeat = 1 if args.quick else args.repeat
    command = QUICK_COMMAND if args.quick else COMMAND
    cold, cold_alone, warm, imports, outputs, rows = [], [], [], [], [], []
    cold_cpu, cold_alone_cpu, warm_cpu = [], [], []
    for k in range(repeat):
        with tempfile.TemporaryDirectory(prefix="fastmem-numba-cache-") as cache:
            env = dict(os.environ) if args.quick else {**os.environ, "NUMBA_CACHE_DIR": cache}
            t_cold, c_cold, out = _timed(command, env)
            t_warm, c_warm, _ = _timed(command, env)
            t_import, _, _ = _timed(["-c", "import fastmem"], env)
        with tempfile.TemporaryDirectory(prefix="fastmem-numba-cache-") as cache:
            env = {**os.environ, "FASTMEM_COMPILE_HELPER": "0"}
            if not args.quick:
                env["NUMBA_CACHE_DIR"] = cache
            t_alone, c_alone, _ = _timed(command, env)
        rows.append(
            {
                "repetition": k,
                "cold_s": t_cold,
                "cold_cpu_s": c_cold,
                "cold_no_helper_s": t_alone,
                "cold_no_helper_cpu_s": c_alone,
                "warm_s": t_warm,
                "warm_cpu_s": c_warm,
                "import_s": t_import,
            }
        )
        cold.append(t_cold)
        cold_cpu.append(c_cold)
        cold_alone_cpu.append(c_alone)
        warm_cpu.append(c_warm)
        cold_alone.append(t_alone)
        warm.append(t_warm)
        imports.append(t_import)
        outputs.append(out)
        progress(
            f"coldstart {k + 1}/{repeat}: cold {t_cold:.1f} s wall, {c_cold:.1f} s CPU "
            f"(without the helper {t_alone:.1f} s, {c_alone:.1f} s CPU), "
            f"warm {t_warm:.2f} s, {c_warm:.2f} s CPU"
        )
    with tempfile.TemporaryDirectory(prefix="fastmem-numba-cache-") as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        res = subprocess.run(
            [
                sys.executable,
                "-m",
                "bench.coldstart",
                "--worker",
                *(["--quick"] if args.quick else []),
            ],
            env=env,
            stdout=subprocess.PIPE,
            text=True,
            check=True,
        )
        compiles = json.loads(res.stdout.strip().splitlines()[-1])
    top = {}
    for row in compiles["compiles"]:
        top[row["kernel"]] = top.get(row["kernel"], 0.0) + row["seconds"]
    for name, sec in sorted(top.items(), key=lambda kv: -kv[1])[:8]:
        progress(f"  {sec:6.2f} s  {name} (inclusive, all specialisations)")
    payload = {
        "description": __doc__.split("\n\n")[0],
        "parameters": {
            "command": "python " + " ".join(command),
            "empty_cache": not args.quick,
            "repeat": repeat,
        },
        "rows": rows,
        "command": "python " + " ".join(command),
        "cold_seconds": cold,
        "warm_seconds": warm,
        "import_seconds": imports,
        "cold": summary(cold),
        "cold_no_helper": summary(cold_alone),
        "cold_cpu": summary(cold_cpu),
        "cold_no_helper_cpu": summary(cold_alone_cpu),
        "warm_cpu": summary(warm_cpu),
        "warm": summary(warm),
        "import": summary(imports),
        "first_output": outputs[0],
        "compile_events": compiles["compiles"],
        "compile_solve_seconds": compiles["solve_seconds"],
        "kernel_seconds_inclusive": dict(sorted(top.items(), key=lambda kv: -kv[1])),
    }
    finish("coldstart", payload, args.quick)
    return 0


if __name__ == "__main__":
    sys.exit(main())
