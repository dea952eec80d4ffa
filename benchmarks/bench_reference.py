"""Timing of the HMP reference (``hybridoc.reference.solve_reference``).

For each built-in scene: the discovered sequence, its cost, HMP residual and the median
wall time over ``--runs`` solves after one warm-up solve (compiled CasADi functions and the
initial-guess evaluation are cached per problem):

* ``shoot ms``: the explicit sequence without re-simulation (IPOPT + Newton + sampling);
* ``verified ms``: the explicit sequence with the built-in re-simulation by
  :func:`hybridoc.evaluate_callable`;
* ``discover ms``: the full call without a sequence (candidates, solves, verification).

Run: ``.venv/bin/python benchmarks/bench_reference.py [--runs 20] [SCENE ...]``.
"""

from __future__ import annotations

import argparse

from _timing import median_ms

import hybridoc
from hybridoc.cli_util import format_table
from hybridoc.reference import solve_reference


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scenes", nargs="*", default=hybridoc.builtin_names())
    p.add_argument("--runs", type=int, default=20)
    p.add_argument("--discover-runs", type=int, default=3)
    args = p.parse_args()
    rows = []
    for name in args.scenes:
        scene = hybridoc.load_scene(name)
        sol = solve_reference(scene)  # warm-up, discovery
        seq = sol.info["sequence"]
        shoot = median_ms(
            lambda sc=scene, sq=seq: solve_reference(sc, sequence=sq, verify=False), args.runs
        )
        verified = median_ms(
            lambda sc=scene, sq=seq: solve_reference(sc, sequence=sq), max(3, args.runs // 4)
        )
        discover = median_ms(lambda sc=scene: solve_reference(sc), args.discover_runs)
        rows.append(
            [
                name,
                ",".join(seq) or "(none)",
                f"{sol.cost:.12f}",
                f"{sol.info['residual']:.1e}",
                sol.info["newton_iterations"],
                f"{shoot:.1f}",
                f"{verified:.0f}",
                f"{discover:.0f}",
            ]
        )
        print(f"done {name}", flush=True)
    print()
    print(
        format_table(
            [
                "scene",
                "sequence",
                "cost",
                "residual",
                "newton",
                "shoot ms",
                "verified ms",
                "discover ms",
            ],
            rows,
            right=[False, False, True, True, True, True, True, True],
        )
    )


if __name__ == "__main__":
    main()
