"""``hybridoc gradcheck`` and ``hybridoc compare-contacts``: the contact models side by side
(the library functions are in :mod:`hybridoc.solvers.gradcheck`), and ``gradcheck --against``:
any simulator's gradient against the exact one (:mod:`hybridoc.workflows.gradcompare`)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hybridoc.cli._util import (
    add_controls_arg,
    add_json_out,
    add_substeps_arg,
    disc_scene_of,
    emit_json,
    fmt,
    format_table,
    load_problem_arg,
    load_substep_controls_arg,
    nonnegative_int,
    output_stem,
    positive_float,
    problem_arg,
    problem_slug,
    say,
    to_jsonable,
)
from hybridoc.cli.vocabulary import add_deprecated_alias, spelled
from hybridoc.errors import HybridocError, OptionError
from hybridoc.outputs import check_folder, check_targets, write_text

if TYPE_CHECKING:  # pragma: no cover
    from matplotlib.figure import Figure

    from hybridoc.problem import ProblemLike
    from hybridoc.solution import Solution

__all__ = ["register"]


def _int_list(text: str) -> list[int]:
    try:
        values = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise OptionError(
            f"--iters: expected a comma-separated list of integers, got {text!r}"
        ) from None
    if any(v < 0 for v in values):
        raise OptionError(f"--iters: iteration counts must be >= 0, got {text!r}")
    return values


def cmd_gradcheck(args: argparse.Namespace) -> int:
    """Compare each contact model's gradient with the exact gradient of the continuous cost,
    or (--against) any simulator's gradient.

    For every contact model and every point (the initial guess and iterates of the paper's
    plain gradient descent), the relative errors ||g_sim - g_exact|| / ||g_exact|| of the
    gradient with respect to the initial positions, the initial velocities and the controls
    (disc scenes). With --against GRAD (.npy or .csv, N x nu or N*nu values), that gradient
    of the cost with respect to the controls (--controls, default the initial guess) against
    the exact adjoint on any problem: cosine, relative error, per control component, and per
    part of the grid split by the judge's events.
    """
    if args.against is not None:
        return _gradcheck_against(args)
    given = [f for f, v in (("--controls", args.controls), ("--substeps", args.substeps),
                            ("--out", args.out)) if v is not None]  # fmt: skip
    if given:
        raise HybridocError(f"{', '.join(given)} applies to --against only")
    import hybridoc
    from hybridoc.solvers.gradcheck import gradcheck_points, gradient_errors, parse_models

    scene = disc_scene_of(load_problem_arg(args.problem), "gradcheck")
    models = parse_models(args.models)
    gd_iters = _int_list("20,100" if args.gd_iters is None else args.gd_iters)
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
            say(args, f"  {label}: {model.label} ...")
            entry = {"model": model.label, **model.settings(), "point": label}
            try:
                entry.update(gradient_errors(scene, u, model, exact))
            except HybridocError as exc:
                entry.update(error=str(exc))
            entries.append(entry)
    elapsed = time.perf_counter() - t0
    if args.json:
        emit_json(
            {
                "problem": scene.name,
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
                e["point"], e["model"], fmt(e["loss"], 7), f"{e['err_position']:.3e}",
                f"{e['err_velocity']:.3e}", f"{e['err_controls']:.3e}", f"{e['cosine']:.5f}",
            ]
        )  # fmt: skip
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


def _gradcheck_against(args: argparse.Namespace) -> int:
    """``gradcheck --against``: an external gradient against the exact adjoint."""
    from hybridoc.cli.evaluate import save
    from hybridoc.io import read_array
    from hybridoc.workflows.gradcompare import GradientError, compare_gradient, gradient_figure

    flags = (
        (spelled(args, "--contact", "--models"), args.models),
        (spelled(args, "--iters", "--gd-iters"), args.gd_iters),
    )
    wrong = [f for f, v in flags if v is not None]
    if wrong:
        raise HybridocError(f"{', '.join(wrong)} compare contact models: not with --against")
    base = load_problem_arg(args.problem)
    ocp, u, source = load_substep_controls_arg(args.controls, base, args.substeps)
    k = ocp.steps // base.steps
    given = read_array(
        args.against, what="gradient", labels=ocp.control_labels, error=GradientError
    )
    out = None if args.out is None else check_folder(args.out)
    stem = None if out is None else output_stem(out, problem_slug(args.problem, ocp), "gradcheck")
    if stem is not None:  # a refused output name fails before the work
        check_targets(f"{stem}.png", f"{stem}.json")
    try:
        cmp = compare_gradient(base, given, u, substeps=k, flag="--substeps")
    except GradientError as exc:
        raise GradientError(f"gradient file {str(args.against)!r}: {exc}") from None
    report = {"gradient_file": str(args.against), "controls": source, **cmp.to_dict()}
    if args.json:
        emit_json(report)
    else:
        say(args, f"problem   {ocp.name} (N = {ocp.steps}, T = {fmt(ocp.horizon)})")
        say(args, f"controls  {source}")
        say(args, f"gradient  {args.against}")
        say(args, f"cost      {cmp.cost!r}")
        say(args, f"events    {_events_line(cmp.events)}")
        say(args, "")
        rows = []
        for part in [cmp.overall, *cmp.components, *cmp.phases]:
            rows.append(
                [
                    part.name, part.cells, fmt(part.exact_norm, 4), fmt(part.given_norm, 4),
                    fmt(part.cosine, 6), fmt(part.relative_error, 4), fmt(part.max_abs_error, 4),
                    f"{100 * part.error_share:.1f}%",
                ]
            )  # fmt: skip
        headers = ["entries", "cells", "|exact|", "|given|", "cosine", "rel. error", "max |err|"]
        headers.append("share of err^2")
        say(args, format_table(headers, rows, right=[False] + [True] * 7))
        say(args, "rel. error: |given - exact| / |exact| over the entries; exact: the adjoint of")
        say(args, "the continuous cost (hybridoc gradient); cells split by the judge's events.")
    if stem is not None:  # after the answer is out: a write that fails loses nothing shown
        written = [save(gradient_figure(cmp, label=args.against.stem), f"{stem}.png")]
        written.append(_write_json(Path(f"{stem}.json"), report))
        for p in written:
            say(args, f"wrote {p}")
    return 0


def _events_line(events: list[dict[str, Any]]) -> str:
    return ", ".join(f"{e['guard']}@{e['time']:.6g}" for e in events) or "none"


def _write_json(path: Path, obj: Any) -> Path:
    """Write a report by the rules of :mod:`hybridoc.outputs`."""
    import json

    return write_text(path, json.dumps(to_jsonable(obj), indent=2) + "\n")


def _learning_curves(scene: ProblemLike, sols: dict[str, Solution]) -> Figure:
    import numpy as np
    from matplotlib.figure import Figure

    from hybridoc.problems.paper import PAPER_OPTIMUM

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
        opt = PAPER_OPTIMUM.get(scene.name)
        if opt is not None:
            ax.axhline(opt, color="k", ls="--", lw=1.0, label=f"paper's grid-search optimum {opt}")
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

    Uses the paper's learning rate and iterations (hybridoc.problems.paper; 50 and 500 on
    other scenes) unless --iters / --lr are given; the true cost
    is the event-exact continuous cost of the learned controls. A model whose learned
    controls make no contact at all is named in one line below the table.
    """
    from hybridoc.problems.paper import PAPER_OPTIMUM
    from hybridoc.solvers.gradcheck import (
        compare_contacts,
        contact_note,
        paper_gd_settings,
        parse_models,
    )

    scene = disc_scene_of(load_problem_arg(args.problem), "compare-contacts")
    models = parse_models(args.models)
    out = None if args.out is None else check_folder(args.out)  # fail before the solves
    stem = None
    if out is not None:
        stem = output_stem(out, problem_slug(args.problem, scene), "compare-contacts")
        names = [f"{stem}_{m.label.replace('/', '-')}" for m in models]
        check_targets(
            *(f"{n}{ext}" for n in names for ext in (".npz", ".json")),
            f"{stem}_learning_curves.png", f"{stem}_controls.png",
        )  # fmt: skip
    lr, iters = paper_gd_settings(scene)
    lr = lr if args.lr is None else args.lr
    iters = iters if args.iters is None else args.iters
    say(args, f"compare-contacts {scene.name}: plain gd, lr {lr:g}, {iters} iterations")
    sols = compare_contacts(scene, models=models, iters=iters, lr=lr, progress=True)
    figures = [] if stem is None else [f"{stem}_{f}.png" for f in ("learning_curves", "controls")]
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
            "note": contact_note(name, sol),
            "loss_history": sol.arrays["loss_history"],
        }
        for name, sol in sols.items()
    ]
    notes = [r["note"] for r in results if r["note"]]
    if args.json:
        emit_json(
            {
                "problem": scene.name,
                "lr": lr,
                "iters": iters,
                "paper_grid_search_optimum": PAPER_OPTIMUM.get(scene.name),
                "models": results,
                "figures": figures,
            }
        )
        _write_compare_contacts(scene, sols, stem)
        return 0
    rows = [
        [r["model"], fmt(r["loss"], 7), fmt(r["cost"], 7), len(r["events"]), f"{r['time_s']:.1f}"]
        for r in results
    ]
    print(f"{scene.name}: plain gradient descent, lr {lr:g}, {iters} iterations")
    print(format_table(["model", "loss", "true cost", "events", "time s"], rows))
    for note in notes:
        print(note)
    if scene.name in PAPER_OPTIMUM:
        print(
            f"the paper's grid-search optimum: {PAPER_OPTIMUM[scene.name]} (the exact optimum: "
            "'hybridoc reference')"
        )
    _write_compare_contacts(scene, sols, stem)
    for f in figures:
        print(f"wrote {f}")
    return 0


