"""``hybridoc evaluate``, ``gradient`` and ``demo``: the judge on the command line."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hybridoc.cli._util import (
    add_controls_arg,
    add_json_out,
    add_policy_arg,
    add_substeps_arg,
    check_controls_file,
    emit_json,
    events_table,
    fmt,
    format_table,
    indent,
    load_controls_arg,
    load_problem_arg,
    load_substep_controls_arg,
    output_stem,
    problem_arg,
    problem_slug,
    say,
)
from hybridoc.errors import EvaluationError, HybridocError
from hybridoc.outputs import check_folder, check_targets

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np

    from hybridoc.ocp import HybridOCP

__all__ = ["register", "save", "write_figures"]

#: The scenes evaluated by ``hybridoc demo``: the paper's two problems.
DEMO_SCENES = ("single-collision", "multiple-collision")
#: The figures of one evaluation, ``<stem>_<figure>.png`` (:func:`write_figures`).
FIGURES = ("trajectory", "controls")


def save(fig: Any, path: str | Path) -> Path:
    """Write a figure by the rules of :mod:`hybridoc.outputs`; an unwritable or refused
    path is a user error (one line)."""
    from hybridoc.plotting import save_figure

    return save_figure(fig, path)


def write_figures(ocp: Any, ev: Any, stem: Path, *, label: str) -> list[Path]:
    """The trajectory and control figures of one evaluation, ``stem_<figure>.png``."""
    from hybridoc.plotting import plot_controls, plot_scene, plot_trajectories

    title = f"{ocp.name}: {label}, cost {ev.cost:.6g}"
    if ocp.capabilities.geometry is not None:  # bodies and walls to draw
        fig = plot_scene(ocp, ev, title=title)
    else:
        fig = plot_trajectories(ocp, {label: ev}, title=title)
    paths = [save(fig, f"{stem}_trajectory.png")]
    fig = plot_controls(
        ocp.time_grid(),
        {label: ev.controls},
        list(ocp.control_labels),
        title=f"{ocp.name}: controls ({label})",
        event_times=[e.time for e in ev.events],
    )
    paths.append(save(fig, f"{stem}_controls.png"))
    return paths


def _evaluate_files(stem: Path) -> list[Path]:
    """The files ``evaluate --out`` writes: the Solution and its two figures."""
    return [Path(f"{stem}{end}") for end in (".npz", ".json", "_trajectory.png", "_controls.png")]


def _timed(fn: Any, *args: Any, repeat: int = 1) -> tuple[Any, float]:
    best = float("inf")
    out = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn(*args)
        best = min(best, time.perf_counter() - t0)
    return out, best


def _evaluated_arg(args: argparse.Namespace, ocp: HybridOCP) -> tuple[HybridOCP, Any, Any, str]:
    """``(problem, policy, controls, source)`` of ``evaluate``'s ``--policy`` or
    ``--controls`` (the problem on the finer grid with ``--substeps``)."""
    if args.policy is not None:
        from hybridoc.workflows.policies import load_policy

        if args.controls is not None:
            raise HybridocError("give --controls or --policy, not both")
        if args.substeps is not None:
            raise HybridocError("--substeps applies to --controls, not to --policy")
        from hybridoc.workflows.policy_format import check_policy_sizes

        policy = load_policy(args.policy)
        # sizes against the problem before any rollout (an MLP for 4 states on 8)
        check_policy_sizes(policy, ocp.nx, ocp.nu, f"policy {args.policy!r}")
        return ocp, policy, None, f"policy {args.policy} (hold {args.hold})"
    if args.hold != "zoh":
        raise HybridocError("--hold applies to --policy only")
    if (
        args.controls is not None
        and args.substeps is None
        and Path(args.controls).suffix.lower() in (".npz", ".json")
    ):
        # a saved Solution is judged by its own control (a dt or reference solution's
        # continuous u(t)), as hybridoc.evaluate(problem, path) does, not its grid averages
        from hybridoc.io import read_controls

        check_controls_file(args.controls)
        return ocp, None, read_controls(args.controls, ocp), str(args.controls)
    ocp, controls, source = load_substep_controls_arg(args.controls, ocp, args.substeps)
    return ocp, None, controls, source


def _solution_horizon(args: argparse.Namespace, ocp: HybridOCP) -> HybridOCP:
    """For a free final time and a saved Solution as ``--controls``: the problem at the
    final time the solution found (:func:`hybridoc.evaluator.at_horizon`)."""
    if not ocp.free_horizon or args.controls is None or args.substeps is not None:
        return ocp
    if Path(args.controls).suffix.lower() not in (".npz", ".json"):
        return ocp
    from hybridoc.evaluator import at_horizon
    from hybridoc.solution import Solution

    return at_horizon(ocp, Solution.load(args.controls))


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Evaluate controls (or a feedback policy, --policy) with the event-exact judge: true cost
    and events."""
    from hybridoc.evaluator import evaluate
    from hybridoc.solution import Solution

    ocp, policy, controls, source = _evaluated_arg(args, load_problem_arg(args.problem))
    ocp = _solution_horizon(args, ocp)
    out = None if args.out is None else check_folder(args.out)
    stem = None if out is None else output_stem(out, problem_slug(args.problem, ocp), "evaluate")
    if stem is not None:  # a refused output name fails before the evaluation
        check_targets(*_evaluate_files(stem))
    try:
        ev, seconds = _timed(
            lambda: (
                evaluate(ocp, controls, policy=policy, hold=args.hold)
                if policy is not None
                else evaluate(ocp, controls)
            )
        )
    except SystemExit as exc:  # the user's policy ended the program: say so
        if policy is None:
            raise
        from hybridoc._pyfile import exit_message
        from hybridoc.workflows.policies import PolicyError

        raise PolicyError(exit_message(f"policy {args.policy!r}", exc, "in the rollout")) from None
    events = ev.event_dicts()
    payload = {
        "problem": ocp.name,
        "controls": source,
        "cost": ev.cost,
        "terminal_cost": ev.terminal_cost,
        "running_cost": ev.running_cost,
        "events": events,
        "sequence": ev.sequence,
        "feasible": ev.feasible,
        "steps": ocp.steps,
        "substeps": args.substeps or 1,
        "horizon": ocp.horizon,
        "free_horizon": ocp.free_horizon,
        "terminal_violation": ev.terminal_violation,
        "terminal_eq": ev.terminal_eq_values,
        "terminal_ineq": ev.terminal_ineq_values,
    }
    if args.json:
        emit_json(payload)
    else:
        _print_evaluation(args, ocp, ev, source, events)
    if out is not None:
        sol = Solution.from_evaluation(
            ev, method="evaluate", scene=ocp.name, settings={"controls": source},
            timings={"evaluate_time_s": seconds},
        )  # fmt: skip
        assert stem is not None
        written = list(sol.save(stem))  # by the rules of hybridoc.outputs
        label = (
            "initial guess"
            if args.controls is None and policy is None
            else (
                f"policy {Path(args.policy).name}"
                if policy is not None
                else Path(args.controls).name
            )
        )
        written += write_figures(ocp, ev, stem, label=label)
        for p in written:
            say(args, f"wrote {p}")
    return 0


