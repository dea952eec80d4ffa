"""The judge on scenes of many discs: all pairs against the broad phase (issue #32).

Each scene is a square grid of discs 1.2 apart (radius 0.5, gaps of 0.2) in a box of four
walls, with seeded random velocities of about 1, so that neighbours collide many times over
the horizon, and one actuated disc pushed by its initial control. Every (scene, mode) runs
in a fresh process: the scene's compile (its guards; the same in both modes) and the judge
(its kernels and one evaluation), each in CPU seconds, the process's peak memory, and the
events and cost of the evaluation. ``all pairs`` samples every guard on every grid interval
(:data:`hybridoc.broadphase.THRESHOLD` raised out of reach); ``broad phase`` samples only
the guards whose bodies' swept boxes meet (:mod:`hybridoc.broadphase`). The last column
says whether both found the same events, and the cost's relative difference (the crossing
search examines fewer guards, so a root can be polished from another bracket: last bits).

Run it by path::

    .venv/bin/python benchmarks/bench_judge_discs.py [--discs 20 50 100] [--steps 200]

202 discs take about 13 minutes of CPU and 3.8 GB all pairs (8 s and 1.5 GB through the
broad phase, after a 46 s compile); ``--discs 202`` runs them.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from _timing import machine_line, run_process

MODES = ("all pairs", "broad phase")


def scene_dict(n: int, steps: int, seed: int = 0) -> dict:
    """A grid of ``n`` discs 1.2 apart in a box, random velocities, one actuated disc."""
    import numpy as np

    rng = np.random.default_rng(seed)
    k = math.ceil(math.sqrt(n))
    discs = []
    for i in range(n):
        disc = {
            "name": f"d{i}",
            "position": [1.2 * (i % k), 1.2 * (i // k)],
            "radius": 0.5,
            "velocity": [float(x) for x in rng.normal(0.0, 0.7, 2)],
        }
        if i == 0:
            disc.update(actuated=True, target=[0.0, 0.0], initial_control=[3.0, 2.0])
        discs.append(disc)
    side = 1.2 * (k - 1)
    walls = [
        {"name": "floor", "point": [0.0, -0.7], "normal": [0.0, 1.0]},
        {"name": "top", "point": [0.0, side + 0.7], "normal": [0.0, -1.0]},
        {"name": "left", "point": [-0.7, 0.0], "normal": [1.0, 0.0]},
        {"name": "right", "point": [side + 0.7, 0.0], "normal": [-1.0, 0.0]},
    ]
    return {
        "name": f"grid{n}",
        "horizon": 1.0,
        "steps": steps,
        "control_weight": 0.01,
        "restitution": 0.9,
        "discs": discs,
        "walls": walls,
    }


def child(n: int, steps: int, mode: str) -> None:
    """One (scene, mode) in this process; prints a JSON line."""
    from hybridoc import broadphase, evaluate, resources
    from hybridoc.kernels import kernels
    from hybridoc.problems import Scene

    broadphase.THRESHOLD = 10**12 if mode == "all pairs" else broadphase.THRESHOLD
    t0 = time.process_time()
    with resources.allowing_large():
        ocp = Scene.from_dict(scene_dict(n, steps)).to_ocp()
    t1 = time.process_time()
    broad = kernels(ocp).broad is not None
    ev = evaluate(ocp)
    t2 = time.process_time()
    events = [(e.time, e.guard) for e in ev.events]
    print(
        json.dumps(
            {
                "guards": len(ocp.guards),
                "compile": t1 - t0,
                "judge": t2 - t1,
                "broad": broad,
                "events": events,
                "cost": ev.cost,
            }
        )
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--discs", type=int, nargs="+", default=[20, 50, 100])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--timeout", type=float, default=3600.0)
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(int(args.child[0]), int(args.child[1]), args.child[2])
        return 0
    print(machine_line())
    head = (
        f"{'discs':>5} {'guards':>7} {'mode':<11} {'compile s':>9} {'judge s':>8} "
        f"{'peak MiB':>8} {'events':>6}  agree"
    )
    print(head)
    print("-" * len(head))
    me = str(Path(__file__).resolve())
    for n in args.discs:
        out = {}
        for mode in MODES:
            cmd = [sys.executable, me, "--child", str(n), str(args.steps), mode]
            res = run_process(cmd, timeout=args.timeout)
            if res.returncode != 0 or res.timed_out:
                tail = (res.stderr.strip().splitlines() or ["?"])[-1]
                print(f"{n:>5} {'':>7} {mode:<11} failed after {res.cpu_s:.1f} s CPU: {tail}")
                continue
            r = json.loads(res.stdout.strip().splitlines()[-1])
            out[mode] = r
            agree = ""
            if mode == MODES[1] and MODES[0] in out:
                a = out[MODES[0]]
                same = [g for _, g in a["events"]] == [g for _, g in r["events"]]
                rel = abs(a["cost"] - r["cost"]) / max(abs(a["cost"]), 1e-300)
                agree = f"{'same events' if same else 'EVENTS DIFFER'}, cost rel. diff {rel:.1e}"
            print(
                f"{n:>5} {r['guards']:>7} {mode:<11} {r['compile']:>9.1f} {r['judge']:>8.2f} "
                f"{res.maxrss_mb:>8.0f} {len(r['events']):>6}  {agree}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
