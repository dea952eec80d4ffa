"""Timing of the multi-phase direct transcription (``hybridoc.solvers.transcription``).

One table, one row per problem (default: both paper problems and every library problem):
the sequence found from the initial guess, the cost, its relative gap to the HMP reference,
the largest event-time difference, and the median wall time over ``--runs`` solves after one
warm-up solve (the NLP is built once per problem and sequence, then cached):

* ``sequence ms``: ``solve_dt`` with the explicit sequence (IPOPT + re-simulation check);
* ``discover ms``: ``solve_dt`` without a sequence (candidates from the initial guess);
* with ``--discrete``, for disc scenes: ``solve_discrete`` (the exact N-step problem of
  gradient descent), once, and its discrete loss.

Target: under 2 s per solve (``discover ms``) on the paper problems. Run it by path::

    .venv/bin/python benchmarks/bench_transcription.py [--quick] [--runs 5] [--discrete] [PROBLEM]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

from _timing import fmt_ms, machine_line, time_calls, verdict

from hybridoc.cli._util import format_table
from hybridoc.problems import Scene, library_names, load_problem
from hybridoc.reference import solve_reference
from hybridoc.solvers.transcription import solve_dt

PAPER = ("single-collision", "multiple-collision")
TARGET_S = 2.0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("problems", nargs="*", help="default: the paper problems and the library")
    p.add_argument("--runs", type=int, default=5, help="timed solves (default 5)")
    p.add_argument("--discrete", action="store_true", help="also time solve_discrete")
    p.add_argument("--quick", action="store_true", help="one timed solve each: a smoke run")
    args = p.parse_args(argv)
    if args.quick:
        args.runs = 1
    if args.runs < 1:
        p.error("--runs must be >= 1")
    names = args.problems or [*PAPER, *library_names()]

    print(machine_line(), flush=True)
    print(f"direct transcription: median of {args.runs} solves after 1 warm-up")
    rows = []
    for name in names:
        problem = load_problem(name)
        ref = solve_reference(problem)
        sol = solve_dt(problem)  # warm-up (builds and caches the NLPs)
        seq = list(sol.info["sequence"])
        gap = (sol.cost - ref.cost) / abs(ref.cost)
        dt_times, ref_times = sol.info["event_times"], ref.info["event_times"]
        dte = (
            max((abs(a - b) for a, b in zip(dt_times, ref_times, strict=True)), default=0.0)
            if len(dt_times) == len(ref_times)
            else float("nan")
        )
        t_seq = statistics.median(
            time_calls(lambda pr=problem, sq=seq: solve_dt(pr, sequence=sq), args.runs, 0)
        )
        t_disc = statistics.median(time_calls(lambda pr=problem: solve_dt(pr), args.runs, 0))
        target_ok = t_disc < TARGET_S if name in PAPER else None
        row = [
            name,
            ",".join(seq) or "(none)",
            f"{sol.cost:.12f}",
            f"{gap:+.1e}",
            f"{dte:.1e}",
            fmt_ms(t_seq),
            fmt_ms(t_disc),
            f"< {1e3 * TARGET_S:.0f} ms" if target_ok is not None else "-",
            verdict(target_ok),
        ]
        if args.discrete:
            if isinstance(problem, Scene):
                from hybridoc.solvers.discrete_transcription import solve_discrete

                t0 = time.perf_counter()
                d = solve_discrete(problem)
                row += [f"{time.perf_counter() - t0:.1f}", f"{d.info['discrete_loss']:.10f}"]
            else:
                row += ["-", "-"]
        rows.append(row)
        print(f"  done {name}", file=sys.stderr, flush=True)
    headers = [
        "problem",
        "sequence",
        "cost",
        "gap to ref",
        "max dt_event",
        "sequence ms",
        "discover ms",
        "target",
        "result",
    ]
    if args.discrete:
        headers += ["discrete s", "discrete loss"]
    right = [False, False, True, True, True, True, True, False, False] + [True] * (len(headers) - 9)
    print(format_table(headers, rows, right=right))
    print("gap to ref: cost / HMP reference cost - 1; max dt_event: largest event-time difference")
    return 0


if __name__ == "__main__":
    sys.exit(main())