def _write_compare_contacts(
    scene: ProblemLike, sols: dict[str, Solution], stem: Path | None
) -> None:
    """Each model's Solution and the two figures of ``compare-contacts --out``, written after
    the answer is out (a write that fails at the end loses nothing shown)."""
    if stem is None:
        return
    from hybridoc.cli.evaluate import save
    from hybridoc.plotting import plot_controls

    for name, sol in sols.items():
        sol.save(f"{stem}_{name.replace('/', '-')}")
    save(_learning_curves(scene, sols), f"{stem}_learning_curves.png")
    fig = plot_controls(
        scene.time_grid(),
        {name: sol.controls for name, sol in sols.items()},
        scene.control_labels(),
        title=f"{scene.name}: controls learned with each contact model",
    )
    save(fig, f"{stem}_controls.png")


def register(sub: Any) -> None:
    """Add ``gradcheck`` and ``compare-contacts``."""
    # their --models help lists the contact models' registry (numpy, CasADi): on first use
    p = sub.add_parser(
        "gradcheck",
        help="each contact model's gradient against the exact gradient",
        description=cmd_gradcheck.__doc__,
    )
    p.defer(_gradcheck_arguments)
    p.set_defaults(func=cmd_gradcheck)

    p = sub.add_parser(
        "compare-contacts",
        help="plain gradient descent with every contact model (paper Figs 5, 10)",
        description=cmd_compare_contacts.__doc__,
    )
    p.defer(_compare_contacts_arguments)
    p.set_defaults(func=cmd_compare_contacts)


