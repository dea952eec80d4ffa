"""Timings of reference datasets and closed-loop policy validation over a distribution.

The single-collision scene with ball 2's start drawn uniformly within +-0.3 in each
coordinate (the issue's distribution): ``hybridoc.workflows.datasets.make_dataset`` for
``--samples`` draws (nominal solve included), then
``hybridoc.workflows.policies.validate_policy`` of a simple Python feedback policy on the
same draws (rollouts only; the references are reused).
Targets on 2 cores: 1000 references in under 60 s, 1000 rollouts in under 10 s.

Run it by path::

    .venv/bin/python benchmarks/bench_dataset.py [--samples 1000] [--workers K] [--quick]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=1000)
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--quick", action="store_true", help="50 samples: a smoke run")
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
    print(f"rollouts: {n} in {t_roll:.1f} s ({n / t_roll:.1f}/s); median gap "
          f"{rep.summary['gap_median']:.4g}")  # fmt: skip
    verdict = "PASS" if t_roll * scale < 10 else "MISS"
    print(f"  per 1000: {t_roll * scale:.1f} s (target < 10 s): {verdict}; CPU {c_roll:.1f} s, "
          f"i.e. {c_roll / workers * scale:.1f} s on {workers} idle cores")  # fmt: skip
    return 0 if np.isfinite(t_refs) else 1


if __name__ == "__main__":
    sys.exit(main())
