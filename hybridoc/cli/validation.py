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
from hybridoc.cli.vocabulary import (
    SET_ALIASES,
    add_deprecated_alias,
    add_deprecated_set_alias,
    add_set_arg,
)
from hybridoc.errors import HybridocError
from hybridoc.methods import BUILTIN, REFERENCE_METHOD

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
    """Run registered methods (default: the reference, the direct transcription and gradient
    descent) on one problem and compare them with the reference.

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

    A method's options are given as --set METHOD.OPTION=VALUE (repeatable; e.g. --set
    gd.starts=8 --set dt.mesh=16), checked against the method's own options.
    """
    from hybridoc.methods import METHODS, parse_settings
    from hybridoc.workflows.validation import crossval

    ocp = load_problem_arg(args.problem)
    out = None if args.out is None else ensure_dir(args.out)  # fail before the solves
    if out is not None:  # a link or a user's file at an output name: refused now
        from hybridoc.outputs import check_targets

        stem = output_stem(out, problem_slug(args.problem, ocp), "crossval")
        check_targets(*(f"{stem}{end}" for end in _CROSSVAL_ENDS))
    methods = _method_list(args.methods)
    names = [REFERENCE_METHOD] + [m for m in methods if m != REFERENCE_METHOD]
    tolerances = dict(args.tolerance or [])
    options = parse_settings(args.set)
    if args.time_limit is not None:
        # each method that has a time limit gets it (a limit per method, not for the whole)
        for name in names:
            if name in METHODS and METHODS[name].takes("time_limit"):
                options.setdefault(name, {})["time_limit"] = args.time_limit
    for name, given in options.items():
        if name in names:  # a size beyond the memory limit is refused now, not after solves
            METHODS[name].checked(ocp, given)
    say(args, f"{ocp.name}: solving with {', '.join(names)} ...")
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
        if base != REFERENCE_METHOD:  # no reference: the gap is to the baseline method
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
    if base == REFERENCE_METHOD:
        say(args, "gap: to the reference J*. proj: J* projected onto the method's control (a")
        say(args, "grid method: J*'s cell averages on the N-grid, an upper bound on the best cost")
        say(args, "the grid can hold, not the best; a continuous one: the method re-solved from")
        say(args, "J* on its own mesh). proj gap: the projection to J* (the discretisation, when")
        say(args, "it keeps J*'s events). to proj: the method to its projection, the disagreement")
        say(args, "(negative: the method beats it).")
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
    for name in names:  # a method's own check of its discrete objective (gd's)
        e = report[name]
        if "discrete_optimum" in e:
            say(
                args,
                f"discrete objective (N = {ocp.steps}, symplectic Euler): {name}'s loss "
                f"{fmt(e['discrete_loss'], 12)}, its optimum {fmt(e['discrete_optimum'], 12)} "
                f"(N-step transcription from {name}'s control), gap "
                f"{e['discrete_gap_relative']:+.2e}",
            )
        elif "discrete_error" in e:
            say(args, f"discrete objective: its transcription failed: {e['discrete_error']}")
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
    ref = solve(ocp, REFERENCE_METHOD)
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
    """Costs of methods against N (default: the direct transcription and gradient descent,
    N = 60 ... 960), against the reference.

    A method whose control is continuous in time (the transcription) is solved once and its
    control averaged on each N-grid; a method on the grid (gradient descent) is re-run at
    each N. Options as --set METHOD.OPTION=VALUE.
    """
    from hybridoc.cli.evaluate import save
    from hybridoc.methods import parse_settings
    from hybridoc.workflows.validation import DEFAULT_STEPS, convergence, convergence_figure

    ocp = load_problem_arg(args.problem)
    steps = tuple(args.steps) if args.steps else DEFAULT_STEPS
    methods = None if args.methods is None else _method_list(args.methods)
    if args.no_gd:  # the deprecated --no-gd: the default methods but gradient descent
        from hybridoc.methods import BUILTIN

        methods = [m for m in (methods or BUILTIN) if m not in (REFERENCE_METHOD, "gd")]
    options = parse_settings(args.set)
    out = None if args.out is None else ensure_dir(args.out)  # fail before the solves
    if out is not None:  # a link or a user's file at an output name: refused now
        from hybridoc.outputs import check_targets

        stem = output_stem(out, problem_slug(args.problem, ocp), "convergence")
        check_targets(f"{stem}.png", f"{stem}.json")
    say(args, f"{ocp.name}: convergence study, N = {', '.join(map(str, steps))} ...")
    report = convergence(ocp, steps=steps, methods=methods, options=options)
    if args.json:
        emit_json(report)
    else:
        _print_convergence(args, report)
    # after the answer is out: a write that fails at the end loses nothing shown (exit 2)
    written: list[Path] = []
    if out is not None:
        written.append(save(convergence_figure(report), f"{stem}.png"))
        written.append(_write_json(Path(f"{stem}.json"), report))
    for p in written:
        say(args, f"wrote {p}")
    return 0


