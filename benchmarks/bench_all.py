"""Every speed target of issue #18 in one run, and one table: target beside measured value.

Runs, in this order, reusing the other scripts' functions (each section's details are in
that script's own table, ``benchmarks/README.md``):

* ``startup``: ``hybridoc --help`` as a whole process, median of ``--startup-runs`` (10)
  after a warm-up (:mod:`bench_startup`); target < 0.25 s;
* ``iter``: one loss and gradient of single-collision at its initial guess, gd's default
  (direct contact, exact integrator, the generated C called natively), median of
  ``--iter-repeats`` (200) after the C is compiled, beside the paper's PyTorch code timed
  in the same run (:func:`bench_gd.paper_per_iteration`, ``--paper-repeats`` pairs);
  stretch target >= 1000x by wall time and by CPU time;
* ``solve``: ``hybridoc solve single-collision --method gd`` (and multiple-collision with 32
  starts) as whole processes, cold then ``--solve-repeats`` (2) warm runs
  (:func:`bench_gd.whole_solves`); target < 2 s warm and within 0.05% of the optimum;
* ``rollouts``: ``validate_policy`` of an MLP policy on ``--samples`` (1000)
  single-collision draws through the compiled rollouts, cold (empty C-code cache) then warm
  (:mod:`bench_rollouts`); target: 1000 < 10 s wall;
* ``dataset``: ``make_dataset`` of ``--samples`` single-collision draws on every usable core,
  wall and CPU, and the per-draw split of ``--split`` (30) draws solved one by one
  (:func:`bench_dataset.split`); target: 1000 < 60 s wall;
* ``reference``: ``solve_reference`` on every library problem, median of ``--runs`` (3)
  after a warm-up (:func:`bench_reference.in_process`); target < 500 ms each;
* ``search``: ``hybridoc reference multiple-collision --search 5 --json`` as a whole
  process, median of ``--search-repeats`` (3) (:func:`bench_reference.cli_search`);
  target < 5 s;
* ``tests``: ``make test`` < 4 min and ``.ci/run`` < 6 min, measured separately (they use
  both cores for minutes) and given as ``--make-test-s`` / ``--ci-run-s`` or in a JSON file
  ``--times FILE`` (``{"make_test_s": ..., "ci_run_s": ..., "note": "..."}``; default
  ``benchmarks/test_times.json``, the last measured, with when and where in its note);
* ``cuda``: the batched torch simulator's rollouts per second at B = 1, 1024, 65536 and its
  agreement with the CPU (:func:`bench_gd.cuda_rollouts`), or ``not checked (no GPU)``.

The table is Markdown (it goes into ``benchmarks/README.md`` as printed). ``load`` is the
1-minute load average at the start and at the end of each measurement: numbers taken under
load are slower than idle ones. At the default settings the run takes about 5 minutes on 2
idle cores. ``--quick`` (a smoke run) times 100 draws instead of 1000 and scales their times
to 1000 (the row says so), with one repeat of everything.

Run it by path::

    .venv/bin/python benchmarks/bench_all.py [--quick] [--skip SECTION] [--times FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from _timing import PEER_DEFAULT, hybridoc_command, machine_line, run_process, verdict

SECTIONS = (
    "startup",
    "iter",
    "solve",
    "rollouts",
    "dataset",
    "reference",
    "search",
    "tests",
    "cuda",
)
HELP_TARGET_S = 0.25
ITER_TARGET_X = 1000.0
SOLVE_TARGET_S, SOLVE_GAP = 2.0, 5e-4
ROLLOUTS_TARGET_S = 10.0
DATASET_TARGET_S = 60.0
REFERENCE_TARGET_S = 0.5
SEARCH_TARGET_S = 5.0
MAKE_TEST_TARGET_S = 240.0
CI_TARGET_S = 360.0
TIMES = Path(__file__).resolve().parent / "test_times.json"
"""The last measured ``make test`` and ``.ci/run`` wall times (default of ``--times``)."""


@dataclass
class Row:
    """One line of the table."""

    what: str
    target: str
    measured: str
    ok: bool | None = None
    load: str = ""
    notes: list[str] = field(default_factory=list)


def _load1() -> float:
    return os.getloadavg()[0]


class Table:
    """Rows in the order measured, each with the load average around its measurement."""

    def __init__(self) -> None:
        self.rows: list[Row] = []

    def section(self, name: str, fn: Callable[[], list[Row]]) -> None:
        """Run one section; a failure is a row that says so, not the end of the run."""
        print(f"== {name} ...", file=sys.stderr, flush=True)
        t0, before = time.perf_counter(), _load1()
        try:
            rows = fn()
        except Exception as exc:  # one section's failure must not lose the others
            traceback.print_exc(file=sys.stderr)
            rows = [Row(name, "-", f"FAILED: {type(exc).__name__}: {str(exc)[:200]}", False)]
        load = f"{before:.1f} / {_load1():.1f}"
        for r in rows:
            r.load = r.load or load
        self.rows += rows
        print(f"   {name} took {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)

    def markdown(self) -> str:
        lines = [
            "| what | target | measured | result | load |",
            "|---|---|---|---|---|",
        ]
        for r in self.rows:
            cells = [r.what, r.target, r.measured, verdict(r.ok), r.load]
            lines.append("| " + " | ".join(c.replace("|", "/") for c in cells) + " |")
        return "\n".join(lines)


# ---------------------------------------------------------------------------- sections
def startup(runs: int) -> list[Row]:
    cmd = [*hybridoc_command(), "--help"]
    res = [run_process(cmd, timeout=60) for _ in range(1 + runs)][1:]
    bad = [r for r in res if r.returncode != 0 or r.timed_out]
    med = statistics.median(r.wall_s for r in res)
    return [
        Row(
            "`hybridoc --help`, whole process",
            f"< {HELP_TARGET_S:g} s",
            f"{med:.3f} s (median of {runs}; min {min(r.wall_s for r in res):.3f} s)",
            med < HELP_TARGET_S and not bad,
        )
    ]


def per_iteration(repeats: int, paper_iters: int, paper_repeats: int, peer: Path) -> list[Row]:
    import bench_gd
    import numpy as np

    from hybridoc.problems import load_problem
    from hybridoc.solvers import codegen
    from hybridoc.solvers.compiled import CompiledLoss

    paper = bench_gd.paper_per_iteration(peer, "single-collision", paper_iters, paper_repeats)
    what = "loss + gradient per iteration, single-collision, gd's default vs the paper's code"
    target = f">= {ITER_TARGET_X:.0f}x wall and CPU (stretch)"
    if "error" in paper:
        return [Row(what, target, f"paper not measured: {paper['error']}", None)]
    problem = load_problem("single-collision")
    u = problem.initial_controls()
    with bench_gd.codegen_env("1"):
        loss = CompiledLoss(problem, "direct", "exact", toi="both")
        for _ in range(codegen.HOT_CALLS):  # hot: its compilation starts
            loss.value_and_grad(u)
        state = bench_gd._wait_for_c(loss, 300.0)  # noqa: SLF001  (bench_gd's own helper)
    if state not in ("ready", "unknown"):
        return [Row(what, target, f"C code {state}", False)]
    for _ in range(20):
        loss.value_and_grad(u)
    walls, cpus = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        loss.value_and_grad(u)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    wall, cpu = float(np.median(walls)), float(np.median(cpus))
    xw, xc = paper["wall"] / wall, (paper["cpu"] / cpu if cpu > 0 else float("inf"))
    return [
        Row(
            what,
            target,
            f"{xw:.0f}x wall, {xc:.0f}x CPU (ours {1e3 * wall:.3f} ms, the paper's "
            f"{1e3 * paper['wall']:.1f} ms)",
            min(xw, xc) >= ITER_TARGET_X,
        )
    ]


def solves(repeats: int) -> list[Row]:
    import bench_gd

    rows = []
    for r in bench_gd.whole_solves(repeats):
        name = r["problem"]
        starts = " --starts 32" if name == "multiple-collision" else ""
        what = f"`hybridoc solve {name} --method gd{starts}`, warm, whole process"
        target = f"< {r['target_s']:g} s, within {100 * r['target_gap']:g}%"
        if "warm" not in r:
            rows.append(Row(what, target, f"failed: {'; '.join(r['errors'])[:200]}", False))
            continue
        ok = r["warm"] < r["target_s"] and abs(r["gap"]) <= r["target_gap"]
        rows.append(
            Row(
                what,
                target,
                f"{r['warm']:.2f} s (cold {r['cold']:.2f} s), gap {100 * r['gap']:+.4f}%, "
                f"torch imported: {'yes' if r['torch'] else 'no'}",
                ok,
            )
        )
    return rows


def rollouts(n: int) -> list[Row]:
    import bench_rollouts

    from hybridoc.workflows.datasets import usable_cores
    from hybridoc.workflows.policy_format import save_mlp_policy
    from hybridoc.workflows.training import mlp_policy

    workers = usable_cores()
    scene = bench_rollouts.scene_with_distribution()
    old = os.environ.get("HYBRIDOC_CACHE")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        os.environ["HYBRIDOC_CACHE"] = str(folder / "cache")  # cold: an empty C-code cache
        try:
            policy = str(
                save_mlp_policy(
                    mlp_policy(scene, hidden=32, layers=2, seed=0), folder / "policy.json"
                )
            )
            refs = bench_rollouts.unsolved_references(scene, n, folder)
            cold = bench_rollouts.timed(scene, policy, n, refs, workers, "compiled")
            warm = bench_rollouts.timed(scene, policy, n, refs, workers, "compiled")
        finally:
            if old is None:
                os.environ.pop("HYBRIDOC_CACHE", None)
            else:
                os.environ["HYBRIDOC_CACHE"] = old
    scale = 1000 / n
    roll = warm["report"].summary["rollouts"]
    scaled = "" if n == 1000 else f" (scaled from {n})"
    return [
        Row(
            f"1000 closed-loop rollouts (MLP policy, single-collision draws), {workers} workers",
            f"< {ROLLOUTS_TARGET_S:g} s wall",
            f"{warm['wall'] * scale:.2f} s wall, {warm['cpu'] * scale:.2f} s CPU{scaled}; cold "
            f"(compiling) {cold['wall'] * scale:.2f} s; certified {roll['compiled']}, per-step "
            f"judge {roll['fallback']}",
            warm["wall"] * scale < ROLLOUTS_TARGET_S,
        )
    ]


def dataset(n: int, split_draws: int) -> list[Row]:
    import bench_dataset
    import bench_rollouts

    from hybridoc.workflows.datasets import make_dataset, usable_cores

    workers = usable_cores()
    scene = bench_rollouts.scene_with_distribution()
    with tempfile.TemporaryDirectory() as tmp:
        t0, c0 = time.perf_counter(), bench_dataset.cpu_seconds()
        ds = make_dataset(scene, n, Path(tmp) / "refs", workers=workers, progress=False)
        wall, cpu = time.perf_counter() - t0, bench_dataset.cpu_seconds() - c0
        parts = bench_dataset.split(scene, ds, min(split_draws, n)) if split_draws else {}
    scale = 1000 / n
    counts = ds.manifest["counts"]
    scaled = "" if n == 1000 else f" (scaled from {n})"
    split_text = ", ".join(f"{k} {v:.1f}" for k, v in parts.items() if k != "total")
    total = parts.get("total", float("nan"))
    return [
        Row(
            f"1000 dataset references of single-collision draws, {workers} workers",
            f"< {DATASET_TARGET_S:g} s wall",
            f"{wall * scale:.1f} s wall, {cpu * scale:.1f} s CPU{scaled}; status {counts}; "
            f"per draw {total:.1f} ms in process (median of {min(split_draws, n)}): "
            f"{split_text} ms",
            wall * scale < DATASET_TARGET_S,
        )
    ]


def references(runs: int) -> list[Row]:
    import bench_reference

    from hybridoc.problems import library_names

    rows = []
    for name in library_names():
        print(f"   {name}", file=sys.stderr, flush=True)
        what = f"reference `{name}` (library), in process"
        target = f"< {1e3 * REFERENCE_TARGET_S:.0f} ms"
        before = _load1()
        try:
            r = bench_reference.in_process(name, runs)
        except Exception as exc:  # a failing problem is a row
            load = f"{before:.1f} / {_load1():.1f}"
            fail = f"fails: {type(exc).__name__}: {str(exc)[:90]}"
            rows.append(Row(what, target, fail, False, load))
            continue
        load = f"{before:.1f} / {_load1():.1f}"
        rows.append(
            Row(
                what,
                target,
                f"{1e3 * r['solve_s']:.0f} ms (multi-start {1e3 * r['ms_src']:.0f}, "
                f"transcription {1e3 * r['dt_src']:.0f}, verify {1e3 * r['verify']:.0f}, rest "
                f"{1e3 * r['rest']:.0f})",
                r["solve_s"] < REFERENCE_TARGET_S,
                load,
            )
        )
    return rows


def search(repeats: int) -> list[Row]:
    import bench_reference

    r = bench_reference.cli_search("multiple-collision", repeats)
    what = "`hybridoc reference multiple-collision --search 5`, whole process"
    target = f"< {SEARCH_TARGET_S:g} s"
    if "wall_s" not in r:
        return [Row(what, target, f"failed: {'; '.join(r['errors'])[:200]}", False)]
    both = all(
        any(abs(c - v) < 1e-9 for c in r["landscape"]) for v in bench_reference.LANDSCAPE.values()
    )
    return [
        Row(
            what,
            target,
            f"{r['wall_s']:.2f} s (median of {r['runs']}), best {r['cost']:.12f}, both "
            f"extremals in the landscape: {'yes' if both else 'NO'}",
            r["wall_s"] < SEARCH_TARGET_S and both,
        )
    ]


def test_times(make_test_s: float | None, ci_run_s: float | None, note: str) -> list[Row]:
    suffix = f" ({note})" if note else ""
    out = []
    for what, value, target in (
        ("`make test`, 2 cores", make_test_s, MAKE_TEST_TARGET_S),
        ("`.ci/run` (make test + docs-check), 2 cores", ci_run_s, CI_TARGET_S),
    ):
        measured = "not given (--make-test-s, --ci-run-s or --times)"
        if value is not None:
            measured = f"{value:.0f} s = {value / 60:.1f} min{suffix}"
        out.append(
            Row(
                what,
                f"< {target / 60:g} min",
                measured,
                None if value is None else value < target,
                "measured separately",
            )
        )
    return out


def cuda(repeats: int) -> list[Row]:
    what = "CUDA: batched torch rollouts of single-collision, B = 1, 1024, 65536"
    try:
        import torch
    except ImportError:
        return [Row(what, "agreement with the CPU; rollouts/s", "not checked (no torch)")]
    if not torch.cuda.is_available():
        return [Row(what, "agreement with the CPU; rollouts/s", "not checked (no GPU)")]
    import bench_gd

    rows = bench_gd.cuda_rollouts("cuda", bench_gd.CUDA_SIZES, repeats) or []
    text = "; ".join(f"{r[0]} B={r[1]}: {r[3]}/s, max rel diff {r[4]}" for r in rows)
    return [Row(what, "agreement with the CPU; rollouts/s", text)]


# ---------------------------------------------------------------------------- main
def _times_file(path: Path) -> tuple[float | None, float | None, str]:
    data = json.loads(path.read_text())
    return data.get("make_test_s"), data.get("ci_run_s"), str(data.get("note", ""))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--skip", action="append", default=[], choices=SECTIONS)
    p.add_argument("--quick", action="store_true", help="100 draws, one repeat: a smoke run")
    p.add_argument("--samples", type=int, default=1000, help="draws (rollouts, dataset)")
    p.add_argument("--split", type=int, default=30, help="draws timed stage by stage")
    p.add_argument("--runs", type=int, default=3, help="reference solves per problem")
    p.add_argument("--search-repeats", type=int, default=3)
    p.add_argument("--solve-repeats", type=int, default=2)
    p.add_argument("--startup-runs", type=int, default=10)
    p.add_argument("--iter-repeats", type=int, default=200)
    p.add_argument("--paper-iters", type=int, default=10)
    p.add_argument("--paper-repeats", type=int, default=3)
    p.add_argument("--peer", type=Path, default=PEER_DEFAULT, help="the paper's code")
    p.add_argument("--make-test-s", type=float, default=None, help="make test's wall time")
    p.add_argument("--ci-run-s", type=float, default=None, help=".ci/run's wall time")
    p.add_argument("--times", type=Path, default=TIMES, help="JSON with both (module notes)")
    args = p.parse_args(argv)
    if args.quick:
        args.samples, args.split, args.runs = 100, 5, 1
        args.search_repeats = args.solve_repeats = 1
        args.startup_runs, args.iter_repeats, args.paper_iters, args.paper_repeats = 3, 20, 3, 1
    make_test_s, ci_run_s, note = args.make_test_s, args.ci_run_s, ""
    if args.times is not None and args.times.is_file():
        f_make, f_ci, note = _times_file(args.times)
        make_test_s = f_make if make_test_s is None else make_test_s
        ci_run_s = f_ci if ci_run_s is None else ci_run_s

    first = machine_line()
    print(first, flush=True)
    t0 = time.perf_counter()
    table = Table()
    sections: dict[str, Callable[[], list[Row]]] = {
        "startup": lambda: startup(args.startup_runs),
        "iter": lambda: per_iteration(
            args.iter_repeats, args.paper_iters, args.paper_repeats, args.peer
        ),
        "solve": lambda: solves(args.solve_repeats),
        "rollouts": lambda: rollouts(args.samples),
        "dataset": lambda: dataset(args.samples, args.split),
        "reference": lambda: references(args.runs),
        "search": lambda: search(args.search_repeats),
        "tests": lambda: test_times(make_test_s, ci_run_s, note),
        "cuda": lambda: cuda(5),
    }
    for name, fn in sections.items():
        if name not in args.skip:
            table.section(name, fn)
    print()
    print(
        f"Issue #18's targets, one run ({time.perf_counter() - t0:.0f} s); load: the 1-minute "
        "load average at the start / end of each measurement"
    )
    print()
    print(table.markdown())
    print()
    start = first.split("load average ")[1].split("  ")[0]
    end = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"load average (1, 5, 15 min) at the start: {start}; at the end: {end}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
