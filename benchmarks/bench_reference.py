"""Timing of the HMP reference: in process on every problem, and ``hybridoc reference --search 5``.

One table, one row per problem (default: both paper problems, every library problem and
issue #15's masked hopper, ``tests/test_reference_accuracy.py:masked_hopper``):

* ``sequence``, ``cost``: what :func:`hybridoc.reference.solve_reference` finds;
* ``steps``: the DOP853 steps per phase the accuracy control chose (generic problems);
* ``seq ms``: median of ``--runs`` solves with the found sequence given explicitly (shooting
  and the judge's re-simulation; no search);
* ``solve ms``: median of ``--runs`` default solves, ``solve_reference(problem)``: the full
  search (candidates from the guess, the direct transcription and the batched multi-start,
  verification). Both after one warm-up solve (CasADi functions are built and cached per
  problem). Target for the library problems: < 500 ms;
* ``cpu ms``: the process's CPU time of the same default solves (median): on a busy
  machine the wall time stretches with the load, the CPU time much less (a generic
  problem's default solve runs in this process alone);
* where that time goes, medians over the same solves: ``ms-src`` the multi-start source,
  ``dt-src`` the transcription source (both in ``hybridoc.solvers``), ``verify`` the judge's
  re-simulations of the extremals, ``rest`` everything else (the judge's evaluation and
  adjoint of the guess, the reference's own shooting, Newton and refinement);
* ``cli s`` (paper problems): ``hybridoc reference PROBLEM --search 5 --json`` as a whole
  process (interpreter start-up and imports included), median of ``--repeats`` (default 3)
  after one untimed run, with Python's bytecode cache on as a user's installation has it
  (:func:`cli_env`). Target (issue #18): < 5 s. Below the table: its best cost, the
  process's CPU time with its screening workers (median: on two cores the wall time cannot
  fall below half of it), and whether the landscape of multiple-collision holds both the
  two-event extremal 0.373636350232 and the three-event optimum 0.356279430543.

Run it by path (``--quick``: one timed run each, for a smoke test)::

    .venv/bin/python benchmarks/bench_reference.py [--runs 3] [--repeats 3] [PROBLEM ...]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time

from _timing import ROOT, fmt_ms, hybridoc_command, machine_line, run_process, verdict

from hybridoc.cli._util import format_table
from hybridoc.problems import library_names, load_problem
from hybridoc.reference import solve_reference

PAPER = ("single-collision", "multiple-collision")
#: problems outside the registry, by name: issue #15's user's hopper (modes by a state)
EXTRA = {"masked-hopper": str(ROOT / "tests" / "test_reference_accuracy.py") + ":masked_hopper"}
LIBRARY_TARGET_S = 0.5
CLI_TARGET_S = 5.0
SEARCH = 5
#: multiple-collision's extremals that ``--search 5`` must list (12 digits)
LANDSCAPE = {
    "two-event extremal": 0.373636350232,
    "three-event optimum": 0.356279430543,
}


def _split(sol: object) -> dict[str, float]:
    """Where one default solve's time went (seconds): the two solver sources, the judge's
    verification, the rest."""
    info, timings = sol.info, sol.timings  # type: ignore[attr-defined]
    by = {row["name"]: row["time_s"] for row in info.get("sources", [])}
    out = {
        "ms_src": by.get("multi-start", 0.0),
        "dt_src": by.get("transcription", 0.0),
        "verify": timings.get("verify_time_s", 0.0),
    }
    out["rest"] = timings["solve_time_s"] - sum(out.values())
    return out


def in_process(name: str, runs: int) -> dict:
    """Warm-up solve, then ``runs`` timed default solves and explicit-sequence solves."""
    problem = load_problem(EXTRA.get(name, name))
    sol = solve_reference(problem)  # warm-up: builds and caches the CasADi functions
    seq = list(sol.info["sequence"])
    full, cpu, parts = [], [], []
    for _ in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        s = solve_reference(problem)
        full.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        parts.append(_split(s))
    explicit = []
    for _ in range(runs):
        t0 = time.perf_counter()
        solve_reference(problem, sequence=seq)
        explicit.append(time.perf_counter() - t0)
    return {
        "sequence": seq,
        "cost": float(sol.cost),
        "status": sol.status.value,
        "steps": sol.info.get("substeps"),
        "solve_s": statistics.median(full),
        "cpu_s": statistics.median(cpu),
        "seq_s": statistics.median(explicit),
        **{k: statistics.median(p[k] for p in parts) for k in parts[0]},
    }


def cli_env(pycache: str) -> dict[str, str]:
    """The environment of the ``--search`` processes: Python's bytecode cache on, in the
    folder ``pycache`` (``PYTHONPYCACHEPREFIX``; the repository gets no ``__pycache__``).

    ``PYTHONDONTWRITEBYTECODE`` (set in some sandboxes) makes every process compile
    hybridoc's sources again, which a user's installation does not do: importing the modules
    of this command took 0.64 s against 0.37 s with their bytecode (medians of 7,
    interleaved, load 11). As ``bench_gd.whole_process_env``."""
    env = dict(os.environ, PYTHONPYCACHEPREFIX=pycache)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def cli_search(name: str, repeats: int) -> dict:
    """``hybridoc reference NAME --search 5 --json`` as whole processes: one untimed run
    (it writes the bytecode), then ``repeats`` timed ones."""
    cmd = [*hybridoc_command(), "reference", name, "--search", str(SEARCH), "--json"]
    walls, cpus, payload, errors = [], [], None, []
    with tempfile.TemporaryDirectory(prefix="hybridoc-pycache-") as pycache:
        env = cli_env(pycache)
        run_process(cmd, env=env, timeout=600)
        results = [run_process(cmd, env=env, timeout=600) for _ in range(repeats)]
    for res in results:
        if res.returncode not in (0, 1) or res.timed_out:
            errors.append(f"exit {res.returncode}: {res.stderr.strip().splitlines()[-1:]}")
            continue
        walls.append(res.wall_s)
        cpus.append(res.cpu_s)  # the workers' too: the process waits for them
        payload = json.loads(res.stdout.strip().splitlines()[-1])
    out: dict = {"cmd": " ".join(["hybridoc", *cmd[1:]]), "errors": errors}
    if walls and payload is not None:
        costs = [r["cost"] for r in payload["info"].get("landscape", []) if r["cost"] is not None]
        out.update(
            wall_s=statistics.median(walls),
            cpu_s=statistics.median(cpus),
            runs=len(walls),
            cost=float(payload["cost"]),
            status=payload["status"],
            landscape=costs,
        )
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("problems", nargs="*", help="default: the paper problems and the library")
    p.add_argument("--runs", type=int, default=3, help="timed in-process solves (default 3)")
    p.add_argument("--repeats", type=int, default=3, help="CLI processes (default 3)")
    p.add_argument("--no-cli", action="store_true", help="skip the --search 5 processes")
    p.add_argument("--quick", action="store_true", help="one run and one process each")
    args = p.parse_args(argv)
    if args.quick:
        args.runs, args.repeats = 1, 1
    if args.runs < 1 or args.repeats < 1:
        p.error("--runs and --repeats must be >= 1")
    names = args.problems or [*PAPER, *library_names(), *EXTRA]
    library = set(library_names())

    print(machine_line(), flush=True)
    print(
        f"HMP reference: in process, median of {args.runs} after 1 warm-up; "
        f"'hybridoc reference --search {SEARCH}' as a whole process, median of {args.repeats}"
    )
    rows, notes, failed = [], [], False
    for name in names:
        try:
            r = in_process(name, args.runs)
        except Exception as exc:  # one problem's failure is a row, not the end of the table
            failed = True
            notes.append(f"{name}: FAILED: {type(exc).__name__}: {exc}")
            rows.append([name, "-", "-", "failed", *["-"] * 9, "-", "FAIL"])
            print(f"  failed {name}", file=sys.stderr, flush=True)
            continue
        cli: dict = {}
        if name in PAPER and not args.no_cli:
            cli = cli_search(name, args.repeats)
        if name in library:
            target, ok = f"< {1e3 * LIBRARY_TARGET_S:.0f} ms", r["solve_s"] < LIBRARY_TARGET_S
        elif "wall_s" in cli:
            target, ok = f"cli < {CLI_TARGET_S:.0f} s", cli["wall_s"] < CLI_TARGET_S
        else:
            target, ok = "-", None
        rows.append(
            [
                name,
                ",".join(r["sequence"]) or "(none)",
                f"{r['cost']:.12f}",
                r["status"],
                "-" if not r["steps"] else ",".join(map(str, r["steps"])),
                fmt_ms(r["seq_s"]),
                fmt_ms(r["solve_s"]),
                fmt_ms(r["cpu_s"]),
                *(fmt_ms(r[k]) for k in ("ms_src", "dt_src", "verify", "rest")),
                f"{cli['wall_s']:.2f}" if "wall_s" in cli else "-",
                target,
                verdict(ok),
            ]
        )
        for err in cli.get("errors", []):
            failed = True
            notes.append(f"{name}: {cli['cmd']} failed: {err}")
        if "wall_s" in cli:
            line = (
                f"{name}: {cli['cmd']}: best cost {cli['cost']:.12f} ({cli['status']}), "
                f"cpu {cli['cpu_s']:.2f} s"
            )
            if name == "multiple-collision":
                present = {
                    label: any(abs(c - value) < 1e-9 for c in cli["landscape"])
                    for label, value in LANDSCAPE.items()
                }
                line += "; landscape: " + ", ".join(
                    f"{label} {LANDSCAPE[label]:.12f} {'present' if ok else 'ABSENT'}"
                    for label, ok in present.items()
                )
                failed |= not all(present.values())
            notes.append(line)
        print(f"  done {name}", file=sys.stderr, flush=True)
    print(
        format_table(
            [
                "problem",
                "sequence",
                "cost",
                "status",
                "steps",
                "seq ms",
                "solve ms",
                "cpu ms",
                "ms-src",
                "dt-src",
                "verify",
                "rest",
                f"cli --search {SEARCH} s",
                "target",
                "result",
            ],
            rows,
            right=[False, False, True, False, False, *[True] * 8, False, False],
        )
    )
    print(
        "seq ms: solve_reference(problem, sequence=found); solve ms: solve_reference(problem) "
        "(full search), cpu ms: its process CPU time; solve ms split into ms-src (the "
        "multi-start source), dt-src (the transcription source), verify (the judge's "
        "re-simulations) and rest; steps: DOP853 steps per phase; targets apply to solve ms "
        "(library) and to the CLI process (paper)"
    )
    for line in notes:
        print(line)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
