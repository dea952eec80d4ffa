"""``hybridoc gradcheck`` and ``hybridoc compare-contacts``: the contact models side by side.

``gradcheck`` measures how right each contact model's gradient is: the gradient of the
discrete loss (torch autograd through :class:`~hybridoc.solvers.simulator.Simulator`) against
the exact gradient of the continuous cost (:func:`hybridoc.gradient`, the HMP adjoint), with
respect to the initial positions, the initial velocities and the controls, at the initial guess
and at iterates of plain gradient descent. ``compare-contacts`` runs the paper's plain gradient
descent with every contact model and reports the discrete loss and the true continuous cost
(the paper's Figures 5/6 and 10/11).

The same measurements are available from Python: :func:`gradient_errors`,
:func:`gradcheck_points` and :func:`compare_contacts`.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass
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
from hybridoc.errors import HybridocError, SceneError

__all__ = [
    "CONTACT_MODELS",
    "ContactModel",
    "compare_contacts",
    "gradcheck_points",
    "gradient_errors",
    "paper_gd_settings",
    "register",
]


@dataclass(frozen=True)
class ContactModel:
    """One contact model of the simulator: impulse solver and TOI setting, or a non-impulse
    model (``contact``)."""

    name: str
    impulse: str = "direct"
    toi: str = "both"
    contact: str | None = None

    @property
    def impulse_based(self) -> bool:
        return self.contact is None

    def simulator(self, scene: Any) -> Any:
        from hybridoc.solvers.simulator import Simulator

        return Simulator(scene, impulse=self.impulse, toi=self.toi, contact=self.contact)

    def settings(self) -> dict[str, Any]:
        return {"impulse": self.impulse, "toi": self.toi, "contact": self.contact}


#: The models compared: the impulse solvers with the paper's TOI corrections (and the plain
#: ``direct`` without them, the paper's baseline), then the compliant and PBD models.
CONTACT_MODELS: tuple[ContactModel, ...] = (
    ContactModel("direct/none", "direct", "none"),
    ContactModel("direct/both", "direct", "both"),
    ContactModel("lcp/both", "lcp", "both"),
    ContactModel("convex/both", "convex", "both"),
    ContactModel("compliant", contact="compliant"),
    ContactModel("pbd", contact="pbd"),
)

#: Paper learning rates of plain gradient descent (section 5), 50 elsewhere.
_PAPER_LR = {"single-collision": 200.0, "multiple-collision": 50.0}
_PAPER_ITERS = {"single-collision": 500, "multiple-collision": 1500}
#: The paper's analytical optimal losses (Table 1), drawn in the learning-curve figure.
_PAPER_OPTIMUM = {"single-collision": 0.3115, "multiple-collision": 0.3737}


def paper_gd_settings(scene: Any) -> tuple[float, int]:
    """``(learning rate, iterations)`` of the paper's plain gradient descent on ``scene``.

    200 and 500 on single-collision, 50 and 1500 on multiple-collision; 50 and 500 elsewhere.
    """
    return _PAPER_LR.get(scene.name, 50.0), _PAPER_ITERS.get(scene.name, 500)


def _rel(a: np.ndarray, b: np.ndarray) -> float:
    nb = float(np.linalg.norm(b))
    diff = float(np.linalg.norm(np.asarray(a) - np.asarray(b)))
    return diff / nb if nb > 0 else (0.0 if diff == 0 else math.inf)


def gradient_errors(
    scene: Any, controls: np.ndarray, model: ContactModel, exact: Any = None
) -> dict[str, Any]:
    """Relative errors of one contact model's gradient against the exact gradient.

    Parameters
    ----------
    scene
        A :class:`~hybridoc.problems.Scene`.
    controls
        ``(N, nu)`` piecewise-constant controls at which both gradients are taken.
    model
        The contact model.
    exact
        The :class:`hybridoc.Gradient` at ``controls`` if already computed.

    Returns
    -------
    dict
        ``loss`` (discrete objective), ``cost`` (continuous cost), and the relative errors
        ``||g_sim - g_exact|| / ||g_exact||`` for the initial positions (``err_position``),
        initial velocities (``err_velocity``) and controls (``err_controls``); ``cosine`` is
        the cosine between the two control gradients.
    """
    import torch

    import hybridoc

    if exact is None:
        exact = hybridoc.gradient(scene, controls)
    sim = model.simulator(scene)
    u = torch.tensor(np.asarray(controls, dtype=float), dtype=torch.float64, requires_grad=True)
    x0 = sim.x0.detach().clone().requires_grad_(True)
    loss = sim.loss(u, x0)
    loss.backward()
    gx = x0.grad.detach().cpu().numpy()
    gu = u.grad.detach().cpu().numpy()
    ex = np.asarray(exact.d_initial_state, dtype=float)
    eu = np.asarray(exact.d_controls, dtype=float)
    n2 = 2 * scene.n_discs
    nu_norm = float(np.linalg.norm(gu) * np.linalg.norm(eu))
    return {
        "loss": float(loss.detach()),
        "cost": float(exact.cost),
        "err_position": _rel(gx[:n2], ex[:n2]),
        "err_velocity": _rel(gx[n2:], ex[n2:]),
        "err_controls": _rel(gu, eu),
        "cosine": float(np.sum(gu * eu) / nu_norm) if nu_norm > 0 else math.nan,
    }


def gradcheck_points(scene: Any, gd_iters: list[int]) -> list[tuple[str, np.ndarray]]:
    """The controls at which ``gradcheck`` compares gradients.

    The initial guess and the iterates ``gd_iters`` of the paper's plain gradient descent with
    the default contact model (``direct``, TOI ``both``), so that the points follow the path an
    optimiser takes towards the optimum.
    """
    points = [("initial", scene.initial_controls())]
    wanted = sorted({int(k) for k in gd_iters if int(k) > 0})
    if not wanted:
        return points
    from hybridoc.solvers.gd import solve_gd

    lr, _ = paper_gd_settings(scene)
    saved: dict[int, np.ndarray] = {}

    def keep(k: int, loss: float, u: np.ndarray) -> bool:
        if k in wanted:
            saved[k] = u
        return k >= wanted[-1]

    solve_gd(scene, optimizer="gd", lr=lr, iters=wanted[-1], callback=keep)
    points += [(f"gd-{k}", saved[k]) for k in wanted if k in saved]
    return points


def _models(names: str | None) -> list[ContactModel]:
    if not names:
        return list(CONTACT_MODELS)
    by_name = {m.name: m for m in CONTACT_MODELS}
    out = []
    for name in names.split(","):
        name = name.strip()
        if name not in by_name:
            raise SceneError(
                f"unknown contact model {name!r}; choose from {', '.join(by_name)} (comma list)"
            )
        out.append(by_name[name])
    return out


def _int_list(text: str) -> list[int]:
    try:
        values = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise SceneError(
            f"--gd-iters: expected a comma-separated list of integers, got {text!r}"
        ) from None
    if any(v < 0 for v in values):
        raise SceneError(f"--gd-iters: iteration counts must be >= 0, got {text!r}")
    return values


def cmd_gradcheck(args: argparse.Namespace) -> int:
    """Compare each contact model's gradient with the exact gradient of the continuous cost.

    For every contact model and every point (the initial guess and iterates of the paper's
    plain gradient descent), the relative errors ||g_sim - g_exact|| / ||g_exact|| of the
    gradient with respect to the initial positions, the initial velocities and the controls.
    """
    import hybridoc

    scene = resolve_scene(args.scene)
    models = _models(args.models)
    gd_iters = _int_list(args.gd_iters)
    t0 = time.perf_counter()
    say(args, f"gradcheck {scene.name}: finding the points (plain gd, direct/both) ...")
    points = gradcheck_points(scene, gd_iters)
    entries = []
    for label, u in points:
        try:
            exact = hybridoc.gradient(scene, u)
        except HybridocError as exc:
            say(args, f"  {label}: no exact gradient ({exc}); point skipped")
            continue
        for model in models:
            entry = {"model": model.name, **model.settings(), "point": label}
            try:
                entry.update(gradient_errors(scene, u, model, exact))
            except HybridocError as exc:
                entry.update(error=str(exc))
            entries.append(entry)
    elapsed = time.perf_counter() - t0
    if args.json:
        emit_json(
            {
                "scene": scene.name,
                "points": [label for label, _ in points],
                "entries": entries,
                "time_s": elapsed,
            }
        )
        return 0
    rows = []
    for e in entries:
        if "error" in e:
            rows.append([e["point"], e["model"], "-", "-", "-", "-", e["error"]])
            continue
        rows.append(
            [
                e["point"],
                e["model"],
                fmt(e["loss"], 7),
                f"{e['err_position']:.3e}",
                f"{e['err_velocity']:.3e}",
                f"{e['err_controls']:.3e}",
                f"{e['cosine']:.5f}",
            ]
        )
    print(f"{scene.name}: relative gradient errors ||g_sim - g_exact|| / ||g_exact||")
    print(
        format_table(
            ["point", "model", "loss", "d p0", "d v0", "d u", "cos(d u)"],
            rows,
            right=[False, False, True, True, True, True, True],
        )
    )
    print(f"({elapsed:.1f} s)")
    return 0


def compare_contacts(
    scene: Any,
    *,
    models: list[ContactModel] | None = None,
    iters: int | None = None,
    lr: float | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Plain gradient descent (the paper's settings) with every contact model.

    Returns ``{model name: hybridoc.solution.Solution}`` in the order of ``models``; each
    Solution carries the discrete loss (``info["loss"]``), the true continuous cost
    (``cost``) and the learning curve (``arrays["loss_history"]``).
    """
    from hybridoc.solvers.gd import solve_gd

    lr0, it0 = paper_gd_settings(scene)
    out = {}
    for model in models or list(CONTACT_MODELS):
        out[model.name] = solve_gd(
            scene,
            optimizer="gd",
            lr=lr0 if lr is None else lr,
            iters=it0 if iters is None else iters,
            progress=progress,
            **model.settings(),
        )
    return out


