"""Feedback policies ``u = pi(t, s)`` from files, and their validation over a distribution.

:func:`load_policy` reads a policy from a spec: a policy file ``policy.json`` (an MLP: its
description and weights, read without running anything, :mod:`hybridoc.workflows.policy_format`),
a TorchScript file (``.pt``/``.pth``, read with :func:`torch.jit.load`) or
``path/to/file.py:name`` (a callable in a Python file; a name that is a class or a factory
taking no arguments is not called: give the callable itself). TorchScript and Python files
run code when loaded: load them only from people you trust. A ``casadi.Function``
``(t, s) -> u`` is a policy too. The judge calls a policy with ``(t, state)`` (torch
modules with float64 tensors) and checks what it returns (:func:`hybridoc.evaluate`).

:func:`validate_policy` judges a policy in closed loop on ``M`` draws of a problem's
distribution (a scene's ``[distribution]`` or a Python one,
:func:`~hybridoc.workflows.datasets.distribution_problem`) and compares each with the exact
reference of the same draw (from a dataset of :mod:`hybridoc.workflows.datasets`, computed
when not given): the cost gap, whether the event sequence differs from the optimal one, the
worst cases. A draw whose closed loop violates the problem's control bounds, path or
terminal constraints (the judge's :attr:`Evaluation.feasible <hybridoc.Evaluation>`) is
``infeasible``: its cost is reported but not compared with the optimum (a control the problem
does not allow can cost less than the optimum), and the report counts such draws and their
largest violations (:attr:`PolicyReport.feasible`). Rollouts run in the same engines as
datasets (a local process pool, or Dask), one chunk of draws per task. An MLP policy file
or a CasADi policy is compiled into the closed-loop step and each chunk runs as one call,
every rollout certified by the judge (:mod:`hybridoc.workflows.rollouts`); other policies,
and rollouts the judge does not certify, go through the per-step judge.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc import tolerances
from hybridoc._pyfile import exit_message, import_file
from hybridoc.errors import ControlsError, EvaluationError, HybridocError
from hybridoc.progress import Progress, ProgressLike, progress_scope
from hybridoc.workflows.datasets import (
    BASELINE_STATUSES,
    CHUNK,
    Dataset,
    check_count,
    check_dask,
    check_draws,
    check_manifest,
    distribution_problem,
    draw_context,
    draw_initial_states,
    draw_problem,
    initial_states_sha256,
    iter_chunks,
    load_dataset,
    make_dataset,
    run_chunks,
    source_draws,
    source_seed,
    usable_cores,
)
from hybridoc.workflows.policy_format import (
    CasadiPolicy,
    PolicyError,
    check_policy_sizes,
    load_mlp_policy,
)
from hybridoc.workflows.policy_report import (
    policy_figures,
    report_figures,
    varying_coordinates,  # noqa: F401 (re-exported)
    violation_lines,
    violation_phrases,
    violation_summary,
)
from hybridoc.workflows.policy_report import violation_text as _violation_text

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.ocp import HybridOCP
    from hybridoc.problems import Scene

__all__ = [
    "ROLLOUTS",
    "PolicyError",
    "PolicyReport",
    "load_policy",
    "policy_figures",
    "report_figures",
    "validate_policy",
    "violation_lines",
    "violation_phrases",
    "violation_summary",
]

_TORCH_SUFFIXES = (".pt", ".pth", ".ts")
WORST = 5
"""Worst cases listed in a report."""
ROLLOUTS = ("auto", "compiled", "judge")
"""How :func:`validate_policy` rolls a policy out: ``compiled`` (the policy compiled into the
closed-loop step, each rollout certified by the judge), ``judge`` (the per-step judge), or
``auto`` (compiled where the policy and problem allow it: an MLP policy file or a
``casadi.Function``, zero-order hold, a problem with a closed-form flow)."""


def load_policy(spec: Any) -> Callable[..., Any]:
    """The policy named by ``spec``.

    Parameters
    ----------
    spec
        ``path/to/policy.json`` (an MLP policy file: nothing in it runs),
        ``path/to/model.pt`` (TorchScript), ``path/to/file.py:name`` (a callable
        ``(t, state) -> u`` in a Python file), a ``casadi.Function`` ``(t, s) -> u``
        (wrapped in a :class:`~hybridoc.workflows.policy_format.CasadiPolicy`), or another
        callable, returned as is.

    Returns
    -------
    callable
        ``(t, state) -> u``.

    Raises
    ------
    PolicyError
        A missing or unreadable file, a policy file that does not describe a policy, a
        missing name, an object that is not callable.
    """
    if type(spec).__name__ == "Function" and type(spec).__module__.startswith("casadi"):
        return CasadiPolicy(spec)
    if callable(spec) and not isinstance(spec, str | Path):
        return spec
    if not isinstance(spec, str | Path):
        raise PolicyError(
            "a policy is a policy.json file, a .pt TorchScript file, path/to/file.py:name or a "
            f"callable, got {spec!r}"
        )
    text = str(spec)
    path_text, _, name = text.rpartition(":") if ".py:" in text else (text, "", "")
    if not name and text.endswith(".py"):
        raise PolicyError(f"policy {text!r}: name the callable, as {text}:NAME")
    path = Path(path_text)
    if name:
        return _load_python(path, name, text)
    if path.suffix.lower() == ".json":
        return load_mlp_policy(path)
    if path.suffix.lower() in _TORCH_SUFFIXES:
        return _load_torchscript(path)
    raise PolicyError(
        f"policy {text!r}: expected a TorchScript file (.pt), an MLP policy file (.json) or "
        "path/to/file.py:name"
    )


def _load_torchscript(path: Path) -> Callable[..., Any]:
    if not path.is_file():
        raise PolicyError(f"policy file {str(path)!r} does not exist")
    import warnings

    import torch

    try:
        with warnings.catch_warnings():  # torch >= 2.9 deprecates TorchScript
            warnings.simplefilter("ignore", DeprecationWarning)
            module = torch.jit.load(str(path), map_location="cpu")
    except Exception as exc:  # torch raises RuntimeError or ValueError for bad files
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise PolicyError(f"cannot load {str(path)!r} as TorchScript: {first}") from None
    module.eval()
    return module


def _load_python(path: Path, name: str, text: str) -> Callable[..., Any]:
    if not name.isidentifier():
        raise PolicyError(f"policy {text!r}: {name!r} is not a Python name")
    module = import_file(path, "policy", PolicyError)
    if not hasattr(module, name):
        public = sorted(k for k, v in vars(module).items() if callable(v) and not k.startswith("_"))
        raise PolicyError(
            f"{str(path)!r} has no {name!r}"
            + (f" (callables: {', '.join(public)})" if public else "")
        )
    obj = getattr(module, name)
    if not callable(obj) or isinstance(obj, type):
        raise PolicyError(
            f"{text!r} is {'a class' if isinstance(obj, type) else type(obj).__name__}, "
            "not a callable policy (t, state) -> u"
        )
    return obj


# ---------------------------------------------------------------------------- validation


@dataclass
class PolicyReport:
    """What :func:`validate_policy` found.

    Attributes
    ----------
    summary
        Scalars: ``samples``, ``judged`` (rollouts the judge could simulate),
        ``infeasible`` (judged rollouts whose controls violate the problem's control
        bounds, path or terminal constraints: :attr:`Evaluation.feasible
        <hybridoc.Evaluation>` is false), ``violations`` (per kind ``bound``, ``path``,
        ``terminal``: ``draws`` that violate it and the largest violation ``max``),
        ``compared`` (feasible, with a successful reference as well: the only draws in
        the gap statistics, as an infeasible control's cost is not comparable with the
        optimum's), gap statistics ``gap_mean``,
        ``gap_median``, ``gap_p95``, ``gap_max`` (absolute, ``J_policy - J*``) and the same
        of the relative gap ``rel_gap_*`` (``(J_policy - J*) / J*``), ``sequence_mismatch_rate``,
        ``negative_gaps`` (compared draws where the policy beats its reference) and of those
        ``negative_gaps_proven`` (against a proven optimum: a contradiction),
        ``rollout_time_s``, and ``rollouts``: how they ran (``mode``, the counts
        ``compiled``, ``fallback`` and ``judge``, ``fallback_kinds``,
        ``compiled_max_rel_diff``; :func:`validate_policy`).
    columns
        Per draw: ``index``, ``x0``, ``policy_cost``, ``reference_cost``,
        ``reference_status`` (the dataset's status of the draw's reference) and
        ``reference_proven`` (it is ``success``), ``gap``,
        ``rel_gap``, ``policy_sequence``, ``reference_sequence``, ``mismatch``,
        ``bound_violation``, ``path_violation``, ``terminal_violation`` (the judge's; NaN for a
        failed rollout), ``feasible``, ``status`` (``ok``, ``reference-failed``,
        ``rollout-failed``, ``infeasible``: the policy's cost is in ``policy_cost``, its gap
        is NaN), ``message`` (for ``infeasible``, what is violated by how much), ``rollout_path``
        (``compiled``: certified by the judge; ``fallback``: compiled, not certified, run in
        the per-step judge; ``judge``: the per-step judge) and ``fallback_reason``.
    worst
        The ``WORST`` largest gaps with their initial states.
    """

    summary: dict[str, Any]
    columns: dict[str, np.ndarray]
    worst: list[dict[str, Any]] = field(default_factory=list)
    settings: dict[str, Any] = field(default_factory=dict)

    @property
    def feasible(self) -> bool:
        """Whether every judged rollout meets the problem's control bounds, path and
        terminal constraints. When not, the gap statistics cover the feasible draws only
        and say nothing of the policy as a whole."""
        return int(self.summary["infeasible"]) == 0

    def to_json(self) -> dict[str, Any]:
        """The JSON shape (summary, worst cases, settings)."""
        return {"summary": self.summary, "worst": self.worst, "settings": self.settings}


_ROLLOUT_POLICY: dict[str, Any] = {}


def _rollout_policy(key: str | None) -> Callable[..., Any]:
    """The policy of a rollout task: the one set by :func:`validate_policy` in this process
    (``key`` ``None``: an object), or loaded from its spec once per process."""
    if key is None:
        return _ROLLOUT_POLICY["policy"]
    policy = _ROLLOUT_POLICY.get(key)
    if policy is None:
        policy = load_policy(key)
        _ROLLOUT_POLICY.clear()
        _ROLLOUT_POLICY[key] = policy
    return policy


_COMPILED: dict[str, Any] = {}


def _compiled_runner(common: dict[str, Any], ctx: Any, policy: Any) -> Any:
    """The :class:`~hybridoc.workflows.rollouts.CompiledRollouts` of a rollout task, built once
    per process and kept for the next call with the same scene and policy (a forked worker
    inherits the one :func:`validate_policy` built)."""
    from hybridoc.workflows.rollouts import CompiledRollouts, fingerprint

    key = json.dumps([common["dataset"], fingerprint(policy)], sort_keys=True)
    runner = _COMPILED.get(key)
    if runner is None:
        runner = CompiledRollouts(ctx.ocp, policy)
        _COMPILED.clear()
        _COMPILED[key] = runner
    return runner


_NOT_JUDGED = (np.nan, np.nan, np.nan, False)


def _judged_row(ev: Any) -> tuple[Any, ...]:
    """What a rollout task keeps of the judge's evaluation: cost, sequence, status, message,
    the three violations and the judge's feasibility verdict."""
    return (
        float(ev.cost), ",".join(ev.sequence), "ok", "",
        float(ev.bound_violation), float(ev.path_violation), float(ev.terminal_violation),
        bool(ev.feasible),
    )  # fmt: skip


def _judge_rollout(ocp: Any, i: int, policy: Any, key: str | None, hold: str) -> tuple[Any, ...]:
    """One rollout in the per-step judge: :func:`_judged_row`, or a failed rollout's."""
    from hybridoc.evaluator import evaluate

    try:
        ev = evaluate(ocp, policy=policy, hold=hold)
    except ControlsError as exc:
        raise ControlsError(f"sample {i}: {exc}") from None
    except SystemExit as exc:  # the user's policy ended the program: say so
        who = "the policy" if key is None else f"policy {key!r}"
        raise PolicyError(exit_message(who, exc, f"in the rollout of sample {i}")) from None
    except EvaluationError as exc:
        return (np.nan, "", "rollout-failed", " ".join(str(exc).split()), *_NOT_JUDGED)
    return _judged_row(ev)


def _rollout_chunk(common: dict[str, Any], indices: list[int]) -> dict[str, np.ndarray]:
    """A worker's task: closed-loop rollouts of ``indices`` (compiled and certified in one
    batch, or one by one in the per-step judge)."""
    ctx = draw_context(common["dataset"])
    key = common["policy"]
    policy = _rollout_policy(key)
    ocps = [draw_problem(ctx, i)[1] for i in indices]
    n = len(indices)
    certs: list[Any] = [None] * n
    if common.get("rollouts") == "compiled":
        certs = _compiled_runner(common, ctx, policy).certify(ocps)
    rows = []
    paths, reasons, kinds = [], [], []
    diff = np.full(n, np.nan)
    for k, (i, ocp, cert) in enumerate(zip(indices, ocps, certs, strict=True)):
        if cert is not None and cert.evaluation is not None:
            rows.append(_judged_row(cert.evaluation))
            paths.append("compiled")
            diff[k] = cert.cost_rel_diff
        else:
            rows.append(_judge_rollout(ocp, i, policy, key, common["hold"]))
            paths.append("judge" if cert is None else "fallback")
        reasons.append("" if cert is None else cert.reason)
        kinds.append("" if cert is None else cert.kind)
    cols = list(zip(*rows, strict=True))
    return {
        "index": np.array(indices, dtype=np.int64),
        "policy_cost": np.array(cols[0], dtype=float),
        "policy_sequence": np.array(cols[1], dtype=str),
        "rollout_status": np.array(cols[2], dtype=str),
        "rollout_message": np.array(cols[3], dtype=str),
        "bound_violation": np.array(cols[4], dtype=float),
        "path_violation": np.array(cols[5], dtype=float),
        "terminal_violation": np.array(cols[6], dtype=float),
        "feasible": np.array(cols[7], dtype=bool),
        "rollout_path": np.array(paths, dtype=str),
        "fallback_reason": np.array(reasons, dtype=str),
        "fallback_kind": np.array(kinds, dtype=str),
        "compiled_rel_diff": diff,
    }


def validate_policy(
    problem: Any,
    policy: Any,
    samples: int,
    *,
    seed: int | None = None,
    dataset: Any = None,
    dataset_out: str | Path | None = None,
    hold: str = "zoh",
    workers: int | None = None,
    dask: Any = None,
    progress: ProgressLike = True,
    rollouts: str = "auto",
    distribution: Any = None,
) -> PolicyReport:
    """Judge a feedback policy against the exact references over a problem's distribution.

    Parameters
    ----------
    problem
        A disc scene with a ``[distribution]`` table, or any problem with a Python
        distribution (:func:`~hybridoc.workflows.datasets.distribution_problem`).
    policy
        A callable ``(t, state) -> u``, a ``torch.nn.Module``, or a spec for
        :func:`load_policy`. With ``dask`` or a process pool without ``fork``, a spec.
    samples
        ``M`` >= 1: the first ``M`` draws.
    seed
        Overrides the distribution's seed.
    dataset
        A :class:`~hybridoc.workflows.datasets.Dataset` or its directory with at least ``M``
        rows of the same scene and seed; default: computed (into ``dataset_out``, or a
        temporary directory).
    hold
        ``"zoh"`` or ``"continuous"`` (:func:`hybridoc.evaluate`).
    workers, dask
        As in :func:`~hybridoc.workflows.datasets.make_dataset`.
    progress
        ``True`` (a progress bar on stderr, the default), ``False``/``None`` or a
        :class:`~hybridoc.progress.Progress`: the references' stages and the rollouts done.
    rollouts
        One of :data:`ROLLOUTS`: ``"auto"`` (default), ``"compiled"`` (an error where the
        policy or problem has no compiled form) or ``"judge"``. Compiled rollouts that the
        judge does not certify run in the per-step judge; the report counts them
        (``summary["rollouts"]``, the ``rollout_path`` column).
    distribution
        A callable ``(rng, M) -> (M, nx)`` overriding the problem's distribution.

    Returns
    -------
    PolicyReport

    Raises
    ------
    HybridocError
        Bad arguments, a dataset of another scene or seed, a bad policy (a
        :class:`~hybridoc.errors.ControlsError` naming the sample: wrong output shape,
        non-finite output, an exception inside the policy).
    """
    samples = check_count(samples, "samples", 1)
    if hold not in ("zoh", "continuous"):
        raise HybridocError(f"hold must be 'zoh' or 'continuous', got {hold!r}")
    if rollouts not in ROLLOUTS:
        raise HybridocError(f"rollouts must be one of {', '.join(ROLLOUTS)}, got {rollouts!r}")
    source = distribution_problem(problem, distribution)
    seed = source_seed(source, seed)
    workers = usable_cores() if workers is None else check_count(workers, "workers", 1)
    check_dask(dask)
    spec_text = str(policy) if isinstance(policy, str | Path) else None
    pol = load_policy(policy)  # errors here, before any work
    from hybridoc.problem import as_ocp

    nominal = as_ocp(source)
    check_policy_sizes(pol, nominal.nx, nominal.nu, f"policy {spec_text or repr(policy)}")
    if dask is not None and spec_text is None:
        raise HybridocError(
            "with dask, give the policy as a spec (model.pt or file.py:name) so that the "
            "workers can load it"
        )
    mode = _rollout_mode(rollouts, source, pol, hold)
    engine = {"workers": workers, "dask": dask}
    with progress_scope(progress, "validate-policy") as p:
        p.stage("references")
        ref, _, ds_path = _references(source, samples, seed, dataset, dataset_out, engine, p)
        # drawn again after the references (whose run registers its own problem spec)
        draws = source_draws(source, problem, samples, seed)
        common = {
            "dataset": _draws_spec(draws, seed), "policy": spec_text, "hold": hold,
            "rollouts": mode,
        }  # fmt: skip
        roll, rollout_time = _rollouts(common, pol, samples, engine, p)
    report = _report(ref, roll, rollout_time)
    report.summary["rollouts"] = _rollout_summary(mode, roll)
    report.settings = {
        "scene": source.name,
        "policy": spec_text or repr(policy),
        "samples": samples,
        "seed": seed,
        "hold": hold,
        "dataset": ds_path,
        "rollouts": rollouts,
    }
    return report


def _rollout_mode(rollouts: str, source: Scene | HybridOCP, policy: Any, hold: str) -> str:
    """``"compiled"`` or ``"judge"``: what ``rollouts`` means for this policy and problem."""
    from hybridoc.problem import as_ocp
    from hybridoc.workflows.rollouts import compilable, unsupported

    if rollouts == "judge" or (rollouts == "auto" and not compilable(policy)):
        return "judge"  # without compiling the scene to find out
    why = (
        "compiled rollouts hold the control over each grid interval: use hold='zoh'"
        if hold != "zoh"
        else unsupported(as_ocp(source), policy)
    )
    if why is None:
        return "compiled"
    if rollouts == "compiled":
        raise PolicyError(f"no compiled rollout: {why}")
    return "judge"


def _rollout_summary(mode: str, roll: dict[str, np.ndarray]) -> dict[str, Any]:
    """How the rollouts ran: ``mode``, ``compiled`` (certified compiled rollouts),
    ``fallback`` (compiled but not certified: run in the per-step judge) with their
    ``fallback_kinds`` counted, ``judge`` (per-step only), ``compiled_max_rel_diff``."""
    path = roll["rollout_path"]
    kinds, counts = np.unique(roll["fallback_kind"][path == "fallback"], return_counts=True)
    d = roll["compiled_rel_diff"][path == "compiled"]
    return {
        "mode": mode,
        "compiled": int(np.sum(path == "compiled")),
        "fallback": int(np.sum(path == "fallback")),
        "judge": int(np.sum(path == "judge")),
        "fallback_kinds": {str(k): int(c) for k, c in zip(kinds, counts, strict=True)},
        "compiled_max_rel_diff": float(np.max(d)) if d.size else None,
    }


def _draws_spec(draws: dict[str, Any], seed: int) -> dict[str, Any]:
    """The :func:`~hybridoc.workflows.datasets.draw_context` specification of the draws that
    a rollout task needs (no warm start: rollouts solve nothing)."""
    return {**draws, "seed": seed, "tol": 1e-10, "full": False, "nominal": None}


def _references(
    source: Scene | HybridOCP,
    samples: int,
    seed: int,
    dataset: Any,
    dataset_out: str | Path | None,
    engine: dict[str, Any],
    progress: Progress,
) -> tuple[dict[str, np.ndarray], dict[str, Any], str | None]:
    """The first ``samples`` rows of the references (``dataset``, or computed), their
    settings, and the dataset's directory (``None`` for a temporary one)."""
    import tempfile

    tmp = None
    if dataset is None:
        if dataset_out is None:
            tmp = tempfile.TemporaryDirectory(prefix="hybridoc-refs-")
            dataset_out = tmp.name
        ds = make_dataset(source, samples, dataset_out, seed=seed, progress=progress, **engine)
    else:
        if hasattr(dataset, "columns"):  # a Dataset object: the checks of load_dataset too
            check_manifest(dataset.manifest, f"the manifest of {str(dataset.path)!r}")
            check_draws(dataset)
            ds = dataset
        else:
            ds = load_dataset(dataset)
        _check_references(ds, source, seed, samples)
    ref = {k: v[:samples] for k, v in ds.columns.items()}
    ref_settings = dict(ds.manifest.get("settings", {}))
    if tmp is not None:
        tmp.cleanup()
    return ref, ref_settings, str(ds.path) if tmp is None else None


def _check_references(ds: Dataset, source: Scene | HybridOCP, seed: int, samples: int) -> None:
    from hybridoc.problems import scene_of, spec_of

    settings = ds.manifest.get("settings", {})
    table = scene_of(source, compiled=False)  # draws from the scene's [distribution] table
    if table is not None:
        same = ds.spec == spec_of(table)
    else:  # the initial states of the dataset's draws, drawn again here
        x0 = draw_initial_states(source, int(settings.get("samples", 0)), seed)
        same = initial_states_sha256(x0) == settings.get("x0_sha256") and np.array_equal(
            x0, ds.columns["x0"]
        )
    if not same or int(settings.get("seed", -1)) != seed:
        what = "scene" if table is not None else "problem, distribution"
        raise HybridocError(
            f"the dataset in {str(ds.path)!r} was drawn from another {what} or seed than "
            f"{source.name!r} with seed {seed}"
        )
    if len(ds) < samples:
        raise HybridocError(
            f"the dataset in {str(ds.path)!r} has {len(ds)} samples; {samples} requested"
        )


def _rollouts(
    common: dict[str, Any],
    policy: Callable[..., Any],
    samples: int,
    engine: dict[str, Any],
    progress: Progress,
) -> tuple[dict[str, np.ndarray], float]:
    """The rollout columns of draws ``0 .. samples - 1``, in order, and their wall time."""
    _ROLLOUT_POLICY.clear()
    _ROLLOUT_POLICY["policy" if common["policy"] is None else common["policy"]] = policy
    parts: dict[int, dict[str, np.ndarray]] = {}
    tally = {"done": 0, "failed": 0}
    progress.stage("rollouts")

    def on_result(cid: int, cols: dict[str, np.ndarray]) -> None:
        parts[cid] = cols
        tally["done"] += len(cols["index"])
        tally["failed"] += int(np.sum(cols["rollout_status"] != "ok"))
        progress.count(tally["done"], samples, f"{tally['failed']} failed")

    t0 = time.perf_counter()
    chunks = list(iter_chunks(samples, CHUNK))
    if common["rollouts"] == "compiled":
        # built (its C code compiled, or loaded from the cache) here, once, and timed with
        # the rollouts: forked workers inherit it, others load the C code from the cache
        _compiled_runner(common, draw_context(common["dataset"]), policy)
    try:
        run_chunks(_rollout_chunk, common, chunks, on_result=on_result, **engine)
    finally:
        _ROLLOUT_POLICY.clear()
    seconds = time.perf_counter() - t0
    roll = {k: np.concatenate([parts[c][k] for c, _ in chunks]) for k in parts[chunks[0][0]]}
    return roll, seconds


def _report(
    ref: dict[str, np.ndarray], roll: dict[str, np.ndarray], seconds: float
) -> PolicyReport:
    # a best-found reference (verified: the HMP holds and it re-simulates to its own events,
    # only not proven globally optimal) is a baseline too; the columns say which are proven
    ref_ok = np.isin(ref["status"], list(BASELINE_STATUSES))
    proven = ref["status"] == "success"
    roll_ok = roll["rollout_status"] == "ok"
    # a rollout whose controls break the bounds, path or terminal constraints is not a
    # control of the problem: its cost is reported, never compared with the optimum
    infeasible = roll_ok & ~roll["feasible"]
    both = ref_ok & roll_ok & ~infeasible
    gap = np.where(both, roll["policy_cost"] - ref["cost"], np.nan)
    rel = np.where(both, gap / np.where(both, ref["cost"], 1.0), np.nan)
    mismatch = both & (roll["policy_sequence"] != ref["sequence"])
    status = np.where(
        ~ref_ok, "reference-failed",
        np.where(~roll_ok, "rollout-failed", np.where(infeasible, "infeasible", "ok")),
    )  # fmt: skip
    violated = _violation_text(roll)
    message = np.where(
        ~ref_ok, ref["message"], np.where(infeasible, violated, roll["rollout_message"])
    )
    cols = {
        "index": ref["index"],
        "x0": ref["x0"],
        "targets": ref["targets"],
        "policy_cost": roll["policy_cost"],
        "reference_cost": ref["cost"],
        "reference_status": ref["status"].astype(str),
        "reference_proven": proven,
        "gap": gap,
        "rel_gap": rel,
        "policy_sequence": roll["policy_sequence"],
        "reference_sequence": ref["sequence"],
        "mismatch": mismatch,
        "status": status.astype(str),
        "message": message.astype(str),
        "bound_violation": roll["bound_violation"],
        "path_violation": roll["path_violation"],
        "terminal_violation": roll["terminal_violation"],
        "feasible": roll_ok & roll["feasible"],
        "rollout_path": roll["rollout_path"],
        "fallback_reason": roll["fallback_reason"],
    }

    n_both = int(both.sum())
    # a policy cheaper than the reference beyond rounding (tolerances.CHEAPER, relative)
    negative = gap < -tolerances.CHEAPER * np.abs(np.nan_to_num(ref["cost"]))
    summary: dict[str, Any] = {
        "samples": int(ref_ok.size),
        "judged": int(roll_ok.sum()),
        "compared": n_both,
        "reference_proven": int((both & proven).sum()),
        "reference_best_found": int((both & ~proven).sum()),
        "reference_failed": int((~ref_ok).sum()),
        "rollout_failed": int((~roll_ok).sum()),
        "infeasible": int(infeasible.sum()),
        "violations": violation_summary(roll),
        **_stats(gap, "gap"),
        **_stats(rel, "rel_gap"),
        "sequence_mismatch_rate": (float(mismatch.sum()) / n_both) if n_both else None,
        "negative_gaps": int(negative.sum()),
        "negative_gaps_proven": int((negative & proven).sum()),
        "rollout_time_s": seconds,
    }
    return PolicyReport(summary, cols, _worst(cols, n_both))


def _stats(x: np.ndarray, prefix: str) -> dict[str, float | None]:
    """Mean, median, 95th percentile and maximum of the finite values of ``x``."""
    x = x[np.isfinite(x)]
    if not x.size:
        return {f"{prefix}_{k}": None for k in ("mean", "median", "p95", "max")}
    return {
        f"{prefix}_mean": float(np.mean(x)),
        f"{prefix}_median": float(np.median(x)),
        f"{prefix}_p95": float(np.percentile(x, 95)),
        f"{prefix}_max": float(np.max(x)),
    }


def _worst(cols: dict[str, np.ndarray], n_both: int) -> list[dict[str, Any]]:
    """The report's :data:`WORST` compared draws of the largest gap, largest first."""
    gap, rel = cols["gap"], cols["rel_gap"]
    order = np.argsort(-np.nan_to_num(gap, nan=-np.inf), kind="stable")[: min(WORST, n_both)]
    return [
        {
            "index": int(cols["index"][i]),
            "x0": [float(x) for x in cols["x0"][i]],
            "policy_cost": float(cols["policy_cost"][i]),
            "reference_cost": float(cols["reference_cost"][i]),
            "reference_status": str(cols["reference_status"][i]),
            "gap": float(gap[i]),
            "rel_gap": float(rel[i]),
            "policy_sequence": str(cols["policy_sequence"][i]),
            "reference_sequence": str(cols["reference_sequence"][i]),
        }
        for i in order
    ]
