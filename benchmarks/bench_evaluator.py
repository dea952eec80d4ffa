"""Timings of the event-exact evaluator and its exact gradient on every built-in scene.

For each built-in at its initial guess: one warm-up call (it compiles the CasADi functions
the evaluator caches per problem), then ``--repeats`` timed calls of
:func:`hybridoc.evaluate` and of :func:`hybridoc.gradient`. Prints median, min and max
wall-clock time per call, the number of events and the grid size N. A gradient call
includes its forward evaluation.

Run it by path (``make bench`` does); running a script by path imports the installed
package even from the repository root::

    .venv/bin/python benchmarks/bench_evaluator.py [--repeats 20] [--scene NAME ...]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any

import hybridoc


def _time_calls(fn: Callable[[], Any], repeats: int) -> list[float]:
    fn()  # warm-up: compiles and caches the per-problem CasADi functions
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def _ms(seconds: float) -> str:
    return f"{1e3 * seconds:9.2f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20, help="timed runs per entry")
    parser.add_argument(
        "--scene",
        action="append",
        help="scene name or TOML path (repeatable; default: every built-in)",
    )
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    try:
        scenes = [hybridoc.load_scene(name) for name in args.scene or hybridoc.builtin_names()]
    except hybridoc.HybridocError as exc:
        print(f"bench_evaluator: error: {exc}", file=sys.stderr)
        return 2

    header = (
        f"{'scene':<20} {'what':<9} {'N':>5} {'events':>6} "
        f"{'median ms':>9} {'min ms':>9} {'max ms':>9} {'ms/step':>8}"
    )
    print(
        f"hybridoc {hybridoc.__version__}: evaluator timings at the initial guess, "
        f"{args.repeats} runs after 1 warm-up"
    )
    print(header)
    print("-" * len(header))
    for scene in scenes:
        controls = scene.initial_controls()
        n_events = len(hybridoc.evaluate(scene, controls).events)
        for what, fn in (("evaluate", hybridoc.evaluate), ("gradient", hybridoc.gradient)):
            times = _time_calls(lambda f=fn, s=scene, u=controls: f(s, u), args.repeats)
            med = statistics.median(times)
            print(
                f"{scene.name:<20} {what:<9} {scene.steps:>5} {n_events:>6} "
                f"{_ms(med)} {_ms(min(times))} {_ms(max(times))} "
                f"{1e3 * med / scene.steps:8.4f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
