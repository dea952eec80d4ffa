"""``hybridoc dataset`` and ``validate-policy``: references over a problem's distribution
of initial states, a scene's ``[distribution]`` or a Python one (library:
:mod:`hybridoc.workflows.datasets`, :mod:`hybridoc.workflows.policies`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hybridoc.cli._util import (
    add_json_out,
    add_policy_arg,
    add_progress_arg,
    emit_json,
    fmt,
    format_table,
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
from hybridoc.errors import HybridocError
from hybridoc.outputs import check_folder, check_subfolder, check_targets, write_text, write_with

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.problem import ProblemLike
    from hybridoc.workflows.policies import PolicyReport

__all__ = ["register"]


def _add_engine(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--samples", type=positive_int, required=True, metavar="M",
        help="number of initial states drawn from the problem's distribution (a scene's "
        "[distribution] table or a HybridOCP's distribution)",
    )  # fmt: skip
    p.add_argument(
        "--seed", type=nonnegative_int, default=None, metavar="S",
        help="seed of the draws (default: the distribution's)",
    )  # fmt: skip
    p.add_argument(
        "--workers", type=positive_int, default=None, metavar="K",
        help="worker processes (default: the usable cores; 1: no pool)",
    )  # fmt: skip
    p.add_argument(
        "--dask", default=None, metavar="ADDRESS",
        help="run on a dask.distributed cluster: a scheduler address (tcp://host:port) or "
        "'local' for a LocalCluster of --workers processes",
    )  # fmt: skip
    add_progress_arg(p)


def _source_arg(text: str) -> ProblemLike:
    from hybridoc.workflows.datasets import distribution_problem

    return distribution_problem(text)


def cmd_dataset(args: argparse.Namespace) -> int:
    """Exact optimal controls, events, costates and costs of M draws of a problem's
    distribution of initial states (a scene's [distribution] table, or a HybridOCP's
    distribution from path/to/file.py:function): DIR/dataset.npz (one row per draw) and
    DIR/manifest.json. Unlike the other commands' --out, DIR is the dataset itself: a
    resumable folder (its shards, manifest and lock) that validate-policy --dataset reads
    whole; validate-policy --out names it <problem>_dataset.

    An interrupted run resumes when started again with the same options (shards that are
    damaged are computed again); one run at a time writes into DIR, and a dataset found
    complete there is checked against its SHA-256. Draws whose reference failed are kept
    with status 'failed' (exit code 1, with a warning line); draws whose reference is
    'best-found' (verified, the best found, not proven optimal) are kept as baselines, with
    exit code 1 and a warning line that counts them.
    """
    from hybridoc.workflows.datasets import DATA_FILE, MANIFEST_FILE, make_dataset

    scene = _source_arg(args.problem)
    check_folder(args.out)  # make_dataset refuses a dataset.npz or manifest it did not write
    ds = make_dataset(
        args.problem, args.samples, args.out, seed=args.seed, workers=args.workers, dask=args.dask,
        tol=args.tol, full=args.full, progress=not args.no_progress,
    )  # fmt: skip
    m = ds.manifest
    counts, methods = m.get("counts", {}), m.get("methods", {})
    run = m.get("last_run", {})
    payload = {
        "problem": scene.name,
        "samples": len(ds),
        "seed": m["settings"]["seed"],
        "counts": counts,
        "methods": methods,
        "data": str(Path(args.out) / DATA_FILE),
        "manifest": str(Path(args.out) / MANIFEST_FILE),
        "sha256": m.get("sha256"),
        "wall_time_s": run.get("wall_time_s"),
        "nominal": None if m.get("nominal") is None else {
            k: m["nominal"][k] for k in ("sequence", "cost")
        },
    }  # fmt: skip
    if args.json:
        emit_json(payload)
    else:
        say(args, f"problem   {scene.name} ({len(ds)} draws, seed {payload['seed']})")
        say(args, "status    " + ", ".join(f"{k} {v}" for k, v in counts.items()))
        say(args, "method    " + ", ".join(f"{k} {v}" for k, v in methods.items()))
        if run.get("wall_time_s") is not None:
            t = float(run["wall_time_s"])
            say(args, f"time      {t:.3g} s ({run.get('engine')}, {run.get('workers')} workers)")
        say(args, f"wrote {payload['data']}")
        say(args, f"wrote {payload['manifest']}")
    best = int(counts.get("best-found", 0))
    bad = sum(v for k, v in counts.items() if k not in ("success", "best-found"))
    if best:
        warn(f"{best} of {len(ds)} draws have a verified reference that is the best found, not "
             "a proven optimum (status best-found)")  # fmt: skip
    if bad:
        warn(f"{bad} of {len(ds)} draws have no verified optimum (see the status column)")
    return 1 if best or bad else 0


def _policy_arg(args: argparse.Namespace) -> str:
    """The policy of ``validate-policy``: ``--policy`` or the deprecated positional one."""
    given = [p for p in (args.policy, args.policy_positional) if p is not None]
    if len(given) != 1:
        raise HybridocError(
            "give the policy once, as --policy FILE" if given else "no policy: give --policy FILE"
        )
    return str(given[0])


def cmd_validate_policy(args: argparse.Namespace) -> int:
    """Judge a feedback policy in closed loop on M draws of a problem's distribution of
    initial states (a scene's [distribution] table or a HybridOCP's) against the exact
    reference of each: the cost gap (mean, median, p95, max), how often the event
    sequence differs from the optimal one, the worst cases with their initial states.

    A draw whose closed loop violates the problem's control bounds, path or terminal
    constraints is infeasible: its cost is not compared with the optimum, and the report
    names what is violated, on how many draws, by how much.

    A draw's reference is a baseline when it is verified: proven optimal ('success') or
    the best control found without proof ('best-found', issue #29); the report counts
    both, and where some are best-found the gap is one to the best known control, not to
    a proven optimum.

    Exit code 1 when the policy is infeasible on some draw, some draw's policy beats its
    proven reference (a reference that is not optimal) or no draw could be compared; a
    policy that beats a best-found reference is a warning (that reference is not the
    optimum, as it did not claim to be).
    """
    from hybridoc.workflows.policies import validate_policy, violation_lines

    scene = _source_arg(args.problem)
    policy = _policy_arg(args)
    out = None if args.out is None else check_folder(args.out)
    slug = problem_slug(args.problem, scene)
    if out is not None:  # a refused output name fails before the work
        check_targets(*_policy_report_files(output_stem(out, slug, "validate-policy")))
        # the dataset's folder too: a link planted there would take the dataset elsewhere
        check_subfolder(output_stem(out, slug, "dataset"))
    report = validate_policy(
        args.problem, policy, args.samples, seed=args.seed, dataset=args.dataset,
        dataset_out=None if out is None else output_stem(out, slug, "dataset"),
        hold=args.hold, workers=args.workers, dask=args.dask, progress=not args.no_progress,
        rollouts=args.rollouts,
    )  # fmt: skip
    s = report.summary
    payload = {"problem": scene.name, **report.to_json()}
    if args.json:
        emit_json(payload)
    else:
        _print_policy_report(args, scene, report)
    # after the answer is out: a write that fails at the end loses nothing shown (exit 2)
    written = [] if out is None else _write_policy_report(out, slug, scene, report, payload)
    if not args.json:
        for p in written:
            say(args, f"wrote {p}")
    if s["reference_failed"]:
        warn(f"{s['reference_failed']} draw(s) without a verified reference are not compared")
    if s["reference_best_found"]:
        warn(f"{s['reference_best_found']} of {s['compared']} compared draw(s) have a reference "
             "that is the best found, not a proven optimum: their gap is to the best known "
             "control")  # fmt: skip
    if s["rollout_failed"]:
        warn(f"{s['rollout_failed']} rollout(s) the judge could not simulate are not compared")
    if s["infeasible"]:
        broken = "; the ".join(violation_lines(s["violations"]))
        warn(f"the policy is INFEASIBLE on {s['infeasible']} of {s['judged']} judged draw(s): "
             f"it violates the {broken}; its cost gaps are not a result")  # fmt: skip
        return 1
    if s["compared"] == 0:
        warn("no draw could be compared (see the status column)")
        return 1
    unproven = s["negative_gaps"] - s["negative_gaps_proven"]
    if unproven:
        warn(f"the policy beats a best-found reference on {unproven} draw(s): those references "
             "are not the optimum")  # fmt: skip
    if s["negative_gaps_proven"]:
        warn(f"the policy beats a proven reference on {s['negative_gaps_proven']} draw(s): "
             "those references are not optimal")  # fmt: skip
        return 1
    return 0


def _write_policy_report(
    out: Path, slug: str, scene: ProblemLike, report: PolicyReport, payload: dict[str, Any]
) -> list[Path]:
    """``<problem>_validate-policy.json``/``.npz`` and the figures in ``out``."""
    import numpy as np

    from hybridoc.problem import as_ocp
    from hybridoc.workflows.policies import report_figures

    stem = output_stem(out, slug, "validate-policy")
    json_path, npz_path = Path(f"{stem}.json"), Path(f"{stem}.npz")
    # by the rules of hybridoc.outputs: atomically, never through a link or over a user's file
    written = [write_text(json_path, json.dumps(to_jsonable(payload), indent=2) + "\n")]
    cols: dict[str, Any] = {k: np.asarray(v) for k, v in report.columns.items()}
    written.append(write_with(npz_path, lambda fh: np.savez(fh, **cols)))
    ocp = as_ocp(scene)
    labels = list(ocp.state_labels or [f"x{i}" for i in range(ocp.nx)])
    written += report_figures(report, labels, stem, title=scene.name)
    return written


def _policy_report_files(stem: Path) -> list[Path]:
    """The files of ``validate-policy --out`` (the references' folder aside)."""
    ends = (".json", ".npz", "_gap_hist.png", "_gap_scatter.png")
    return [Path(f"{stem}{end}") for end in ends]


def _print_policy_report(
    args: argparse.Namespace, scene: ProblemLike, report: PolicyReport
) -> None:
    """The summary, the gap table and the worst cases, on stdout."""
    s = report.summary
    say(args, f"problem    {scene.name} ({s['samples']} draws, hold {args.hold})")
    say(args, f"policy     {_policy_arg(args)}")
    say(args, f"compared   {s['compared']} (reference failed {s['reference_failed']}, "
              f"rollout failed {s['rollout_failed']}, infeasible {s['infeasible']})")  # fmt: skip
    say(args, f"references {s['reference_proven']} proven optimal, {s['reference_best_found']} "
              "best found (not proven) among the compared")  # fmt: skip
    if s["infeasible"]:
        from hybridoc.workflows.policies import violation_lines

        broken = "; ".join(violation_lines(s["violations"]))
        say(args, f"INFEASIBLE on {s['infeasible']} draw(s): {broken}")
    rows = [
        ["absolute", fmt(s["gap_mean"], 6), fmt(s["gap_median"], 6), fmt(s["gap_p95"], 6),
         fmt(s["gap_max"], 6)],
        ["relative", fmt(s["rel_gap_mean"], 6), fmt(s["rel_gap_median"], 6),
         fmt(s["rel_gap_p95"], 6), fmt(s["rel_gap_max"], 6)],
    ]  # fmt: skip
    baseline = "optimum" if not s["reference_best_found"] else "best known control"
    say(args, f"gap to the reference (policy - {baseline})" if not s["infeasible"] else
        f"gap to the reference over the {s['compared']} feasible draw(s) only: NOT the "
        "policy's gap (it is infeasible elsewhere)")  # fmt: skip
    for line in format_table(["gap", "mean", "median", "p95", "max"], rows).splitlines():
        say(args, "  " + line)
    rate = s["sequence_mismatch_rate"]
    pct = fmt(float("nan") if rate is None else 100 * rate, 4)
    say(args, f"events differ from the optimum in {pct}% of the draws")
    r = s["rollouts"]
    how = f"compiled {r['compiled']}, per-step judge {r['judge'] + r['fallback']}"
    if r["fallback"]:
        kinds = ", ".join(f"{k} {v}" for k, v in r["fallback_kinds"].items())
        how += f" (of which {r['fallback']} not certified: {kinds})"
    say(args, f"rollouts   {s['rollout_time_s']:.3g} s: {how}")
    if report.worst:
        say(args, "worst cases")
        rows = [
            [w["index"], fmt(w["gap"], 6), fmt(w["rel_gap"], 4),
             "(" + ", ".join(f"{x:.4g}" for x in w["x0"]) + ")",
             w["policy_sequence"] or "-", w["reference_sequence"] or "-"]
            for w in report.worst
        ]  # fmt: skip
        table = format_table(["draw", "gap", "rel", "x0", "policy events", "optimal events"], rows)
        for line in table.splitlines():
            say(args, "  " + line)


def register(sub: Any) -> None:
    """Add ``dataset`` and ``validate-policy``."""
    p = sub.add_parser(
        "dataset",
        help="exact references for M draws of a scene's [distribution] (resumable)",
        description=cmd_dataset.__doc__,
    )
    problem_arg(p)
    _add_engine(p)
    p.add_argument(
        "--out", metavar="DIR", type=Path, required=True,
        help="directory of dataset.npz and manifest.json (a rerun resumes there)",
    )  # fmt: skip
    p.add_argument(
        "--tol", type=positive_float, default=1e-10, help="HMP residual required (default 1e-10)"
    )
    p.add_argument(
        "--full", action="store_true",
        help="solve every draw with the reference's full discovery (no warm start; slower)",
    )  # fmt: skip
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=cmd_dataset)

    p = sub.add_parser(
        "validate-policy",
        help="a feedback policy's cost gap to the exact references over a distribution",
        description=cmd_validate_policy.__doc__,
    )
    problem_arg(p)
    p.add_argument(
        "policy_positional", metavar="POLICY", nargs="?", default=None,
        help="deprecated: the same as --policy",
    )  # fmt: skip
    add_policy_arg(p)
    _add_engine(p)
    p.add_argument(
        "--dataset", metavar="DIR", type=Path, default=None,
        help="reuse the references of 'hybridoc dataset' (same scene and seed, >= M draws)",
    )  # fmt: skip
    p.add_argument(
        "--hold", choices=("zoh", "continuous"), default="zoh",
        help="zoh: the policy sampled at the grid times and held (default); continuous",
    )  # fmt: skip
    p.add_argument(
        "--rollouts", choices=("auto", "compiled", "judge"), default="auto",
        help="compiled: the policy compiled into the closed-loop step, each rollout certified "
        "by the judge (an MLP policy file); judge: the per-step judge; auto (default): "
        "compiled where possible",
    )  # fmt: skip
    add_json_out(
        p,
        out_help="write DIR/<problem>_validate-policy.json/.npz, the figures "
        "..._gap_hist.png and ..._gap_scatter.png, and the references computed "
        "(DIR/<problem>_dataset/)",
    )
    p.set_defaults(func=cmd_validate_policy)
