"""Run the stress matrix and print a Markdown table.

Usage (from the repository root)::

    python -m tests.stress.report                 # fast subset
    python -m tests.stress.report --mode full     # bigger meshes, every method
    python -m tests.stress.report -k mu= -k lshape    # only cases whose name contains a pattern

Columns: case, solver variant, outcome (converged / not converged with the
stop reason / error class), Newton steps, safeguard use ("-" when the solver
does not record it), eta, true energy error and effectivity eta/error (where
an exact solution is known), solve time (including the estimate), and the
check verdict (``ok``, ``xfail`` for a known breakage, or the problems).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

from .cases import CASES, matrix
from .checks import run
from .known import known_breakage


def _fmt(x, spec=".3e"):
    return "-" if x is None else format(x, spec)


def row(rec) -> str:
    """One Markdown table row of a :class:`~tests.stress.checks.Record`."""
    if rec.skipped:
        verdict = f"skipped: {rec.skipped}"
    elif rec.problems:
        known = known_breakage(rec.case, rec.variant, rec.mode)
        verdict = ("**xfail** " if known else "**FAIL** ") + "; ".join(rec.problems)
    else:
        known = known_breakage(rec.case, rec.variant, rec.mode)
        verdict = "ok (XPASS: known breakage not seen)" if known else "ok"
    eff = rec.effectivity
    cells = [
        rec.case,
        rec.variant,
        rec.outcome,
        "-" if rec.n_newton is None else str(rec.n_newton),
        rec.safeguard,
        _fmt(rec.eta),
        _fmt(rec.error),
        _fmt(eff, ".3f"),
        _fmt(rec.seconds if rec.seconds == rec.seconds else None, ".2f"),
        verdict.replace("|", "/"),
    ]
    return "| " + " | ".join(cells) + " |"


HEADER = (
    "| case | variant | outcome | Newton | safeguard | eta | error | eff | time [s] | checks |\n"
    "|---|---|---|---|---|---|---|---|---|---|"
)


def main(argv=None) -> int:
    """Entry point; returns the number of unexpected failures (0: all ok or known)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", choices=("fast", "full"), default="fast")
    parser.add_argument("-k", action="append", default=[], help="case name substring")
    parser.add_argument("--verbose", action="store_true", help="show fastmem log warnings")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING if args.verbose else logging.CRITICAL)
    names = {c.name for c in CASES}
    pairs = [(c, v) for c, v in matrix(args.mode) if not args.k or any(k in c.name for k in args.k)]
    if not pairs:
        print(f"no case matches {args.k}; cases: {sorted(names)}", file=sys.stderr)
        return 1
    print(f"## fastmem stress matrix, mode {args.mode} ({len(pairs)} runs)\n")
    print(HEADER, flush=True)
    t0 = time.perf_counter()
    unexpected = 0
    for case, variant in pairs:
        rec = run(case, variant, args.mode)
        known = known_breakage(case.name, variant, args.mode)
        if bool(rec.problems) != bool(known) and not rec.skipped:
            unexpected += 1
        print(row(rec), flush=True)
    print(f"\nTotal wall time {time.perf_counter() - t0:.1f} s; unexpected results: {unexpected}")
    return min(unexpected, 100)


if __name__ == "__main__":
    sys.exit(main())
