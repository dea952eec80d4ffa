"""``hybridoc problems`` and ``hybridoc show``: what problems there are, and one of them."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from hybridoc.cli._util import fmt, format_table, indent, load_problem_arg, problem_arg
from hybridoc.errors import HybridocError

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.problem import ProblemLike

__all__ = ["register"]


def _vec(p: Sequence[float]) -> str:
    return "(" + ", ".join(fmt(x, 6) for x in p) + ")"


def cmd_problems(args: argparse.Namespace) -> int:
    """List the built-in problems: disc scenes and the library of other hybrid systems."""
    from hybridoc.problems import builtin_names, library_names, load_problem, load_scene

    rows = []
    for name in builtin_names():
        s = load_scene(name)
        rows.append(
            [
                name,
                "disc scene",
                s.to_ocp().nx,
                s.n_controls,
                s.steps,
                fmt(s.horizon),
                s.description,
            ]
        )
    from hybridoc.problems.library import describe

    for name in library_names():
        ocp = load_problem(name)
        doc = describe(name)
        rows.append([name, "library", ocp.nx, ocp.nu, ocp.steps, fmt(ocp.horizon), doc])
    print(
        format_table(
            ["name", "kind", "nx", "nu", "N", "T", "description"],
            rows,
            right=[False, False, True, True, True, True, False],
        )
    )
    print("\nshow one with: hybridoc show NAME [--plot FILE.png]")
    print("your own: a .toml scene file, or path/to/file.py:function returning a HybridOCP")
    return 0


def _guess_text(scene: ProblemLike) -> str:
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


def _scene_lines(scene: ProblemLike) -> list[str]:
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
    headers = ["name", "position", "velocity", "radius", "mass", "actuated", "target"]
    lines.append(indent(format_table(headers, rows, right=[False] * 7)))
    if scene.walls:
        rows = [[w.name, _vec(w.point), _vec(w.normal)] for w in scene.walls]
        lines += ["", "walls (the normal points into free space)"]
        lines.append(indent(format_table(["name", "point", "normal"], rows, right=[False] * 3)))
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
    return lines


def _ocp_lines(ocp: Any) -> list[str]:
    import numpy as np

    lines = [
        f"problem {ocp.name}"
        + (f": {ocp.meta['description']}" if ocp.meta.get("description") else "")
    ]
    lines.append(
        f"horizon T = {fmt(ocp.horizon)}, steps N = {ocp.steps} (dt = {fmt(ocp.dt, 6)}), "
        f"flow map: {'closed form' if ocp.has_closed_form_flow else 'CVODES integration'}"
    )
    lines.append(f"state ({ocp.nx}): {', '.join(ocp.state_labels)}")
    lines.append(f"initial state: {_vec(ocp.x0)}")
    lines.append(f"controls ({ocp.nu}): {', '.join(ocp.control_labels)}")
    if ocp.has_bounds:
        lines.append(f"control bounds: {_vec(ocp.u_min)} <= u <= {_vec(ocp.u_max)}")
    if ocp.path is not None:
        lines.append(f"path constraints: {ocp.path.size1_out(0)} (c(s, u) >= 0)")
    if ocp.horizon_bounds is not None:
        lo, hi = ocp.horizon_bounds
        lines.append(
            f"free final time: T in [{fmt(lo)}, {fmt(hi)}] (the horizon above is its guess)"
        )
    for attr, rel in (("terminal_eq", "= 0"), ("terminal_ineq", ">= 0")):
        fn = getattr(ocp, attr)
        if fn is not None:
            lines.append(f"terminal constraints: {fn.size1_out(0)} (h(s(T)) {rel})")
    if ocp.modes is not None:
        lines.append(
            f"modes ({len(ocp.modes)}): {', '.join(ocp.modes)}; initial {ocp.initial_mode}"
        )
    u = np.asarray(ocp.u_guess)
    lines.append(
        f"initial guess: {u.shape[0]} rows, values in [{fmt(u.min(), 4)}, {fmt(u.max(), 4)}]"
    )
    rows = [[g.name, g.kind, "-" if g.degree is None else str(g.degree)] for g in ocp.guards]
    headers = ["name", "kind", "degree"]
    if ocp.modes is not None:
        headers.append("modes")
        for row, g in zip(rows, ocp.guards, strict=True):
            row.append(f"{g.source} -> {g.target}")
    lines += ["", "guards (psi >= 0 in free space; the reset fires when psi reaches 0)"]
    lines.append(indent(format_table(headers, rows, right=[False] * len(headers))))
    return lines


def cmd_show(args: argparse.Namespace) -> int:
    """Describe a problem; optionally plot it with the initial guess's trajectory."""
    from hybridoc.evaluator import evaluate

    ocp = load_problem_arg(args.problem)
    if args.plot is not None:
        from hybridoc.plotting import figure_path

        figure_path(args.plot)  # a bad suffix fails before the description is printed
    from hybridoc.problems import scene_of

    scene = scene_of(ocp)  # a scene file's own words: its description, each disc's guess
    lines = _scene_lines(scene) if scene is not None else _ocp_lines(ocp)
    ev = None
    try:
        ev = evaluate(ocp)
    except HybridocError as exc:
        lines.append(f"initial guess cannot be evaluated: {exc}")
    if ev is not None:
        lines.append(
            f"initial guess cost: {fmt(ev.cost)} (terminal {fmt(ev.terminal_cost)}, running "
            f"{fmt(ev.running_cost)}), {len(ev.events)} event(s)"
        )
        if ocp.has_terminal_constraints:
            lines.append(f"initial guess terminal violation: {fmt(ev.terminal_violation, 3)}")
    print("\n".join(lines))
    if args.plot is not None:
        from hybridoc.cli.evaluate import save
        from hybridoc.plotting import plot_scene, plot_trajectories

        title = f"{ocp.name}: initial guess" + (f", cost {ev.cost:.6g}" if ev else "")
        if ocp.capabilities.geometry is not None:  # bodies and walls to draw
            fig = plot_scene(ocp, ev, title=title)
        elif ev is not None:
            fig = plot_trajectories(ocp, {"initial guess": ev}, title=title)
        else:
            raise HybridocError("nothing to plot: the initial guess cannot be evaluated")
        print(f"\nwrote {save(fig, args.plot)}")
    return 0


def register(sub: Any) -> None:
    """Add ``problems`` and ``show``."""
    p = sub.add_parser(
        "problems", help="list the built-in problems", description=cmd_problems.__doc__
    )
    p.set_defaults(func=cmd_problems)
    p = sub.add_parser("show", help="describe a problem", description=cmd_show.__doc__)
    problem_arg(p)
    p.add_argument(
        "--plot",
        metavar="FILE",
        default=None,
        help="write a figure of the problem with the initial guess's trajectory (PNG; "
        "another format by its suffix, e.g. .pdf; .png is appended to a name without one)",
    )
    p.set_defaults(func=cmd_show)