def _print_evaluation(
    args: argparse.Namespace, ocp: Any, ev: Any, source: str, events: list[dict[str, Any]]
) -> None:
    """The human block of ``evaluate``: costs, final mode, constraints, events."""
    free = " (free final time: judged at this T)" if ocp.free_horizon else ""
    say(args, f"problem   {ocp.name} (N = {ocp.steps}, T = {fmt(ocp.horizon)}){free}")
    say(args, f"controls  {source}")
    say(args, f"cost      {ev.cost!r}")
    say(args, f"terminal  {ev.terminal_cost!r}")
    say(args, f"running   {ev.running_cost!r}")
    if ocp.final_mode is not None:
        verdict = "as required" if ev.final_mode == ocp.final_mode else "required"
        say(args, f"final mode {ev.final_mode} ({ocp.final_mode} {verdict})")
    if ocp.has_terminal_constraints:
        say(args, f"terminal constraints violated by {ev.terminal_violation:.3g}")
        rows = [[f"h_eq[{i}] = 0", fmt(x)] for i, x in enumerate(ev.terminal_eq_values)]
        rows += [[f"h_ineq[{i}] >= 0", fmt(x)] for i, x in enumerate(ev.terminal_ineq_values)]
        say(args, indent(format_table(["constraint", "value at T"], rows, right=[False, True])))
    if not ev.feasible:
        say(
            args,
            f"feasible  no (bounds {ev.bound_violation:.3g}, path {ev.path_violation:.3g}, "
            f"terminal {ev.terminal_violation:.3g})",
        )
    say(args, f"events    {len(events)}")
    if events:
        say(args, indent(events_table(events)))


