"""Closed-loop rollouts: compiled and certified by the judge, against the per-step judge.

``hybridoc.workflows.policies.validate_policy`` of one MLP policy file (the form
``hybridoc.workflows.training.mlp_policy`` trains: 2 hidden layers of 32 tanh units, seed 0,
saved with ``save_mlp_policy``) on ``--samples`` draws of the single-collision scene with
ball 2's start drawn uniformly within +-0.3 in each coordinate (the issue's distribution),
side by side in one run:

* ``compiled``: ``rollouts="compiled"``, the policy compiled into the closed-loop step, each
  chunk of 25 draws one call of the C code, every rollout certified by the judge (its
  open-loop evaluation of the rollout's controls). The first run starts from an empty
  C-code cache (``cold``: the compilation is in its time); the others reuse the compiled
  rollout that the first built in this process (``warm``). The set-up a new process pays
  with the C code already cached (build the graph, load the library) is timed apart.
* ``judge``: ``rollouts="judge"``, the per-step judge calling the same policy at every grid
  time (the path every policy took before).

Times are the whole ``validate_policy`` call without the references (they are given, see
below): wall and CPU (this process and its pool workers), median of ``--repeats``. The
target (issue #18): 1000 rollouts in under 10 s wall on 2 cores. The costs of the two paths
are compared draw by draw (relative difference, target <= 1e-9).

References are not what is timed: by default the dataset given to ``validate_policy`` has
its rows marked as not solved (the rollouts do not depend on them, and 1000 references
take a minute or more); ``--dataset DIR`` uses the references of ``hybridoc dataset`` (same
scene and seed) and prints the policy's gap to them as well.

Run it by path::

    .venv/bin/python benchmarks/bench_rollouts.py [--samples 1000] [--repeats 3] [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from _timing import machine_line, verdict

from hybridoc.problems import load_scene
from hybridoc.problems.scene import DiscSpread, Distribution, Spread
from hybridoc.workflows.datasets import Dataset, load_dataset, usable_cores
from hybridoc.workflows.policies import validate_policy
from hybridoc.workflows.policy_format import save_mlp_policy

TARGET_S = 10.0


def cpu_seconds() -> float:
    """User + system CPU seconds of this process and its finished children (the pool)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def scene_with_distribution() -> Any:
    return dataclasses.replace(
        load_scene("single-collision"),
        name="single-collision-dist",
        distribution=Distribution(
            discs=(DiscSpread("ball2", position=Spread("uniform", (0.3, 0.3))),)
        ),
    )


def unsolved_references(scene: Any, n: int, folder: Path) -> Dataset:
    """A dataset of the first ``n`` draws whose rows say that no reference was solved."""
    assert scene.distribution is not None
    seed = scene.distribution.seed
    x0 = np.array([scene.distribution.draw(scene, i, seed).initial_state() for i in range(n)])
    cols = {
        "index": np.arange(n), "x0": x0, "targets": np.zeros((n, 1, 2)),
        "status": np.array(["not-solved"] * n), "cost": np.full(n, np.nan),
        "message": np.array(["not solved by the benchmark"] * n),
        "sequence": np.array([""] * n),
    }  # fmt: skip
    return Dataset(folder, cols, {"settings": {"scene": scene.to_toml(), "seed": seed}})


