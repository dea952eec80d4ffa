"""Timing of the multi-phase direct transcription (``hybridoc.solvers.transcription``).

For each scene: the sequence found, the cost, its relative gap to the HMP reference, the
largest event-time difference, and the median wall time over ``--runs`` solves after one
warm-up solve (the NLP is built once per problem and sequence, then cached):

* ``sequence ms``: ``solve_dt`` with the explicit sequence (IPOPT + re-simulation check);
* ``discover ms``: ``solve_dt`` without a sequence (candidates from the initial guess);
* ``discrete s``: ``solve_discrete`` (the exact N-step problem of gradient descent), once.

Target (issue 5): under 2 s per solve on the paper problems. Run:
``.venv/bin/python benchmarks/bench_transcription.py [--runs 5] [--discrete] [SCENE ...]``.
"""

from __future__ import annotations

import argparse
import time

from _timing import median_ms

from hybridoc.cli_util import format_table
from hybridoc.problems import load_scene
from hybridoc.reference import solve_reference
from hybridoc.solvers.transcription import solve_dt


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenes", nargs="*", default=["single-collision", "multiple-collision"])
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--discrete", action="store_true", help="also time solve_discrete")
    args = p.parse_args()
    rows = []
    for name in args.scenes:
        scene = load_scene(name)
        ref = solve_reference(scene)
        sol = solve_dt(scene)  # warm-up (builds and caches the NLPs)
        seq = sol.info["sequence"]
        gap = (sol.cost - ref.cost) / ref.cost
        dte = max(
            (
                abs(a - b)
                for a, b in zip(sol.info["event_times"], ref.info["event_times"], strict=True)
            ),
            default=0.0,
        )
        t_seq = median_ms(lambda sc=scene, sq=seq: solve_dt(sc, sequence=sq), args.runs)
        t_disc = median_ms(lambda sc=scene: solve_dt(sc), args.runs)
        row = [name, " ".join(seq) or "-", f"{sol.cost:.10f}", f"{gap:+.1e}", f"{dte:.1e}"]
        row += [f"{t_seq:.0f}", f"{t_disc:.0f}"]
        if args.discrete:
            from hybridoc.solvers.discrete_transcription import solve_discrete

            t0 = time.perf_counter()
            d = solve_discrete(scene)
            row += [f"{time.perf_counter() - t0:.1f}", f"{d.info['discrete_loss']:.10f}"]
        rows.append(row)
    headers = ["scene", "sequence", "cost", "gap", "max dt_ev", "sequence ms", "discover ms"]
    if args.discrete:
        headers += ["discrete s", "discrete loss"]
    print(format_table(headers, rows))


if __name__ == "__main__":
    main()
