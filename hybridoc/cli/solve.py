"""``hybridoc solve`` (every registered method) and ``hybridoc ablation`` (the paper's Table 1).

The flags of ``hybridoc solve`` are built from the registered methods' options
(:mod:`hybridoc.methods`), and what it prints about a solution is the method's
``summary_lines``: this module names no method.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hybridoc.cli._util import (
    add_initial_arg,
    add_json_out,
    add_method_options,
    add_progress_arg,
    emit_json,
    ensure_dir,
    exit_code,
    fmt,
    format_table,
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

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np

__all__ = ["register"]

# the arguments of ``hybridoc solve`` itself, which no method option may be called
_RESERVED = ("problem", "method", "initial", "json", "out", "func", "command", "no_progress")


def _learning_curve_figure(
    curves: dict[str, np.ndarray], optimum: float | None, title: str, stages: Any = None
) -> Any:
    import numpy as np
    from matplotlib.figure import Figure

    from hybridoc.plotting import mark_stages

    fig = Figure(figsize=(6.4, 4.2), layout="constrained")
    ax = fig.subplots()
    for label, hist in curves.items():
        ax.plot(np.arange(len(hist)), hist, label=label, lw=1.4)
    if optimum is not None:
        ax.axhline(optimum, color="k", ls="--", lw=1, label=f"optimum {optimum:.4f}")
    ax.set_xlabel("iteration")
    ax.set_ylabel("discrete loss")
    ax.set_title(title)
    finals = [h[-1] for h in curves.values()] + ([optimum] if optimum else [])
    lo, hi = min(finals), max(h[0] for h in curves.values())
    if hi > lo:
        ax.set_ylim(lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo))
    mark_stages(ax, stages)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return fig


def cmd_solve(args: argparse.Namespace) -> int:
    """Solve a problem with any registered method (see --method).

    Every method reports the judge's true cost of its control, its events and a status; a
    result that is not what it claims to be exits with code 1.
    """

    from hybridoc.methods import METHODS, get_method, solve

    method = get_method(args.method)
    options = method_options_given(args, method.name, METHODS)
    ocp = load_problem_arg(args.problem)
    initial = None
    if args.initial is not None:
        initial, _ = load_controls_arg(args.initial, ocp)
    out = None if args.out is None else ensure_dir(args.out)  # fail before the solve
    if out is not None:
        from hybridoc.outputs import check_targets

        stem = output_stem(out, problem_slug(args.problem, ocp), "solve", method.name)
        ends = (".npz", ".json", "_trajectory.png", "_controls.png", "_landscape.png",
                "_learning_curve.png")  # fmt: skip
        check_targets(*(f"{stem}{end}" for end in ends))  # a link or a user's file: refused now
    sol = solve(ocp, method.name, initial=initial, progress=not args.no_progress, **options)
    written: list[Path] = []
    write_error: HybridocError | None = None
    try:
        if out is not None:
            written += _write_solve_outputs(ocp, sol, stem, method.name)
    except HybridocError as exc:
        write_error = exc  # the answer is still printed, then this one line (exit 2)
    if args.json:
        emit_json(solution_payload(sol, files=[str(p) for p in written]))
    else:
        print_solution(args, sol, ocp, method.summary_lines(sol))
        for p in written:
            say(args, f"wrote {p}")
    if write_error is not None:
        raise write_error
    # the result is out; the reason for a non-zero exit stays the last line on stderr. An
    # interrupted run does not wait for compilations, and a Ctrl-C during the wait ends it
    # (the compiler's process group is ended at exit: hybridoc.compiled)
    if sol.info.get("stopped") != "interrupted":
        try:
            _finish_compilations()
        except KeyboardInterrupt:
            pass
    return exit_code(sol.status, sol.message)


def _write_solve_outputs(ocp: Any, sol: Any, stem: Path, method: str) -> list[Path]:
    """The files of ``hybridoc solve --out``: the Solution, its figures, a landscape and a
    learning curve where the method has them."""
    import numpy as np

    from hybridoc.cli.evaluate import save, write_figures
    from hybridoc.workflows.validation import figure_evaluation

    written = list(sol.save(stem))
    written += write_figures(ocp, figure_evaluation(ocp, sol), stem, label=method)
    if sol.info.get("landscape"):  # any method that reports extremals by sequence
        from hybridoc.cli.reference import write_landscape

        written += write_landscape(ocp, sol, stem)
    hist = sol.arrays.get("loss_history")
    if hist is not None and len(hist):
        fig = _learning_curve_figure(
            {method: np.asarray(hist)},
            None,
            f"{ocp.name}: learning curve",
            sol.info.get("history_stages"),
        )
        written.append(save(fig, f"{stem}_learning_curve.png"))
    return written


#: how long ``hybridoc solve`` waits, after its output, for a C compilation still running
COMPILATION_WAIT_S = 120.0


def _finish_compilations() -> None:
    """Let the C compilations the solve started finish before the process exits.

    A solve that ends before the compilation of its loss (it starts after a few dozen calls
    and takes seconds) would otherwise lose it, and every later run would start on CasADi's
    virtual machine again, about fifty times slower per call.
    """
    import sys

    from hybridoc.compiled import wait_for_compilations

    if not wait_for_compilations(0.0):
        print(
            "hybridoc: finishing the C compilation for the next runs (HYBRIDOC_CODEGEN=0 "
            "turns it off)",
            file=sys.stderr,
            flush=True,
        )
        wait_for_compilations(COMPILATION_WAIT_S)


def cmd_ablation(args: argparse.Namespace) -> int:
    """Rerun the paper's Table 1 (TOI-Position x TOI-Velocity, both paper problems).

    Plain gradient descent with the paper's symplectic Euler, learning rates and iterations
    ({settings}), direct impulses. Prints the final discrete loss beside the paper's and the
    true continuous cost of the learned controls.
    """
    from hybridoc.problems.paper import EXACT_OPTIMUM, TOI_LABELS
    from hybridoc.workflows.ablation import run_ablation

    out = None if args.out is None else ensure_dir(args.out)  # fail before minutes of work
    res = run_ablation(progress=True)
    rows = res["rows"]
    written = [] if out is None else _ablation_files(res, out)
    if args.json:
        emit_json({"rows": rows})
        return 0
    table = [
        [
            r["scene"], TOI_LABELS[r["toi"]], fmt(r["loss"], 5), fmt(r["paper_loss"], 4),
            fmt(r["cost"], 5), fmt(r["paper_optimum"], 4),
        ]
        for r in rows
    ]  # fmt: skip
    headers = ["scene", "TOI", "loss", "paper loss", "true cost", "paper grid-search optimum"]
    say(args, format_table(headers, table, right=[False, False, True, True, True, True]))
    say(args, "loss: final discrete loss of plain gd; true cost: the judge's cost of its controls")
    exact = " and ".join(repr(float(v)) for v in EXACT_OPTIMUM.values())
    say(args, f"exact optima (hybridoc reference): {exact}")
    for p in written:
        say(args, f"wrote {p}")
    return 0


def _ablation_files(res: dict[str, Any], out: Path) -> list[Path]:
    """Write the ablation's learning curves, learned controls and Solutions into ``out``."""
    import numpy as np

    from hybridoc.cli.evaluate import save
    from hybridoc.plotting import plot_controls
    from hybridoc.problems.paper import PAPER_OPTIMUM, PAPER_SETTINGS, TOI_LABELS

    rows, sols = res["rows"], res["solutions"]
    tois = list(dict.fromkeys(r["toi"] for r in rows))
    written: list[Path] = []
    for name in PAPER_SETTINGS:
        curves = {
            TOI_LABELS[r["toi"]]: np.asarray(r["loss_history"]) for r in rows if r["scene"] == name
        }
        fig = _learning_curve_figure(
            curves, PAPER_OPTIMUM[name], f"{name}: plain gd learning curves"
        )
        stem = output_stem(out, name, "ablation")
        written.append(save(fig, f"{stem}_learning_curves.png"))
        ocp = load_problem_arg(name)
        controls = {TOI_LABELS[t]: sols[(t, name)].controls for t in tois}
        fig = plot_controls(
            ocp.time_grid(), controls, list(ocp.control_labels),
            title=f"{name}: learned controls (plain gd)",
        )  # fmt: skip
        written.append(save(fig, f"{stem}_controls.png"))
        for toi in tois:
            written += list(sols[(toi, name)].save(f"{stem}_{toi}"))
    return written