def _print_convergence(args: argparse.Namespace, report: dict[str, Any]) -> None:
    """The table of a convergence report and what each method's cost at N is."""
    say(args, f"reference optimum J* = {report['reference_cost']!r}")
    names = report["methods"]
    headers = ["N"] + [f"{name} {col}" for name in names for col in ("cost", "err", "order")]
    rows = []
    for k, n in enumerate(report["steps"]):
        row: list[Any] = [n]
        for name in names:
            b = report[name]
            order = b["order"][k]
            row += [
                fmt(b["cost"][k], 10),
                f"{b['error'][k]:.2e}",
                "-" if order is None else f"{order:.2f}",
            ]
        rows.append(row)
    say(args, format_table(headers, rows))
    for name in names:
        if f"{name}_continuous_cost" in report:
            say(args, f"{name}: its continuous optimum averaged on the N-grid and judged "
                "piecewise constant.")  # fmt: skip
        else:
            say(args, f"{name}: re-run at N, true continuous cost.")


def _method_list(text: str) -> list[str]:
    """``--methods M,M``: registered method names (unknown: one OptionError line)."""
    from hybridoc.errors import OptionError
    from hybridoc.methods import METHODS

    names = list(dict.fromkeys(m.strip() for m in text.split(",") if m.strip()))
    unknown = [m for m in names if m not in METHODS]
    if unknown:
        raise OptionError(
            f"--methods: unknown method(s) {', '.join(unknown)}; choose from {', '.join(METHODS)}"
        )
    return names


def register(sub: Any) -> None:
    """Add ``crossval``, ``validate`` and ``convergence``."""
    p = sub.add_parser(
        "crossval",
        help="reference vs direct transcription vs gradient descent on one problem",
        description=cmd_crossval.__doc__,
    )
    p.defer(_crossval_arguments)  # --time-limit's parser is the methods': read on first use
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
    p.add_argument(
        "--methods", default=None, metavar="M,M",
        help="registered methods to study (default: every built-in one but the reference: "
        "dt,gd)",
    )  # fmt: skip
    add_set_arg(p)
    add_deprecated_alias(p, "--no-gd", dest="no_gd", instead="--methods dt", switch=True)
    p.set_defaults(no_gd=False)
    add_json_out(p, out_help="write the log-log figure and DIR/<problem>_convergence.json")
    p.set_defaults(func=cmd_convergence)


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
    from hybridoc.methods import METHODS, positive_float

    problem_arg(p)
    p.add_argument(
        "--methods", default=",".join(BUILTIN), metavar="M,M",
        help=f"registered methods to compare with the reference (default {','.join(BUILTIN)}; "
        f"registered: {', '.join(METHODS)})",
    )  # fmt: skip
    add_set_arg(p)
    for flag, setting in SET_ALIASES["crossval"].items():  # the old flags, for one release
        add_deprecated_set_alias(p, flag, setting)
    p.add_argument(
        "--time-limit", type=option_type(positive_float, "time limit"), default=None,
        metavar="SECONDS",
        help="each method's time limit (every method that has one: its best so far is "
        "then a not-converged row); default none",
    )  # fmt: skip
    p.add_argument(
        "--tolerance", type=_tolerance_item, action="append", default=None,
        metavar="METHOD=VALUE",
        help="relative gap to the reference's projection on the method's control beyond which "
        "it disagrees (repeatable; default: the method's own, "
        + ", ".join(f"{m.name} {m.tolerance:.0e}" for m in METHODS.values()
                    if m.name != REFERENCE_METHOD)
        + ")",
    )  # fmt: skip
    add_progress_arg(p)
    add_json_out(p, out_help="write DIR/<problem>_crossval.json and the figures "
                 "DIR/<problem>_crossval_<figure>.png")  # fmt: skip