def _learning_curves(scene: Any, sols: dict[str, Any]) -> Any:
    from matplotlib.figure import Figure

    groups = [
        ("velocity-impulse models", [k for k in sols if "/" in k]),
        ("compliant and PBD", [k for k in sols if "/" not in k]),
    ]
    groups = [(t, ks) for t, ks in groups if ks]
    fig = Figure(figsize=(5.0 * len(groups), 3.8), layout="constrained")
    axes = fig.subplots(1, len(groups), squeeze=False)[0]
    for ax, (title, keys) in zip(axes, groups, strict=True):
        for k in keys:
            h = np.asarray(sols[k].arrays["loss_history"])
            ax.plot(np.arange(h.size), h, lw=1.3, label=f"{k} (cost {sols[k].cost:.4f})")
        opt = _PAPER_OPTIMUM.get(scene.name)
        if opt is not None:
            ax.axhline(opt, color="k", ls="--", lw=1.0, label=f"paper's optimum {opt}")
        ax.set_xlabel("iteration")
        ax.set_ylabel("discrete loss")
        ax.set_title(title)
        ax.grid(True, lw=0.4, alpha=0.5)
        ax.legend(fontsize=7)
        lo = min(float(np.nanmin(sols[k].arrays["loss_history"])) for k in keys)
        hi = max(float(np.nanmax(sols[k].arrays["loss_history"])) for k in keys)
        if opt is not None:
            lo = min(lo, opt)
        # the start is far above the end: zoom on the part where the models differ
        top = min(hi, lo + 3.0 * (np.nanmedian([sols[k].info["loss"] for k in keys]) - lo) + 0.05)
        ax.set_ylim(lo - 0.02 * (top - lo), top)
    fig.suptitle(f"{scene.name}: plain gradient descent with each contact model")
    return fig


