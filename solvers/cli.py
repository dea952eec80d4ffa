"""``hybridoc solve`` and ``hybridoc ablation``: the solvers on the command line.

``solve SCENE --method gd`` runs :func:`hybridoc.solvers.gd.solve_gd`; ``--method dt``
dispatches to the direct transcription (:func:`hybridoc.solvers.transcription.cli_solve_dt`).
``ablation`` reruns the paper's Table 1: the four time-of-impact settings on both paper
problems with the paper's plain gradient descent, beside the paper's numbers.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from hybridoc.cli_util import (
    add_json_out,
    emit_json,
    ensure_dir,
    fmt,
    format_table,
    nonnegative_int,
    positive_float,
    resolve_scene,
    say,
    scene_arg,
)
from hybridoc.errors import HybridocError

__all__ = ["register", "cmd_solve", "cmd_ablation", "PAPER_TABLE1"]

CONTACT_CHOICES = ("direct", "lcp", "convex", "compliant", "pbd")
TOI_CHOICES = ("none", "position", "velocity", "both")
OPTIMIZER_CHOICES = ("gd", "adam", "lbfgs")

#: The paper's Table 1 (final loss of its plain gradient descent) and analytical optimum.
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


def _contact_kwargs(name: str | None) -> dict[str, Any]:
    if name is None or name == "direct":
        return {"impulse": "direct", "contact": None}
    if name in ("lcp", "convex"):
        return {"impulse": name, "contact": None}
    return {"impulse": "direct", "contact": name}


def _write_solution_figures(scene: Any, sol: Any, out: Path, stem: str, label: str) -> list[Path]:
    import hybridoc
    from hybridoc.plotting import plot_controls, plot_scene, save_figure

    ev = hybridoc.evaluate(scene, sol.controls)
    paths = [
        save_figure(
            plot_scene(scene, ev, title=f"{scene.name}: {label}, cost {sol.cost:.6g}"),
            out / f"{stem}_trajectory.png",
        ),
        save_figure(
            plot_controls(
                scene.time_grid(),
                {label: sol.controls},
                scene.control_labels(),
                title=f"{scene.name}: controls ({label})",
                event_times=[e["time"] for e in sol.events],
            ),
            out / f"{stem}_controls.png",
        ),
    ]
    return paths


def _learning_curve_figure(curves: dict[str, np.ndarray], optimum: float | None, title: str) -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for label, hist in curves.items():
        ax.plot(np.arange(len(hist)), hist, label=label, lw=1.4)
    if optimum is not None:
        ax.axhline(optimum, color="k", ls="--", lw=1, label=f"optimum {optimum:.4f}")
    ax.set_xlabel("iteration")
    ax.set_ylabel("discrete loss")
    ax.set_title(title)
    finals = [h[-1] for h in curves.values()] + ([optimum] if optimum else [])
    lo, hi = min(finals), max(h[0] for h in curves.values())
    ax.set_ylim(lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo))
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


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


# ---------------------------------------------------------------------- solve
def cmd_solve(args: argparse.Namespace) -> int:
    """Solve a scene's optimal control problem.

    ``--method gd`` runs gradient descent through the differentiable simulator and reports
    the discrete loss and the true continuous cost of the returned controls (evaluator);
    ``--method dt`` runs the direct transcription.
    """
    if args.method == "dt":
        gd_only = [
            f"--{name}"
            for name in ("contact", "toi", "integrator", "optimizer", "smoothing", "iters", "lr")
            if getattr(args, name) is not None
        ]
        if gd_only:
            verb = "applies" if len(gd_only) == 1 else "apply"
            raise HybridocError(
                f"{', '.join(gd_only)} {verb} only to --method gd (the transcription has no "
                "contact model, optimizer or iterations)"
            )
        try:
            from hybridoc.solvers.transcription import cli_solve_dt
        except ImportError:
            raise HybridocError(
                "--method dt needs hybridoc.solvers.transcription.cli_solve_dt, which this "
                "installation does not have"
            ) from None
        return int(cli_solve_dt(args))
    from hybridoc.solvers.gd import solve_gd

    scene = resolve_scene(args.scene)
    args.toi = args.toi or "both"
    args.optimizer = args.optimizer or "lbfgs"
    args.integrator = args.integrator or "symplectic-euler"
    smoothing = _smoothing_arg(args.smoothing)
    out = None if args.out is None else ensure_dir(args.out)  # fail before the solve, not after
    t0 = time.perf_counter()
    sol = solve_gd(
        scene,
        toi=args.toi,
        optimizer=args.optimizer,
        iters=args.iters,
        lr=args.lr,
        integrator=args.integrator,
        smoothing=smoothing,
        progress=True,
        **_contact_kwargs(args.contact),
    )
    elapsed = time.perf_counter() - t0
    result = {
        "scene": scene.name,
        "method": "gd",
        "contact": args.contact or "direct",
        "toi": args.toi,
        "integrator": args.integrator,
        "optimizer": args.optimizer,
        "loss": sol.info["loss"],
        "cost": sol.cost,
        "terminal_cost": sol.terminal_cost,
        "running_cost": sol.running_cost,
        "iterations": sol.info["iterations"],
        "time_s": elapsed,
        "message": sol.info["message"],
        "loss_history": sol.arrays["loss_history"],
        "events": sol.events,
    }
    written: list[Path] = []
    if out is not None:
        npz, js = sol.save(out / "solution")
        written += [npz, js]
        written += _write_solution_figures(scene, sol, out, "gd", f"gd ({args.optimizer})")
        fig = _learning_curve_figure(
            {f"{args.contact or 'direct'}/{args.toi}": sol.arrays["loss_history"]},
            None,
            f"{scene.name}: learning curve ({args.optimizer})",
        )
        from hybridoc.plotting import save_figure

        written.append(save_figure(fig, out / "gd_learning_curve.png"))
    if args.json:
        emit_json(result)
        return 0
    say(
        args,
        f"scene {scene.name}: gd ({args.optimizer}), contact {result['contact']}, toi {args.toi}",
    )
    rows = [
        ["discrete loss", fmt(sol.info["loss"])],
        ["cost (evaluator)", fmt(sol.cost)],
        ["  terminal", fmt(sol.terminal_cost)],
        ["  running", fmt(sol.running_cost)],
        ["iterations", str(sol.info["iterations"])],
        ["time [s]", f"{elapsed:.3g}"],
    ]
    say(args, format_table(["quantity", "value"], rows, right=[False, True]))
    say(args, sol.info["message"])
    for e in sol.events:
        say(args, f"  event t = {e['time']:.6f}  {e['kind']}  {'|'.join(e['bodies'])}")
    for p in written:
        say(args, f"wrote {p}")
    return 0


# ---------------------------------------------------------------------- ablation
def run_ablation(progress: bool = False) -> dict[str, Any]:
    """The paper's Table 1: plain gd with each TOI setting on both paper problems.

    Returns ``{"rows": [...], "solutions": {(toi, scene): Solution}}``; each row has the scene,
    the TOI setting, the final discrete loss, the true cost and the paper's number.
    """
    from hybridoc.solvers.gd import PAPER_SETTINGS, solve_gd

    rows, sols = [], {}
    for name, (lr, iters) in PAPER_SETTINGS.items():
        for toi in TOI_CHOICES:
            sol = solve_gd(name, toi=toi, optimizer="gd", lr=lr, iters=iters, progress=progress)
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

    Plain gradient descent with the paper's learning rates and iterations (200 x 500 on
    single-collision, 50 x 1500 on multiple-collision), direct impulses. Prints the final
    discrete loss beside the paper's and the true continuous cost of the learned controls.
    """
    out = None if args.out is None else ensure_dir(args.out)  # fail before minutes of work
    res = run_ablation(progress=True)
    rows = res["rows"]
    written: list[Path] = []
    if out is not None:
        from hybridoc.plotting import plot_controls, save_figure

        for name in ("single-collision", "multiple-collision"):
            curves = {
                _TOI_LABEL[r["toi"]]: np.asarray(r["loss_history"])
                for r in rows
                if r["scene"] == name
            }
            fig = _learning_curve_figure(
                curves, PAPER_TABLE1["optimum"][name], f"{name}: plain gd learning curves"
            )
            written.append(save_figure(fig, out / f"ablation_{name}_learning_curves.png"))
            scene = resolve_scene(name)
            controls = {
                _TOI_LABEL[toi]: res["solutions"][(toi, name)].controls for toi in TOI_CHOICES
            }
            fig = plot_controls(
                scene.time_grid(),
                controls,
                scene.control_labels(),
                title=f"{name}: learned controls (plain gd)",
            )
            written.append(save_figure(fig, out / f"ablation_{name}_controls.png"))
            for toi in TOI_CHOICES:
                npz, js = res["solutions"][(toi, name)].save(out / f"ablation_{name}_{toi}")
                written += [npz, js]
    if args.json:
        emit_json({"rows": rows})
        return 0
    table = [
        [
            r["scene"],
            _TOI_LABEL[r["toi"]],
            fmt(r["loss"], 5),
            fmt(r["paper_loss"], 4),
            fmt(r["cost"], 5),
            fmt(r["paper_optimum"], 4),
        ]
        for r in rows
    ]
    say(
        args,
        format_table(
            ["scene", "TOI", "loss", "paper loss", "true cost", "paper optimum"],
            table,
            right=[False, False, True, True, True, True],
        ),
    )
    say(args, "loss: final discrete loss of plain gd; true cost: evaluator cost of its controls")
    for p in written:
        say(args, f"wrote {p}")
    return 0


