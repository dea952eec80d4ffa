"""``hybridoc reference SCENE [--sequence EVENTS] [--initial FILE] [--json] [--out DIR]``.

Solves the scene by HMP shooting (:func:`hybridoc.reference.solve_reference`), prints the
cost, events, residual and timing (or one JSON object with ``--json``), and with ``--out``
writes the Solution (``DIR/reference.npz`` + ``.json``) and figures: the trajectory, the
control against time and the costates with their jumps.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from hybridoc.cli_util import (
    add_json_out,
    emit_json,
    ensure_dir,
    fmt,
    format_table,
    resolve_scene,
    say,
    scene_arg,
)

__all__ = ["register", "run", "write_outputs"]


def register(subparsers: Any) -> None:
    """Add the ``reference`` subcommand."""
    p = subparsers.add_parser(
        "reference",
        help="the optimal control by shooting on the hybrid minimum principle",
        description=(
            "Solve SCENE exactly by shooting on the hybrid minimum principle. Without "
            "--sequence the event sequence is discovered from the scene's initial guess; the "
            "result is re-simulated by the event-exact evaluator before it is reported."
        ),
    )
    scene_arg(p)
    p.add_argument(
        "--sequence",
        metavar="EVENTS",
        default=None,
        help="comma-separated guard names in event order, e.g. 'ball1|ball2,ball2|wall' "
        "(an empty string: no event)",
    )
    p.add_argument(
        "--initial",
        metavar="FILE",
        type=Path,
        default=None,
        help="start from another solution: a saved Solution (.json/.npz) or controls "
        "(.npy/.csv); its events and adjoint costate start Newton",
    )
    p.add_argument("--verbose", action="store_true", help="print Newton's iterations to stderr")
    add_json_out(p, out_help="write the Solution and figures to this directory")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Handler of ``hybridoc reference``."""
    from hybridoc.reference import solve_reference

    scene = resolve_scene(args.scene)
    initial = _load_initial(args.initial, scene) if args.initial is not None else None
    out_dir = None if args.out is None else ensure_dir(args.out)  # fail before the solve
    sol = solve_reference(scene, sequence=args.sequence, initial=initial, verbose=args.verbose)
    out = {
        "scene": scene.name,
        "cost": sol.cost,
        "terminal_cost": sol.terminal_cost,
        "running_cost": sol.running_cost,
        "events": sol.events,
        "sequence": sol.info["sequence"],
        "residual": sol.info["residual"],
        "newton_iterations": sol.info["newton_iterations"],
        "grazing": sol.info["grazing"],
        "solve_time_s": sol.timings["solve_time_s"],
    }
    files: list[Path] = []
    if out_dir is not None:
        files = write_outputs(scene, sol, out_dir)
        out["files"] = [str(f) for f in files]
    if args.json:
        emit_json(out)
        return 0
    say(args, f"reference for {scene.name} (N = {scene.steps}, T = {fmt(scene.horizon)})")
    say(args, f"  cost          {sol.cost!r}")
    say(args, f"  terminal      {sol.terminal_cost!r}")
    say(args, f"  running       {sol.running_cost!r}")
    say(
        args,
        f"  HMP residual  {sol.info['residual']:.2e} (max norm, "
        f"{sol.info['newton_iterations']} Newton iterations)",
    )
    say(
        args,
        f"  solve time    {sol.timings['solve_time_s']:.3f} s "
        f"(verification {sol.timings.get('verify_time_s', 0.0):.3f} s)",
    )
    if sol.info["grazing"]:
        say(args, "  WARNING: grazing event (approach speed ~ 0): the HMP may not hold there")
    rows = [
        [k, repr(e["time"]), e["kind"], ", ".join(e["bodies"])]
        for k, e in enumerate(sol.events, start=1)
    ]
    if rows:
        say(args, "  events:")
        table = format_table(
            ["#", "time", "kind", "bodies"], rows, right=[True, False, False, False]
        )
        say(args, "\n".join("    " + line for line in table.splitlines()))
    else:
        say(args, "  no events")
    for f in files:
        say(args, f"wrote {f}")
    return 0


def _load_initial(path: Path, scene: Any) -> Any:
    """Controls from a saved Solution or a controls file (user errors: HybridocError)."""
    from hybridoc.errors import ControlsError
    from hybridoc.io import load_controls
    from hybridoc.solution import Solution

    if path.suffix.lower() in (".json", ".npz"):
        try:
            return Solution.load(path).controls
        except (OSError, ValueError, KeyError) as exc:
            raise ControlsError(f"cannot read the solution {str(path)!r}: {exc}") from None
    return load_controls(path, scene)


def write_outputs(scene: Any, sol: Any, out: Path) -> list[Path]:
    """Save the Solution and the three figures; return the files written."""
    from hybridoc.callable_eval import evaluate_callable
    from hybridoc.plotting import plot_controls, plot_costates, plot_scene, save_figure
    from hybridoc.reference import reference_control

    ocp = scene.to_ocp()
    files = list(sol.save(out / "reference"))
    u, bps = reference_control(sol)
    sim = evaluate_callable(ocp, u, breakpoints=bps)
    # draw the paths from the reference's own samples (grid and events): the integrator's
    # steps are too coarse to show the cubic arcs
    sim = dataclasses.replace(sim, times=sol.state_times, states=sol.states)
    title = f"{scene.name}: reference, J = {sol.cost:.10g}"
    files.append(save_figure(plot_scene(scene, sim, title=title), out / "reference_trajectory.png"))
    times = sol.info["event_times"]
    fig = plot_controls(
        sol.time_grid,
        {"cell mean": sol.controls},
        ocp.control_labels,
        title=f"{scene.name}: optimal control u(t) (line) and its cell means",
        event_times=times,
    )
    t_fine = np.union1d(np.linspace(0, scene.horizon, 2001), times)
    for k, ax in enumerate(fig.axes[: ocp.nu]):
        # the exact control is linear between events: draw each phase separately
        edges = np.concatenate([[0.0], times, [scene.horizon]])
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            tt = t_fine[(t_fine >= a) & (t_fine <= b)]
            vals = [u(min(max(x, a), b - 1e-15 if b > a else b))[k] for x in tt]
            ax.plot(tt, vals, color="k", lw=0.9, label="u(t)" if a == 0 else None)
    fig.axes[0].legend(fontsize=8, loc="best")
    files.append(save_figure(fig, out / "reference_controls.png"))
    files.append(
        save_figure(
            plot_costates(
                sol.costate_times,
                sol.costates,
                ocp.state_labels,
                times,
                title=f"{scene.name}: costates (jumps at events)",
            ),
            out / "reference_costates.png",
        )
    )
    return files
