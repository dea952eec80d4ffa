"""Feedback policies trained through the simulator, with and without TOI, against the optimum.

The experiment of issue 11 ("Validate learned controllers against the reference"): on
``single-collision`` the passive disc ``ball2`` starts at its nominal position plus an
offset drawn uniformly in ``[-0.3, 0.3]^2``. Two MLP feedback policies
(:func:`hybridoc.workflows.training.mlp_policy`, same initial weights) are trained on
the same training draws through the closed-loop differentiable simulator (symplectic Euler,
``direct`` impulses, zero-order hold; full-batch Adam, keeping the best iterate), one with
the paper's time-of-impact corrections (``toi="both"``) and one without (``toi="none"``).
On separate validation draws each policy is judged by the event-exact evaluator in closed
loop (``hybridoc.evaluate(scene_i, policy=pi)``, zero-order hold) and compared with the
exact optimum of that draw (``hybridoc.reference.solve_reference(scene_i)``), an open-loop
optimum that knows the draw. The relative gap is ``(J_pi - J*) / J*``. The untrained
policy (close to the scene's initial guess) is the baseline. Draws that overlap or touch
another body (gap < 0.01) are redrawn.

Prints the first line of every benchmark, the settings, one row per validation draw
(``--per-draw``) and the summary table. Run it by path::

    .venv/bin/python benchmarks/policy_gap.py [--quick] [--per-draw]
"""

from __future__ import annotations

import argparse
import copy
import math
import sys
import time
from typing import Any

import numpy as np
import torch
from _timing import machine_line

import hybridoc
from hybridoc.cli._util import format_table
from hybridoc.errors import HybridocError
from hybridoc.problems import Scene
from hybridoc.reference import solve_reference
from hybridoc.solvers.simulator import Simulator
from hybridoc.workflows.training import mlp_policy, train_policy

PASSIVE = "ball2"
HALF_WIDTH = 0.3
MIN_GAP = 0.01


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def min_gap(scene: Scene) -> float:
    """Smallest gap between two discs or a disc and a wall at t = 0."""
    gaps = [math.inf]
    for i, a in enumerate(scene.discs):
        for b in scene.discs[i + 1 :]:
            gaps.append(math.dist(a.position, b.position) - a.radius - b.radius)
        for w in scene.walls:
            d = np.dot(np.subtract(a.position, w.point), w.normal) - a.radius
            gaps.append(float(d))
    return min(gaps)