def register(subparsers: Any) -> None:
    """Add ``solve`` and ``ablation`` to the ``hybridoc`` command."""
    p = subparsers.add_parser(
        "solve",
        help="solve a scene (gradient descent or transcription)",
        description=cmd_solve.__doc__,
    )
    scene_arg(p)
    p.add_argument("--method", choices=("gd", "dt"), default="gd", help="solver (default gd)")
    p.add_argument(
        "--contact",
        choices=CONTACT_CHOICES,
        default=None,
        help="contact model of the simulator (default direct)",
    )
    # gd-only options default to None so that --method dt can reject them
    p.add_argument(
        "--toi",
        choices=TOI_CHOICES,
        default=None,
        help="time-of-impact correction (default both)",
    )
    p.add_argument(
        "--integrator",
        choices=("symplectic-euler", "exact"),
        default=None,
        help="symplectic-euler (the paper's, default) or exact (exact flow and time of impact)",
    )
    p.add_argument(
        "--optimizer", choices=OPTIMIZER_CHOICES, default=None, help="optimizer (default lbfgs)"
    )
    p.add_argument(
        "--smoothing",
        default=None,
        metavar="MU,MU",
        help="continuation weights of the control-smoothness penalty, or 'none' "
        "(default: 1e-4,1e-5,1e-6 for lbfgs, none otherwise)",
    )
    p.add_argument(
        "--iters",
        type=nonnegative_int,
        default=None,
        help="iterations (default: per optimizer); with lbfgs's smoothing continuation, "
        "per stage, so the total is (stages + 1) x ITERS",
    )
    p.add_argument(
        "--lr", type=positive_float, default=None, help="learning rate (default: per optimizer)"
    )
    add_json_out(p, out_help="write DIR/solution.npz + .json and figures")
    p.set_defaults(func=cmd_solve)

    p = subparsers.add_parser(
        "ablation",
        help="the paper's Table 1: TOI settings x paper problems (plain gd)",
        description=cmd_ablation.__doc__,
    )
    add_json_out(p, out_help="write learning-curve and learned-control figures and Solutions")
    p.set_defaults(func=cmd_ablation)
