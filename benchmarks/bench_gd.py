"""Per-iteration time and peak memory of gradient descent through the simulator.

For each path (``torch``: eager autograd through :class:`~hybridoc.solvers.simulator.Simulator`;
``compiled``: the CasADi graph of :class:`~hybridoc.solvers.compiled.CompiledLoss`) and
contact model, in float64 on the single-collision problem (N = 480), a fresh subprocess

1. times ``--repeats`` evaluations of the discrete loss and its full gradient (one iteration of
   the paper's plain gradient descent costs exactly one) after a warm-up, and
2. runs a whole :func:`~hybridoc.solvers.gd.solve_gd` (plain gd, ``--solve-iters``
   iterations, then the evaluator) and reports the process's peak resident memory
   (``ru_maxrss``, which includes the Python interpreter, torch and CasADi themselves).

The paper's public PyTorch implementation needs about 250 ms per iteration and 5 GB on this
problem; the project's target is at least 100x faster (<= 2.5 ms per iteration) and under
600 MB for a whole solve. Medians are quoted. Run it by path::

    .venv/bin/python benchmarks/bench_gd.py [--repeats 30] [--solve-iters 50]
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

PAPER_MS_PER_ITER = 250.0
PAPER_PEAK_MB = 5000.0
TARGET_MS_PER_ITER = 2.5
TARGET_PEAK_MB = 600.0

CONFIGS = [
    ("compiled", "direct"),
    ("torch", "direct"),
    ("torch", "lcp"),
    ("torch", "convex"),
    ("torch", "compliant"),
    ("torch", "pbd"),
]


def _contact_kwargs(contact: str) -> dict[str, object]:
    if contact in ("direct", "lcp", "convex"):
        return {"impulse": contact, "contact": None}
    return {"impulse": "direct", "contact": contact}


def worker(path: str, contact: str, repeats: int, solve_iters: int, scene_name: str) -> dict:
    """Run one configuration in this process; returns the measurements."""
    import numpy as np
    import torch

    import hybridoc
    from hybridoc.solvers.gd import solve_gd

    torch.set_num_threads(1)
    scene = hybridoc.load_scene(scene_name)
    u0 = torch.tensor(scene.initial_controls(), dtype=torch.float64)
    t_build = time.perf_counter()
    if path == "compiled":
        from hybridoc.solvers.compiled import CompiledLoss

        model = CompiledLoss(scene, toi="both")
    else:
        from hybridoc.solvers.simulator import Simulator

        model = Simulator(scene, toi="both", **_contact_kwargs(contact))
    build_s = time.perf_counter() - t_build

    def iteration() -> float:
        u = u0.clone().requires_grad_(True)
        loss = model.loss(u)
        loss.backward()
        return float(loss.detach())

    iteration()  # warm-up
    times, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        iteration()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    t0 = time.perf_counter()
    sol = solve_gd(scene, optimizer="gd", iters=solve_iters, path=path, **_contact_kwargs(contact))
    solve_s = time.perf_counter() - t0
    maxrss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "path": path,
        "contact": contact,
        "ms_per_iter_median": 1e3 * statistics.median(times),
        "ms_per_iter_min": 1e3 * min(times),
        "cpu_ms_per_iter_median": 1e3 * statistics.median(cpu),
        "build_s": build_s,
        "solve_iters": solve_iters,
        "solve_s": solve_s,
        "solve_loss": sol.info["loss"],
        "peak_mb": maxrss_kb / 1024.0,
        "finite": bool(np.isfinite(sol.cost)),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=30, help="timed iterations (default 30)")
    ap.add_argument("--solve-iters", type=int, default=50, help="gd iterations of the solve")
    ap.add_argument("--scene", default="single-collision")
    ap.add_argument("--only", default=None, help="comma-separated path:contact subset")
    ap.add_argument("--worker", nargs=2, metavar=("PATH", "CONTACT"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        res = worker(args.worker[0], args.worker[1], args.repeats, args.solve_iters, args.scene)
        print(json.dumps(res))
        return 0
    configs = CONFIGS
    if args.only:
        wanted = {tuple(s.split(":")) for s in args.only.split(",")}
        configs = [c for c in CONFIGS if c in wanted]
    rows = []
    for path, contact in configs:
        repeats = args.repeats if path == "compiled" else max(3, args.repeats // 6)
        cmd = [sys.executable, __file__, "--worker", path, contact, "--repeats", str(repeats)]
        cmd += ["--solve-iters", str(args.solve_iters), "--scene", args.scene]
        proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if proc.returncode != 0:
            print(f"{path}/{contact} failed:\n{proc.stderr}", file=sys.stderr)
            continue
        rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        print(f"  done {path}/{contact}: {r['ms_per_iter_median']:.3g} ms", file=sys.stderr)
    print(f"scene {args.scene}, float64, loss + full gradient per iteration (median)")
    head = f"{'path':<9} {'contact':<10} {'ms/iter':>9} {'min':>8} {'cpu ms':>8} {'speed-up':>9} "
    head += f"{'peak MB':>8} {'build s':>8}"
    print(head)
    print("-" * len(head))
    print(
        f"{'paper':<9} {'direct':<10} {PAPER_MS_PER_ITER:>9.3g} {'':>8} {'':>8} {1.0:>8.1f}x "
        f"{PAPER_PEAK_MB:>8.0f} {'':>8}"
    )
    for r in rows:
        speed = PAPER_MS_PER_ITER / r["ms_per_iter_median"]
        print(
            f"{r['path']:<9} {r['contact']:<10} {r['ms_per_iter_median']:>9.3g} "
            f"{r['ms_per_iter_min']:>8.3g} {r['cpu_ms_per_iter_median']:>8.3g} {speed:>8.1f}x "
            f"{r['peak_mb']:>8.0f} "
            f"{r['build_s']:>8.2f}"
        )
    print(
        "ms/iter: wall-clock median (min); cpu ms: process CPU time median (robust to other "
        "load on the machine); speed-up: paper / wall-clock median"
    )
    print(
        f"targets: <= {TARGET_MS_PER_ITER} ms/iter (100x the paper), < {TARGET_PEAK_MB:.0f} MB "
        "peak for a whole solve (ru_maxrss of a fresh process: interpreter, torch and CasADi "
        f"included; solve = {args.solve_iters} plain gd iterations + the evaluator)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
