"""Start-up time of the ``hybridoc`` command and of ``import hybridoc``, as whole processes.

Each command runs once untimed (to warm the file cache), then ``--runs`` times; one table
with the median, min and max wall time, the median CPU time (user + system, less sensitive
to other load) and the target: ``hybridoc --help`` < 250 ms (issue #18). ``python -c pass``
is the interpreter's own start-up, the floor under the others. Exit status 1 when a command
fails, else 0 whatever the verdicts.

Run it by path (running a script by path imports the installed package even from the
repository root)::

    .venv/bin/python benchmarks/bench_startup.py [--quick] [--runs 10]
"""

from __future__ import annotations

import argparse
import statistics
import sys

from _timing import fmt_ms, hybridoc_command, machine_line, run_process, verdict

from hybridoc.cli._util import format_table

HELP_TARGET_S = 0.25
"""``hybridoc --help`` on a 2-core machine (issue #18)."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10, help="timed runs of each (default 10)")
    parser.add_argument("--quick", action="store_true", help="3 timed runs: a smoke run")
    args = parser.parse_args(argv)
    if args.quick:
        args.runs = 3
    if args.runs < 1:
        parser.error("--runs must be >= 1")

    py = [sys.executable, "-c"]
    commands = [
        ("python -c pass", [*py, "pass"], None),
        ("python -c 'import hybridoc'", [*py, "import hybridoc"], None),
        ("hybridoc --help", [*hybridoc_command(), "--help"], HELP_TARGET_S),
        ("hybridoc --version", [*hybridoc_command(), "--version"], None),
    ]
    print(machine_line(), flush=True)
    print(f"start-up, whole processes: median of {args.runs} runs after 1 warm-up")
    rows = []
    failed = False
    for label, cmd, target in commands:
        print(f"  {label} ...", file=sys.stderr, flush=True)
        runs = [run_process(cmd, timeout=60) for _ in range(1 + args.runs)][1:]
        bad = next((r for r in runs if r.returncode != 0 or r.timed_out), None)
        if bad is not None:
            print(f"bench_startup: {label} failed: {bad.stderr.strip()}", file=sys.stderr)
            failed = True
        walls = [r.wall_s for r in runs]
        med = statistics.median(walls)
        rows.append(
            [
                label,
                fmt_ms(med),
                fmt_ms(min(walls)),
                fmt_ms(max(walls)),
                fmt_ms(statistics.median(r.cpu_s for r in runs)),
                "-" if target is None else f"< {1e3 * target:.0f} ms",
                verdict(None if target is None else med < target and bad is None),
            ]
        )
    print(
        format_table(
            ["command", "median ms", "min ms", "max ms", "cpu ms", "target", "result"],
            rows,
            right=[False, True, True, True, True, True, False],
        )
    )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
