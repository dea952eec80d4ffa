"""Timings of reference datasets and closed-loop policy validation over a distribution.

The single-collision scene with ball 2's start drawn uniformly within +-0.3 in each
coordinate (the issue's distribution): ``hybridoc.workflows.datasets.make_dataset`` for
``--samples`` draws (nominal solve included), then
``hybridoc.workflows.policies.validate_policy`` of a simple Python feedback policy on the
same draws (rollouts only; the references are reused).
Targets on 2 cores: 1000 references in under 60 s, 1000 rollouts in under 10 s.

Where a reference's time goes (``--split`` draws, default 40, solved one after another in
this process after the dataset, with the same warm start as the dataset's workers): the
warm start's Newton (with continuation) and refinement, the judge's verification of the
extremal (``judged_reference``: the re-simulation of ``u(t)`` and its comparison), the
judge's evaluation of the initial guess (the screen against a cheaper guess), and the rest
(drawing the problem, the lower-bound screens, the record).

Run it by path::

    .venv/bin/python benchmarks/bench_dataset.py [--samples 1000] [--workers K] [--quick]
        [--split 40] [--skip-rollouts]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from _timing import machine_line

from hybridoc.problems import load_scene
from hybridoc.problems.scene import DiscSpread, Distribution, Spread
from hybridoc.workflows.datasets import make_dataset, usable_cores
from hybridoc.workflows.policies import validate_policy

POLICY = """
import numpy as np

def pd(t, s):
    return np.array([2.0 * (s[2] - s[0]) + 1.0, 2.0 * (s[3] - s[1]) + 2.0])
"""


def cpu_seconds() -> float:
    """User + system CPU seconds of this process and its finished children (the pool)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def split(scene: Any, ds: Any, draws: int) -> dict[str, float]:
    """Median milliseconds per draw of each stage of the warm-started reference (module
    notes), over ``draws`` draws solved in this process."""
    import hybridoc.reference.warm as warm
    from hybridoc.workflows import datasets as D

    spent: dict[str, float] = defaultdict(float)

    def timed(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def wrapper(*a: Any, **k: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent[name] += time.perf_counter() - t0

        return wrapper

    names = {
        "_newton_with_continuation": "newton",
        "refine": "refine",
        "judged_reference": "verify",
        "evaluate": "guess",
    }
    saved = {attr: getattr(warm, attr) for attr in names}
    st = ds.manifest["settings"]
    # the workers' task specification, rebuilt from the dataset's manifest
    spec = {
        **D.source_draws(scene, scene, st["samples"], st["seed"]),
        **{k: st[k] for k in ("seed", "tol", "full")},
        "nominal": ds.manifest.get("nominal"),
    }
    ctx = D.draw_context(spec)
    rows: dict[str, list[float]] = defaultdict(list)
    try:
        for attr, name in names.items():
            setattr(warm, attr, timed(name, saved[attr]))
        for i in range(draws):
            spent.clear()
            t0 = time.perf_counter()
            D._solve_draw(ctx, i)  # noqa: SLF001  (the worker's own per-draw function)
            total = time.perf_counter() - t0
            for name in names.values():
                rows[name].append(1e3 * spent.get(name, 0.0))
            rows["rest"].append(1e3 * (total - sum(spent.values())))
            rows["total"].append(1e3 * total)
    finally:
        for attr, fn in saved.items():
            setattr(warm, attr, fn)
    return {k: statistics.median(v) for k, v in rows.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--quick", action="store_true", help="50 samples: a smoke run")
    parser.add_argument("--split", type=int, default=40, help="draws timed stage by stage")
    parser.add_argument("--skip-rollouts", action="store_true", help="references only")
    args = parser.parse_args(argv)
    n = 50 if args.quick else args.samples
    workers = args.workers or usable_cores()
    print(machine_line())
    scene = dataclasses.replace(
        load_scene("single-collision"),
        name="single-collision-dist",
        distribution=Distribution(
            discs=(DiscSpread("ball2", position=Spread("uniform", (0.3, 0.3))),)
        ),
    )
    with tempfile.TemporaryDirectory() as tmp:
        t0, c0 = time.perf_counter(), cpu_seconds()
        ds = make_dataset(scene, n, Path(tmp) / "refs", workers=workers, progress=False)
        t_refs, c_refs = time.perf_counter() - t0, cpu_seconds() - c0
        parts = split(scene, ds, min(args.split, n)) if args.split > 0 else {}
        rep = None
        if not args.skip_rollouts:
            (Path(tmp) / "pol.py").write_text(POLICY)
            t0, c0 = time.perf_counter(), cpu_seconds()
            rep = validate_policy(
                scene, f"{tmp}/pol.py:pd", n, dataset=ds, workers=workers, progress=False
            )
            t_roll, c_roll = time.perf_counter() - t0, cpu_seconds() - c0
    counts = ds.manifest["counts"]
    methods = ds.manifest["methods"]
    scale = 1000 / n
    print(f"references: {n} draws in {t_refs:.1f} s ({n / t_refs:.1f}/s, {workers} workers); "
          f"status {counts}, methods {methods}")  # fmt: skip
    verdict = "PASS" if t_refs * scale < 60 else "MISS"
    print(f"  per 1000: {t_refs * scale:.1f} s (target < 60 s): {verdict}; CPU {c_refs:.1f} s, "
          f"i.e. {c_refs / workers * scale:.1f} s on {workers} idle cores")  # fmt: skip
    if parts:
        print(f"  per draw, median of {min(args.split, n)} solved one by one in process (ms): "
              + ", ".join(f"{k} {v:.1f}" for k, v in parts.items())
              + " (newton: the warm start's Newton and continuation; refine: its accuracy "
              "control; verify: the judge's re-simulation of u(t) and comparison; guess: the "
              "judge's evaluation of the initial guess)")  # fmt: skip
    if rep is None:
        return 0
    print(f"rollouts: {n} in {t_roll:.1f} s ({n / t_roll:.1f}/s); median gap "
          f"{rep.summary['gap_median']:.4g}")  # fmt: skip
    verdict = "PASS" if t_roll * scale < 10 else "MISS"
    print(f"  per 1000: {t_roll * scale:.1f} s (target < 10 s): {verdict}; CPU {c_roll:.1f} s, "
          f"i.e. {c_roll / workers * scale:.1f} s on {workers} idle cores")  # fmt: skip
    return 0 if np.isfinite(t_refs) else 1


if __name__ == "__main__":
    sys.exit(main())