def draw_states(scene: Scene, n: int, rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """``n`` initial states with the passive disc moved; also the number redrawn."""
    k = [d.name for d in scene.discs].index(PASSIVE)
    x_nom = scene.initial_state()
    out, redrawn = [], 0
    while len(out) < n:
        x = x_nom.copy()
        x[2 * k : 2 * k + 2] += rng.uniform(-HALF_WIDTH, HALF_WIDTH, 2)
        try:
            ok = min_gap(scene.with_initial_state(x)) >= MIN_GAP
        except HybridocError:  # overlapping discs
            ok = False
        if ok:
            out.append(x)
        else:
            redrawn += 1
    return np.array(out), redrawn


def judge(scene: Scene, policy: Any) -> tuple[float, str]:
    try:
        ev = hybridoc.evaluate(scene, policy=policy)
    except HybridocError as exc:
        return math.nan, type(exc).__name__
    return ev.cost, ",".join(ev.sequence) or "-"


def pct(x: float) -> str:
    return "n/a" if not np.isfinite(x) else f"{100 * x:.2f}%"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="few draws and iterations (smoke run)")
    ap.add_argument("--train", type=int, default=None, help="training draws (24; quick 6)")
    ap.add_argument("--val", type=int, default=None, help="validation draws (20; quick 4)")
    ap.add_argument("--iters", type=int, default=None, help="Adam iterations (500; quick 15)")
    ap.add_argument("--lr", type=float, default=1e-2, help="Adam learning rate (1e-2)")
    ap.add_argument("--hidden", type=int, default=32, help="hidden width (32)")
    ap.add_argument("--layers", type=int, default=2, help="hidden layers (2)")
    ap.add_argument("--seed", type=int, default=0, help="seed of draws and weights (0)")
    ap.add_argument("--per-draw", action="store_true", help="print one row per validation draw")
    args = ap.parse_args(argv)
    n_train = args.train or (6 if args.quick else 24)
    n_val = args.val or (4 if args.quick else 20)
    iters = args.iters or (15 if args.quick else 500)

    print(machine_line())
    scene = hybridoc.load_scene("single-collision")
    rng_train = np.random.default_rng([args.seed, 1])
    rng_val = np.random.default_rng([args.seed, 2])
    x_train, re_t = draw_states(scene, n_train, rng_train)
    x_val, re_v = draw_states(scene, n_val, rng_val)
    print(
        f"single-collision, N = {scene.steps}: {PASSIVE} start + U[-{HALF_WIDTH}, {HALF_WIDTH}]^2; "
        f"{n_train} training draws, {n_val} validation draws ({re_t + re_v} redrawn); "
        f"MLP {args.layers}x{args.hidden} tanh, Adam lr {args.lr}, {iters} iterations, "
        f"seed {args.seed}; simulator: symplectic Euler, direct impulses, zero-order hold"
    )

    untrained = mlp_policy(scene, hidden=args.hidden, layers=args.layers, seed=args.seed)
    policies: dict[str, Any] = {"untrained (guess)": untrained}
    train_rows = []
    for toi in ("both", "none"):
        pol = copy.deepcopy(untrained)
        log(f"training toi={toi} ...")
        res = train_policy(scene, pol, x_train, toi=toi, iters=iters, lr=args.lr, seed=args.seed)
        policies[f"toi={toi}"] = pol
        train_rows.append(
            [f"toi={toi}", f"{res.losses[0]:.4f}", f"{res.final_loss:.4f}", f"{res.seconds:.1f}"]
        )
    print()
    print("Training (simulator loss, mean over the training draws)")
    print(format_table(["policy", "initial loss", "final loss", "time s"], train_rows))

    sims = {
        "toi=both": Simulator(scene, toi="both"),
        "toi=none": Simulator(scene, toi="none"),
    }
    gaps: dict[str, list[float]] = {name: [] for name in policies}
    sim_gaps: dict[str, list[float]] = {name: [] for name in sims}
    seq_ok: dict[str, int] = {name: 0 for name in policies}
    fails: dict[str, int] = {name: 0 for name in policies}
    rows = []
    t_ref = 0.0
    for i, x in enumerate(x_val):
        sc = scene.with_initial_state(x)
        t0 = time.perf_counter()
        ref = solve_reference(sc)
        t_ref += time.perf_counter() - t0
        j_star = ref.cost
        ref_seq = ",".join(ref.sequence) if ref.sequence is not None else "?"
        log(f"draw {i}: reference {ref.status} {j_star:.6f} {ref_seq}")
        row = [i, f"{x[2]:+.3f}", f"{x[3]:+.3f}", f"{j_star:.6f}", str(ref.status)]
        for name, pol in policies.items():
            j, seq = judge(sc, pol)
            gap = (j - j_star) / j_star
            gaps[name].append(gap)
            fails[name] += not np.isfinite(j)
            seq_ok[name] += seq == ref_seq
            row.append(pct(gap))
            if name in sims:
                with torch.no_grad():
                    j_sim = float(sims[name].policy_loss(pol, x[None, :]))
                sim_gaps[name].append((j_sim - j) / j)
        rows.append(row)
    if args.per_draw:
        print()
        print(
            "Validation draws: optimum J* and gap (J_pi - J*) / J* of the judge's closed-loop cost"
        )
        print(format_table(["draw", "ball2 x", "ball2 y", "J*", "reference", *policies], rows))

    print()
    print(
        f"Validation ({n_val} draws; reference {t_ref / n_val:.2f} s per draw): relative gap "
        "of the judge's closed-loop cost (zoh) to the exact optimum of each draw"
    )
    summary = []
    for name in policies:
        g = np.array(gaps[name])
        ok = g[np.isfinite(g)]
        sg = np.array(sim_gaps.get(name, []))
        summary.append(
            [
                name,
                pct(float(np.median(ok))) if ok.size else "n/a",
                pct(float(np.mean(ok))) if ok.size else "n/a",
                pct(float(np.max(ok))) if ok.size else "n/a",
                f"{int(np.sum(ok < 0.01))}/{n_val}",
                f"{seq_ok[name]}/{n_val}",
                fails[name],
                pct(float(np.median(sg))) if sg.size else "-",
            ]
        )
    print(
        format_table(
            [
                "policy",
                "median gap",
                "mean gap",
                "max gap",
                "gap < 1%",
                "same events as J*",
                "judge errors",
                "sim vs judge",
            ],
            summary,
        )
    )
    print(
        "sim vs judge: median of (simulator loss - judge cost) / judge cost of the policy on "
        "the validation draws, in the simulator it was trained in."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