def cmd_compare_contacts(args: argparse.Namespace) -> int:
    """Plain gradient descent with every contact model: discrete loss and true cost.

    Uses the paper's learning rate (200 on single-collision, 50 elsewhere) and iterations (500,
    1500 on multiple-collision, 500 elsewhere) unless --iters / --lr are given; the true cost
    is the event-exact continuous cost of the learned controls.
    """
    scene = resolve_scene(args.scene)
    models = _models(args.models)
    out = None if args.out is None else ensure_dir(args.out)  # fail before the solves
    lr, iters = paper_gd_settings(scene)
    lr = lr if args.lr is None else args.lr
    iters = iters if args.iters is None else args.iters
    say(args, f"compare-contacts {scene.name}: plain gd, lr {lr:g}, {iters} iterations")
    sols = compare_contacts(scene, models=models, iters=iters, lr=lr, progress=True)
    figures: list[str] = []
    if out is not None:
        from hybridoc.plotting import plot_controls, save_figure

        for name, sol in sols.items():
            sol.save(out / f"gd_{name.replace('/', '_')}")
        figures.append(str(save_figure(_learning_curves(scene, sols), out / "learning_curves.png")))
        fig = plot_controls(
            scene.time_grid(),
            {name: sol.controls for name, sol in sols.items()},
            scene.control_labels(),
            title=f"{scene.name}: controls learned with each contact model",
        )
        figures.append(str(save_figure(fig, out / "learned_controls.png")))
    results = [
        {
            "model": name,
            **sol.settings,
            "loss": sol.info["loss"],
            "cost": sol.cost,
            "iterations": sol.info["iterations"],
            "time_s": sol.timings.get("solve_time_s"),
            "message": sol.info.get("message"),
            "events": sol.events,
            "loss_history": sol.arrays["loss_history"],
        }
        for name, sol in sols.items()
    ]
    if args.json:
        emit_json(
            {
                "scene": scene.name,
                "lr": lr,
                "iters": iters,
                "paper_optimum": _PAPER_OPTIMUM.get(scene.name),
                "models": results,
                "figures": figures,
            }
        )
        return 0
    rows = [
        [r["model"], fmt(r["loss"], 7), fmt(r["cost"], 7), len(r["events"]), f"{r['time_s']:.1f}"]
        for r in results
    ]
    print(f"{scene.name}: plain gradient descent, lr {lr:g}, {iters} iterations")
    print(format_table(["model", "loss", "true cost", "events", "time s"], rows))
    if scene.name in _PAPER_OPTIMUM:
        print(f"paper's analytical optimal loss: {_PAPER_OPTIMUM[scene.name]}")
    for f in figures:
        print(f"wrote {f}")
    return 0


