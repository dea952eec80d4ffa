"""``hybridoc crossval``, ``validate`` and ``convergence``: methods measured against the
reference (library: :mod:`hybridoc.workflows.validation`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from hybridoc.cli._util import (
    add_json_out,
    add_progress_arg,
    add_substeps_arg,
    emit_json,
    ensure_dir,
    exit_code,
    fmt,
    format_table,
    grid_steps,
    load_problem_arg,
    load_substep_controls_arg,
    option_type,
    output_stem,
    problem_arg,
    problem_slug,
    say,
    to_jsonable,
    warn,
)
from hybridoc.errors import HybridocError

__all__ = ["register"]


def _write_json(path: Path, obj: Any) -> Path:
    from hybridoc.outputs import write_text

    return write_text(path, json.dumps(to_jsonable(obj), indent=2) + "\n")


def _events_text(events: list[dict[str, Any]]) -> str:
    return (
        ", ".join(f"{e.get('guard') or '|'.join(e['bodies'])}@{e['time']:.6f}" for e in events)
        or "none"
    )


def cmd_crossval(args: argparse.Namespace) -> int:
    """Run the reference, the direct transcription and gradient descent; compare them.

    Each method gets two gaps: to the reference J* (the exact optimum), and to J* projected
    onto the method's representation (J*'s cell averages on the N-step grid for gradient
    descent, an upper bound on the best cost the grid can hold; the transcription
    re-solved from J* on its own mesh for dt). The first includes the method's
    discretisation error; the second is the disagreement. A method is a finding when it
    beats J*, lands beyond its tolerance of the projection, has other events than J*, or
    is beyond its tolerance of J* while only the projection excuses it, unless an
    independent check explains it (a tie of the two sequences' extremals; the projection
    on a grid twice as fine shrinking like a discretisation error): a warning line per
    reason and exit code 1 (status disagree). Agreement with a reference that does not prove
    its optimum (best-found), or with no reference (it refused the problem: dt and gd are
    then compared with each other), is status best-found, exit code 1. A method that fails
    is a row that says so; the others still run and the files are still written.
    """
    from hybridoc.methods import METHODS
    from hybridoc.workflows.validation import crossval

    ocp = load_problem_arg(args.problem)
    out = None if args.out is None else ensure_dir(args.out)  # fail before the solves
    if out is not None:  # a link or a user's file at an output name: refused now
        from hybridoc.outputs import check_targets

        stem = output_stem(out, problem_slug(args.problem, ocp), "crossval")
        check_targets(*(f"{stem}{end}" for end in _CROSSVAL_ENDS))
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    names = ["reference"] + [m for m in methods if m != "reference"]
    tolerances = dict(args.tolerance or [])
    if args.starts is not None and "gd" in methods:
        from hybridoc.solvers.gd import GDOptions, checked_options

        # a size beyond the memory limit is refused now, not after the other solves
        checked_options(ocp, GDOptions(starts=args.starts))
    say(args, f"{ocp.name}: solving with {', '.join(names)} ...")
    options: dict[str, dict[str, Any]] = {"gd": {}, "dt": {}}
    if args.gd_integrator is not None:
        options["gd"]["integrator"] = args.gd_integrator
    if args.starts is not None:
        options["gd"]["starts"] = args.starts
    if args.mesh is not None:
        options["dt"]["mesh"] = args.mesh
    if args.time_limit is not None:
        # each method that has a time limit gets it (a limit per method, not for the whole)
        for name in names:
            if name in METHODS and any(s.name == "time_limit" for s in METHODS[name].specs()):
                options.setdefault(name, {})["time_limit"] = args.time_limit
    report, sols = crossval(
        ocp, methods=methods, options=options, tolerances=tolerances,
        progress=not args.no_progress,
    )  # fmt: skip
    if args.json:
        emit_json(report)
    else:
        _print_crossval(args, ocp, report)
    # after the answer is out: a write that fails at the end loses nothing shown (exit 2)
    written = [] if out is None else _write_crossval(out, problem_slug(args.problem, ocp), ocp,
                                                     report, sols)  # fmt: skip
    for p in written:
        say(args, f"wrote {p}")
    if not report["agree"]:
        for reason in report["reasons"]:
            exit_code("disagree", reason)
        return 1
    # a report without a status (one written before it had one) agrees with a proven J*
    return exit_code(report.get("status", "success"), report.get("verdict", ""))


#: the files crossval writes: the report, then the figures of crossval_figures
_CROSSVAL_ENDS = (".json", "_controls.png", "_trajectories.png", "_learning_curve.png")
#: the files validate writes: the figures of validation_figures, then the report
_VALIDATE_ENDS = (".json", "_controls.png", "_trajectories.png")


def _write_crossval(
    out: Path, slug: str, ocp: Any, report: dict[str, Any], sols: dict[str, Any]
) -> list[Path]:
    """``<slug>_crossval.json`` first, then the figures (a figure that fails is a warning:
    the report is written whatever happens to them)."""
    from hybridoc.cli.evaluate import save
    from hybridoc.workflows.validation import crossval_figures

    stem = output_stem(out, slug, "crossval")
    written = [_write_json(Path(f"{stem}.json"), report)]
    try:
        figures = crossval_figures(ocp, sols)
    except Exception as exc:  # the figures are extras: the report is the result
        warn(f"crossval figures not drawn: {type(exc).__name__}: {exc}")
        return written
    for name, fig in figures.items():
        written.append(save(fig, f"{stem}_{name}.png"))
    return written


def _gap(x: Any) -> str:
    return "-" if x is None else f"{x:+.2e}"


def _print_crossval(args: argparse.Namespace, ocp: Any, report: dict[str, Any]) -> None:
    """The table of a crossval report, with its notes and events."""
    rows = []
    names = [k for k in report if isinstance(report[k], dict)]
    base = report.get("baseline")
    for name in names:
        e = report[name]
        if "error" in e:
            rows.append([name, "refused" if e.get("refused") else "failed", "-", "-", "-", "-",
                         e.get("error_type", "error"), "-", f"{e['wall_time_s']:.2f}"])  # fmt: skip
            continue
        if base != "reference":  # no reference: the gap is to the baseline method
            gap, same = e.get("baseline_gap_relative"), e.get("baseline_sequence_matches")
        else:
            gap, same = e["cost_gap_relative"], e["sequence_matches"]
        rows.append(
            [
                name, fmt(e["cost"], 12), _gap(gap),
                _gap(e.get("discretisation_gap_relative")),
                _gap(e.get("representable_gap_relative")),
                "yes" if e.get("converged") else "no", e["status"],
                {True: "yes", False: "no", None: "-"}[same],
                f"{e['wall_time_s']:.2f}",
            ]
        )  # fmt: skip
    headers = ["method", "cost", "gap", "proj gap", "to proj", "converged", "status",
               "same events", "time s"]  # fmt: skip
    right = [False, True, True, True, True, False, False, False, True]
    say(args, format_table(headers, rows, right=right))
    if base == "reference":
        say(args, "gap: to the reference J*. proj: J* projected onto the method's control (gd:")
        say(args, "J*'s cell averages on the N-grid, an upper bound on the best cost the grid can")
        say(args, "hold, not the best; dt: dt re-solved from J* on its mesh). proj gap: the")
        say(args, "projection to J* (the discretisation, when it keeps J*'s events). to proj: the")
        say(args, "method to its projection, the disagreement (negative: the method beats it).")
    elif base is not None:
        say(args, f"no reference: gap and same events are to {base}, the cheapest answer.")
    if report.get("grid_cost") is not None:
        grid = f"{fmt(report['grid_cost'], 12)} ({_gap(report['grid_gap_relative'])})"
        say(args, f"J* on the N = {ocp.steps} grid (cell averages, judged): {grid}")
    for name in names:
        e = report[name]
        if "error" in e:
            verb = "refused" if e.get("refused") else "failed"
            say(args, f"  {name:9s} {verb}: {e['error']}")
        elif "events" in e:
            say(args, f"  {name:9s} events: {_events_text(e['events'])}")
        if e.get("terminal_violation") is not None:
            say(args, f"  {name:9s} terminal-constraint violation {e['terminal_violation']:.3g}")
    gd = report.get("gd", {})
    if "discrete_optimum" in gd:
        say(
            args,
            f"discrete objective (N = {ocp.steps}, symplectic Euler): gd's loss "
            f"{fmt(gd['discrete_loss'], 12)}, its optimum {fmt(gd['discrete_optimum'], 12)} "
            f"(N-step transcription from gd's control), gap "
            f"{gd['discrete_gap_relative']:+.2e}",
        )
    elif "discrete_error" in gd:
        say(args, f"discrete objective: its transcription failed: {gd['discrete_error']}")
    for note in report.get("notes", []):
        say(args, f"note: {note}")
    verdict = f" ({report['verdict']})" if report.get("verdict") else ""
    say(args, "agree: " + ("yes" if report["agree"] else "NO") + verdict)


def cmd_validate(args: argparse.Namespace) -> int:
    """Judge a control file (.npy, .csv or a saved Solution) against the reference optimum.

    Controls that violate the problem's control bounds, path or terminal constraints are
    not a solution of the problem: the report says which constraints, by how much, and
    the exit code is 1 (their cost gap is not a result).
    """
    import dataclasses

    import numpy as np

    from hybridoc.cli.evaluate import save
    from hybridoc.methods import solve
    from hybridoc.workflows.validation import validate_controls, validation_figures

    ocp = load_problem_arg(args.problem)
    path = _validate_controls_path(args)
    fine, u, source = load_substep_controls_arg(path, ocp, args.substeps)
    k = fine.steps // ocp.steps
    out = None if args.out is None else ensure_dir(args.out)  # fail before the reference
    if out is not None:  # a link or a user's file at an output name: refused now
        from hybridoc.outputs import check_targets

        stem = output_stem(out, problem_slug(args.problem, ocp), "validate")
        check_targets(*(f"{stem}{end}" for end in _VALIDATE_ENDS))
    ref = solve(ocp, "reference")
    report = validate_controls(ocp, u, reference=ref, substeps=k)
    report["controls_file"] = source
    broken = _violated(report)
    if args.json:
        emit_json(report)
    else:
        say(args, f"{ocp.name}: controls {source}")
        say(args, f"  true cost         {report['cost']!r}")
        say(args, f"  reference cost    {report['reference_cost']!r}")
        say(args, f"  cost gap relative {report['cost_gap_relative']:+.3e}")
        ce = report["control_error"]
        say(args, f"  control error     L2 {ce['l2']:.4g}, max {ce['max']:.4g}")
        say(args, f"  events            {_events_text(report['events'])}")
        say(args, f"  reference events  {_events_text(report['reference_events'])}")
        if report["sequence_matches"]:
            errs = ", ".join(f"{x:+.2e}" for x in report["event_time_errors"])
            say(args, f"  same event sequence; time errors {errs or '-'}")
        else:
            say(args, "  event sequence DIFFERS from the reference's")
        if broken:
            say(args, f"  INFEASIBLE        violates the {', the '.join(broken)}")
    # after the answer is out: a write that fails at the end loses nothing shown (exit 2)
    written: list[Path] = []
    if out is not None:
        # on the controls' grid: the reference's values held over the K substeps
        shown = ref if k == 1 else dataclasses.replace(
            ref, controls=np.repeat(ref.controls, k, axis=0), time_grid=fine.time_grid()
        )  # fmt: skip
        for name, fig in validation_figures(fine, u, shown, label=path.stem).items():
            written.append(save(fig, f"{stem}_{name}.png"))
        written.append(_write_json(Path(f"{stem}.json"), report))
    for p in written:
        say(args, f"wrote {p}")
    # the controls' own verdict first: a reference that is not proven (best-found, issue #29)
    # or that failed must not hide that the controls break the problem's constraints
    if broken:
        warn(f"the controls are INFEASIBLE: they violate the {', the '.join(broken)}; their "
             "cost gap is not a result")  # fmt: skip
    if not ref.success:
        return max(exit_code(ref.status, f"the reference itself: {ref.message}"), int(broken != []))
    return 1 if broken else 0


def _violated(report: dict[str, Any]) -> list[str]:
    """What a :func:`~hybridoc.workflows.validation.validate_controls` report's controls
    violate, with the largest violation (empty when they are feasible)."""
    if report["feasible"]:
        return []
    from hybridoc.workflows.policies import violation_phrases

    return violation_phrases(report)


def _validate_controls_path(args: argparse.Namespace) -> Path:
    """The controls file of ``validate``: the positional ``CONTROLS`` or ``--controls``."""
    given = [p for p in (args.controls, args.controls_option) if p is not None]
    if len(given) != 1:
        raise HybridocError(
            "give the controls file once: as --controls FILE (or the deprecated CONTROLS)"
            if given
            else "no controls file: give --controls FILE"
        )
    return given[0]


def cmd_convergence(args: argparse.Namespace) -> int:
    """Costs of the transcription and gradient descent for N in 60 ... 960."""
    from hybridoc.cli.evaluate import save
    from hybridoc.workflows.validation import DEFAULT_STEPS, convergence, convergence_figure

    ocp = load_problem_arg(args.problem)
    steps = tuple(args.steps) if args.steps else DEFAULT_STEPS
    out = None if args.out is None else ensure_dir(args.out)  # fail before the solves
    if out is not None:  # a link or a user's file at an output name: refused now
        from hybridoc.outputs import check_targets

        stem = output_stem(out, problem_slug(args.problem, ocp), "convergence")
        check_targets(f"{stem}.png", f"{stem}.json")
    say(args, f"{ocp.name}: convergence study, N = {', '.join(map(str, steps))} ...")
    report = convergence(ocp, steps=steps, include_gd=not args.no_gd)
    if args.json:
        emit_json(report)
    else:
        say(args, f"reference optimum J* = {report['reference_cost']!r}")
        headers = ["N", "dt cost", "dt err", "dt order"]
        if "gd" in report:
            headers += ["gd cost", "gd err", "gd order"]
        rows = []
        for k, n in enumerate(report["steps"]):
            row: list[Any] = [n]
            for name in ("dt", "gd"):
                if name not in report:
                    continue
                b = report[name]
                order = b["order"][k]
                row += [
                    fmt(b["cost"][k], 10),
                    f"{b['error'][k]:.2e}",
                    "-" if order is None else f"{order:.2f}",
                ]
            rows.append(row)
        say(args, format_table(headers, rows))
        say(args, "dt: the transcription's continuous optimum averaged on the N-grid and judged")
        tail = (
            "; gd: gradient descent re-run at N, true continuous cost." if "gd" in report else "."
        )
        say(args, "piecewise constant" + tail)
    # after the answer is out: a write that fails at the end loses nothing shown (exit 2)
    written: list[Path] = []
    if out is not None:
        written.append(save(convergence_figure(report), f"{stem}.png"))
        written.append(_write_json(Path(f"{stem}.json"), report))
    for p in written:
        say(args, f"wrote {p}")
    return 0


def register(sub: Any) -> None:
    """Add ``crossval``, ``validate`` and ``convergence``."""
    p = sub.add_parser(
        "crossval",
        help="reference vs direct transcription vs gradient descent on one problem",
        description=cmd_crossval.__doc__,
    )
    p.defer(_crossval_arguments)  # --gd-integrator's choices are gd's: read on first use
    p.set_defaults(func=cmd_crossval)

    p = sub.add_parser(
        "validate",
        help="judge a control file against the reference optimum",
        description=cmd_validate.__doc__,
    )
    problem_arg(p)
    p.add_argument(
        "controls", metavar="CONTROLS", type=Path, nargs="?", default=None,
        help="deprecated: the same as --controls FILE",
    )  # fmt: skip
    p.add_argument(
        "--controls", dest="controls_option", metavar="FILE", type=Path, default=None,
        help="the controls to judge: .npy or .csv (N rows, one column per control) or a saved "
        "Solution (.npz/.json)",
    )  # fmt: skip
    add_substeps_arg(p)
    add_json_out(p, out_help="write the overlay figures and DIR/<problem>_validate.json")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser(
        "convergence",
        help="transcription and gradient-descent costs against N",
        description=cmd_convergence.__doc__,
    )
    problem_arg(p)
    p.add_argument(
        "--steps",
        type=grid_steps,
        nargs="+",
        default=None,
        help="grid sizes, each at most 10**6 (default 60 ... 960)",
    )
    p.add_argument("--no-gd", action="store_true", help="skip gradient descent (fast)")
    add_json_out(p, out_help="write the log-log figure and DIR/<problem>_convergence.json")
    p.set_defaults(func=cmd_convergence)


def _method_option(method: str, name: str) -> Any:
    """The :class:`~hybridoc.methods.OptionSpec` of one option of a registered method."""
    from hybridoc.methods import METHODS

    (spec,) = (s for s in METHODS[method].specs() if s.name == name)
    return spec


def _tolerance_item(text: str) -> tuple[str, float]:
    """argparse type of ``--tolerance METHOD=VALUE``."""
    from hybridoc.methods import METHODS
    from hybridoc.methods import positive_float as parse

    name, sep, value = text.partition("=")
    name = name.strip()
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected METHOD=VALUE (e.g. gd=1e-2), got {text!r}")
    if name not in METHODS:
        raise argparse.ArgumentTypeError(
            f"unknown method {name!r} in {text!r}; choose from {', '.join(METHODS)}"
        )
    return name, option_type(parse, "tolerance")(value)


def _crossval_arguments(p: argparse.ArgumentParser) -> None:
    integrator = _method_option("gd", "integrator")
    starts = _method_option("gd", "starts")
    mesh = _method_option("dt", "mesh")
    time_limit = _method_option("gd", "time_limit")
    problem_arg(p)
    p.add_argument(
        "--methods", default="reference,dt,gd", metavar="M,M",
        help="registered methods to compare with the reference (default reference,dt,gd)",
    )  # fmt: skip
    p.add_argument(
        "--gd-integrator",
        choices=integrator.choices,
        default=None,
        help="gradient descent's time stepping on disc scenes: exact (default) or the paper's "
        "symplectic Euler",
    )
    p.add_argument(
        "--starts", type=option_type(starts.parser, "starts"), default=None, metavar="K",
        help="gradient descent's multi-start: K starts (default: crossval's, 32 on disc "
        "scenes, 16 on others)",
    )  # fmt: skip
    p.add_argument(
        "--mesh", type=option_type(mesh.parser, "mesh"), default=None, metavar="M",
        help="the transcription's collocation elements per phase (default: dt's)",
    )  # fmt: skip
    p.add_argument(
        "--time-limit", type=option_type(time_limit.parser, "time limit"), default=None,
        metavar="SECONDS",
        help="each method's time limit (every method that has one: its best so far is "
        "then a not-converged row); default none",
    )  # fmt: skip
    p.add_argument(
        "--tolerance", type=_tolerance_item, action="append", default=None,
        metavar="METHOD=VALUE",
        help="relative gap to the reference's projection on the method's control beyond which "
        "it disagrees (repeatable; default: the method's own, gd 5e-3, dt 1e-6)",
    )  # fmt: skip
    add_progress_arg(p)
    add_json_out(p, out_help="write DIR/<problem>_crossval.json and the figures "
                 "DIR/<problem>_crossval_<figure>.png")  # fmt: skip
