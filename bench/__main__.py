"""Run the whole benchmark suite: ``python -m bench [--quick] [--results DIR] [--only NAME ...]``.

Each benchmark runs as ``python -m bench.<name>`` in its own process, one
after the other (never two at once: they measure time), with ``--quick`` and
``--results`` passed through.  A summary of the key numbers of every result
file follows (``bench.report``).  The exit code is non-zero when a benchmark failed.
"""

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

from bench.report import BENCHMARKS, summary_lines


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="tiny sizes: checks the machinery")
    p.add_argument("--results", type=Path, default=None, help="folder for JSON/PNG output")
    p.add_argument("--only", nargs="*", choices=BENCHMARKS, default=None)
    p.add_argument("--skip", nargs="*", choices=BENCHMARKS, default=())
    p.add_argument("--list", action="store_true", help="print the benchmark names and exit")
    args = p.parse_args(argv)
    if args.list:
        print("\n".join(BENCHMARKS))
        return 0
    names = [b for b in (args.only or BENCHMARKS) if b not in args.skip]
    extra = ["--quick"] if args.quick else []
    env = dict(os.environ)
    if args.results is not None:
        extra += ["--results", str(args.results.resolve())]
    status = []
    for name in names:
        sys.stderr.write(f"\n=== bench.{name} {' '.join(extra)}\n")
        sys.stderr.flush()
        t0 = time.perf_counter()
        rc = subprocess.run([sys.executable, "-m", f"bench.{name}", *extra], env=env).returncode
        status.append((name, rc, time.perf_counter() - t0))
    print("\nbenchmark        exit   seconds")
    for name, rc, sec in status:
        print(f"{name:15s} {rc:5d} {sec:9.1f}")
    print("\nkey numbers" + (" (quick)" if args.quick else "") + ":")
    for line in summary_lines(args.quick, args.results):
        print("  " + line)
    return 0 if all(rc == 0 for _, rc, _ in status) else 1


if __name__ == "__main__":
    sys.exit(main())