def cmd_gradient(args: argparse.Namespace) -> int:
    """Exact gradient of the continuous cost (adjoint with the HMP jump relation)."""
    import numpy as np

    from hybridoc.evaluator import gradient

    ocp = load_problem_arg(args.problem)
    controls, source = load_controls_arg(args.controls, ocp)
    g = gradient(ocp, controls)
    lam0 = np.asarray(g.d_initial_state)
    du = np.asarray(g.d_controls)
    bad = [what for what, x in (("dJ/du", du), ("dJ/ds0", lam0)) if not np.isfinite(x).all()]
    if bad:
        # a NaN printed as a number (or as '-' in the table) would read as an answer
        raise EvaluationError(
            f"the gradient is not finite (NaN or infinite entries in {' and '.join(bad)}; "
            f"cost {g.cost!r}): the problem's numbers or the controls overflow floating point"
        )
    if args.json:
        emit_json(
            {
                "problem": ocp.name,
                "cost": g.cost,
                "state_labels": list(ocp.state_labels),
                "control_labels": list(ocp.control_labels),
                "d_cost_d_initial_state": lam0,
                "d_cost_d_controls": du,
            }
        )
        return 0
    row, col = np.unravel_index(int(np.argmax(np.abs(du))), du.shape)
    labels = list(ocp.control_labels)
    print(f"problem   {ocp.name} (N = {ocp.steps}, T = {fmt(ocp.horizon)})")
    print(f"controls  {source}")
    print(f"cost      {g.cost!r}")
    print(f"events    {len(g.evaluation.events)}")
    print()
    print(f"dJ/du: {du.shape[0]} x {du.shape[1]} values (one per grid interval and component)")
    print(f"  norm (all values)  {fmt(_norm(du))}")
    for k, name in enumerate(labels):
        print(f"  norm {name:<13} {fmt(_norm(du[:, k]))}")
    print(f"  largest |dJ/du|    {fmt(abs(du[row, col]))} at interval {row}, {labels[col]}")
    print()
    print("dJ/d(initial state) = lambda(0):")
    rows = [[name, fmt(x)] for name, x in zip(ocp.state_labels, lam0, strict=True)]
    print(indent(format_table(["state", "dJ/ds0"], rows, right=[False, True])))
    return 0


def _norm(x: np.ndarray) -> float:
    """The 2-norm of finite values without overflow: entries near 1e300 have finite norms
    whose squares are not."""
    import numpy as np

    scale = float(np.max(np.abs(x), initial=0.0))
    return 0.0 if scale == 0.0 else scale * float(np.linalg.norm(x / scale))


def cmd_demo(args: argparse.Namespace) -> int:
    """Evaluate the initial guesses of the paper's two problems; table and figures."""
    import numpy as np

    from hybridoc.evaluator import evaluate, gradient

    out = check_folder(args.out)
    check_targets(*(f"{output_stem(out, n, 'demo')}_{f}.png" for n in DEMO_SCENES for f in FIGURES))
    rows = []
    judged = []
    for name in DEMO_SCENES:
        ocp = load_problem_arg(name)
        u = ocp.u_guess
        evaluate(ocp, u)  # the first call compiles the CasADi functions; time the next ones
        ev, t_eval = _timed(evaluate, ocp, u, repeat=3)
        g, t_grad = _timed(gradient, ocp, u, repeat=3)
        times = ", ".join(f"{e.time:.4f}" for e in ev.events) or "-"
        rows.append(
            [
                name, f"{ev.cost:.6f}", f"{ev.terminal_cost:.6f}", f"{ev.running_cost:.6f}",
                len(ev.events), times, f"{np.linalg.norm(g.d_controls):.6f}",
                f"{1e3 * t_eval:.1f}", f"{1e3 * t_grad:.1f}",
            ]
        )  # fmt: skip
        judged.append((name, ocp, ev))
    print("Initial guesses of the paper's problems, judged by the event-exact evaluator")
    print("(N = 480, T = 1; times are the best of 3 runs)\n")
    headers = ["scene", "cost", "terminal", "running", "events", "event times", "|dJ/du|"]
    headers += ["eval [ms]", "grad [ms]"]
    right = [False, True, True, True, True, False, True, True, True]
    print(format_table(headers, rows, right=right))
    print()
    # after the table is out: a write that fails at the end loses nothing shown (exit 2)
    for name, ocp, ev in judged:
        for p in write_figures(ocp, ev, output_stem(out, name, "demo"), label="initial guess"):
            print(f"wrote {p}")
    return 0


def register(sub: Any) -> None:
    """Add ``evaluate``, ``gradient`` and ``demo``."""
    p = sub.add_parser(
        "evaluate",
        help="true cost and events of controls (event-exact)",
        description=cmd_evaluate.__doc__,
    )
    problem_arg(p)
    add_controls_arg(p)
    add_substeps_arg(p)
    add_policy_arg(p, extra=", instead of controls")
    p.add_argument(
        "--hold", choices=("zoh", "continuous"), default="zoh",
        help="with --policy: sampled at the grid times and held (zoh, default) or continuous",
    )  # fmt: skip
    add_json_out(
        p,
        out_help="write DIR/<problem>_evaluate.npz + .json and its trajectory and controls figures",
    )
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser(
        "gradient",
        help="exact gradient of the cost w.r.t. controls and initial state",
        description=cmd_gradient.__doc__,
    )
    problem_arg(p)
    add_controls_arg(p)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=cmd_gradient)

    p = sub.add_parser(
        "demo",
        help="evaluate the paper problems' initial guesses; table and figures",
        description=cmd_demo.__doc__,
    )
    p.add_argument(
        "--out", metavar="DIR", type=Path, default=Path("out"),
        help="write the figures as DIR/<problem>_demo_<figure>.png (default: ./out)",
    )  # fmt: skip
    p.set_defaults(func=cmd_demo)