def register(sub: Any) -> None:
    """Add ``solve`` and ``ablation``."""
    p = sub.add_parser(
        "solve",
        help="solve a problem with any registered method (see its --method)",
        description=cmd_solve.__doc__,
    )
    p.defer(_solve_arguments)  # the flags come from the methods' options: on first use
    p.set_defaults(func=cmd_solve)

    p = sub.add_parser(
        "ablation",
        help="the paper's Table 1: TOI settings x paper problems (plain gd)",
    )
    p.defer(_ablation_description)  # the paper's settings, read on first use
    add_json_out(
        p,
        out_help="write the Solutions and the figures (learning curves, learned controls) as "
        "DIR/<problem>_ablation_*",
    )
    p.set_defaults(func=cmd_ablation)


def _ablation_description(p: argparse.ArgumentParser) -> None:
    from hybridoc.problems.paper import PAPER_SETTINGS

    settings = ", ".join(f"{lr:g} x {n} on {name}" for name, (lr, n) in PAPER_SETTINGS.items())
    p.description = (cmd_ablation.__doc__ or "").format(settings=settings)


def _solve_arguments(p: argparse.ArgumentParser) -> None:
    from hybridoc.methods import CLI_METHOD, METHODS

    problem_arg(p)
    summaries = "; ".join(f"{m.name}: {m.summary}" for m in METHODS.values())
    p.add_argument(
        "--method",
        choices=tuple(METHODS),
        default=CLI_METHOD,
        help=f"{summaries} (default {CLI_METHOD})",
    )
    add_initial_arg(p)
    add_progress_arg(p)
    add_method_options(p, METHODS, reserved=_RESERVED)
    add_json_out(p, out_help="write DIR/<problem>_solve_<method>.npz + .json and figures")
