"""``hybridoc crossval``, ``hybridoc validate`` and ``hybridoc convergence``.

Loaded by :mod:`hybridoc.cli` through :func:`register`. With ``--json`` each command prints
one JSON object on stdout and nothing else; ``--out DIR`` writes the figures (and the JSON
report) there.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from hybridoc.cli_util import (
    add_json_out,
    emit_json,
    ensure_dir,
    fmt,
    format_table,
    positive_int,
    resolve_scene,
    say,
    scene_arg,
    to_jsonable,
)

__all__ = ["cmd_convergence", "cmd_crossval", "cmd_validate", "register"]


def _write_json(out: Path, name: str, obj: Any) -> Path:
    import json

    p = out / name
    p.write_text(json.dumps(to_jsonable(obj), indent=2) + "\n")
    return p


def _save(fig: Any, path: Path) -> Path:
    from hybridoc.plotting import save_figure

    return save_figure(fig, path)


def _events_text(events: list[dict[str, Any]]) -> str:
    return ", ".join(f"{'|'.join(e['bodies'])}@{e['time']:.6f}" for e in events) or "none"


# ---------------------------------------------------------------------------- crossval
def cmd_crossval(args: argparse.Namespace) -> int:
    """Run the reference, the direct transcription and gradient descent; compare them."""
    from hybridoc.validation import crossval, crossval_figures

    scene = resolve_scene(args.scene)
    out = None if args.out is None else ensure_dir(args.out)  # fail before the solves
    say(args, f"{scene.name}: solving with reference, dt and gd ({args.gd_integrator}) ...")
    report, sols = crossval(scene, gd_options={"integrator": args.gd_integrator})
    written: list[Path] = []
    if out is not None:
        for name, fig in crossval_figures(scene, sols).items():
            written.append(_save(fig, out / f"{scene.name}_crossval_{name}.png"))
        written.append(_write_json(out, f"{scene.name}_crossval.json", report))
    if args.json:
        emit_json(report)
    else:
        rows = []
        for name in ("reference", "dt", "gd"):
            e = report[name]
            rows.append(
                [
                    name,
                    fmt(e["cost"], 10),
                    f"{e['cost_gap_relative']:+.2e}",
                    "-"
                    if e.get("cost_gap_local_relative") is None
                    else f"{e['cost_gap_local_relative']:+.2e}",
                    fmt(e["control_error"]["l2"], 3),
                    fmt(e["control_error"]["max"], 3),
                    "yes" if e["sequence_matches"] else "no",
                    f"{e['wall_time_s']:.2f}",
                ]
            )
        headers = [
            "method",
            "cost",
            "gap",
            "gap (own seq.)",
            "u err L2",
            "u err max",
            "same events",
            "time s",
        ]
        right = [False, True, True, True, True, True, False, True]
        say(args, format_table(headers, rows, right=right))
        say(args, "gap: to the lowest-cost verified HMP extremal (the reference); gap (own seq.):")
        say(args, "to the HMP extremal with the method's own event sequence (its local optimum).")
        for name in ("reference", "dt", "gd"):
            say(args, f"  {name:9s} events: {_events_text(report[name]['events'])}")
    for p in written:
        say(args, f"wrote {p}")
    return 0


# ---------------------------------------------------------------------------- validate
def cmd_validate(args: argparse.Namespace) -> int:
    """Judge a control file against the reference optimum."""
    from hybridoc.io import load_controls
    from hybridoc.reference import solve_reference
    from hybridoc.validation import validate_controls, validation_figure

    scene = resolve_scene(args.scene)
    u = load_controls(args.controls, scene)  # ControlsError -> exit 2 in main()
    out = None if args.out is None else ensure_dir(args.out)
    ref = solve_reference(scene)
    report = validate_controls(scene, u, reference=ref)
    report["controls_file"] = str(args.controls)
    written: list[Path] = []
    if out is not None:
        fig_u, fig_x = validation_figure(scene, u, ref, label=Path(args.controls).stem)
        written.append(_save(fig_u, out / f"{scene.name}_validate_controls.png"))
        written.append(_save(fig_x, out / f"{scene.name}_validate_trajectory.png"))
        written.append(_write_json(out, f"{scene.name}_validate.json", report))
    if args.json:
        emit_json(report)
    else:
        say(args, f"{scene.name}: controls {args.controls}")
        say(args, f"  true cost         {report['cost']:.12g}")
        say(args, f"  reference cost    {report['reference_cost']:.12g}")
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
    for p in written:
        say(args, f"wrote {p}")
    return 0


# ---------------------------------------------------------------------------- convergence
def cmd_convergence(args: argparse.Namespace) -> int:
    """Costs of the transcription and gradient descent for N in 60 ... 960."""
    from hybridoc.validation import DEFAULT_STEPS, convergence, convergence_figure

    scene = resolve_scene(args.scene)
    steps = tuple(args.steps) if args.steps else DEFAULT_STEPS
    out = None if args.out is None else ensure_dir(args.out)  # fail before the solves
    say(args, f"{scene.name}: convergence study, N = {', '.join(map(str, steps))} ...")
    report = convergence(scene, steps=steps, include_gd=not args.no_gd)
    written: list[Path] = []
    if out is not None:
        written.append(_save(convergence_figure(report), out / f"{scene.name}_convergence.png"))
        written.append(_write_json(out, f"{scene.name}_convergence.json", report))
    if args.json:
        emit_json(report)
    else:
        say(args, f"reference optimum J* = {report['reference_cost']:.12g}")
        headers = ["N", "dt cost", "dt err", "dt order"]
        if "gd" in report:
            headers += ["gd cost", "gd err", "gd order"]
        rows = []
        for k, n in enumerate(report["steps"]):
            row = [n]
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
        say(
            args,
            "piecewise constant"
            + (
                "; gd: gradient descent re-run at N, true continuous cost."
                if "gd" in report
                else "."
            ),
        )
    for p in written:
        say(args, f"wrote {p}")
    return 0


def register(subparsers: Any) -> None:
    """Add ``crossval``, ``validate`` and ``convergence`` to the ``hybridoc`` command."""
    p = subparsers.add_parser(
        "crossval",
        help="reference vs direct transcription vs gradient descent on one scene",
        description=cmd_crossval.__doc__,
    )
    scene_arg(p)
    p.add_argument(
        "--gd-integrator",
        choices=("symplectic-euler", "exact"),
        default="symplectic-euler",
        help="gradient descent's time stepping: the paper's symplectic Euler (default) or the "
        "exact polynomial flow with Newton-refined impact times",
    )
    add_json_out(p, out_help="write the figures and the JSON report to DIR")
    p.set_defaults(func=cmd_crossval)

    p = subparsers.add_parser(
        "validate",
        help="judge a control file (.npy/.csv) against the reference optimum",
        description=cmd_validate.__doc__,
    )
    scene_arg(p)
    p.add_argument(
        "controls",
        metavar="CONTROLS",
        type=Path,
        help=".npy or .csv file: N rows, one column per actuated control component",
    )
    add_json_out(p, out_help="write the overlay figures and the JSON report to DIR")
    p.set_defaults(func=cmd_validate)

    p = subparsers.add_parser(
        "convergence",
        help="transcription and gradient-descent costs against N",
        description=cmd_convergence.__doc__,
    )
    scene_arg(p)
    p.add_argument(
        "--steps",
        type=positive_int,
        nargs="+",
        default=None,
        help="grid sizes (default 60 ... 960)",
    )
    p.add_argument("--no-gd", action="store_true", help="skip gradient descent (fast)")
    add_json_out(p, out_help="write the log-log figure and the JSON report to DIR")
    p.set_defaults(func=cmd_convergence)