def register(subparsers: Any) -> None:
    """Add ``gradcheck`` and ``compare-contacts`` to the ``hybridoc`` command."""
    names = ", ".join(m.name for m in CONTACT_MODELS)
    p = subparsers.add_parser(
        "gradcheck",
        help="each contact model's gradient against the exact gradient",
        description=cmd_gradcheck.__doc__,
    )
    scene_arg(p)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument(
        "--gd-iters",
        default="20,100",
        metavar="K,K",
        help="also compare at these iterates of the paper's plain gd (default 20,100; '' none)",
    )
    p.add_argument("--models", default=None, metavar="M,M", help=f"subset of: {names}")
    p.set_defaults(func=cmd_gradcheck)

    p = subparsers.add_parser(
        "compare-contacts",
        help="plain gradient descent with every contact model (paper Figs 5, 10)",
        description=cmd_compare_contacts.__doc__,
    )
    scene_arg(p)
    add_json_out(
        p,
        out_help="write each model's Solution, learning_curves.png and learned_controls.png",
    )
    p.add_argument(
        "--iters", type=nonnegative_int, default=None, help="iterations (default: the paper's)"
    )
    p.add_argument(
        "--lr", type=positive_float, default=None, help="learning rate (default: the paper's)"
    )
    p.add_argument("--models", default=None, metavar="M,M", help=f"subset of: {names}")
    p.set_defaults(func=cmd_compare_contacts)
