"""``hybridoc train-policy``: a feedback policy trained on draws of a problem's distribution
of initial states, saved as an MLP policy file (library: :mod:`hybridoc.workflows.training`,
:mod:`hybridoc.workflows.policy_format`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from hybridoc.cli._util import (
    add_json_out,
    add_progress_arg,
    emit_json,
    fmt,
    nonnegative_int,
    output_stem,
    positive_float,
    positive_int,
    problem_arg,
    problem_slug,
    say,
    to_jsonable,
    warn,
)
from hybridoc.cli.vocabulary import add_deprecated_alias, spelled
from hybridoc.errors import HybridocError, SceneError
from hybridoc.outputs import check_folder, check_targets, write_text

__all__ = ["register"]

#: train-policy's --toi: the time-of-impact corrections (gd's toi option's values)
TOI_MODES = ("none", "position", "velocity", "both")


def cmd_train_policy(args: argparse.Namespace) -> int:
    """Train an MLP feedback policy u = pi(t, s) by full-batch Adam on the mean closed-loop
    cost of M initial states drawn from the problem's distribution (a scene's
    [distribution] table, or the distribution of a HybridOCP from path/to/file.py:function),
    and save it as an MLP policy file: DIR/<problem>_train-policy.json (the architecture,
    read without running code) with its weights in DIR/<problem>_train-policy.npz.
    'hybridoc validate-policy PROBLEM --policy DIR/<problem>_train-policy.json' judges it
    against the exact references.

    A disc scene trains through the differentiable simulator, with its time-of-impact
    corrections (--toi both, the paper's method; --toi none: without them). Any other problem
    trains through the judge's event-exact closed loop and its exact adjoint: the loss is
    the judged cost, and the event times' sensitivity is always in the gradient (--toi none
    is refused there). The training draws use the seed --seed (default: the distribution's
    seed + 1), so that they are not the draws that validate-policy judges by default.

    On a problem with control bounds the policy's output is clipped to them (the policy
    file's saturation), so its controls never leave them. The training minimises the cost
    alone: when the trained policy's closed loop on some training draw still violates the
    problem's path or terminal constraints (judged once more after the training), the
    report says which, on how many draws and by how much, and the exit code is 1.
    """
    import numpy as np

    from hybridoc.problems import scene_of
    from hybridoc.workflows.policies import violation_lines, violation_summary
    from hybridoc.workflows.policy_format import save_mlp_policy
    from hybridoc.workflows.training import mlp_policy, train_policy, training_draws

    source = _source(args.problem)
    disc = scene_of(source, compiled=False) is not None  # a scene's own [distribution]
    if not disc and args.toi != "both":
        given = spelled(args, f"--toi {args.toi}", "--no-toi")
        raise HybridocError(
            f"{given} needs a disc scene (it changes the differentiable simulator's "
            f"time-of-impact corrections); {source.name!r} trains through the judge's "
            "event-exact closed loop, whose exact adjoint always has the event times' "
            "sensitivity: leave --toi both"
        )
    out = check_folder(args.out)
    stem = output_stem(out, problem_slug(args.problem, source), "train-policy")
    path, weights, report = (Path(f"{stem}{end}") for end in (".json", ".npz", "_report.json"))
    check_targets(path, weights, report)  # a refused output name fails before the training
    x0, seed = training_draws(source, args.samples, seed=args.seed)
    policy = mlp_policy(source, hidden=args.hidden, layers=args.layers, seed=seed)
    res = train_policy(
        source, policy, x0, toi=args.toi, iters=args.iters, lr=args.lr,
        seed=seed, progress=not args.no_progress,
    )  # fmt: skip
    payload = {
        "problem": source.name,
        "policy": str(path),
        "weights": str(weights),
        "samples": args.samples,
        "seed": seed,
        "iters": args.iters,
        "epochs": args.iters,  # the old name of iters, for one release
        "engine": res.engine,
        "toi": res.toi,
        "hidden": args.hidden,
        "layers": args.layers,
        "lr": args.lr,
        "initial_loss": res.losses[0] if res.losses else None,
        "final_loss": res.final_loss,
        "losses": res.losses,
        "seconds": res.seconds,
        "message": res.message,
        "saturated": getattr(res.policy, "u_min", None) is not None,
        "infeasible": res.infeasible,
        "violations": violation_summary(res.feasibility) if res.feasibility else None,
    }
    what = (
        "the simulator's mean closed-loop loss"
        if res.engine == "simulator"
        else "the judge's mean closed-loop cost"
    )
    if args.json:
        emit_json(payload)
    else:
        _print_training(args, source, seed, res, payload, what)
    # after the answer is out: a write that fails at the end loses nothing shown (exit 2)
    save_mlp_policy(res.policy, path)
    write_text(report, json.dumps(to_jsonable(payload), indent=2) + "\n")
    if not args.json:
        for p in (path, weights, report):
            say(args, f"wrote {p}")
        say(args, f"judge it: hybridoc validate-policy {args.problem} --policy {path} --samples M")
    if res.message:
        warn(res.message)
    if not np.isfinite(res.final_loss):
        raise HybridocError("the training diverged: the final loss is not finite (a smaller --lr?)")
    if res.infeasible:
        broken = "; the ".join(violation_lines(payload["violations"]))
        warn(f"the trained policy is INFEASIBLE on {res.infeasible} of {args.samples} training "
             f"draw(s): it violates the {broken}; its loss is the cost of controls the problem "
             "does not allow")  # fmt: skip
        return 1
    return 0


def _print_training(
    args: argparse.Namespace, source: Any, seed: int, res: Any, payload: dict[str, Any], what: str
) -> None:
    """The human block of ``train-policy``: draws, training, loss, time, feasibility."""
    from hybridoc.workflows.policies import violation_lines

    say(args, f"problem     {source.name} ({args.samples} draws, seed {seed})")
    say(args, f"training    {args.iters} iterations of Adam, lr {args.lr}, through the "
              f"{res.engine} (toi {res.toi})")  # fmt: skip
    say(args, f"loss        {fmt(payload['initial_loss'], 8)} -> {fmt(res.final_loss, 8)} "
              f"({what})")  # fmt: skip
    say(args, f"time        {res.seconds:.3g} s")
    if payload["saturated"]:
        say(args, "output      clipped to the control bounds")
    if res.infeasible:
        say(args, f"INFEASIBLE  on {res.infeasible} of {args.samples} training draws: "
                  + "; ".join(violation_lines(payload["violations"])))  # fmt: skip


def _source(text: str) -> Any:
    """The scene with a ``[distribution]`` or the problem with a Python distribution that
    ``text`` names; a problem without one is a user error that says how to give one."""
    from hybridoc.workflows.datasets import distribution_problem

    try:
        return distribution_problem(text)
    except SceneError as exc:
        if "has no distribution" not in str(exc):
            raise
        raise HybridocError(
            f"train-policy draws its initial states from a distribution, and {text!r} has "
            "none: give a scene a [distribution] table, or give path/to/file.py:function "
            "returning the problem with one, e.g. hybridoc.as_ocp(NAME).replace("
            "distribution=lambda rng, M: x0 + rng.uniform(-0.1, 0.1, (M, nx))) "
            "(see docs: datasets)"
        ) from None


def register(sub: Any) -> None:
    """Add ``train-policy``."""
    p = sub.add_parser(
        "train-policy",
        help="train an MLP feedback policy on draws of a problem's distribution",
        description=cmd_train_policy.__doc__,
    )
    problem_arg(p)
    p.add_argument(
        "--samples", type=positive_int, required=True, metavar="M",
        help="initial states drawn from the problem's distribution to train on (a scene's "
        "[distribution] table or a HybridOCP's distribution)",
    )  # fmt: skip
    p.add_argument(
        "--iters", type=positive_int, default=100, metavar="K",
        help="full-batch Adam iterations (default 100)",
    )  # fmt: skip
    add_deprecated_alias(p, "--epochs", dest="iters", instead="--iters K", type=positive_int)
    p.add_argument(
        "--toi", choices=TOI_MODES, nargs="?", const="both", default="both",
        help="disc scenes: the simulator's time-of-impact corrections, none, position, "
        "velocity or both (the paper's method; the default); other problems train through "
        "the judge, whose gradient always has the event times' sensitivity (only both)",
    )  # fmt: skip
    add_deprecated_alias(p, "--no-toi", dest="toi", instead="--toi none", switch="none")
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
