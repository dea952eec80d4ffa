"""The ``hybridoc`` command.

Core subcommands: ``problems``, ``show``, ``evaluate``, ``gradient`` and ``demo``. Further
subcommands come from plugin modules (see :data:`PLUGINS`); each defines
``register(subparsers)``. A user error (:class:`~hybridoc.errors.HybridocError`) ends the
command with one line ``hybridoc: error: <message>`` on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hybridoc.cli_util import (
    HybridocArgumentParser,
    add_controls_arg,
    add_json_out,
    emit_json,
    ensure_dir,
    fmt,
    format_table,
    load_controls_arg,
    resolve_scene,
    say,
    scene_arg,
)
from hybridoc.errors import HybridocError

__all__ = ["PLUGINS", "build_parser", "main"]

#: Modules that may add subcommands; a module that does not exist is skipped.
PLUGINS = (
    "hybridoc.reference.cli",
    "hybridoc.solvers.cli",
    "hybridoc.solvers.cli_contacts",
    "hybridoc.validation_cli",
)

#: The scenes evaluated by ``hybridoc demo``: the paper's two problems.
DEMO_SCENES = ("single-collision", "multiple-collision")


# ---------------------------------------------------------------------- small helpers
def _vec(p: Sequence[float]) -> str:
    return "(" + ", ".join(fmt(x, 6) for x in p) + ")"


def _events_table(events: Sequence[dict[str, Any]]) -> str:
    rows = [
        [k, _exact(e["time"]), e["kind"], ", ".join(e["bodies"])]
        for k, e in enumerate(events, start=1)
    ]
    return format_table(["#", "time", "kind", "bodies"], rows, right=[True, False, False, False])


def _exact(x: float) -> str:
    """Shortest repr that reads back to the identical float64."""
    return repr(float(x))


def _indent(text: str, prefix: str = "  ") -> str:
    return "\n".join(prefix + line for line in text.splitlines())


def _scene_header(scene: Any) -> str:
    return f"{scene.name} (N = {scene.steps}, T = {fmt(scene.horizon)})"


def _guess_text(scene: Any) -> str:
    parts = []
    for i in scene.actuated_indices:
        d = scene.discs[i]
        u = d.initial_control
        if u is None:
            parts.append(f"{d.name}: zeros")
        elif u.ndim == 1:
            parts.append(f"{d.name}: constant {_vec(u)}")
        else:
            parts.append(
                f"{d.name}: {u.shape[0]} rows, ux in [{fmt(u[:, 0].min(), 4)}, "
                f"{fmt(u[:, 0].max(), 4)}], uy in [{fmt(u[:, 1].min(), 4)}, "
                f"{fmt(u[:, 1].max(), 4)}]"
            )
    return "; ".join(parts)


def _timed(fn: Any, *args: Any, repeat: int = 1) -> tuple[Any, float]:
    """Result of ``fn(*args)`` and the best wall time of ``repeat`` calls."""
    best = float("inf")
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn(*args)
        best = min(best, time.perf_counter() - t0)
    return out, best


def _write_figures(scene: Any, ev: Any, out: Path, *, stem: str = "", label: str) -> list[Path]:
    from hybridoc.plotting import plot_controls, plot_scene, save_figure

    prefix = f"{stem}_" if stem else ""
    events = [e.time for e in ev.events]
    title = f"{scene.name}: {label}, cost {ev.cost:.6g}"
    fig = plot_scene(scene, ev, title=title)
    paths = [_save(save_figure, fig, out / f"{prefix}trajectory.png")]
    fig = plot_controls(
        scene.time_grid(),
        {label: ev.controls},
        scene.control_labels(),
        title=f"{scene.name}: controls ({label})",
        event_times=events,
    )
    paths.append(_save(save_figure, fig, out / f"{prefix}controls.png"))
    return paths


def _save(save_figure: Any, fig: Any, path: Path) -> Path:
    try:
        return save_figure(fig, path)
    except OSError as exc:
        raise HybridocError(f"cannot write {str(path)!r}: {exc.strerror or exc}") from None


# ---------------------------------------------------------------------- subcommands
def cmd_problems(args: argparse.Namespace) -> int:
    """List the built-in scenes."""
    from hybridoc.problems import builtin_names, load_scene

    rows = []
    for name in builtin_names():
        s = load_scene(name)
        rows.append([name, s.n_discs, len(s.walls), s.steps, fmt(s.horizon), s.description])
    print(
        format_table(
            ["name", "discs", "walls", "N", "T", "description"],
            rows,
            right=[False, True, True, True, True, False],
        )
    )
    print("\nshow one with: hybridoc show NAME [--plot FILE.png]")
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    """Describe a scene; optionally plot it with the initial guess's trajectory."""
    from hybridoc.evaluator import evaluate

    scene = resolve_scene(args.scene)
    lines = [f"scene {scene.name}" + (f": {scene.description}" if scene.description else "")]
    lines.append(
        f"horizon T = {fmt(scene.horizon)}, steps N = {scene.steps} (dt = {fmt(scene.dt, 6)}), "
        f"control weight eps = {fmt(scene.control_weight)}, "
        f"restitution e = {fmt(scene.restitution)}"
    )
    rows = [
        [
            d.name,
            _vec(d.position),
            _vec(d.velocity),
            fmt(d.radius),
            fmt(d.mass),
            "yes" if d.actuated else "no",
            _vec(d.target) if d.target is not None else "-",
        ]
        for d in scene.discs
    ]
    lines += ["", "discs"]
    lines.append(
        _indent(
            format_table(
                ["name", "position", "velocity", "radius", "mass", "actuated", "target"],
                rows,
                right=[False] * 7,
            )
        )
    )
    if scene.walls:
        rows = [[w.name, _vec(w.point), _vec(w.normal)] for w in scene.walls]
        lines += ["", "walls (the normal points into free space)"]
        lines.append(_indent(format_table(["name", "point", "normal"], rows, right=[False] * 3)))
    else:
        lines += ["", "walls: none"]
    targets = [d.name for d in scene.discs if d.target is not None]
    n_pairs = scene.n_discs * (scene.n_discs - 1) // 2
    lines += [
        "",
        f"controls: {', '.join(scene.control_labels())} (nu = {scene.n_controls}, "
        f"piecewise constant on N = {scene.steps} intervals)",
        f"initial guess: {_guess_text(scene)}",
        f"cost: |p(T) - target|^2 of {', '.join(targets)} "
        f"+ {fmt(scene.control_weight)} * integral |u|^2 dt",
        f"guards: {n_pairs} disc-disc, {scene.n_discs * len(scene.walls)} disc-wall",
    ]
    ev = None
    try:
        ev = evaluate(scene)
    except HybridocError as exc:
        lines.append(f"initial guess cannot be evaluated: {exc}")
    if ev is not None:
        lines.append(
            f"initial guess cost: {fmt(ev.cost)} (terminal {fmt(ev.terminal_cost)}, running "
            f"{fmt(ev.running_cost)}), {len(ev.events)} event(s)"
        )
    print("\n".join(lines))
    if args.plot is not None:
        from hybridoc.plotting import plot_scene, save_figure

        title = f"{scene.name}: initial guess, cost {ev.cost:.6g}" if ev else scene.name
        path = _save(save_figure, plot_scene(scene, ev, title=title), args.plot)
        print(f"\nwrote {path}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Evaluate controls with the event-exact judge."""
    from hybridoc.evaluator import evaluate
    from hybridoc.solution import Solution

    scene = resolve_scene(args.scene)
    controls, source = load_controls_arg(args, scene)
    if args.out is not None:
        out = ensure_dir(args.out)
    ev, seconds = _timed(evaluate, scene, controls)
    events = ev.event_dicts()
    if args.json:
        emit_json(
            {
                "scene": scene.name,
                "cost": ev.cost,
                "terminal_cost": ev.terminal_cost,
                "running_cost": ev.running_cost,
                "events": events,
            }
        )
    else:
        print(f"scene     {_scene_header(scene)}")
        print(f"controls  {source}")
        print(f"cost      {_exact(ev.cost)}")
        print(f"terminal  {_exact(ev.terminal_cost)}")
        print(f"running   {_exact(ev.running_cost)}")
        print(f"events    {len(events)}")
        if events:
            print(_indent(_events_table(events)))
    if args.out is not None:
        sol = Solution.from_evaluation(
            ev,
            method="evaluate",
            scene=scene.name,
            settings={"controls": source},
            timings={"evaluate_time_s": seconds},
        )
        try:
            written = list(sol.save(out / "solution"))
        except OSError as exc:
            raise HybridocError(f"cannot write to {str(out)!r}: {exc.strerror or exc}") from None
        label = "initial guess" if args.controls is None else Path(source).name
        written += _write_figures(scene, ev, out, label=label)
        say(args, "")
        for p in written:
            say(args, f"wrote {p}")
    return 0


def cmd_gradient(args: argparse.Namespace) -> int:
    """Exact gradient of the continuous cost (adjoint with the HMP jump relation)."""
    from hybridoc.evaluator import gradient

    scene = resolve_scene(args.scene)
    controls, source = load_controls_arg(args, scene)
    g = gradient(scene, controls)
    n = scene.n_discs
    lam0 = np.asarray(g.d_initial_state)
    d_pos = lam0[: 2 * n].reshape(n, 2)
    d_vel = lam0[2 * n : 4 * n].reshape(n, 2)
    if args.json:
        emit_json(
            {
                "scene": scene.name,
                "cost": g.cost,
                "discs": [d.name for d in scene.discs],
                "control_labels": scene.control_labels(),
                "d_cost_d_initial_position": d_pos,
                "d_cost_d_initial_velocity": d_vel,
                "d_cost_d_controls": g.d_controls,
            }
        )
        return 0
    du = np.asarray(g.d_controls)
    row, col = np.unravel_index(int(np.argmax(np.abs(du))), du.shape)
    labels = scene.control_labels()
    print(f"scene     {_scene_header(scene)}")
    print(f"controls  {source}")
    print(f"cost      {_exact(g.cost)}")
    print(f"events    {len(g.evaluation.events)}")
    print()
    print(f"dJ/du: {du.shape[0]} x {du.shape[1]} values (one per grid interval and component)")
    print(f"  norm (all values)  {fmt(np.linalg.norm(du))}")
    for k, name in enumerate(labels):
        print(f"  norm {name:<13} {fmt(np.linalg.norm(du[:, k]))}")
    print(f"  largest |dJ/du|    {fmt(abs(du[row, col]))} at interval {row}, {labels[col]}")
    print()
    print("dJ/d(initial state), per disc:")
    rows = [
        [d.name, *(fmt(x) for x in d_pos[i]), *(fmt(x) for x in d_vel[i])]
        for i, d in enumerate(scene.discs)
    ]
    table = format_table(
        ["disc", "dJ/dx0", "dJ/dy0", "dJ/dvx0", "dJ/dvy0"],
        rows,
        right=[False, True, True, True, True],
    )
    print(_indent(table))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """Evaluate the initial guesses of the paper's two problems; table and figures."""
    from hybridoc.evaluator import evaluate, gradient

    out = ensure_dir(args.out)
    rows = []
    written: list[Path] = []
    for name in DEMO_SCENES:
        scene = resolve_scene(name)
        u = scene.initial_controls()
        evaluate(scene, u)  # first call compiles the CasADi functions; time the next ones
        ev, t_eval = _timed(evaluate, scene, u, repeat=3)
        g, t_grad = _timed(gradient, scene, u, repeat=3)
        times = ", ".join(f"{e.time:.4f}" for e in ev.events) or "-"
        rows.append(
            [
                name,
                f"{ev.cost:.6f}",
                f"{ev.terminal_cost:.6f}",
                f"{ev.running_cost:.6f}",
                len(ev.events),
                times,
                f"{np.linalg.norm(g.d_controls):.6f}",
                f"{1e3 * t_eval:.1f}",
                f"{1e3 * t_grad:.1f}",
            ]
        )
        written += _write_figures(scene, ev, out, stem=name, label="initial guess")
    print("Initial guesses of the paper's problems, judged by the event-exact evaluator")
    print("(N = 480, T = 1; times are the best of 3 runs)\n")
    print(
        format_table(
            [
                "scene",
                "cost",
                "terminal",
                "running",
                "events",
                "event times",
                "|dJ/du|",
                "eval [ms]",
                "grad [ms]",
            ],
            rows,
            right=[False, True, True, True, True, False, True, True, True],
        )
    )
    print()
    for p in written:
        print(f"wrote {p}")
    return 0


# ---------------------------------------------------------------------- parser
def _load_plugins() -> list[Any]:
    modules = []
    for name in PLUGINS:
        try:
            modules.append(importlib.import_module(name))
        except ModuleNotFoundError as exc:
            if exc.name != name:  # the plugin exists but one of its imports is broken
                raise
    return modules


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with the core subcommands and every available plugin."""
    from hybridoc import __version__

    parser = HybridocArgumentParser(
        prog="hybridoc",
        description="Optimal control of hybrid systems (rigid discs with impacts): scenes, "
        "an event-exact evaluator with exact gradients, and solvers.",
        epilog="Run 'hybridoc COMMAND --help' for the options of a command.",
    )
    parser.add_argument("--version", action="version", version=f"hybridoc {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("problems", help="list the built-in scenes")
    p.set_defaults(func=cmd_problems)

    p = sub.add_parser("show", help="describe a scene", description=cmd_show.__doc__)
    scene_arg(p)
    p.add_argument(
        "--plot",
        metavar="FILE",
        type=Path,
        default=None,
        help="write a PNG of the scene with the initial guess's trajectory",
    )
    p.set_defaults(func=cmd_show)

    p = sub.add_parser(
        "evaluate",
        help="cost and events of controls (event-exact)",
        description=cmd_evaluate.__doc__,
    )
    scene_arg(p)
    add_controls_arg(p)
    add_json_out(
        p, out_help="write DIR/solution.npz + .json, DIR/trajectory.png and DIR/controls.png"
    )
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser(
        "gradient",
        help="exact gradient of the cost w.r.t. controls and initial state",
        description=cmd_gradient.__doc__,
    )
    scene_arg(p)
    add_controls_arg(p)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=cmd_gradient)

    p = sub.add_parser(
        "demo",
        help="evaluate the paper problems' initial guesses; table and figures",
        description=cmd_demo.__doc__,
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        type=Path,
        default=Path("out"),
        help="directory for the figures (default: ./out)",
    )
    p.set_defaults(func=cmd_demo)

    for module in _load_plugins():
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit code.

    Parameters
    ----------
    argv
        Arguments without the program name; default ``sys.argv[1:]``.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except HybridocError as exc:
        message = " ".join(str(exc).splitlines()) or type(exc).__name__
        print(f"hybridoc: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("hybridoc: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # stdout closed early (e.g. piped into head): stop quietly, as other tools do
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 1
