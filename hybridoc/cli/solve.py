"""``hybridoc solve`` (every registered method) and ``hybridoc ablation`` (the paper's Table 1)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hybridoc.cli._util import (
    add_initial_arg,
    add_json_out,
    emit_json,
    ensure_dir,
    exit_code,
    fmt,
    format_table,
    load_controls_arg,
    load_problem_arg,
    nonnegative_int,
    output_stem,
    positive_float,
    positive_int,
    print_solution,
    problem_arg,
    say,
    solution_payload,
)
from hybridoc.errors import HybridocError

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np

__all__ = ["PAPER_TABLE1", "register", "run_ablation"]

#: The paper's Table 1 (final loss of its plain gradient descent) and its grid-search optima.
PAPER_TABLE1: dict[str, dict[str, float]] = {
    "none": {"single-collision": 0.3616, "multiple-collision": 0.5261},
    "position": {"single-collision": 0.3949, "multiple-collision": 0.5841},
    "velocity": {"single-collision": 0.4797, "multiple-collision": 0.6142},
    "both": {"single-collision": 0.3151, "multiple-collision": 0.3785},
    "optimum": {"single-collision": 0.3115, "multiple-collision": 0.3737},
}
_TOI_LABEL = {
    "none": "no TOI",
    "position": "TOI-Position",
    "velocity": "TOI-Velocity",
    "both": "TOI-Position + TOI-Velocity",
}
# command-line option -> API option of the methods
_OPTIONS = {
    "contact": "contact",
    "toi": "toi",
    "integrator": "integrator",
    "optimizer": "optimizer",
    "iters": "iters",
    "lr": "lr",
    "smoothing": "smoothing",
    "sequence": "sequence",
    "mesh": "mesh",
    "degree": "degree",
    "search": "search",
    "starts": "starts",
    "seed": "seed",
    "hops": "hops",
    "time_limit": "time_limit",
}


def _smoothing_arg(text: str | None) -> tuple[float, ...] | None:
    if text is None:
        return None
    if text.strip().lower() in ("none", ""):
        return ()
    try:
        return tuple(float(x) for x in text.split(","))
    except ValueError:
        raise HybridocError(
            f"--smoothing must be comma-separated numbers or 'none', got {text!r}"
        ) from None


def _learning_curve_figure(curves: dict[str, np.ndarray], optimum: float | None, title: str) -> Any:
    import numpy as np
    from matplotlib.figure import Figure

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
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    return fig


def cmd_solve(args: argparse.Namespace) -> int:
    """Solve a problem with any registered method: --method reference (HMP shooting), dt
    (direct transcription) or gd (gradient descent through the differentiable simulation).

    Every method reports the judge's true cost of its control, its events and a status; a
    result that is not what it claims to be exits with code 1.
    """
    import numpy as np

    from hybridoc.solvers.registry import METHODS, solve

    method = METHODS.get(args.method)
    if method is None:  # pragma: no cover - argparse restricts the choices
        raise HybridocError(f"unknown method {args.method!r}")
    given = {k: getattr(args, k) for k in _OPTIONS if getattr(args, k, None) is not None}
    accepted = set(method.accepted())
    wrong = [k for k in given if _OPTIONS[k] not in accepted]
    if wrong:
        owners = {
            k: [m for m, mm in METHODS.items() if _OPTIONS[k] in mm.accepted()] for k in wrong
        }
        parts = [
            f"--{k.replace('_', '-')} applies to --method {'/'.join(v) or '-'}"
            for k, v in owners.items()
        ]
        raise HybridocError(f"{'; '.join(parts)}, not to --method {args.method}")
    options = {_OPTIONS[k]: v for k, v in given.items()}
    if "smoothing" in options:
        options["smoothing"] = _smoothing_arg(options["smoothing"])
    ocp = load_problem_arg(args.problem)
    if args.initial is not None:
        options["initial"], _ = load_controls_arg(args.initial, ocp)
    if "progress" in accepted:  # gd's bar, dt's and the reference's stage lines
        options["progress"] = True
    out = None if args.out is None else ensure_dir(args.out)  # fail before the solve
    sol = solve(ocp, args.method, **options)
    written: list[Path] = []
    if out is not None:
        from hybridoc.cli.evaluate import save, write_figures
        from hybridoc.evaluator import evaluate

        stem = output_stem(out, ocp.name, "solve", args.method)
        written += list(sol.save(stem))
        written += write_figures(ocp, evaluate(ocp, sol.controls), stem, label=args.method)
        hist = sol.arrays.get("loss_history")
        if hist is not None and len(hist):
            fig = _learning_curve_figure(
                {args.method: np.asarray(hist)}, None, f"{ocp.name}: learning curve"
            )
            written.append(save(fig, f"{stem}_learning_curve.png"))
    if args.json:
        emit_json(solution_payload(sol, files=[str(p) for p in written]))
        return exit_code(sol.status, sol.message)
    details: list[tuple[str, str]] = []
    if "loss" in sol.info:
        details.append(("loss", f"{fmt(sol.info['loss'], 12)} (the simulation's discrete loss)"))
    if "iterations" in sol.info:
        details.append(("iterations", str(sol.info["iterations"])))
    if "nlp_cost" in sol.info:
        details.append(("nlp cost", f"{fmt(sol.info['nlp_cost'], 12)} (the transcription's)"))
    if "residual" in sol.info:
        details.append(("residual", f"{sol.info['residual']:.2e} (HMP, max norm)"))
    settings = ", ".join(f"{k} {v}" for k, v in sol.settings.items() if v is not None)
    if settings:
        details.append(("settings", settings))
    print_solution(args, sol, ocp, details)
    for p in written:
        say(args, f"wrote {p}")
    return exit_code(sol.status, sol.message)


def run_ablation(progress: bool = False) -> dict[str, Any]:
    """The paper's Table 1: plain gd (symplectic Euler) with each TOI setting on both paper
    problems. Returns ``{"rows": [...], "solutions": {(toi, scene): Solution}}``."""
    from hybridoc.solvers.contacts import TOI_MODES
    from hybridoc.solvers.gd import PAPER_SETTINGS, solve_gd

    rows, sols = [], {}
    for name, (lr, iters) in PAPER_SETTINGS.items():
        for toi in TOI_MODES:
            sol = solve_gd(
                name, toi=toi, integrator="symplectic-euler", optimizer="gd", lr=lr, iters=iters,
                progress=progress,
            )  # fmt: skip
            sols[(toi, name)] = sol
            rows.append(
                {
                    "scene": name,
                    "toi": toi,
                    "loss": sol.info["loss"],
                    "cost": sol.cost,
                    "paper_loss": PAPER_TABLE1[toi][name],
                    "paper_optimum": PAPER_TABLE1["optimum"][name],
                    "lr": lr,
                    "iterations": sol.info["iterations"],
                    "events": sol.events,
                    "loss_history": sol.arrays["loss_history"],
                }
            )
    return {"rows": rows, "solutions": sols}


def cmd_ablation(args: argparse.Namespace) -> int:
    """Rerun the paper's Table 1 (TOI-Position x TOI-Velocity, both paper problems).

    Plain gradient descent with the paper's symplectic Euler, learning rates and iterations
    (200 x 500 on single-collision, 50 x 1500 on multiple-collision), direct impulses. Prints
    the final discrete loss beside the paper's and the true continuous cost of the learned
    controls.
    """
    import numpy as np

    from hybridoc.cli.evaluate import save
    from hybridoc.solvers.contacts import TOI_MODES

    out = None if args.out is None else ensure_dir(args.out)  # fail before minutes of work
    res = run_ablation(progress=True)
    rows = res["rows"]
    written: list[Path] = []
    if out is not None:
        from hybridoc.plotting import plot_controls

        for name in ("single-collision", "multiple-collision"):
            curves = {
                _TOI_LABEL[r["toi"]]: np.asarray(r["loss_history"])
                for r in rows
                if r["scene"] == name
            }
            fig = _learning_curve_figure(
                curves, PAPER_TABLE1["optimum"][name], f"{name}: plain gd learning curves"
            )
            stem = output_stem(out, name, "ablation")
            written.append(save(fig, f"{stem}_learning_curves.png"))
            ocp = load_problem_arg(name)
            controls = {_TOI_LABEL[t]: res["solutions"][(t, name)].controls for t in TOI_MODES}
            fig = plot_controls(
                ocp.time_grid(), controls, list(ocp.control_labels),
                title=f"{name}: learned controls (plain gd)",
            )  # fmt: skip
            written.append(save(fig, f"{stem}_controls.png"))
            for toi in TOI_MODES:
                written += list(res["solutions"][(toi, name)].save(f"{stem}_{toi}"))
    if args.json:
        emit_json({"rows": rows})
        return 0
    table = [
        [
            r["scene"], _TOI_LABEL[r["toi"]], fmt(r["loss"], 5), fmt(r["paper_loss"], 4),
            fmt(r["cost"], 5), fmt(r["paper_optimum"], 4),
        ]
        for r in rows
    ]  # fmt: skip
    headers = ["scene", "TOI", "loss", "paper loss", "true cost", "paper grid-search optimum"]
    say(args, format_table(headers, table, right=[False, False, True, True, True, True]))
    say(args, "loss: final discrete loss of plain gd; true cost: the judge's cost of its controls")
    say(args, "exact optima (hybridoc reference): 0.311416870358 and 0.356279430543")
    for p in written:
        say(args, f"wrote {p}")
    return 0


def register(sub: Any) -> None:
    """Add ``solve`` and ``ablation``."""
    p = sub.add_parser(
        "solve",
        help="solve a problem with any method (reference, dt, gd)",
        description=cmd_solve.__doc__,
    )
    p.defer(_solve_arguments)  # the choices come from the solvers' registries: on first use
    p.set_defaults(func=cmd_solve)

    p = sub.add_parser(
        "ablation",
        help="the paper's Table 1: TOI settings x paper problems (plain gd)",
        description=cmd_ablation.__doc__,
    )
    add_json_out(p, out_help="write learning-curve and learned-control figures and Solutions")
    p.set_defaults(func=cmd_ablation)


def _solve_arguments(p: argparse.ArgumentParser) -> None:
    from hybridoc.reference.solve import MAX_SEARCH
    from hybridoc.solvers.contacts import TOI_MODES, model_names
    from hybridoc.solvers.gd import INTEGRATORS, OPTIMIZERS
    from hybridoc.solvers.registry import METHODS
    from hybridoc.solvers.transcription import MAX_DEGREE, MAX_MESH

    problem_arg(p)
    p.add_argument(
        "--method",
        choices=tuple(METHODS),
        default="gd",
        help="; ".join(f"{m.name}: {m.summary}" for m in METHODS.values()) + " (default gd)",
    )
    add_initial_arg(p)
    g = p.add_argument_group("gd options")
    g.add_argument("--contact", choices=tuple(model_names()), default=None,
                   help="disc contact model (default direct)")  # fmt: skip
    g.add_argument("--toi", choices=TOI_MODES, default=None,
                   help="time-of-impact correction (default both)")  # fmt: skip
    g.add_argument("--integrator", choices=INTEGRATORS, default=None,
                   help="exact (default) or the paper's symplectic-euler")  # fmt: skip
    g.add_argument("--optimizer", choices=OPTIMIZERS, default=None, help="default lbfgs")
    g.add_argument(
        "--smoothing", default=None, metavar="MU,MU",
        help="continuation weights of the control-smoothness penalty, or 'none' "
        "(default: 1e-4,1e-5,1e-6 for lbfgs, none otherwise)",
    )  # fmt: skip
    g.add_argument("--iters", type=nonnegative_int, default=None,
                   help="iterations (per continuation stage with lbfgs)")  # fmt: skip
    g.add_argument("--lr", type=positive_float, default=None, help="learning rate")
    g.add_argument("--starts", type=positive_int, default=None, metavar="K",
                   help="batched multi-start: K initial controls at once (the guess, its "
                   "perturbations, random smooth and aimed controls); the best is returned, "
                   "all K in the JSON (default 1)")  # fmt: skip
    g.add_argument("--seed", type=nonnegative_int, default=None,
                   help="seed of the multi-start's random starts (default 0)")  # fmt: skip
    g.add_argument("--hops", type=nonnegative_int, default=None, metavar="K",
                   help="up to K rounds of batched restarts around the result, to get past "
                   "the kinks of the symplectic Euler loss (default 0)")  # fmt: skip
    g = p.add_argument_group("dt and reference options")
    g.add_argument("--sequence", metavar="EVENTS", default=None,
                   help="comma-separated guard names in event order ('' for none)")  # fmt: skip
    g.add_argument("--mesh", type=positive_int, default=None,
                   help=f"dt: collocation elements per phase, at most {MAX_MESH} "
                   "(default 4)")  # fmt: skip
    g.add_argument("--degree", type=positive_int, default=None,
                   help=f"dt: collocation degree, 1 to {MAX_DEGREE} (default 3)")  # fmt: skip
    g.add_argument("--search", type=nonnegative_int, default=None, metavar="K",
                   help=f"reference: enumerate event sequences of up to K events, K at most "
                   f"{MAX_SEARCH}")  # fmt: skip
    g.add_argument("--time-limit", type=positive_float, default=None, metavar="SECONDS",
                   help="dt: stop IPOPT and exit 2 after this much wall time (default: no "
                   "limit; at most 500 IPOPT iterations per candidate sequence)")  # fmt: skip
    add_json_out(p, out_help="write DIR/<problem>_solve_<method>.npz + .json and figures")
