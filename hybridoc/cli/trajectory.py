"""``hybridoc compare-trajectory``: another simulator's trajectory against the judge's
(library: :mod:`hybridoc.workflows.trajectories`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from hybridoc.cli._util import (
    add_controls_arg,
    add_json_out,
    add_substeps_arg,
    emit_json,
    fmt,
    format_table,
    indent,
    load_problem_arg,
    load_substep_controls_arg,
    output_stem,
    problem_arg,
    problem_slug,
    say,
    to_jsonable,
)
from hybridoc.outputs import check_folder, check_targets, write_text

__all__ = ["register"]


def cmd_compare_trajectory(args: argparse.Namespace) -> int:
    """Compare a trajectory from another simulator with the judge's trajectory of the same
    controls: the state error at every given time, and the events.

    --states X (.npy or .csv, M rows, one column per state component in the order of the
    problem's state labels; a CSV header may name them) holds the states at the M times of
    --times t (.npy or .csv, nondecreasing, in [0, T]; a time given twice is a jump recorded
    before and after). The events of the given trajectory are where a guard is reached and
    its approach reverses (see hybridoc.workflows.trajectories.detect_events); they are
    paired with the judge's guard by guard.
    """
    from hybridoc.cli.evaluate import save
    from hybridoc.io import read_array
    from hybridoc.workflows.trajectories import (
        TrajectoryError,
        compare_trajectory,
        trajectory_figure,
    )

    base = load_problem_arg(args.problem)
    ocp, u, source = load_substep_controls_arg(args.controls, base, args.substeps)
    times = read_array(args.times, what="times", error=TrajectoryError)
    states = read_array(args.states, what="states", labels=ocp.state_labels, error=TrajectoryError)
    out = None if args.out is None else check_folder(args.out)
    stem = None
    if out is not None:  # a refused output name fails before the work
        stem = output_stem(out, problem_slug(args.problem, ocp), "compare-trajectory")
        check_targets(f"{stem}.png", f"{stem}.json")
    try:
        cmp = compare_trajectory(base, times, states, u, substeps=ocp.steps // base.steps)
    except TrajectoryError as exc:
        raise TrajectoryError(f"--states {args.states} / --times {args.times}: {exc}") from None
    report = {
        "states_file": str(args.states),
        "times_file": str(args.times),
        "controls": source,
        **cmp.to_dict(),
    }
    if args.json:
        emit_json(report)
    else:
        _print(args, ocp, cmp, source, report)
    if stem is not None:  # after the answer is out: a write that fails loses nothing shown
        written = [save(trajectory_figure(cmp, label=args.states.stem), f"{stem}.png")]
        written.append(_write_json(Path(f"{stem}.json"), report))
        for p in written:
            say(args, f"wrote {p}")
    return 0


def _print(args: argparse.Namespace, ocp: Any, cmp: Any, source: str, report: dict) -> None:
    t = cmp.times
    say(args, f"problem   {ocp.name} (N = {ocp.steps}, T = {fmt(ocp.horizon)})")
    say(args, f"controls  {source}")
    say(args, f"samples   {t.size} times from {fmt(t[0])} to {fmt(t[-1])}")
    say(args, f"cost      {cmp.cost!r} (the judge's, of these controls)")
    say(
        args,
        f"error     max |x - x_judge| {fmt(report['max_error_norm'], 4)} at t = "
        f"{fmt(report['max_error_time'], 6)}; at the last time, t = "
        f"{fmt(report['final_time'], 6)}: {fmt(report['final_error_norm'], 4)}",
    )
    rows = [
        [c["state"], fmt(c["max_error"], 4), fmt(c["max_error_time"], 6), fmt(c["final_error"], 4)]
        for c in report["components"]
    ]
    headers = ["state", "max |error|", "at t", "last |error|"]
    say(args, indent(format_table(headers, rows, right=[False, True, True, True])))
    say(args, "")
    say(
        args,
        f"events    judge {len(cmp.judge_events)}, given {len(cmp.given_events)}"
        + ("" if cmp.sequence_matches else "; the sequences DIFFER"),
    )
    if cmp.matches:
        rows = [
            [
                m.guard,
                "-" if m.judge_time is None else repr(m.judge_time),
                "-" if m.given_time is None else repr(m.given_time),
                "-" if m.shift is None else f"{m.shift:+.3e}",
            ]
            for m in cmp.matches
        ]
        headers = ["guard", "judge time", "given time", "shift"]
        say(args, indent(format_table(headers, rows, right=[False, False, False, True])))


def _write_json(path: Path, obj: Any) -> Path:
    """Write a report by the rules of :mod:`hybridoc.outputs`."""
    return write_text(path, json.dumps(to_jsonable(obj), indent=2) + "\n")


def register(sub: Any) -> None:
    """Add ``compare-trajectory``."""
    p = sub.add_parser(
        "compare-trajectory",
        help="another simulator's trajectory against the judge's: state error and events",
        description=cmd_compare_trajectory.__doc__,
    )
    problem_arg(p)
    p.add_argument(
        "--states", metavar="X", type=Path, required=True,
        help="the states (.npy or .csv): M rows, one column per state component",
    )  # fmt: skip
    p.add_argument(
        "--times", metavar="t", type=Path, required=True,
        help="the M times of the states (.npy or .csv), nondecreasing, in [0, T]",
    )  # fmt: skip
    add_controls_arg(p)
    add_substeps_arg(p)
    add_json_out(
        p,
        out_help="write DIR/<problem>_compare-trajectory.json and its figure (.png): the state "
        "error against time with both trajectories' events",
    )
    p.set_defaults(func=cmd_compare_trajectory)