def timed(scene: Any, policy: str, n: int, refs: Any, workers: int, mode: str) -> dict[str, Any]:
    t0, c0 = time.perf_counter(), cpu_seconds()
    rep = validate_policy(
        scene, policy, n, dataset=refs, workers=workers, progress=False, rollouts=mode
    )
    return {
        "wall": time.perf_counter() - t0,
        "cpu": cpu_seconds() - c0,
        "report": rep,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--dataset", type=Path, default=None, help="references to compare with")
    parser.add_argument("--quick", action="store_true", help="50 samples, 1 repeat: a smoke run")
    args = parser.parse_args(argv)
    n = 50 if args.quick else args.samples
    repeats = 1 if args.quick else args.repeats
    workers = args.workers or usable_cores()
    print(machine_line())
    from hybridoc.workflows.training import mlp_policy

    scene = scene_with_distribution()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        os.environ["HYBRIDOC_CACHE"] = str(folder / "cache")  # cold: an empty C-code cache
        policy = str(save_mlp_policy(mlp_policy(scene, hidden=32, layers=2, seed=0),
                                     folder / "policy.json"))  # fmt: skip
        refs = load_dataset(args.dataset) if args.dataset else unsolved_references(scene, n, folder)
        runs: dict[str, list[dict[str, Any]]] = {"compiled": [], "judge": []}
        for r in range(repeats):
            for mode in ("compiled", "judge"):
                print(f"run {r + 1}/{repeats}: {mode} ...", file=sys.stderr, flush=True)
                runs[mode].append(timed(scene, policy, n, refs, workers, mode))
        # what a new process pays before its first rollout, the C code already in the cache
        from hybridoc.workflows.policy_format import load_mlp_policy
        from hybridoc.workflows.rollouts import CompiledRollouts

        t0 = time.perf_counter()
        built = CompiledRollouts(scene.to_ocp(), load_mlp_policy(policy))
        build_s = time.perf_counter() - t0
    comp, judge = runs["compiled"], runs["judge"]
    scale = 1000 / n
    med = {m: (statistics.median(x["wall"] for x in v), statistics.median(x["cpu"] for x in v))
           for m, v in runs.items()}  # fmt: skip
    warm = comp[1:] or comp
    med["compiled, warm"] = (statistics.median(x["wall"] for x in warm),
                             statistics.median(x["cpu"] for x in warm))  # fmt: skip
    print(f"{n} closed-loop rollouts of single-collision draws (ball2 +-0.3), MLP 2x32 tanh, "
          f"{workers} workers, median of {repeats}")  # fmt: skip
    print(f"{'path':<16} {'wall s':>8} {'cpu s':>8} {'per 1000 wall':>14} {'target':>8}  verdict")
    rows = [("judge", med["judge"]), ("compiled, cold", (comp[0]["wall"], comp[0]["cpu"])),
            ("compiled, warm", med["compiled, warm"])]  # fmt: skip
    for name, (wall, cpu) in rows:
        ok = None if name == "judge" else wall * scale < TARGET_S
        print(f"{name:<16} {wall:8.2f} {cpu:8.2f} {wall * scale:14.2f} {'< 10 s':>8}  "
              f"{verdict(ok)}")  # fmt: skip
    print(f"set-up of the compiled rollout in a new process (C code in the cache, loaded: "
          f"{built.compiled}): {build_s:.2f} s; the warm runs reuse it")  # fmt: skip
    jw, jc = med["judge"]
    cw, cc = med["compiled, warm"]
    print(f"ratio judge / compiled (warm): wall {jw / cw:.1f}x, cpu {jc / cc:.1f}x")
    a = comp[-1]["report"].columns["policy_cost"]
    b = judge[-1]["report"].columns["policy_cost"]
    ok_rows = np.isfinite(a) & np.isfinite(b)
    rel = np.abs(a - b)[ok_rows] / np.abs(b[ok_rows])
    roll = comp[-1]["report"].summary["rollouts"]
    print(f"compiled rollouts certified: {roll['compiled']}, per-step judge (not certified): "
          f"{roll['fallback']} {roll['fallback_kinds'] or ''}; failed in both: "
          f"{int(np.sum(~ok_rows))}")  # fmt: skip
    worst = float(rel.max()) if rel.size else float("nan")
    print(f"cost, compiled vs per-step judge: largest relative difference {worst:.3g} "
          f"(target <= 1e-9): {verdict(bool(worst <= 1e-9))}")  # fmt: skip
    s = comp[-1]["report"].summary
    if s["compared"]:
        print(f"gap to the references: median {s['rel_gap_median']:.4g} (relative), "
              f"{s['compared']} compared")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
