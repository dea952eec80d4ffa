"""hybridoc's methods beside MuJoCo's gradient descent on single-collision, side by side.

One table, one row per method, all judged by :func:`hybridoc.evaluate` against the exact
optimum ``J*`` (the reference's cost):

* ``reference``, ``dt`` and ``gd``: :func:`hybridoc.solve` from the scene's initial guess,
  median wall time of ``--runs`` solves after one warm-up solve (compilations and caches
  are not timed); the time to a control within 1% of ``J*`` is the solve's time when its
  judged cost is within 1% (these methods give no intermediate controls);
* ``mujoco k=.. K=..``: the scene exported to MuJoCo (:mod:`hybridoc.workflows.mujoco`,
  stiffness ``k``, ``K`` substeps per control interval), optimised the way MuJoCo users
  do: SciPy's L-BFGS (default settings) on MuJoCo's cost and its gradient from
  ``mjd_transitionFD`` Jacobians chained backwards, from the same initial guess, until
  L-BFGS stops or ``--max-evals`` evaluations. Every control it evaluates is judged; the
  time to within 1% is the optimiser's own time (the judge's calls are not counted) at
  the first evaluation whose judged cost is within 1% of ``J*``, or ``never``. One run:
  L-BFGS on MuJoCo's cost is deterministic.

Columns: ``time s`` (whole run), ``to 1% s``, ``work`` (the solver's iterations, or
MuJoCo's cost-and-gradient evaluations), ``own cost`` (the cost the method itself sees:
MuJoCo's cost for MuJoCo, the judge's for hybridoc's methods), ``judged`` and ``gap``
(judged cost / J* - 1).
No target is fixed. Run it by path::

    .venv/bin/python benchmarks/bench_peers.py [--quick] [--runs 3] [--max-evals 200]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from typing import Any

import numpy as np
from _timing import machine_line
from scipy.optimize import minimize

import hybridoc
from hybridoc.cli._util import format_table
from hybridoc.problems import load_scene

SCENE = "single-collision"
HYBRIDOC_METHODS = ("reference", "dt", "gd")
# (stiffness, substeps): issue #19's two MuJoCo models, the second the export's default
MUJOCO_SETTINGS = ((1e4, 1), (1e6, 10))
WITHIN = 0.01


def _row(
    method: str,
    settings: str,
    wall: float,
    to_target: float | None,
    work: str,
    own: float,
    judged: float,
    optimum: float,
) -> list[str]:
    gap = judged / optimum - 1
    return [
        method,
        settings,
        f"{wall:.2f}",
        "never" if to_target is None else f"{to_target:.2f}",
        work,
        f"{own:.6f}",
        f"{judged:.6f}",
        f"{100 * gap:+.3f}%",
    ]


def bench_hybridoc(problem: Any, method: str, runs: int, optimum: float) -> list[str]:
    """One row: ``hybridoc.solve(problem, method)``, median of ``runs`` after a warm-up."""
    hybridoc.solve(problem, method)
    walls, sol = [], None
    for _ in range(runs):
        t0 = time.perf_counter()
        sol = hybridoc.solve(problem, method)
        walls.append(time.perf_counter() - t0)
    wall = statistics.median(walls)
    judged = sol.cost  # the judge's (Solution.cost always is)
    within = judged <= (1 + WITHIN) * optimum
    iters = sol.info.get("iterations")
    work = "-" if iters is None else f"{iters} iterations"
    return _row(method, "defaults", wall, wall if within else None, work, judged, judged, optimum)


def bench_mujoco(
    scene: Any, stiffness: float, substeps: int, max_evals: int, optimum: float
) -> tuple[list[str], str]:
    """One row: L-BFGS on MuJoCo's cost and chained gradient, every evaluation judged."""
    from hybridoc.workflows.mujoco import load_model

    problem = scene.to_ocp()
    model = load_model(scene, substeps=substeps, stiffness=stiffness)
    u0 = scene.initial_controls()
    model.cost(u0)  # warm-up: CasADi's cost functions
    hybridoc.evaluate(problem, u0)
    judge_time = 0.0
    first = None
    evals = 0
    t_start = time.perf_counter()

    def fg(x: np.ndarray) -> tuple[float, np.ndarray]:
        nonlocal judge_time, first, evals
        u = x.reshape(u0.shape)
        cost, grad = model.cost_and_gradient(u)
        evals += 1
        t0 = time.perf_counter()
        judged = hybridoc.evaluate(problem, u).cost
        judge_time += time.perf_counter() - t0
        if first is None and judged <= (1 + WITHIN) * optimum:
            first = time.perf_counter() - t_start - judge_time
        return cost, grad.ravel()

    res = minimize(fg, u0.ravel(), jac=True, method="L-BFGS-B", options={"maxfun": max_evals})
    wall = time.perf_counter() - t_start - judge_time
    u = res.x.reshape(u0.shape)
    judged = hybridoc.evaluate(problem, u).cost
    label = f"mujoco k={stiffness:g} K={substeps}"
    work = f"{evals} evaluations"
    row = _row(label, "L-BFGS", wall, first, work, float(res.fun), judged, optimum)
    return row, str(res.message)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=3, help="timed solves per hybridoc method")
    p.add_argument(
        "--max-evals", type=int, default=200, help="MuJoCo L-BFGS evaluations at most (200)"
    )
    p.add_argument("--quick", action="store_true", help="1 run, 8 MuJoCo evaluations")
    args = p.parse_args(argv)
    if args.quick:
        args.runs, args.max_evals = 1, 8
    if args.runs < 1 or args.max_evals < 1:
        p.error("--runs and --max-evals must be >= 1")
    try:
        import mujoco
    except ImportError:
        print("bench_peers: error: MuJoCo is not installed (pip install hybridoc[mujoco])")
        return 2

    print(machine_line() + f"  MuJoCo {mujoco.__version__}", flush=True)
    scene = load_scene(SCENE)
    problem = scene.to_ocp()
    optimum = hybridoc.solve(problem, "reference").cost
    print(f"{SCENE}: exact optimum J* = {optimum!r} (the reference); within 1%: <= "
          f"{(1 + WITHIN) * optimum:.6f}")  # fmt: skip
    rows, notes = [], []
    for method in HYBRIDOC_METHODS:
        print(f"  {method} ...", file=sys.stderr, flush=True)
        rows.append(bench_hybridoc(problem, method, args.runs, optimum))
    for stiffness, substeps in MUJOCO_SETTINGS:
        print(f"  mujoco k={stiffness:g} K={substeps} ...", file=sys.stderr, flush=True)
        row, message = bench_mujoco(scene, stiffness, substeps, args.max_evals, optimum)
        rows.append(row)
        notes.append(f"{row[0]}: L-BFGS stopped: {message}")
    print(
        format_table(
            ["method", "how", "time s", "to 1% s", "work", "own cost", "judged", "gap"],
            rows,
            right=[False, False, True, True, True, True, True, True],
        )
    )
    print(f"hybridoc methods: median of {args.runs} solves after a warm-up; MuJoCo: one run, "
          "the judge's time not counted")  # fmt: skip
    for note in notes:
        print(note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
