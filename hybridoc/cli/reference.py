"""``hybridoc reference``: the optimal control by shooting on the hybrid minimum principle."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from hybridoc.cli._util import (
    add_initial_arg,
    add_json_out,
    add_method_options,
    emit_json,
    ensure_dir,
    exit_code,
    format_table,
    indent,
    load_controls_arg,
    load_problem_arg,
    method_options_given,
    output_stem,
    print_solution,
    problem_arg,
    problem_slug,
    say,
    solution_payload,
)
from hybridoc.errors import HybridocError

__all__ = ["register", "terminal_lines", "write_landscape", "write_reference_outputs"]

# the arguments of ``hybridoc reference`` itself, which no option may be called
_RESERVED = ("problem", "initial", "json", "out", "func", "command")


def cmd_reference(args: argparse.Namespace) -> int:
    """Solve PROBLEM exactly by shooting on the hybrid minimum principle.

    Without --sequence the event sequence is searched: candidates come from the initial
    guess, the direct transcription and a batched multi-start of the simulator (and, with
    --search K, every feasible sequence of up to K events). The result is re-simulated by the
    event-exact judge and compared with every cheaper control the search met before it is
    reported; a result that is not the optimum it would claim to be exits with code 1.
    """
    from hybridoc.reference import solve_reference
    from hybridoc.reference.solve import METHOD, coverage_line, families_line

    ocp = load_problem_arg(args.problem)
    initial = None
    if args.initial is not None:
        initial, _ = load_controls_arg(args.initial, ocp)
    out_dir = None if args.out is None else ensure_dir(args.out)  # fail before the solve
    if out_dir is not None:
        from hybridoc.outputs import check_targets

        stem = output_stem(out_dir, problem_slug(args.problem, ocp), "reference")
        ends = (".npz", ".json", "_trajectory.png", "_controls.png", "_costates.png",
                "_landscape.png")  # fmt: skip
        check_targets(*(f"{stem}{end}" for end in ends))  # a link or a user's file: refused now
    options = method_options_given(args, METHOD.name, {METHOD.name: METHOD})
    sol = solve_reference(ocp, initial=initial, progress=True, **options)
    files: list[Path] = []
    write_error: HybridocError | None = None
    try:
        if out_dir is not None:
            files = write_reference_outputs(ocp, sol, stem)
    except HybridocError as exc:
        write_error = exc  # the answer is still printed, then this one line (exit 2)
    landscape = sol.info.get("landscape")
    if args.json:
        emit_json(solution_payload(sol, files=[str(f) for f in files]))
        if write_error is not None:
            raise write_error
        return exit_code(sol.status, sol.message)
    its = sol.info["newton_iterations"]
    details = [
        ("residual", f"{sol.info['residual']:.2e} (HMP, max norm; {its} Newton iterations)"),
        ("tried", f"{len(sol.info.get('candidates', []))} sequence(s)"),
        ("coverage", coverage_line(sol.info.get("coverage"))),
        ("families", families_line(sol.info.get("coverage"))),
    ]
    details += terminal_lines(sol)
    shown = ocp if sol.info.get("horizon") is None else ocp.replace(horizon=sol.info["horizon"])
    print_solution(args, sol, shown, details)
    if sol.info.get("grazing"):
        say(args, "note: a grazing event (approach speed ~ 0): the HMP may not hold there")
    if landscape:
        say(args, "")
        say(args, "landscape of extremals (by event sequence):")
        rows = [
            [
                ",".join(r["sequence"]) or "(none)",
                "-" if r["cost"] is None else repr(r["cost"]),
                _short(r["verdict"]),
                f"{r['time_s']:.3f}",
            ]
            for r in landscape
        ]
        say(args, indent(format_table(["sequence", "cost", "verdict", "time s"], rows)))
    for f in files:
        say(args, f"wrote {f}")
    if write_error is not None:
        raise write_error
    return exit_code(sol.status, sol.message)


def terminal_lines(sol: Any) -> list[tuple[str, str]]:
    """The final time found (a free one) and the terminal constraints' multipliers and
    judged violation, as ``(label, text)`` rows; none for a problem without them."""
    rows = []
    info = sol.info
    if info.get("horizon") is not None:
        at = info.get("horizon_at_bound")
        where = f"at its {'lower' if at == 'min' else 'upper'} bound" if at else "free"
        rows.append(
            (
                "final time",
                f"T = {info['horizon']:.12g} ({where}; H(T) = {info['final_hamiltonian']:.2e})",
            )
        )
    mult = info.get("terminal_multipliers")
    if mult is not None:
        parts = []
        if mult["eq"]:
            parts.append("nu = [" + ", ".join(f"{v:.10g}" for v in mult["eq"]) + "]")
        if mult["ineq"]:
            parts.append("mu = [" + ", ".join(f"{v:.10g}" for v in mult["ineq"]) + "]")
        rows.append(
            ("multipliers", "; ".join(parts) + " (lambda(T) = grad phi - Dh_eq^T nu - Dh_in^T mu)")
        )
        if info.get("terminal_violation") is not None:
            rows.append(("terminal", f"violation {info['terminal_violation']:.2e} (judged)"))
    return rows


def _short(text: str, width: int = 72) -> str:
    """A verdict cut to one table cell (the JSON and ``--verbose`` keep the whole text)."""
    text = " ".join(text.split())
    return text if len(text) <= width else text[: width - 3].rstrip() + "..."


def write_reference_outputs(ocp: Any, sol: Any, stem: Path) -> list[Path]:
    """Save the Solution and three figures (trajectory, control, costates)."""
    import dataclasses

    import numpy as np

    from hybridoc.callable_eval import evaluate_callable
    from hybridoc.cli.evaluate import save
    from hybridoc.plotting import plot_controls, plot_costates, plot_scene, plot_trajectories
    from hybridoc.reference import reference_control

    files = list(sol.save(stem))
    if sol.info.get("horizon") is not None:
        ocp = ocp.replace(horizon=float(sol.info["horizon"]))  # a free final time as found
    u, bps = reference_control(sol)
    sim = evaluate_callable(ocp, u, breakpoints=bps)
    # draw the paths from the reference's own samples (grid and events): the integrator's
    # steps are too coarse to show the arcs
    sim = dataclasses.replace(sim, times=sol.state_times, states=sol.states)
    title = f"{ocp.name}: reference, J = {sol.cost:.10g}"
    from hybridoc.problems import scene_of

    scene = scene_of(ocp)
    fig = (
        plot_scene(scene, sim, title=title)
        if scene is not None
        else plot_trajectories(ocp, {"reference": sim}, title=title)
    )
    files.append(save(fig, f"{stem}_trajectory.png"))
    times = sol.info["event_times"]
    fig = plot_controls(
        sol.time_grid,
        {"cell mean": sol.controls},
        list(ocp.control_labels),
        title=f"{ocp.name}: optimal control u(t) (line) and its cell means",
        event_times=times,
    )
    t_fine = np.union1d(np.linspace(0, ocp.horizon, 2001), times)
    edges = np.concatenate([[0.0], times, [ocp.horizon]])
    for k, ax in enumerate(fig.axes[: ocp.nu]):
        # the exact control is smooth between events: draw each phase separately
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            tt = t_fine[(t_fine >= a) & (t_fine <= b)]
            vals = [u(min(max(x, a), b - 1e-15 if b > a else b))[k] for x in tt]
            ax.plot(tt, vals, color="k", lw=0.9, label="u(t)" if a == 0 else None)
    fig.axes[0].legend(fontsize=8, loc="best")
    files.append(save(fig, f"{stem}_controls.png"))
    fig = plot_costates(
        sol.costate_times, sol.costates, list(ocp.state_labels), times,
        title=f"{ocp.name}: costates (jumps at events)",
    )  # fmt: skip
    files.append(save(fig, f"{stem}_costates.png"))
    files += write_landscape(ocp, sol, stem)
    return files


def write_landscape(ocp: Any, sol: Any, stem: Path) -> list[Path]:
    """``<stem>_landscape.png`` when ``sol`` has a landscape (``--search K``): the cost of
    every extremal found, sorted, the chosen optimum marked; else nothing."""
    from hybridoc.cli.evaluate import save
    from hybridoc.plotting import plot_landscape

    landscape = sol.info.get("landscape")
    if not landscape:
        return []
    found = sum(r["cost"] is not None for r in landscape)
    fig = plot_landscape(
        landscape, sol.sequence,
        title=f"{ocp.name}: extremal landscape ({found} of {len(landscape)} sequences have one)",
    )  # fmt: skip
    return [save(fig, f"{stem}_landscape.png")]


def register(sub: Any) -> None:
    """Add ``reference``."""
    p = sub.add_parser(
        "reference",
        help="the optimal control by shooting on the hybrid minimum principle",
        description=cmd_reference.__doc__,
    )
    p.defer(_reference_arguments)  # imports the reference (CasADi): on first use
    p.set_defaults(func=cmd_reference)


def _reference_arguments(p: argparse.ArgumentParser) -> None:
    """The arguments of ``hybridoc reference``: the problem, one flag per command-line
    option of :class:`~hybridoc.reference.ReferenceOptions` (built as ``hybridoc solve``
    builds them, :func:`~hybridoc.cli._util.add_method_options`), the initial guess and the
    outputs."""
    from hybridoc.reference.solve import METHOD

    problem_arg(p)
    add_method_options(p, {METHOD.name: METHOD}, reserved=_RESERVED)
    add_initial_arg(p)
    add_json_out(
        p,
        out_help="write DIR/<problem>_reference.npz + .json and three figures (four with "
        "--search: the extremal landscape)",
    )