def _model_names() -> str:
    from hybridoc.solvers.contacts import model_names

    return ", ".join(model_names())


def _contact_arg(p: argparse.ArgumentParser) -> None:
    """``--contact M,M``: the contact models compared, each MODEL or MODEL/TOI (``--models``
    is its deprecated spelling)."""
    p.add_argument(
        "--contact", dest="models", default=None, metavar="M,M",
        help=f"the contact models to compare, each MODEL or MODEL/TOI, e.g. "
        f"direct/none,lcp/both,pbd (models: {_model_names()})",
    )  # fmt: skip
    add_deprecated_alias(p, "--models", dest="models", instead="--contact M,M", metavar="M,M")


def _gradcheck_arguments(p: argparse.ArgumentParser) -> None:
    problem_arg(p)
    add_json_out(
        p, out_help="with --against: write DIR/<problem>_gradcheck.json and its figure (.png)"
    )
    p.add_argument(
        "--iters",
        dest="gd_iters",
        default=None,
        metavar="K,K",
        help="also compare at these iterates of the paper's plain gd (default 20,100; '' none)",
    )
    add_deprecated_alias(p, "--gd-iters", dest="gd_iters", instead="--iters K,K", metavar="K,K")
    p.add_argument(
        "--against", metavar="GRAD", type=Path, default=None,
        help="instead of the contact models: this gradient dJ/du (.npy or .csv; N x nu, or N*nu "
        "values row by row) from any simulator, against the exact adjoint (any problem)",
    )  # fmt: skip
    add_controls_arg(p)
    add_substeps_arg(p)
    _contact_arg(p)


def _compare_contacts_arguments(p: argparse.ArgumentParser) -> None:
    problem_arg(p)
    add_json_out(
        p,
        out_help="write each model's Solution DIR/<problem>_compare-contacts_<model>.npz/.json "
        "and the figures DIR/<problem>_compare-contacts_<figure>.png",
    )
    p.add_argument(
        "--iters", type=nonnegative_int, default=None, help="iterations (default: the paper's)"
    )
    p.add_argument(
        "--lr", type=positive_float, default=None, help="learning rate (default: the paper's)"
    )
    _contact_arg(p)
