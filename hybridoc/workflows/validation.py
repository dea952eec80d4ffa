"""Validation against the HMP reference: user controls, cross-validation, convergence.

Three reports, each a JSON-ready dict plus figures:

- :func:`validate_controls`: the true continuous cost of a user's piecewise-constant control
  (the judge), its relative gap to the reference optimum, control errors on the grid, and
  whether its events are the reference's.
- :func:`crossval`: registered methods (:data:`hybridoc.methods.METHODS`) on one problem,
  each measured against the reference within the tolerance the method declares
  (:attr:`~hybridoc.methods.Method.tolerance`); disagreements are findings (``agree`` false
  with the reasons), not table rows.
- :func:`convergence`: costs of the transcription's control sampled on grids of N cells and
  of gradient descent at each N, errors against the reference and observed orders.

Control errors are taken on the N-grid (cell averages for continuous-time controls):
``l2 = sqrt(sum_n |u_n - u*_n|^2 dt)`` (an approximation of the L2(0, T) norm) and
``max = max_n,k |u_nk - u*_nk|``.
"""

from __future__ import annotations

import math
import numbers
import time
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.errors import HybridocError, SceneError
from hybridoc.evaluator import evaluate
from hybridoc.methods import METHODS, solve
from hybridoc.problem import ControlsLike, ProblemLike, as_ocp
from hybridoc.progress import Progress, ProgressLike, progress_scope
from hybridoc.solution import Solution

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.ocp import HybridOCP

__all__ = [
    "DEFAULT_STEPS",
    "control_errors",
    "convergence",
    "convergence_figure",
    "crossval",
    "crossval_figures",
    "event_comparison",
    "local_gap",
    "method_entry",
    "observed_orders",
    "validate_controls",
    "validation_figures",
]

#: Grid sizes of the convergence study.
DEFAULT_STEPS: tuple[int, ...] = (60, 120, 240, 480, 960)


def control_errors(controls: np.ndarray, reference: np.ndarray, dt: float) -> dict[str, float]:
    """Grid L2 and max errors of ``(N, nu)`` controls against the reference's.

    Returns
    -------
    dict
        ``{"l2": sqrt(sum |u - u*|^2 dt), "max": max |u - u*|}``.
    """
    diff = np.asarray(controls, dtype=float) - np.asarray(reference, dtype=float)
    return {"l2": float(np.sqrt(np.sum(diff**2) * dt)), "max": float(np.abs(diff).max())}


def _event_key(e: Mapping[str, Any]) -> str:
    return str(e.get("guard") or "|".join(e.get("bodies", [])))


def event_comparison(
    events: Sequence[Mapping[str, Any]], reference: Sequence[Mapping[str, Any]]
) -> dict[str, Any]:
    """Whether two event lists have the same sequence (guards in time order), and the time
    errors if they do (``None`` when the sequences differ)."""
    same = [_event_key(e) for e in events] == [_event_key(e) for e in reference]
    errs = (
        [float(e["time"] - r["time"]) for e, r in zip(events, reference, strict=True)]
        if same
        else None
    )
    return {
        "sequence_matches": same,
        "time_errors": errs,
        "max_time_error": max((abs(x) for x in errs), default=0.0) if errs is not None else None,
    }


def method_entry(
    sol: Solution, ref: Solution, *, wall_time_s: float | None = None
) -> dict[str, Any]:
    """The cross-validation row of one Solution measured against the reference Solution."""
    dt = float(sol.time_grid[1] - sol.time_grid[0])
    ev = event_comparison(sol.events, ref.events)
    out: dict[str, Any] = {
        "status": sol.status.value,
        "success": sol.success,
        "message": sol.message,
        "cost": float(sol.cost),
        "terminal_cost": float(sol.terminal_cost),
        "running_cost": float(sol.running_cost),
        "cost_gap_relative": float((sol.cost - ref.cost) / abs(ref.cost)) if ref.cost else 0.0,
        "events": list(sol.events),
        "sequence": sol.sequence,
        "event_times": [float(e["time"]) for e in sol.events],
        "sequence_matches": ev["sequence_matches"],
        "event_time_errors": ev["time_errors"],
        "control_error": control_errors(sol.controls, ref.controls, dt),
        "solve_time_s": float(sol.timings.get("solve_time_s", float("nan"))),
    }
    if wall_time_s is not None:
        out["wall_time_s"] = float(wall_time_s)
    if "loss" in sol.info:
        out["discrete_loss"] = float(sol.info["loss"])
    return out


