"""``hybridoc train-policy``: a feedback policy trained through the differentiable simulator
on draws of a scene's distribution, saved as an MLP policy file (library:
:mod:`hybridoc.workflows.training`, :mod:`hybridoc.workflows.policy_format`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from hybridoc.cli._util import (
    add_json_out,
    add_progress_arg,
    emit_json,
    ensure_dir,
    fmt,
    nonnegative_int,
    output_stem,
    positive_float,
    positive_int,
    problem_arg,
    problem_slug,
    say,
    to_jsonable,
)
from hybridoc.errors import HybridocError

__all__ = ["register"]


def cmd_train_policy(args: argparse.Namespace) -> int:
    """Train an MLP feedback policy u = pi(t, s) through the differentiable simulator
    (full-batch Adam on the mean closed-loop loss of M initial states drawn from the
    problem's distribution) and save it as an MLP policy file: DIR/<problem>_train-policy.json
    (the architecture, read without running code) with its weights in
    DIR/<problem>_train-policy.npz. 'hybridoc validate-policy PROBLEM --policy
    DIR/<problem>_train-policy.json' judges it against the exact references.

    The training draws use the seed --seed (default: the distribution's seed + 1), so that
    they are not the draws that validate-policy judges by default. Needs a disc scene (the
    differentiable simulator's model).
    """
    import numpy as np

    from hybridoc.problems import Scene
    from hybridoc.workflows.datasets import distribution_problem
    from hybridoc.workflows.policy_format import save_mlp_policy
    from hybridoc.workflows.training import mlp_policy, train_policy

    source = distribution_problem(args.problem)
    if not isinstance(source, Scene):
        raise HybridocError(
            f"train-policy needs a disc scene (the differentiable simulator's model); "
            f"{source.name!r} is a generic HybridOCP"
        )
    out = ensure_dir(args.out)
    seed = source.distribution.seed + 1 if args.seed is None else args.seed
    x0 = np.stack(
        [source.distribution.draw(source, i, seed).initial_state() for i in range(args.samples)]
    )
    policy = mlp_policy(source, hidden=args.hidden, layers=args.layers, seed=seed)
    res = train_policy(
        source, policy, x0, toi="both" if args.toi else "none", iters=args.epochs, lr=args.lr,
        seed=seed, progress=not args.no_progress,
    )  # fmt: skip
    stem = output_stem(out, problem_slug(args.problem, source), "train-policy")
    path = save_mlp_policy(res.policy, f"{stem}.json")
    payload = {
        "problem": source.name,
        "policy": str(path),
        "weights": str(path.with_suffix(".npz")),
        "samples": args.samples,
        "seed": seed,
        "epochs": args.epochs,
        "toi": res.toi,
        "hidden": args.hidden,
        "layers": args.layers,
        "lr": args.lr,
        "initial_loss": res.losses[0] if res.losses else None,
        "final_loss": res.final_loss,
        "losses": res.losses,
        "seconds": res.seconds,
    }
    report = Path(f"{stem}_report.json")
    try:
        report.write_text(json.dumps(to_jsonable(payload), indent=2) + "\n", encoding="utf-8")
    except OSError as exc:
        raise HybridocError(f"cannot write {str(report)!r}: {exc.strerror or exc}") from None
    if args.json:
        emit_json(payload)
    else:
        say(args, f"problem     {source.name} ({args.samples} draws, seed {seed})")
        say(args, f"training    {args.epochs} epochs of Adam, lr {args.lr}, toi {res.toi}")
        say(args, f"loss        {fmt(payload['initial_loss'], 8)} -> {fmt(res.final_loss, 8)} "
                  f"(the simulator's mean closed-loop loss)")  # fmt: skip
        say(args, f"time        {res.seconds:.3g} s")
        for p in (path, path.with_suffix(".npz"), report):
            say(args, f"wrote {p}")
        say(args, f"judge it: hybridoc validate-policy {args.problem} --policy {path} --samples M")
    if not np.isfinite(res.final_loss):
        raise HybridocError("the training diverged: the final loss is not finite (a smaller --lr?)")
    return 0


def register(sub: Any) -> None:
    """Add ``train-policy``."""
    p = sub.add_parser(
        "train-policy",
        help="train an MLP feedback policy on draws of a scene's distribution",
        description=cmd_train_policy.__doc__,
    )
    problem_arg(p)
    p.add_argument(
        "--samples", type=positive_int, required=True, metavar="M",
        help="initial states drawn from the scene's [distribution] to train on",
    )  # fmt: skip
    p.add_argument(
        "--epochs", type=positive_int, default=100, metavar="E",
        help="full-batch Adam iterations (default 100)",
    )  # fmt: skip
    p.add_argument(
        "--toi", action=argparse.BooleanOptionalAction, default=True,
        help="the simulator's time-of-impact corrections (the paper's method; default on)",
    )  # fmt: skip
    p.add_argument("--lr", type=positive_float, default=1e-2, help="learning rate (default 1e-2)")
    p.add_argument(
        "--hidden", type=positive_int, default=32, metavar="H",
        help="width of each hidden layer (default 32)",
    )  # fmt: skip
    p.add_argument(
        "--layers", type=positive_int, default=2, metavar="L",
        help="hidden layers (default 2)",
    )  # fmt: skip
    p.add_argument(
        "--seed", type=nonnegative_int, default=None, metavar="S",
        help="seed of the training draws and of the initial weights (default: the "
        "distribution's seed + 1)",
    )  # fmt: skip
    add_progress_arg(p)
    add_json_out(
        p,
        out_help="write the policy DIR/<problem>_train-policy.json (+ .npz weights) and "
        "DIR/<problem>_train-policy_report.json",
        out_required=True,
    )
    p.set_defaults(func=cmd_train_policy)
