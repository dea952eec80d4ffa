"""Gradient descent through the differentiable simulation: speed, accuracy, set-up, memory.

Five tables, each measured in this one run:

1. **Per iteration** (loss + full gradient, what one iteration of the paper's plain gradient
   descent costs) at the initial guess of ``--scene`` (default ``single-collision``,
   N = 480), float64, for every contact model of :mod:`hybridoc.solvers.contacts` and both
   integrators, on the compiled path (:class:`~hybridoc.solvers.compiled.CompiledLoss`, in
   CasADi's virtual machine and as the C code of :mod:`hybridoc.solvers.codegen`) and on
   the torch path (:class:`~hybridoc.solvers.simulator.Simulator` + autograd), beside the
   paper's own PyTorch implementation (float32), timed in the same run. The C code is timed
   through three call paths, interleaved call by call (round robin, so that load moves them
   alike): ``C native`` (:meth:`~hybridoc.solvers.compiled.CompiledLoss.value_and_grad`, what
   gd calls: the generated C through :class:`~hybridoc.solvers.codegen.NativeFunction`, raw
   pointers), ``C casadi call`` (the same library through ``casadi.Function``'s call on numpy
   arrays, the call path before) and ``C torch autograd`` (:meth:`CompiledLoss.loss` and
   ``backward``, what this table timed until then). The paper's script is copied
   to a scratch folder with ``train_iters`` set and run twice (1 and 1 + ``--paper-iters``
   iterations); the difference of the two times, divided by ``--paper-iters``, is its time
   per iteration. Stretch target: 1000x the paper's speed on single-collision, by wall time
   and by CPU time both (load inflates the paper's longer runs more than ours).
2. **Whole solves**: ``hybridoc solve single-collision --method gd`` and multiple-collision
   with 32 starts (``--starts 32``, or ``hybridoc.solve(..., starts=32)`` where the CLI has
   no ``--starts``) as whole processes: the first run with an empty C-code cache (cold),
   then the median of ``--solve-repeats`` (warm); the true cost and its gap to the HMP
   optimum; peak memory (``ru_maxrss`` of the process); the C libraries in the cache as
   each run starts (the warm runs must find the cold run's). Python's bytecode cache is on
   (``PYTHONPYCACHEPREFIX`` beside the C cache, ``PYTHONDONTWRITEBYTECODE`` dropped), as in
   a user's installation. Targets: single < 2 s and within 0.05%; multiple < 10 s and
   within 0.1%; < 600 MB.
3. **Set-up** of the compiled loss (construction from the scene + the first loss/gradient
   call), exact integrator, with the background C code generation off
   (``HYBRIDOC_CODEGEN=0``): against N (single-collision at N = 480, 2400, 9600; target
   < 0.5 s at 9600) and against the number of discs (a grid of 2, 4, 8, 16 discs and a
   wall, built in code; target < 5 s at 16).
4. **CUDA**: rollouts per second of the batched torch simulator at B = 1, 1024, 65536 in
   float32 and float64 and the largest relative difference of the loss from the CPU's
   float64 one; one line ``CUDA: not checked (no GPU)`` without a GPU.

Run it by path; ``--quick`` takes few repeats (a smoke run of about two minutes)::

    .venv/bin/python benchmarks/bench_gd.py [--quick] [--skip solve] [--peer DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from _timing import (
    PEER_DEFAULT,
    fmt_ms,
    hybridoc_command,
    machine_line,
    run_process,
    verdict,
)

from hybridoc.cli._util import format_table

SECTIONS = ("iter", "solve", "setup", "cuda")
PAPER_SCRIPTS = {
    "single-collision": "single_collision/single_torch.py",
    "multiple-collision": "multiple_collisions/multiple_torch.py",
}
OPTIMA = {"single-collision": 0.31141687035847165, "multiple-collision": 0.356279430543373}
STRETCH_SPEEDUP = 1000.0
PEAK_TARGET_MB = 600.0
#: whole solves: (problem, starts, wall-time target s, relative gap target)
SOLVES = [("single-collision", 1, 2.0, 5e-4), ("multiple-collision", 32, 10.0, 1e-3)]
SETUP_STEPS = (480, 2400, 9600)
SETUP_STEPS_TARGET = (9600, 0.5)
SETUP_DISCS = (2, 4, 8, 16)
SETUP_DISCS_TARGET = (16, 5.0)
CUDA_SIZES = (1, 1024, 65536)


@contextmanager
def codegen_env(value: str | None) -> Iterator[None]:
    """``HYBRIDOC_CODEGEN`` set to ``value`` (removed for None) while constructing losses
    (:class:`~hybridoc.solvers.codegen.Accelerated` reads it when it is created)."""
    old = os.environ.get("HYBRIDOC_CODEGEN")
    if value is None:
        os.environ.pop("HYBRIDOC_CODEGEN", None)
    else:
        os.environ["HYBRIDOC_CODEGEN"] = value
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("HYBRIDOC_CODEGEN", None)
        else:
            os.environ["HYBRIDOC_CODEGEN"] = old


# ---------------------------------------------------------------------------- the paper
_PAPER_RUNNER = """\
import json, resource, runpy, sys, time
import numpy, torch  # imported before the clock starts
t0, c0 = time.perf_counter(), time.process_time()
runpy.run_path(sys.argv[1], run_name="__main__")
print(json.dumps({"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0,
                  "maxrss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}))
"""


def paper_per_iteration(peer: Path, scene: str, iters: int, repeats: int) -> dict[str, Any]:
    """The paper's script run with 1 and ``1 + iters`` iterations; the difference per
    iteration (median over ``repeats`` pairs). ``{"error": ...}`` when it cannot run."""
    script = peer / PAPER_SCRIPTS.get(scene, "")
    if scene not in PAPER_SCRIPTS or not script.is_file():
        return {"error": f"the paper's implementation is not at {script} (pass --peer DIR)"}
    text = script.read_text()
    walls, cpus = [], []
    with tempfile.TemporaryDirectory(prefix="hybridoc-peer-") as tmp:
        runner = Path(tmp) / "run_peer.py"
        runner.write_text(_PAPER_RUNNER)
        copies = {}
        for k in (1, 1 + iters):
            body, n1 = re.subn(r"train_iters\s*=\s*\d+", f"train_iters = {k}", text)
            body, n2 = re.subn(r"verbose\s*=\s*True", "verbose = False", body)
            if n1 != 1 or n2 != 1:
                return {"error": f"cannot set train_iters/verbose in {script}"}
            copies[k] = Path(tmp) / f"{script.stem}_{k}.py"
            copies[k].write_text(body)
        for _ in range(repeats):
            out = {}
            for k, path in copies.items():
                res = run_process([sys.executable, str(runner), str(path)], cwd=tmp, timeout=900)
                if res.returncode != 0:
                    return {"error": f"the paper's script failed: {res.stderr.strip()[-300:]}"}
                out[k] = json.loads(res.stdout.strip().splitlines()[-1])
            walls.append((out[1 + iters]["wall"] - out[1]["wall"]) / iters)
            cpus.append((out[1 + iters]["cpu"] - out[1]["cpu"]) / iters)
    return {"wall": statistics.median(walls), "min": min(walls), "cpu": statistics.median(cpus)}


# ---------------------------------------------------------------------------- per iteration
def _wait_for_c(loss: Any, limit: float) -> str:
    """Wait until the C version of a CompiledLoss's loss and gradient is loaded; a status
    word."""
    fns = [f for f in (getattr(loss, "_value_grad", None),) if f is not None]
    if not fns:
        return "unknown"  # the private attributes changed: cannot tell
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < limit:
        if all(f.compiled or f.error for f in fns):
            break
        time.sleep(0.1)
    if fns[0].compiled:
        return "ready"
    return f"failed: {fns[0].error[:80]}" if fns[0].error else f"not ready after {limit:.0f} s"


def per_iteration(
    scene: str, repeats: int, torch_repeats: int, codegen_wait: float
) -> list[dict[str, Any]]:
    """One row per (contact model, integrator, path) that exists; n/a rows say why not."""
    import numpy as np
    import torch

    from hybridoc.errors import HybridocError
    from hybridoc.problems import load_problem
    from hybridoc.solvers import codegen
    from hybridoc.solvers.compiled import CompiledLoss
    from hybridoc.solvers.contacts import contact_model, model_names
    from hybridoc.solvers.gd import INTEGRATORS
    from hybridoc.solvers.simulator import Simulator

    problem = load_problem(scene)
    u0 = torch.tensor(problem.initial_controls(), dtype=torch.float64)

    def iteration(model: Any) -> float:
        u = u0.clone().requires_grad_(True)
        loss = model.loss(u)
        loss.backward()
        return float(loss.detach())

    def interleaved(calls: dict[str, Any], runs: int) -> dict[str, dict[str, Any]]:
        """Each callable once per round, ``runs`` rounds: medians of each."""
        for call in calls.values():
            call()  # warm-up
        walls: dict[str, list[float]] = {k: [] for k in calls}
        cpus: dict[str, list[float]] = {k: [] for k in calls}
        for _ in range(runs):
            for key, call in calls.items():
                t0, c0 = time.perf_counter(), time.process_time()
                call()
                walls[key].append(time.perf_counter() - t0)
                cpus[key].append(time.process_time() - c0)
        return {
            k: {
                "wall": statistics.median(walls[k]),
                "min": min(walls[k]),
                "cpu": statistics.median(cpus[k]),
            }
            for k in calls
        }

    def c_paths(loss: Any) -> list[dict[str, Any]]:
        """The C library of ``loss`` through its three call paths (module docstring)."""
        u_np = problem.initial_controls()
        vg = loss._value_grad  # the Accelerated loss-and-gradient function

        def casadi_call() -> float:
            J, gx, gU = vg.fn(loss._x0, u_np.T)  # CasADi's call of the same library
            np.asarray(gU).T.copy(), np.asarray(gx).ravel()
            return float(J)

        def native() -> float:
            return loss.value_and_grad(u_np)[0]

        calls = {"C native": native, "C casadi call": casadi_call}
        calls["C torch autograd"] = lambda: iteration(loss)
        values = {k: float(f()) for k, f in calls.items()}
        if vg.native is None:
            calls.pop("C native")  # value_and_grad is CasADi's call then: not a third path
        times = interleaved(calls, repeats)
        out = [{"path": k, "loss": values[k]} | times[k] for k in calls]
        if vg.native is None:
            out.insert(0, {"path": "C native", "na": "library not bound through ctypes"})
        return out

    def timed(model: Any, runs: int) -> dict[str, Any]:
        value = iteration(model)  # warm-up
        walls, cpus = [], []
        for _ in range(runs):
            t0, c0 = time.perf_counter(), time.process_time()
            iteration(model)
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
        return {
            "wall": statistics.median(walls),
            "min": min(walls),
            "cpu": statistics.median(cpus),
            "loss": value,
        }

    def exact_ok(name: str) -> bool:
        model = contact_model(name)
        return model.impulse_based and getattr(model, "toi", None) == "both"

    rows: list[dict[str, Any]] = []
    compiled = [n for n in model_names() if contact_model(n).compiled]
    c_errors: dict[tuple[str, str], str] = {}
    c_state: dict[tuple[str, str], str] = {}
    # the C versions first, so that no compilation runs while anything else is timed
    c_losses = {}
    if codegen.enabled():
        with codegen_env("1"):
            for name in compiled:
                for integ in INTEGRATORS:
                    if integ != "exact" or exact_ok(name):
                        try:
                            loss = CompiledLoss(problem, name, integ, toi="both")
                        except HybridocError as exc:
                            c_errors[name, integ] = str(exc)
                            continue
                        c_losses[name, integ] = loss
                        u_np = problem.initial_controls()
                        for _ in range(codegen.HOT_CALLS):  # hot: its compilation starts
                            loss.value_and_grad(u_np)
        # one compilation at a time, in the background: wait for all before timing anything
        t0 = time.perf_counter()
        c_state = {
            key: _wait_for_c(loss, max(1.0, codegen_wait - (time.perf_counter() - t0)))
            for key, loss in c_losses.items()
        }
        print(f"  C code ready after {time.perf_counter() - t0:.1f} s", file=sys.stderr)

    def compiled_rows(name: str, integ: str, base: dict[str, str]) -> list[dict[str, Any]]:
        key = (name, integ)
        if key in c_errors:
            return [base | {"path": "compiled", "na": c_errors[key][:80]}]
        out = []
        if key in c_losses and c_state[key] in ("ready", "unknown"):
            out += [base | row for row in c_paths(c_losses[key])]
        elif key in c_losses:
            out.append(base | {"path": "C native", "na": f"C code {c_state[key]}"})
        else:
            off = "codegen off (HYBRIDOC_CODEGEN=0 or no C compiler)"
            out.append(base | {"path": "C native", "na": off})
        try:
            with codegen_env("0"):
                loss = CompiledLoss(problem, name, integ, toi="both")
        except HybridocError as exc:
            return out + [base | {"path": "compiled VM", "na": str(exc)[:80]}]
        return out + [base | {"path": "compiled VM"} | timed(loss, max(3, repeats // 10))]

    for name in model_names():
        for integ in INTEGRATORS:
            base = {"contact": name, "integrator": integ}
            if integ == "exact" and not exact_ok(name):
                rows.append(base | {"path": "-", "na": "exact needs an impulse model"})
                continue
            if name in compiled:
                rows += compiled_rows(name, integ, base)
            try:
                sim = Simulator(problem, contact=name, toi="both", integrator=integ)
            except HybridocError as exc:
                rows.append(base | {"path": "torch", "na": str(exc)[:80]})
            else:
                rows.append(base | {"path": "torch"} | timed(sim, torch_repeats))
            print(f"  timed {name}/{integ}", file=sys.stderr, flush=True)
    return rows


def print_per_iteration(scene: str, rows: list[dict[str, Any]], paper: dict[str, Any]) -> None:
    paper_ms = 1e3 * paper["wall"] if "wall" in paper else None
    table = []
    if paper_ms is not None:
        table.append(
            ["paper (float32)", "-", "torch", fmt_ms(paper["wall"]), fmt_ms(paper["min"])]
            + [fmt_ms(paper["cpu"]), "1x", "1x", "-"]
        )
    best = None
    for r in rows:
        if "na" in r:
            table.append([r["contact"], r["integrator"], r["path"], "n/a", "", "", "", "", r["na"]])
            continue
        speed = paper_ms / (1e3 * r["wall"]) if paper_ms else None
        speed_cpu = paper["cpu"] / r["cpu"] if paper_ms and r["cpu"] > 0 else None
        if speed and (best is None or speed > best[0]):
            best = (speed, r)
        table.append(
            [
                r["contact"],
                r["integrator"],
                r["path"],
                fmt_ms(r["wall"]),
                fmt_ms(r["min"]),
                fmt_ms(r["cpu"]),
                _ratio(speed),
                _ratio(speed_cpu),
                f"{r['loss']:.12g}",
            ]
        )
    print()
    print(f"[1] per iteration (loss + gradient), {scene} at its initial guess, float64")
    print(
        format_table(
            ["contact", "integrator", "path", "ms/iter", "min ms", "cpu ms"]
            + ["vs paper", "vs paper cpu", "loss"],
            table,
            right=[False, False, False, True, True, True, True, True, False],
        )
    )
    print(
        "ms/iter: median wall time; cpu ms: median process CPU time (less sensitive to other "
        "load); vs paper: the paper's ms/iter / ours, both measured in this run; vs paper cpu: "
        "the same with CPU times (the paper's over all its torch threads); C native: what gd "
        "calls; C casadi call: the same library through casadi.Function (the call before "
        "NativeFunction); C torch autograd: CompiledLoss.loss + backward"
    )
    if "error" in paper:
        print(f"paper: not measured: {paper['error']}")
    elif best is not None and scene == "single-collision":
        lines = []
        for integ in ("exact", "symplectic-euler"):
            lines += [
                (f"direct, {integ}, C native" + (" (gd's default)" if integ == "exact" else ""), r)
                for r in rows
                if (r["contact"], r["integrator"], r["path"]) == ("direct", integ, "C native")
                and "na" not in r
            ]
        lines.append(("fastest", best[1]))
        for what, r in lines:
            # met only when both the wall-time and the CPU-time ratios reach it: load inflates
            # the paper's longer runs more than ours, which flatters the wall-time ratio
            speed = paper_ms / (1e3 * r["wall"])
            speed_cpu = paper["cpu"] / r["cpu"] if r["cpu"] > 0 else 0.0
            ok = min(speed, speed_cpu) >= STRETCH_SPEEDUP
            print(
                f"stretch target {STRETCH_SPEEDUP:.0f}x the paper, {what}: {r['contact']}/"
                f"{r['integrator']}/{r['path']} {speed:.0f}x wall, {speed_cpu:.0f}x cpu: "
                f"{verdict(ok)}"
            )


def _ratio(x: float | None) -> str:
    if not x:
        return "-"
    return f"{x:.0f}x" if x >= 10 else f"{x:.2g}x"


# ---------------------------------------------------------------------------- whole solves
_MULTISTART_PROGRAM = """\
import json, sys, hybridoc
s = hybridoc.solve(sys.argv[1], method="gd", starts=int(sys.argv[2]))
print(json.dumps({"cost": s.cost, "status": s.status.value, "timings": s.timings}))
"""


def cli_has_starts() -> bool:
    res = run_process([*hybridoc_command(), "solve", "--help"], timeout=120)
    return "--starts" in res.stdout


def _imports_torch(cmd: list[str], env: dict[str, str]) -> bool | None:
    """Whether the solve ``cmd`` imports torch: one more run under ``python -X importtime``
    (not timed); ``None`` when it fails."""
    prog = cmd[1:] if cmd[0] == sys.executable else cmd
    res = run_process([sys.executable, "-X", "importtime", *prog], env=env, timeout=900)
    if res.returncode not in (0, 1) or res.timed_out:
        return None
    return any(line.rstrip().endswith("| torch") for line in res.stderr.splitlines())


def whole_process_env(cache: str) -> dict[str, str]:
    """The environment of a whole-process run: the C-code cache ``cache`` and Python's
    bytecode cache on, as a user's installation has it.

    ``PYTHONDONTWRITEBYTECODE`` (set in some sandboxes) made every run compile hybridoc's
    sources again (about 0.1-0.3 s of each run); the bytecode goes to a folder beside the
    C cache instead (``PYTHONPYCACHEPREFIX``), so the cold run compiles it and the warm runs
    read it, and the repository gets no ``__pycache__``.
    """
    env = dict(os.environ, HYBRIDOC_CACHE=cache)
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    env["PYTHONPYCACHEPREFIX"] = str(Path(cache) / "pycache")
    return env


def whole_solves(repeats: int) -> list[dict[str, Any]]:
    """Each case: one cold run (empty C-code and bytecode caches), then ``repeats`` warm
    runs (:func:`whole_process_env`)."""
    has_starts = cli_has_starts()
    out = []
    for name, starts, target_s, target_gap in SOLVES:
        if starts == 1 or has_starts:
            cmd = [*hybridoc_command(), "solve", name, "--method", "gd"]
            cmd += ["--starts", str(starts)] if starts > 1 else []
            shown = " ".join(["hybridoc", *cmd[1:]])
            cmd.append("--json")
        else:
            cmd = [sys.executable, "-c", _MULTISTART_PROGRAM, name, str(starts)]
            shown = f"python -c 'hybridoc.solve({name!r}, method=\"gd\", starts={starts})'"
        walls, solve_s, peak, errors, payload = [], [], 0.0, [], None
        libs_before: list[int] = []
        with tempfile.TemporaryDirectory(prefix="hybridoc-cache-") as cache:
            env = whole_process_env(cache)
            for _ in range(1 + repeats):
                libs_before.append(len(list(Path(cache).glob("*.so"))))
                res = run_process(cmd, env=env, timeout=900)
                if res.returncode not in (0, 1) or res.timed_out:
                    errors.append(f"exit {res.returncode}: {res.stderr.strip()[-200:]}")
                    break
                payload = json.loads(res.stdout.strip().splitlines()[-1])
                walls.append(res.wall_s)
                solve_s.append(payload.get("timings", {}).get("solve_time_s", float("nan")))
                peak = max(peak, res.maxrss_mb)
            libs = len(list(Path(cache).glob("*.so")))
            torch_imported = _imports_torch(cmd, env) if not errors else None
        row: dict[str, Any] = {
            "problem": name,
            "cmd": shown,
            "target_s": target_s,
            "target_gap": target_gap,
            "errors": errors,
            "libs": libs,
            # C libraries in the cache when each run started: a warm run starts with the
            # cold run's (0 would mean the cold run lost its compilation)
            "libs_before": libs_before,
            "torch": torch_imported,
        }
        if walls and payload is not None:
            warm = walls[1:] or walls[:1]
            row |= {
                "cold": walls[0],
                "warm": statistics.median(warm),
                "solve_warm": statistics.median(solve_s[1:] or solve_s[:1]),
                "cost": float(payload["cost"]),
                "status": payload["status"],
                "gap": float(payload["cost"]) / OPTIMA[name] - 1.0,
                "peak": peak,
            }
        out.append(row)
        print(f"  solved {name}", file=sys.stderr, flush=True)
    return out


def print_solves(rows: list[dict[str, Any]], repeats: int) -> None:
    codegen = os.environ.get("HYBRIDOC_CODEGEN", "1") not in ("0", "false", "no")
    table = []
    for r in rows:
        if "warm" not in r:
            table.append([r["problem"], "failed", *[""] * 10])
            continue
        ok_t, ok_gap = r["warm"] < r["target_s"], abs(r["gap"]) <= r["target_gap"]
        table.append(
            [
                r["problem"],
                f"{r['cold']:.2f}",
                f"{r['warm']:.2f}",
                f"{r['solve_warm']:.2f}",
                f"< {r['target_s']:g} s {verdict(ok_t)}",
                f"{r['cost']:.12f}",
                f"{100 * r['gap']:+.4f}%",
                f"<= {100 * r['target_gap']:g}% {verdict(ok_gap)}",
                r["status"],
                {None: "?", True: "yes", False: "no"}[r["torch"]],
                f"{r['peak']:.0f}",
                verdict(r["peak"] < PEAK_TARGET_MB),
            ]
        )
    print()
    print(
        f"[2] whole solves as processes: cold = first run with an empty C-code cache, warm = "
        f"median of the next {repeats}; C code generation {'on' if codegen else 'off'}"
    )
    print(
        format_table(
            [
                "problem",
                "cold s",
                "warm s",
                "solve s",
                "time target",
                "cost",
                "gap",
                "gap target",
                "status",
                "torch",
                "peak MB",
                f"< {PEAK_TARGET_MB:.0f} MB",
            ],
            table,
            right=[False, True, True, True, False, True, True, False, False, False, True, False],
        )
    )
    print(
        "cold s: includes compiling hybridoc's bytecode and the C code (hybridoc solve waits "
        "for its compilations after its output, so that the warm runs find them); solve s: the "
        "solver's own solve_time_s (warm), without interpreter start-up and imports; gap: "
        "cost / HMP optimum - 1; torch: whether the solve imports torch (one more run under "
        "python -X importtime); peak MB: the process's ru_maxrss (max over runs)"
    )
    for r in rows:
        print(
            f"{r['problem']}: {r['cmd']} ({r['libs']} C libraries cached after the runs; "
            f"cached when each run started: {r.get('libs_before')})"
        )
        for err in r["errors"]:
            print(f"{r['problem']}: failed: {err}")


# ---------------------------------------------------------------------------- set-up
def grid_scene(n_discs: int, steps: int = 480) -> Any:
    """A striker and ``n_discs - 1`` passive discs on a grid below a wall y = 1.2."""
    import numpy as np

    from hybridoc.problems import Disc, Scene, Wall

    discs = [
        Disc(
            name="striker",
            position=(-1.5, 0.0),
            radius=0.1,
            actuated=True,
            initial_control=np.array([3.0, 0.0]),
        )
    ]
    cols = max(1, int(np.ceil(np.sqrt(n_discs - 1))))
    for k in range(1, n_discs):
        r, c = divmod(k - 1, cols)
        discs.append(
            Disc(
                name=f"d{k}",
                position=(-0.8 + 0.3 * c, -0.45 + 0.3 * r),
                radius=0.1,
                target=(1.0, 0.5) if k == n_discs - 1 else None,
            )
        )
    wall = Wall(point=(0.0, 1.2), normal=(0.0, -1.0), name="top")
    return Scene(
        horizon=1.0, discs=tuple(discs), walls=(wall,), steps=steps, name=f"grid-{n_discs}"
    )


def setup_times(repeats: int) -> list[dict[str, Any]]:
    """Construction (scene -> CompiledLoss) and first value_and_grad, codegen off."""
    from hybridoc.problems import load_problem
    from hybridoc.problems.physics import contacts
    from hybridoc.solvers.compiled import CompiledLoss

    base = load_problem("single-collision")
    cases = [(f"single-collision N={n}", lambda n=n: base.with_steps(n)) for n in SETUP_STEPS]
    cases += [(f"grid {n} discs N=480", lambda n=n: grid_scene(n)) for n in SETUP_DISCS]
    rows = []
    with codegen_env("0"):
        CompiledLoss(grid_scene(2, steps=10), "direct", "exact")  # one-time imports
        for label, make in cases:
            builds, firsts = [], []
            for _ in range(repeats):
                scene = make()  # a fresh Scene: nothing cached from the last repeat
                u = scene.initial_controls()
                t0 = time.perf_counter()
                loss = CompiledLoss(scene, "direct", "exact")
                t1 = time.perf_counter()
                loss.value_and_grad(u)
                t2 = time.perf_counter()
                builds.append(t1 - t0)
                firsts.append(t2 - t1)
            totals = [b + f for b, f in zip(builds, firsts, strict=True)]
            rows.append(
                {
                    "label": label,
                    "N": scene.steps,
                    "discs": scene.n_discs,
                    "contacts": len(contacts(scene.n_discs, len(scene.walls))),
                    "build": statistics.median(builds),
                    "first": statistics.median(firsts),
                    "total": statistics.median(totals),
                }
            )
            print(f"  set up {label}", file=sys.stderr, flush=True)
    return rows


def print_setup(rows: list[dict[str, Any]], repeats: int) -> None:
    table = []
    for r in rows:
        target = None
        if r["label"].startswith("single") and r["N"] == SETUP_STEPS_TARGET[0]:
            target = SETUP_STEPS_TARGET[1]
        if r["label"].startswith("grid") and r["discs"] == SETUP_DISCS_TARGET[0]:
            target = SETUP_DISCS_TARGET[1]
        table.append(
            [
                r["label"],
                r["N"],
                r["discs"],
                r["contacts"],
                fmt_ms(r["build"]),
                fmt_ms(r["first"]),
                fmt_ms(r["total"]),
                "-" if target is None else f"< {1e3 * target:.0f} ms",
                verdict(None if target is None else r["total"] < target),
                "off",
            ]
        )
    print()
    print(
        f"[3] set-up of the compiled loss (direct, toi both, exact integrator), median of "
        f"{repeats}; HYBRIDOC_CODEGEN=0 (no background C compilation)"
    )
    print(
        format_table(
            [
                "problem",
                "N",
                "discs",
                "contacts",
                "build ms",
                "first call ms",
                "total ms",
                "target",
                "result",
                "codegen",
            ],
            table,
            right=[False, True, True, True, True, True, True, False, False, False],
        )
    )
    print("build: CompiledLoss(scene, ...) from a fresh Scene; first call: value_and_grad")


# ---------------------------------------------------------------------------- CUDA
def cuda_rollouts(device: str, sizes: tuple[int, ...], repeats: int) -> list[list[Any]] | None:
    """Rollouts per second of the batched Simulator on ``device``; None without CUDA."""
    import numpy as np
    import torch

    from hybridoc.problems import load_problem
    from hybridoc.solvers.simulator import Simulator

    if device == "cuda" and not torch.cuda.is_available():
        return None

    def sync() -> None:
        if device == "cuda":
            torch.cuda.synchronize()

    problem = load_problem("single-collision")
    rng = np.random.default_rng(0)
    u_np = problem.initial_controls()[None] + 0.3 * rng.standard_normal(
        (max(sizes), problem.steps, problem.n_controls)
    )
    n_check = 64
    cpu = Simulator(problem, integrator="exact", dtype=torch.float64, device="cpu")
    with torch.no_grad():
        ref = cpu.loss(torch.as_tensor(u_np[:n_check])).numpy()
    rows = []
    for dtype in (torch.float32, torch.float64):
        sim = Simulator(problem, integrator="exact", dtype=dtype, device=device)
        for B in sizes:
            u = torch.as_tensor(u_np[:B], dtype=dtype, device=device)
            with torch.no_grad():
                sim.loss(u)  # warm-up
                sync()
                times = []
                for _ in range(repeats):
                    t0 = time.perf_counter()
                    out = sim.loss(u)
                    sync()
                    times.append(time.perf_counter() - t0)
            k = min(B, n_check)
            got = out[:k].double().cpu().numpy()
            rel = float(np.max(np.abs(got - ref[:k]) / np.abs(ref[:k])))
            t = statistics.median(times)
            name = str(dtype).removeprefix("torch.")
            rows.append([name, B, fmt_ms(t), f"{B / t:.3g}", f"{rel:.1e}"])
            print(f"  {device} {dtype} B={B}", file=sys.stderr, flush=True)
    return rows


def print_cuda(rows: list[list[Any]] | None, device: str, repeats: int) -> None:
    print()
    if rows is None:
        print("CUDA: not checked (no GPU)")
        return
    print(
        f"[4] batched torch simulator on {device} (single-collision, direct, exact, no grad), "
        f"median of {repeats}"
    )
    print(
        format_table(
            ["dtype", "B", "ms/rollout batch", "rollouts/s", "max rel diff vs CPU float64"],
            rows,
            right=[False, True, True, True, True],
        )
    )


# ---------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", action="append", help="per-iteration scene (repeatable)")
    p.add_argument("--peer", type=Path, default=PEER_DEFAULT, help="the paper's code")
    p.add_argument("--repeats", type=int, default=200, help="compiled iterations timed")
    p.add_argument("--torch-repeats", type=int, default=5, help="torch iterations timed")
    p.add_argument("--paper-iters", type=int, default=10, help="extra paper iterations")
    p.add_argument("--paper-repeats", type=int, default=3, help="paper run pairs")
    p.add_argument("--solve-repeats", type=int, default=3, help="warm whole solves")
    p.add_argument("--setup-repeats", type=int, default=3, help="set-ups per size")
    p.add_argument("--cuda-repeats", type=int, default=5, help="timed batches per size")
    p.add_argument("--codegen-wait", type=float, default=300.0, help="max s to wait for C")
    p.add_argument("--skip", action="append", default=[], choices=SECTIONS)
    p.add_argument("--quick", action="store_true", help="few repeats: a smoke run")
    p.add_argument("--cuda-device", default="cuda", help=argparse.SUPPRESS)  # "cpu": test
    args = p.parse_args(argv)
    if args.quick:
        args.repeats, args.torch_repeats = 20, 1
        args.paper_iters, args.paper_repeats = 3, 1
        args.solve_repeats, args.setup_repeats, args.cuda_repeats = 1, 1, 2
    scenes = args.scene or ["single-collision"]

    print(machine_line(), flush=True)
    if "iter" not in args.skip:
        for scene in scenes:
            paper = paper_per_iteration(args.peer, scene, args.paper_iters, args.paper_repeats)
            print(f"  timed the paper on {scene}", file=sys.stderr, flush=True)
            rows = per_iteration(scene, args.repeats, args.torch_repeats, args.codegen_wait)
            print_per_iteration(scene, rows, paper)
            sys.stdout.flush()
    if "solve" not in args.skip:
        print_solves(whole_solves(args.solve_repeats), args.solve_repeats)
        sys.stdout.flush()
    if "setup" not in args.skip:
        print_setup(setup_times(args.setup_repeats), args.setup_repeats)
        sys.stdout.flush()
    if "cuda" not in args.skip:
        sizes = CUDA_SIZES if args.cuda_device == "cuda" else (1, 64)
        rows = cuda_rollouts(args.cuda_device, sizes, args.cuda_repeats)
        print_cuda(rows, args.cuda_device, args.cuda_repeats)
    print(f"\nload average at the end: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