# ---------------------------------------------------------------------------- validate
def validate_controls(
    problem: ProblemLike,
    controls: ControlsLike,
    *,
    reference: Solution | None = None,
    substeps: int = 1,
) -> dict[str, Any]:
    """Judge a user's piecewise-constant control against the reference optimum.

    Parameters
    ----------
    problem
        Any problem.
    controls
        ``(N, nu)`` array or a Solution (validated: shape, finiteness); ``(N * K, nu)``
        with ``substeps=K``.
    reference
        The reference Solution of ``problem`` (on its own grid); solved when not given.
    substeps
        ``K``: the controls hold ``K`` values per grid interval (a simulator's log at ``K``
        substeps) and are judged exactly on the ``K`` times finer grid
        (:func:`hybridoc.io.substep_problem`); the gap is to the reference of ``problem``,
        and the control error compares them with the reference's values held over the
        ``K`` substeps.

    Returns
    -------
    dict
        ``cost``, ``terminal_cost``, ``running_cost``, ``reference_cost``,
        ``cost_gap_relative`` (``(J - J*) / J*``), ``control_error`` (``l2``, ``max``),
        ``events``, ``reference_events``, ``sequence_matches``, ``event_time_errors``,
        ``reference_status``, ``feasible``, ``substeps``.
    """
    from hybridoc.io import substep_problem

    ocp = as_ocp(problem)
    fine = substep_problem(ocp, substeps)
    u = fine.check_controls(getattr(controls, "controls", controls))
    if reference is None:
        reference = solve(ocp, "reference")
    ev = evaluate(fine, u)
    events = ev.event_dicts()
    cmp = event_comparison(events, reference.events)
    return {
        "problem": ocp.name,
        "cost": float(ev.cost),
        "terminal_cost": float(ev.terminal_cost),
        "running_cost": float(ev.running_cost),
        "reference_cost": float(reference.cost),
        "reference_status": reference.status.value,
        "cost_gap_relative": float((ev.cost - reference.cost) / abs(reference.cost)),
        "control_error": control_errors(
            u, np.repeat(np.asarray(reference.controls), fine.steps // ocp.steps, axis=0), fine.dt
        ),
        "events": events,
        "reference_events": list(reference.events),
        "sequence_matches": cmp["sequence_matches"],
        "event_time_errors": cmp["time_errors"],
        "feasible": ev.feasible,
        "substeps": fine.steps // ocp.steps,
    }


def validation_figures(
    problem: ProblemLike, controls: np.ndarray, reference: Solution, *, label: str = "user"
) -> dict[str, Any]:
    """Figures ``controls`` (user vs reference) and ``trajectories`` (overlaid)."""
    from hybridoc.plotting import plot_controls, plot_trajectories

    ocp = as_ocp(problem)
    ev_user = evaluate(ocp, controls)
    fig_u = plot_controls(
        ocp.time_grid(),
        {"reference": reference.controls, label: controls},
        list(ocp.control_labels or []),
        title=f"{ocp.name}: {label} control vs reference",
        event_times={
            "reference": [e["time"] for e in reference.events],
            label: [e.time for e in ev_user.events],
        },
    )
    fig_x = plot_trajectories(
        ocp,
        {"reference": evaluate(ocp, reference.controls), label: ev_user},
        title=f"{ocp.name}: {label} trajectory vs reference",
    )
    return {"controls": fig_u, "trajectories": fig_x}


# ---------------------------------------------------------------------------- crossval
def crossval(
    problem: ProblemLike,
    *,
    methods: Sequence[str] = ("reference", "dt", "gd"),
    options: Mapping[str, Mapping[str, Any]] | None = None,
    tolerances: Mapping[str, float] | None = None,
    progress: ProgressLike = None,
) -> tuple[dict[str, Any], dict[str, Solution]]:
    """Run several methods on one problem and measure each against the reference.

    Parameters
    ----------
    problem
        Any problem.
    methods
        Registered method names (:data:`hybridoc.methods.METHODS`); ``"reference"`` is
        always run (first).
    options
        ``{method: {option: value}}`` passed to :func:`hybridoc.solve`, completed by the
        method's :attr:`~hybridoc.methods.Method.crossval_defaults` where it declares them
        (gradient descent: a multi-start).
    tolerances
        ``{method: relative cost gap}`` overriding the methods' own
        :attr:`~hybridoc.methods.Method.tolerance`.
    progress
        ``None``/``False`` (silent, the default), ``True`` (a meter on stderr) or a
        :class:`~hybridoc.progress.Progress`: a stage per method, and the same object is
        passed to each method's run.

    Returns
    -------
    report, solutions
        ``report``: ``{"problem", "agree", "reasons", <method>: entry}``; ``agree`` is false
        when the reference is beaten by another method's true cost, when a method's cost is
        outside its tolerance of the reference's, when a method failed, when a method's own
        check (:attr:`~hybridoc.methods.Method.crossval_check`) finds a disagreement, or
        when a method's own status is not a success; ``reasons`` says which. Each entry is
        :func:`method_entry` plus the gap to the reference extremal of the method's own
        event sequence (:func:`local_gap`). ``solutions``: the Solutions.
    """
    ocp = as_ocp(problem)
    names = ["reference"] + [m for m in methods if m != "reference"]
    unknown = [m for m in names if m not in METHODS]
    if unknown:
        raise SceneError(f"unknown method(s) {unknown}; choose from {', '.join(METHODS)}")
    opts = _run_options(ocp, names, options)
    tol = {name: METHODS[name].tolerance for name in names} | dict(tolerances or {})
    with progress_scope(progress, "crossval") as p:
        sols, walls, errors = _run_methods(ocp, names, opts, p)
        ref = sols["reference"]
        report: dict[str, Any] = {"problem": ocp.name}
        reasons: list[str] = []
        if not ref.success:
            reasons.append(f"the reference reports {ref.status.value}: {ref.message}")
        for name in names:
            if name in errors:
                report[name] = {"error": errors[name], "wall_time_s": walls[name]}
                reasons.append(f"{name} failed: {errors[name]}")
                continue
            if name != "reference":
                p.stage(f"comparing {name} with the reference")
            report[name], why = _judge_method(ocp, name, sols[name], ref, walls[name], tol[name], p)
            reasons += why
    report["agree"] = not reasons
    report["reasons"] = reasons
    return report, sols


def _run_options(
    ocp: HybridOCP, names: Sequence[str], options: Mapping[str, Mapping[str, Any]] | None
) -> dict[str, dict[str, Any]]:
    """Each method's options: the caller's, completed by its crossval defaults."""
    given = {k: dict(v) for k, v in (options or {}).items()}
    out = {}
    for name in names:
        opts = given.get(name, {})
        defaults = METHODS[name].crossval_defaults
        out[name] = dict(defaults(ocp, opts)) if defaults is not None else opts
    return out


def _run_methods(
    ocp: HybridOCP, names: Sequence[str], opts: Mapping[str, Mapping[str, Any]], progress: Progress
) -> tuple[dict[str, Solution], dict[str, float], dict[str, str]]:
    """Solve with each method: the solutions, wall times and errors (a failure of the
    reference is raised)."""
    sols: dict[str, Solution] = {}
    walls: dict[str, float] = {}
    errors: dict[str, str] = {}
    for name in names:
        progress.stage(name)
        t0 = time.perf_counter()
        try:
            sols[name] = solve(ocp, name, progress=progress, **opts[name])
        except HybridocError as exc:
            if name == "reference":
                raise
            errors[name] = str(exc)
        walls[name] = time.perf_counter() - t0
    return sols, walls, errors


def _judge_method(
    ocp: HybridOCP,
    name: str,
    sol: Solution,
    ref: Solution,
    wall: float,
    tolerance: float,
    progress: Progress,
) -> tuple[dict[str, Any], list[str]]:
    """The report entry of one method and the reasons it disagrees with the reference."""
    entry = method_entry(sol, ref, wall_time_s=wall)
    entry.update(local_gap(ocp, sol, ref, progress=progress))
    entry["tolerance"] = tolerance
    reasons: list[str] = []
    if name == "reference":
        return entry, reasons
    gap = entry["cost_gap_relative"]
    if sol.cost < ref.cost - max(1e-9 * abs(ref.cost), 1e-15):
        reasons.append(
            f"{name} beats the reference: cost {sol.cost:.10g} < {ref.cost:.10g} "
            f"({gap:+.3e}); the reference is not the optimum"
        )
    elif gap > tolerance:
        local = entry.get("cost_gap_local_relative")
        why = (
            f" (it is within {local:+.2e} of the extremal of its own event sequence "
            f"{entry['local_reference_sequence']}: another local optimum)"
            if local is not None and abs(local) <= tolerance
            else ""
        )
        reasons.append(
            f"{name} is {gap:+.3e} above the reference, beyond its tolerance {tolerance:.0e}{why}"
        )
    check = METHODS[name].crossval_check
    if check is not None:
        fields, own = check(ocp, sol)
        entry.update(fields)
        reasons += own
    if not sol.success:
        reasons.append(f"{name} reports {sol.status.value}: {sol.message}")
    return entry, reasons


def local_gap(
    problem: ProblemLike, sol: Solution, ref: Solution, *, progress: ProgressLike = None
) -> dict[str, Any]:
    """The gap of ``sol`` to the reference extremal with ``sol``'s own event sequence.

    Local methods (gradient descent above all) converge to the HMP extremal of the basin
    they start in, which need not be the lowest-cost one the reference finds (on
    multiple-collision a three-event extremal lies 4.6% below the paper's two-event one).
    This measures a method against the extremal of its own mode sequence (solved, with
    ``progress`` passed to the reference, when it is not the reference's own).

    Returns
    -------
    dict
        ``local_reference_cost``, ``local_reference_sequence`` and
        ``cost_gap_local_relative``; ``local_reference_error`` instead when the reference
        has no verified extremal for that sequence.
    """
    sequence = sol.sequence
    if event_comparison(sol.events, ref.events)["sequence_matches"]:
        local = ref
    else:
        try:
            local = solve(problem, "reference", sequence=sequence, initial=sol, progress=progress)
        except HybridocError as exc:
            return {
                "local_reference_cost": None,
                "local_reference_sequence": sequence,
                "cost_gap_local_relative": None,
                "local_reference_error": str(exc),
            }
    return {
        "local_reference_cost": float(local.cost),
        "local_reference_sequence": sequence,
        "cost_gap_local_relative": float((sol.cost - local.cost) / abs(local.cost)),
    }


def crossval_figures(problem: ProblemLike, sols: Mapping[str, Solution]) -> dict[str, Any]:
    """Figures of a cross-validation: ``controls``, ``trajectories``, ``learning_curve``."""
    from matplotlib.figure import Figure

    from hybridoc.plotting import plot_controls, plot_trajectories

    ocp = as_ocp(problem)
    figs: dict[str, Any] = {}
    figs["controls"] = plot_controls(
        ocp.time_grid(),
        {name: s.controls for name, s in sols.items()},
        list(ocp.control_labels or []),
        title=f"{ocp.name}: controls",
        event_times={name: [e["time"] for e in s.events] for name, s in sols.items()},
    )
    evals = {name: evaluate(ocp, s.controls) for name, s in sols.items()}
    figs["trajectories"] = plot_trajectories(
        ocp, evals, title=f"{ocp.name}: trajectories (reference drawn, others dashed)"
    )
    gd = sols.get("gd")
    hist = None if gd is None else gd.arrays.get("loss_history")
    if hist is not None and len(hist):
        fig = Figure(figsize=(6.4, 6.4), layout="constrained")
        ax, ax2 = fig.subplots(2, 1, sharex=True)
        hist = np.asarray(hist, dtype=float)
        it = np.arange(hist.size)
        ref_cost = sols["reference"].cost
        ax.plot(it, hist, lw=1.4, label="gd discrete loss")
        ax.axhline(ref_cost, color="k", ls="--", lw=1, label=f"reference optimum {ref_cost:.6f}")
        ax.set_yscale("log")
        ax.set_ylabel("loss")
        ax.set_title(f"{ocp.name}: gradient descent learning curve")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
        gap = (hist - ref_cost) / abs(ref_cost)
        ax2.semilogy(it[gap > 0], gap[gap > 0], lw=1.4, color="C1")
        ax2.set_xlabel("iteration")
        ax2.set_ylabel("(loss - J*) / J*")
        ax2.grid(alpha=0.3, which="both")
        figs["learning_curve"] = fig
    return figs


# ---------------------------------------------------------------------------- convergence
def observed_orders(steps: Sequence[int], errors: Sequence[float]) -> list[float | None]:
    """Observed orders ``log(e_k / e_{k+1}) / log(N_{k+1} / N_k)``, ``None`` at the first N."""
    out: list[float | None] = [None]
    for k in range(1, len(steps)):
        a, b = errors[k - 1], errors[k]
        if a > 0 and b > 0 and math.isfinite(a) and math.isfinite(b):
            out.append(math.log(a / b) / math.log(steps[k] / steps[k - 1]))
        else:
            out.append(None)
    return out


def convergence(
    problem: ProblemLike,
    *,
    steps: Sequence[int] = DEFAULT_STEPS,
    gd_options: dict[str, Any] | None = None,
    include_gd: bool = True,
) -> dict[str, Any]:
    """Costs of the transcription and of gradient descent on grids of N cells.

    The direct transcription's optimum is a continuous-time control (exact for disc
    scenes, independent of N); its N-dependent cost is that of its cell averages on the
    N-grid, judged piecewise constant by the evaluator: what a user of an N-step simulator
    gets from it. Gradient descent is re-run at each N; its cost is the true continuous
    cost of its piecewise-constant control.

    Returns
    -------
    dict
        ``problem``, ``steps``, ``reference_cost``, ``dt`` and ``gd`` with lists ``cost``,
        ``error`` (``|J_N - J*| / J*``) and ``order`` (observed, against N).
    """
    from hybridoc.ocp import MAX_STEPS
    from hybridoc.solvers.transcription import resample_controls

    ocp = as_ocp(problem)
    steps = tuple(steps)
    if not steps or not all(
        isinstance(n, numbers.Integral) and not isinstance(n, bool) and 1 <= n <= MAX_STEPS
        for n in steps
    ):
        raise SceneError(
            f"steps must be a non-empty list of integers from 1 to {MAX_STEPS}, got {steps!r}"
        )
    ref = solve(ocp, "reference")
    dt_sol = solve(ocp, "dt", initial=ref)

    out: dict[str, Any] = {
        "problem": ocp.name,
        "steps": [int(n) for n in steps],
        "reference_cost": float(ref.cost),
        "dt_continuous_cost": float(dt_sol.cost),
    }
    dt_costs, gd_costs, gd_losses, gd_times = [], [], [], []
    for n in steps:
        sc = ocp.replace(steps=int(n))
        grid = sc.time_grid()
        u_n = resample_controls(dt_sol, grid)
        dt_costs.append(float(evaluate(sc, u_n).cost))
        if include_gd:
            t0 = time.perf_counter()
            g = solve(sc, "gd", **(gd_options or {}))
            gd_times.append(time.perf_counter() - t0)
            gd_costs.append(float(g.cost))
            gd_losses.append(float(g.info.get("loss", float("nan"))))
    J = ref.cost

    def block(costs: list[float]) -> dict[str, Any]:
        err = [abs(c - J) / J for c in costs]
        return {"cost": costs, "error": err, "order": observed_orders(steps, err)}

    out["dt"] = block(dt_costs)
    if include_gd:
        out["gd"] = block(gd_costs)
        out["gd"]["discrete_loss"] = gd_losses
        out["gd"]["solve_time_s"] = gd_times
    return out


def convergence_figure(report: dict[str, Any]) -> Any:
    """Log-log plot of the relative cost errors against N."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.4), layout="constrained")
    ax = fig.subplots()
    steps = np.array(report["steps"], dtype=float)
    for name, marker in (("dt", "o"), ("gd", "s")):
        if name in report:
            err = np.array(report[name]["error"], dtype=float)
            ok = err > 0
            label = {
                "dt": "transcription, cell averages on the N-grid",
                "gd": "gradient descent at N (true continuous cost)",
            }[name]
            ax.loglog(steps[ok], err[ok], marker=marker, label=label)
    e0 = report["dt"]["error"][0] if report["dt"]["error"][0] > 0 else 1e-6
    ax.loglog(steps, e0 * steps[0] / steps, "k--", lw=0.8, label="slope -1")
    ax.loglog(steps, e0 * steps[0] ** 2 / steps**2, "k:", lw=1, label="slope -2")
    ax.set_xlabel("N (grid cells)")
    ax.set_ylabel("|J_N - J*| / J*")
    ax.set_title(f"{report['problem']}: convergence to the reference optimum")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return fig
