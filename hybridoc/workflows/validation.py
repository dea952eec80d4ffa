"""Validation against the HMP reference: user controls, cross-validation, convergence.

Three reports, each a JSON-ready dict plus figures:

- :func:`validate_controls`: the true continuous cost of a user's piecewise-constant control
  (the judge), its relative gap to the reference optimum, control errors on the grid, and
  whether its events are the reference's.
- :func:`crossval`: registered methods (:data:`hybridoc.methods.METHODS`) on one problem,
  each measured twice: against the reference, and against the reference projected onto
  the method's own representation (:func:`representable`), within the tolerance the method
  declares (:attr:`~hybridoc.methods.Method.tolerance`). A gap to the projection beyond the
  tolerance is a disagreement; so is an event sequence other than the reference's, or a
  projection that is itself beyond the tolerance of the reference, unless an independent
  check explains it (:data:`EXPLAINING_CHECKS`). When the reference refuses the problem
  the other methods are compared with each other. Disagreements are findings (``agree``
  false with the reasons, ``status`` ``disagree``); a method that fails is a row that says
  so.
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

from hybridoc.errors import HybridocError, OptionError, SceneError
from hybridoc.evaluator import evaluate
from hybridoc.methods import BUILTIN, METHODS, REFERENCE_METHOD, Method, solve
from hybridoc.problem import ControlsLike, ProblemLike, as_ocp
from hybridoc.progress import Progress, ProgressLike, progress_scope
from hybridoc.solution import Solution, Status

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.evaluation import Evaluation
    from hybridoc.ocp import HybridOCP

__all__ = [
    "DEFAULT_STEPS",
    "EXPLAINING_CHECKS",
    "REFINE_RATIO",
    "RESULT_STATUSES",
    "control_errors",
    "convergence",
    "convergence_figure",
    "crossval",
    "crossval_figures",
    "event_comparison",
    "judged_evaluation",
    "local_gap",
    "method_entry",
    "observed_orders",
    "refined_projection",
    "representable",
    "validate_controls",
    "validation_figures",
]

#: Grid sizes of the convergence study.
DEFAULT_STEPS: tuple[int, ...] = (60, 120, 240, 480, 960)

RESULT_STATUSES: frozenset[Status] = frozenset({Status.SUCCESS, Status.EXTREMAL, Status.BEST_FOUND})
"""The statuses of a method's own result that crossval compares without a finding of their
own: ``success``, ``extremal`` (a given sequence's extremal) and ``best-found`` (a search's
best, not proven). The others (``not-optimal``, ``events-differ``, ``infeasible``,
``not-converged``, ``disagree``) are findings the method made about itself."""

REFINE_RATIO = 0.75
"""A projection's gap to the reference is explained as discretisation when the same
projection on a grid (mesh) twice as fine keeps the reference's events and has a gap at most
this fraction of it (an order-1 error halves, an order-2 one quarters)."""

EXPLAINING_CHECKS: dict[str, str] = {
    "refinement": "the reference's projection on a grid (mesh) twice as fine keeps the "
    "reference's events and its gap shrinks by at least REFINE_RATIO: the gap is the grid's",
    "tie": "the reference's extremal of the method's own event sequence costs within the "
    "method's tolerance of the reference: the sequences tie",
    "costs agree": "with no reference, the two methods' judged costs agree within the "
    "tolerance: their differing events cost nothing that the tolerance can see",
}
"""The independent checks that can explain a sequence mismatch or a projection beyond the
tolerance; anything they do not explain is a disagreement."""


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
    sol: Solution, ref: Solution | None, *, wall_time_s: float | None = None
) -> dict[str, Any]:
    """The cross-validation row of one Solution measured against the reference Solution
    (``None`` when there is none: the comparisons are then ``None``)."""
    dt = float(sol.time_grid[1] - sol.time_grid[0])
    ev = (
        event_comparison(sol.events, ref.events)
        if ref is not None
        else {"sequence_matches": None, "time_errors": None}
    )
    out: dict[str, Any] = {
        "status": sol.status.value,
        "success": sol.success,
        "message": sol.message,
        "cost": float(sol.cost),
        "terminal_cost": float(sol.terminal_cost),
        "running_cost": float(sol.running_cost),
        "cost_gap_relative": None if ref is None else _relative(sol.cost, ref.cost),
        "events": list(sol.events),
        "sequence": sol.sequence,
        "event_times": [float(e["time"]) for e in sol.events],
        "sequence_matches": ev["sequence_matches"],
        "event_time_errors": ev["time_errors"],
        "control_error": None if ref is None else control_errors(sol.controls, ref.controls, dt),
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
        with ``substeps=K``. A Solution is judged by its own control
        (:meth:`~hybridoc.Solution.control`), so ``cost`` is its ``cost`` bit for bit.
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
        ``reference_status``, ``feasible``, ``bound_violation``, ``path_violation``,
        ``terminal_violation`` (the judge's), ``substeps``.
    """
    from hybridoc.io import substep_problem

    ocp = as_ocp(problem)
    fine = substep_problem(ocp, substeps)
    u = fine.check_controls(getattr(controls, "controls", controls))
    if reference is None:
        reference = solve(ocp, REFERENCE_METHOD)
    # a Solution is judged by its own control (so its cost comes back bit for bit)
    own = substeps == 1 and hasattr(controls, "control_kind")
    ev = evaluate(fine, controls if own else u)
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
        "bound_violation": float(ev.bound_violation),
        "path_violation": float(ev.path_violation),
        "terminal_violation": float(ev.terminal_violation),
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
        {REFERENCE_METHOD: reference.controls, label: controls},
        list(ocp.control_labels or []),
        title=f"{ocp.name}: {label} control vs reference",
        event_times={
            REFERENCE_METHOD: [e["time"] for e in reference.events],
            label: [e.time for e in ev_user.events],
        },
    )
    fig_x = plot_trajectories(
        ocp,
        {REFERENCE_METHOD: evaluate(ocp, reference.controls), label: ev_user},
        title=f"{ocp.name}: {label} trajectory vs reference",
    )
    return {"controls": fig_u, "trajectories": fig_x}


# ---------------------------------------------------------------------------- crossval
def crossval(
    problem: ProblemLike,
    *,
    methods: Sequence[str] = tuple(BUILTIN),
    options: Mapping[str, Mapping[str, Any]] | None = None,
    tolerances: Mapping[str, float] | None = None,
    progress: ProgressLike = None,
) -> tuple[dict[str, Any], dict[str, Solution]]:
    """Run several methods on one problem and measure each against the reference.

    Each method gets two gaps. The gap to the reference, ``(J - J*) / |J*|``, holds the
    method's discretisation error as well as any disagreement. The gap to the reference
    projected onto the method's representation (:func:`representable`: ``J*``'s cell
    averages on the N-step grid for a piecewise-constant method, an upper bound on the best
    cost that grid can represent, not the best; the transcription re-solved from the
    reference on its own mesh for ``dt``) holds only the disagreement, provided the
    projection is a faithful one. So a method disagrees when

    - its gap to the projection exceeds its tolerance (or, with no projection, its gap to
      the reference does);
    - its event sequence is not the reference's, unless the reference's extremal of the
      method's own sequence costs within the tolerance of ``J*`` (check ``"tie"``);
    - the projection itself is beyond the tolerance of ``J*`` (a gap that would otherwise be
      written off as discretisation: a projection that loses the reference's events
      cost +333% on a switched linear system), unless the same projection on a grid or mesh
      twice as fine keeps the reference's events and shrinks the gap by
      :data:`REFINE_RATIO` (check ``"refinement"``);
    - it beats the reference, failed, or reports a status outside
      :data:`RESULT_STATUSES`, or its own check
      (:attr:`~hybridoc.methods.Method.crossval_check`) finds a disagreement.

    Every explanation that was accepted is in ``notes`` with the check that made it
    (:data:`EXPLAINING_CHECKS`). A ``best-found`` (or ``extremal``) reference is still the
    baseline, but nothing proves it the optimum: the report's ``status`` is then
    ``best-found``, not ``success``. When the reference refuses the problem (a
    :class:`~hybridoc.errors.HybridocError`, e.g. a Hamiltonian linear in the control) the
    other methods are compared with each other: each against the cheapest of them
    (``baseline``), within its tolerance, and with the same event sequence unless their
    costs agree within the tolerance (check ``"costs agree"``); nothing is proven then
    either.

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
        ``report``: ``{"problem", "status", "verdict", "agree", "reasons", "notes",
        "baseline", "proven", "grid_cost", "grid_gap_relative", <method>: entry}``.
        ``status`` is ``"success"`` (the methods agree with a reference that proves its
        optimum), ``"best-found"`` (they agree, but the baseline is not proven the optimum:
        a ``best-found`` or ``extremal`` reference, or no reference) or ``"disagree"``;
        ``verdict`` says it in a sentence. ``baseline`` is the method every other is
        measured against (``"reference"``, or the cheapest method when the reference
        refused), ``proven`` whether it is the proven optimum. ``grid_cost`` is the judged
        cost of the reference's control averaged over the cells of the problem's N-step
        grid (``grid_gap_relative`` its gap to ``J*``): an upper bound on the best a
        piecewise-constant method on that grid can reach. Each entry is
        :func:`method_entry` plus the gap to the reference extremal of the method's own
        event sequence (:func:`local_gap`), :func:`representable`'s fields,
        ``representable_gap_relative`` (the method's gap to the projection: negative when
        the method beats it, which the projection allows), ``projection_checks`` (the
        refinement check, when it ran), ``converged`` (its own status is in
        :data:`RESULT_STATUSES`), ``tolerance`` and, for a problem with terminal
        constraints, ``terminal_violation``; with no reference, ``baseline_gap_relative``
        and ``baseline_sequence_matches`` instead of the reference's comparisons. A method
        that raised is an entry ``{"error", "error_type", "wall_time_s", "converged":
        False}``; the others still run. ``agree`` is true when ``reasons`` is empty.
        ``solutions``: the Solutions of the methods that returned one.
    """
    ocp = as_ocp(problem)
    names = [REFERENCE_METHOD] + [m for m in methods if m != REFERENCE_METHOD]
    unknown = [m for m in names if m not in METHODS]
    if unknown:
        raise OptionError(f"unknown method(s) {unknown}; choose from {', '.join(METHODS)}")
    bad_tol = [k for k in (tolerances or {}) if k not in METHODS]
    if bad_tol:
        raise OptionError(
            f"tolerance for unknown method(s) {bad_tol}; choose from {', '.join(METHODS)}"
        )
    tol = {name: METHODS[name].tolerance for name in names} | {
        k: _checked_tolerance(k, v) for k, v in (tolerances or {}).items()
    }
    opts = _run_options(ocp, names, options)
    with progress_scope(progress, "crossval") as p:
        sols, walls, errors = _run_methods(ocp, names, opts, p)
        ref = sols.get(REFERENCE_METHOD)
        report: dict[str, Any] = {"problem": ocp.name}
        reasons: list[str] = []
        notes: list[str] = []
        report.update(_grid_projection(ocp, ref))
        for name in names:
            if name in errors:
                report[name] = {**errors[name], "wall_time_s": walls[name], "converged": False}
                if name == REFERENCE_METHOD and errors[name]["refused"]:
                    notes.append(f"the reference refused the problem: {errors[name]['error']}")
                else:
                    reasons.append(f"{name} failed: {errors[name]['error']}")
        if ref is None:
            baseline = _compare_without_reference(report, sols, walls, tol, reasons, notes)
            proven = False
        else:
            baseline, proven = REFERENCE_METHOD, ref.status is Status.SUCCESS
            _reference_status(ref, reasons, notes)
            for name in names:
                if name in errors:
                    continue
                if name != REFERENCE_METHOD:
                    p.stage(f"comparing {name} with the reference")
                try:
                    report[name], why, explained = _judge_method(
                        ocp, name, sols[name], ref, walls[name], tol[name], opts[name], p
                    )
                except Exception as exc:  # a comparison that breaks is that method's failure
                    report[name] = {**_error_fields(exc), "wall_time_s": walls[name]}
                    report[name]["converged"] = sols[name].status in RESULT_STATUSES
                    why, explained = [f"{name} could not be compared: {report[name]['error']}"], []
                reasons += why
                notes += explained
    report["baseline"] = baseline
    report["proven"] = bool(proven and not reasons)
    report["agree"] = not reasons
    report["reasons"] = reasons
    report["notes"] = notes
    report["status"], report["verdict"] = _verdict(report, ref, baseline, sols)
    return report, sols


def _verdict(
    report: Mapping[str, Any], ref: Solution | None, baseline: str | None, sols: Mapping[str, Any]
) -> tuple[str, str]:
    """The report's status (a :class:`~hybridoc.solution.Status` value) and its sentence."""
    if report["reasons"]:
        return Status.DISAGREE.value, f"disagree: {len(report['reasons'])} finding(s)"
    others = [n for n in sols if n != baseline]
    if ref is not None and report["proven"]:
        return Status.SUCCESS.value, "agree with the reference, which proves its optimum"
    if ref is not None:
        return Status.BEST_FOUND.value, (
            f"agree with the reference, but the reference is {ref.status.value}: not proven "
            "the global optimum"
        )
    if baseline is None:
        return Status.BEST_FOUND.value, "no method returned a solution to compare"
    if not others:
        return Status.BEST_FOUND.value, (
            f"the reference refused the problem and only {baseline} answered: nothing compared"
        )
    return Status.BEST_FOUND.value, (
        f"the reference refused the problem; {', '.join(others)} agree(s) with {baseline} "
        "(the cheapest answer), but nothing proves it the optimum"
    )


def _reference_status(ref: Solution, reasons: list[str], notes: list[str]) -> None:
    """A reference that is not ``success``: ``best-found`` and ``extremal`` are baselines
    that prove nothing (a note); any other status is a finding (a reason)."""
    if ref.status is Status.SUCCESS:
        return
    if ref.status in RESULT_STATUSES:
        notes.append(
            f"the reference is {ref.status.value}, not proven the global optimum: every gap "
            f"is to the best control known ({ref.message})"
        )
    else:
        reasons.append(f"the reference reports {ref.status.value}: {ref.message}")


def _compare_without_reference(
    report: dict[str, Any],
    sols: Mapping[str, Solution],
    walls: Mapping[str, float],
    tol: Mapping[str, float],
    reasons: list[str],
    notes: list[str],
) -> str | None:
    """With no reference: each method against the cheapest feasible answer (the baseline),
    within its tolerance and with the baseline's events unless their costs agree within it
    (check ``"costs agree"``). Returns the baseline's name (``None`` when no method
    answered)."""
    answered = {n: s for n, s in sols.items() if n != REFERENCE_METHOD}
    feasible = {n: s for n, s in answered.items() if _feasible(s)} or answered
    if not feasible:
        return None
    baseline = min(feasible, key=lambda n: float(feasible[n].cost))
    base = feasible[baseline]
    others = [n for n in answered if n != baseline]
    if others:
        notes.append(
            f"no reference: {', '.join(others)} compared with {baseline}, the cheapest answer "
            f"(cost {float(base.cost):.10g})"
        )
    for name, sol in answered.items():
        entry = method_entry(sol, None, wall_time_s=walls[name])
        entry["converged"] = sol.status in RESULT_STATUSES
        entry["tolerance"] = tol[name]
        gap = _relative(float(sol.cost), float(base.cost))
        same = event_comparison(sol.events, base.events)["sequence_matches"]
        entry["baseline_gap_relative"] = gap
        entry["baseline_sequence_matches"] = same
        report[name] = entry
        if sol.status not in RESULT_STATUSES:
            reasons.append(f"{name} reports {sol.status.value}: {sol.message}")
        if name == baseline:
            continue
        if gap > tol[name]:
            reasons.append(
                f"{name} is {gap:+.3e} above {baseline} (cost {float(sol.cost):.10g} against "
                f"{float(base.cost):.10g}), beyond its tolerance {tol[name]:.0e}; with no "
                "reference, no other check can explain it"
            )
        elif not same:
            notes.append(
                f"{name}'s events ({_sequence_text(sol)}) are not {baseline}'s "
                f"({_sequence_text(base)}); explained by check 'costs agree': {gap:+.3e}, "
                f"within the tolerance {tol[name]:.0e}"
            )
    return baseline


def _feasible(sol: Solution) -> bool:
    return sol.status is not Status.INFEASIBLE and not (
        float(sol.info.get("terminal_violation", 0.0) or 0.0) > 1e-6
    )


def _sequence_text(sol: Solution | Mapping[str, Any]) -> str:
    events = sol.events if isinstance(sol, Solution) else sol.get("events", [])
    return ", ".join(_event_key(e) for e in events) or "no event"


def _checked_tolerance(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise OptionError(f"tolerance of {name} must be a number, got {value!r}")
    if not (math.isfinite(float(value)) and float(value) > 0):
        raise OptionError(f"tolerance of {name} must be a positive number, got {value!r}")
    return float(value)


def _error_fields(exc: BaseException) -> dict[str, Any]:
    """An exception as report fields; ``refused``: a user-level refusal (a
    :class:`~hybridoc.errors.HybridocError`, e.g. a problem the method cannot solve), not a
    crash."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return {
        "error": text,
        "error_type": type(exc).__name__,
        "refused": isinstance(exc, HybridocError),
    }


def _grid_projection(ocp: HybridOCP, ref: Solution | None) -> dict[str, Any]:
    """The judged cost of the reference's cell averages on the problem's N-step grid."""
    if ref is None or ocp.free_horizon:
        return {"grid_cost": None, "grid_gap_relative": None}
    try:
        grid = ref.to_grid(problem=ocp)
        cost = float(grid.cost)
    except HybridocError as exc:
        return {"grid_cost": None, "grid_gap_relative": None, "grid_error": str(exc)}
    out = {"grid_cost": cost, "grid_gap_relative": _relative(cost, ref.cost)}
    violation = _terminal_violation(ocp, grid)
    if violation is not None:
        out["grid_terminal_violation"] = violation
    return out


def _relative(cost: float, against: float) -> float:
    return float((cost - against) / abs(against)) if against else float(cost - against)


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
) -> tuple[dict[str, Solution], dict[str, float], dict[str, dict[str, Any]]]:
    """Solve with each method: the solutions, wall times and errors (``{"error",
    "error_type"}`` of each method that raised; the others still run)."""
    sols: dict[str, Solution] = {}
    walls: dict[str, float] = {}
    errors: dict[str, dict[str, Any]] = {}
    for name in names:
        progress.stage(name)
        t0 = time.perf_counter()
        try:
            sols[name] = solve(ocp, name, progress=progress, **opts[name])
        except KeyboardInterrupt:
            raise
        except Exception as exc:  # any method's failure is its row, not the end of the run
            errors[name] = _error_fields(exc)
        walls[name] = time.perf_counter() - t0
    return sols, walls, errors


def representable(
    problem: ProblemLike,
    method: str,
    ref: Solution,
    *,
    options: Mapping[str, Any] | None = None,
    progress: ProgressLike = None,
) -> dict[str, Any]:
    """The reference projected onto ``method``'s representation of a control, and its cost.

    A method's gap to the reference mixes two things: what its representation of the
    control cannot express (discretisation) and how far it is from the best it could
    express (disagreement: a local optimum, a failure to converge, a wrong gradient). The
    projection is the second's yardstick:

    ``dt``
        The transcription re-solved from the reference (its control and its event sequence
        as the initial guess) with ``options`` (the same mesh and degree): the optimum of
        dt's own discretisation near the reference, judged like any dt answer. Holding the
        reference on dt's mesh instead would give a control that dt's NLP never optimises
        (its quadrature and collocation differ from the judge's exact cost). It bounds
        nothing: dt may land below it or above it.
    any other method
        The reference's control averaged over the cells of the N-step grid and judged: a
        control of the grid, so an upper bound on the best cost the grid can represent,
        not that best (the best piecewise-constant control may be cheaper: a negative gap
        of the method to it is no finding).

    Either projection is a faithful yardstick only when it keeps the reference's events
    (``representable_sequence_matches``): one that loses them (a control that stops short
    of a guard on re-simulation) measures the loss, not the discretisation.

    Parameters
    ----------
    problem
        Any problem.
    method
        A registered method name.
    ref
        The reference Solution.
    options
        The method's options (``dt``: ``mesh``, ``degree``).
    progress
        Passed to a re-solve.

    Returns
    -------
    dict
        ``representable`` (what it is, in words), ``representable_cost``,
        ``discretisation_gap_relative`` (``(J_proj - J*) / |J*|``), ``representable_sequence``
        (its events' guards) and ``representable_sequence_matches``; ``representable_cost``
        is ``None`` with ``representable_error`` when it could not be built. On a problem
        with terminal constraints or a final mode the grid projection also reports its
        judged ``representable_terminal_violation``: the projection does not keep the
        constraints, so a method that meets them may cost more than it, or less.
    """
    ocp = as_ocp(problem)
    m = METHODS[method]
    if m.representation == "continuous":
        opt = m.resolution_option
        what = f"{method} re-solved from the reference on its own {opt or 'discretisation'}"
        keep = {k: v for k, v in (options or {}).items() if k in m.projection_options}
        try:
            best = _resolved_from(ocp, m, ref, keep, progress)
        except HybridocError as exc:
            return _no_representable(what, str(exc))
        out = _projection_fields(what, best, ref)
        if opt is not None:
            out[f"representable_{opt}"] = [int(x) for x in best.info.get(opt) or []]
        return out
    what = f"the reference's cell averages on the N = {ocp.steps} grid"
    if ocp.free_horizon:
        return _no_representable(what, "a free final time has no fixed grid to project on")
    try:
        grid = ref.to_grid(problem=ocp)
    except HybridocError as exc:
        return _no_representable(what, str(exc))
    out = _projection_fields(what, grid, ref)
    violation = _terminal_violation(ocp, grid)
    if violation is not None:
        out["representable_terminal_violation"] = violation
    return out


def _resolved_from(
    ocp: HybridOCP, m: Method, ref: Solution, options: Mapping[str, Any], progress: ProgressLike
) -> Solution:
    """A ``"continuous"`` method re-solved from the reference: its control as the initial
    guess and, when the method takes one, its event sequence."""
    seq = {"sequence": ref.sequence} if m.takes("sequence") else {}
    return solve(ocp, m.name, initial=ref, **seq, progress=progress, **options)


def _projection_fields(what: str, proj: Solution, ref: Solution) -> dict[str, Any]:
    cost = float(proj.cost)
    return {
        "representable": what,
        "representable_cost": cost,
        "discretisation_gap_relative": _relative(cost, ref.cost),
        "representable_sequence": [_event_key(e) for e in proj.events],
        "representable_sequence_matches": event_comparison(proj.events, ref.events)[
            "sequence_matches"
        ],
    }


def refined_projection(
    problem: ProblemLike,
    method: str,
    ref: Solution,
    *,
    options: Mapping[str, Any] | None = None,
    progress: ProgressLike = None,
) -> dict[str, Any]:
    """:func:`representable` on a grid (``dt``: a mesh) twice as fine: check
    ``"refinement"`` of :func:`crossval`.

    For a piecewise-constant method the reference's cell averages on the ``2 N`` grid; for
    ``dt`` the transcription re-solved from the reference with twice the elements of the
    mesh it used (its ``mesh`` option, else the mesh its solution reports). A gap that is the
    discretisation's shrinks (an order-1 error halves) and the projection keeps the
    reference's events; a lost event or a local optimum does neither.

    Returns
    -------
    dict
        ``refined`` (what it is), ``refined_cost``, ``refined_gap_relative`` and
        ``refined_sequence_matches``; ``refined_gap_relative`` ``None`` with
        ``refined_error`` when it could not be built.
    """
    from hybridoc.ocp import MAX_STEPS

    ocp = as_ocp(problem)
    opts = dict(options or {})
    m = METHODS[method]
    try:
        if m.representation == "continuous":
            opt = m.resolution_option
            if opt is None:
                raise SceneError(f"{method} declares no resolution option to refine")
            keep = {k: v for k, v in opts.items() if k in m.projection_options and k != opt}
            res = opts.get(opt)
            if res is None:  # the resolution of the projection at the method's options
                first = _resolved_from(ocp, m, ref, keep, progress)
                res = max(int(x) for x in first.info.get(opt) or [first.settings[opt]])
            res = 2 * (max(int(x) for x in res) if isinstance(res, Sequence) else int(res))
            what = f"{method} re-solved from the reference on {opt} {res}"
            fine = _resolved_from(ocp, m, ref, {**keep, opt: res}, progress)
        else:
            steps = 2 * ocp.steps
            what = f"the reference's cell averages on the N = {steps} grid"
            if steps > MAX_STEPS or ocp.free_horizon:
                raise SceneError(f"no grid of {steps} steps")
            fine = ref.to_grid(problem=ocp.replace(steps=steps))
    except HybridocError as exc:
        return {
            "refined": f"{method}'s projection refined",
            "refined_cost": None,
            "refined_gap_relative": None,
            "refined_sequence_matches": None,
            "refined_error": " ".join(str(exc).split()),
        }
    return {
        "refined": what,
        "refined_cost": float(fine.cost),
        "refined_gap_relative": _relative(float(fine.cost), ref.cost),
        "refined_sequence_matches": event_comparison(fine.events, ref.events)["sequence_matches"],
    }


def _terminal_violation(ocp: HybridOCP, sol: Solution) -> float | None:
    """The judged terminal violation of ``sol`` (a :meth:`Solution.to_grid` projection) on a
    problem with terminal constraints or a final mode (the grid projection of ``J*`` does
    not keep them: a method that meets them may cost more than it, so a gap to it is no
    finding), else ``None``."""
    if not (ocp.has_terminal_constraints or ocp.final_mode is not None):
        return None
    return float(sol.info["terminal_violation"])  # Solution.to_grid's judged violation


def _no_representable(what: str, why: str) -> dict[str, Any]:
    return {
        "representable": what,
        "representable_cost": None,
        "discretisation_gap_relative": None,
        "representable_sequence": None,
        "representable_sequence_matches": None,
        "representable_error": " ".join(why.split()),
    }


def _judge_method(
    ocp: HybridOCP,
    name: str,
    sol: Solution,
    ref: Solution,
    wall: float,
    tolerance: float,
    options: Mapping[str, Any],
    progress: Progress,
) -> tuple[dict[str, Any], list[str], list[str]]:
    """The report entry of one method, the reasons it disagrees with the reference and the
    notes of the checks that explained a mismatch or a projection's gap."""
    entry = method_entry(sol, ref, wall_time_s=wall)
    entry["converged"] = sol.status in RESULT_STATUSES
    if ocp.has_terminal_constraints:
        v = sol.info.get("terminal_violation")
        entry["terminal_violation"] = None if v is None else float(v)
    entry["tolerance"] = tolerance
    reasons: list[str] = []
    notes: list[str] = []
    entry.update(local_gap(ocp, sol, ref, progress=progress))
    if name == REFERENCE_METHOD:
        return entry, reasons, notes
    entry.update(representable(ocp, name, ref, options=options, progress=progress))
    best = entry["representable_cost"]
    entry["representable_gap_relative"] = None if best is None else _relative(sol.cost, best)
    if best is not None and best < ref.cost - max(1e-9 * abs(ref.cost), 1e-15):
        reasons.append(
            f"{entry['representable']} costs {best:.10g} < {ref.cost:.10g}: the reference is "
            "not the optimum"
        )
    gap = entry["cost_gap_relative"]
    # the yardstick of a disagreement: the reference's projection when there is one
    own = entry["representable_gap_relative"]
    measured, against = (gap, "the reference") if own is None else (own, entry["representable"])
    if sol.cost < ref.cost - max(1e-9 * abs(ref.cost), 1e-15):
        reasons.append(
            f"{name} beats the reference: cost {sol.cost:.10g} < {ref.cost:.10g} "
            f"({gap:+.3e}); the reference is not the optimum"
        )
    elif own is not None and own <= tolerance < gap:
        # within its tolerance of the projection, beyond it of J*: the projection's own gap
        # is written off as discretisation only when an independent check says it is
        why, note = _projection_beyond_tolerance(
            ocp, name, entry, ref, tolerance, options, progress
        )
        reasons += why
        notes += note
    elif measured > tolerance:
        local = entry.get("cost_gap_local_relative")
        why = (
            f" (it is within {local:+.2e} of the extremal of its own event sequence "
            f"{entry['local_reference_sequence']}: another local optimum)"
            if local is not None and abs(local) <= tolerance
            else ""
        )
        reasons.append(
            f"{name} is {measured:+.3e} above {against}, beyond its tolerance "
            f"{tolerance:.0e} (gap to the reference {gap:+.3e}){why}"
        )
    if entry.get("representable_sequence_matches") is False and not reasons:
        notes.append(
            f"{name}'s yardstick, {entry['representable']}, loses the reference's events "
            f"({entry['discretisation_gap_relative']:+.3e} from J*): {name} is measured by its "
            f"gap to J* itself ({gap:+.3e}, within its tolerance {tolerance:.0e})"
        )
    if not entry["sequence_matches"]:
        why, note = _sequence_mismatch(name, entry, ref, tolerance)
        reasons += why
        notes += note
    check = METHODS[name].crossval_check
    if check is not None:
        fields, own_reasons = check(ocp, sol)
        entry.update(fields)
        reasons += own_reasons
    if sol.status not in RESULT_STATUSES:
        reasons.append(f"{name} reports {sol.status.value}: {sol.message}")
    return entry, reasons, notes


def _sequence_mismatch(
    name: str, entry: Mapping[str, Any], ref: Solution, tolerance: float
) -> tuple[list[str], list[str]]:
    """A method whose events are not the reference's: explained only by check ``"tie"``
    (the reference's extremal of the method's own sequence costs within the tolerance of
    ``J*``), else a reason."""
    theirs, ours = _sequence_text(entry), _sequence_text(ref)
    local = entry.get("local_reference_cost")
    tie = None if local is None else _relative(float(local), float(ref.cost))
    if tie is not None and abs(tie) <= tolerance:
        return [], [
            f"{name}'s events ({theirs}) are not the reference's ({ours}); explained by check "
            f"'tie': the reference's extremal of {name}'s sequence costs {float(local):.10g}, "
            f"{tie:+.3e} from J*, within the tolerance {tolerance:.0e}"
        ]
    if local is None:
        unexplained = (
            "the reference has no verified extremal of that sequence "
            f"({entry.get('local_reference_error', 'not solved')})"
        )
    else:
        unexplained = (
            f"the reference's extremal of that sequence costs {float(local):.10g}, "
            f"{tie:+.3e} from J*: no tie"
        )
    return [
        f"{name}'s events ({theirs}) are not the reference's ({ours}): {unexplained}; "
        f"{name} is {entry['cost_gap_relative']:+.3e} from J*"
    ], []


def _projection_beyond_tolerance(
    ocp: HybridOCP,
    name: str,
    entry: dict[str, Any],
    ref: Solution,
    tolerance: float,
    options: Mapping[str, Any],
    progress: Progress,
) -> tuple[list[str], list[str]]:
    """A method beyond its tolerance of ``J*`` but within it of the reference's projection:
    the projection's gap is discretisation only if check ``"refinement"`` says so (the
    projection keeps the reference's events, and on a grid or mesh twice as fine it keeps
    them and its gap shrinks by :data:`REFINE_RATIO`); else a reason. Sets
    ``entry["projection_checks"]``."""
    projected = float(entry["discretisation_gap_relative"])
    head = (
        f"{name} is {entry['cost_gap_relative']:+.3e} from J*, beyond its tolerance "
        f"{tolerance:.0e}; its yardstick, {entry['representable']}, is {projected:+.3e} from J*"
    )
    if entry.get("representable_sequence_matches") is False:
        entry["projection_checks"] = {"refinement": None}
        lost = ", ".join(entry.get("representable_sequence") or []) or "no event"
        return [
            f"{head} and loses the reference's events (it has {lost}): not a discretisation error"
        ], []
    opt = METHODS[name].resolution_option
    used = None if opt is None else entry.get(f"representable_{opt}")
    if used and options.get(opt) is None:
        options = {**options, opt: max(used)}  # the resolution the projection was solved on
    fine = refined_projection(ocp, name, ref, options=options, progress=progress)
    entry["projection_checks"] = {"refinement": fine}
    fine_gap = fine.get("refined_gap_relative")
    if (
        fine_gap is not None
        and fine["refined_sequence_matches"]
        and projected > 0
        and abs(fine_gap) <= REFINE_RATIO * projected
    ):
        return [], [
            f"{head}; explained by check 'refinement': {fine['refined']} is {fine_gap:+.3e} "
            f"from J* with the reference's events (ratio {fine_gap / projected:.2f}): the gap "
            "is the discretisation's"
        ]
    if fine_gap is None:
        detail = f"the refinement check could not run: {fine.get('refined_error')}"
    elif not fine["refined_sequence_matches"]:
        detail = f"{fine['refined']} loses the reference's events"
    else:
        detail = (
            f"{fine['refined']} is {fine_gap:+.3e} from J*: it does not shrink by "
            f"{REFINE_RATIO} like a discretisation error"
        )
    return [f"{head}, unexplained: {detail}"], []


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
            local = solve(
                problem, REFERENCE_METHOD, sequence=sequence, initial=sol, progress=progress
            )
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


def judged_evaluation(sol: Solution) -> Evaluation | None:
    """The judge's evaluation ``sol``'s cost came from (:attr:`Solution.evaluation`), so
    that a figure need not judge again; ``None`` where the Solution keeps none (a loaded
    file, changed costs)."""
    from hybridoc.evaluation import Evaluation

    ev = getattr(sol, "evaluation", None)
    return ev if isinstance(ev, Evaluation) else None


def crossval_figures(problem: ProblemLike, sols: Mapping[str, Solution]) -> dict[str, Any]:
    """Figures of a cross-validation: ``controls``, ``trajectories``, ``learning_curve``."""
    from matplotlib.figure import Figure

    from hybridoc.plotting import mark_stages, plot_controls, plot_trajectories

    ocp = as_ocp(problem)
    figs: dict[str, Any] = {}
    figs["controls"] = plot_controls(
        ocp.time_grid(),
        {name: s.controls for name, s in sols.items()},
        list(ocp.control_labels or []),
        title=f"{ocp.name}: controls",
        event_times={name: [e["time"] for e in s.events] for name, s in sols.items()},
    )
    evals = {
        name: ev if (ev := judged_evaluation(s)) is not None else evaluate(ocp, s.controls)
        for name, s in sols.items()
    }
    figs["trajectories"] = plot_trajectories(
        ocp, evals, title=f"{ocp.name}: trajectories (reference drawn, others dashed)"
    )
    curves = _loss_histories(sols)
    if curves and REFERENCE_METHOD in sols:
        fig = Figure(figsize=(6.4, 6.4), layout="constrained")
        ax, ax2 = fig.subplots(2, 1, sharex=True)
        ref_cost = sols[REFERENCE_METHOD].cost
        for k, (name, hist) in enumerate(curves.items()):
            it = np.arange(hist.size)
            ax.plot(it, hist, lw=1.4, label=f"{name} discrete loss")
            gap = (hist - ref_cost) / abs(ref_cost)
            ax2.semilogy(it[gap > 0], gap[gap > 0], lw=1.4, color=f"C{k + 1}", label=name)
        ax.axhline(ref_cost, color="k", ls="--", lw=1, label=f"reference optimum {ref_cost:.6f}")
        ax.set_yscale("log")
        ax.set_ylabel("loss")
        ax.set_title(f"{ocp.name}: {', '.join(curves)} learning curve")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
        ax2.set_xlabel("iteration")
        ax2.set_ylabel("(loss - J*) / J*")
        ax2.grid(alpha=0.3, which="both")
        if len(curves) == 1:  # the stages of one run (a multi-start's, a hop's)
            stages = sols[next(iter(curves))].info.get("history_stages")
            mark_stages(ax, stages)
            mark_stages(ax2, stages)
        figs["learning_curve"] = fig
    return figs


def _loss_histories(sols: Mapping[str, Solution]) -> dict[str, np.ndarray]:
    """The learning curve of each registered method's Solution that has one
    (:attr:`~hybridoc.methods.Method.loss_history`)."""
    out = {}
    for name, sol in sols.items():
        hist = METHODS[name].loss_history(sol) if name in METHODS else None
        if hist is not None and len(hist):
            out[name] = np.asarray(hist, dtype=float)
    return out


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
    methods: Sequence[str] | None = None,
    options: Mapping[str, Mapping[str, Any]] | None = None,
    gd_options: dict[str, Any] | None = None,
    include_gd: bool = True,
) -> dict[str, Any]:
    """Costs of methods on grids of N cells, against the reference.

    What a method's cost at N is depends on what its control can express
    (:attr:`~hybridoc.methods.Method.representation`). A ``"continuous"`` method (the
    direct transcription) is solved once, from the reference; its optimum is a
    continuous-time control (exact for disc scenes, independent of N), and its
    N-dependent cost is that of its cell averages on the N-grid, judged piecewise constant
    by the evaluator: what a user of an N-step simulator gets from it. A ``"grid"`` method
    (gradient descent) is re-run at each N; its cost is the true continuous cost of its
    piecewise-constant control.

    Parameters
    ----------
    problem
        Any problem.
    steps
        The grid sizes N.
    methods
        Registered method names; default: every built-in method but the reference.
    options
        ``{method: {option: value}}`` passed to :func:`hybridoc.solve`.
    gd_options, include_gd
        Deprecated: ``options={"gd": ...}`` and ``methods`` without ``"gd"``.

    Returns
    -------
    dict
        ``problem``, ``steps``, ``methods``, ``reference_cost``,
        ``<method>_continuous_cost`` for each continuous method, and for each method a block
        with lists ``cost``, ``error`` (``|J_N - J*| / J*``) and ``order`` (observed,
        against N); a grid method's block also has ``discrete_loss`` (its
        ``info["loss"]``) and ``solve_time_s`` at each N.
    """
    from hybridoc.ocp import MAX_STEPS

    ocp = as_ocp(problem)
    steps = tuple(steps)
    if not steps or not all(
        isinstance(n, numbers.Integral) and not isinstance(n, bool) and 1 <= n <= MAX_STEPS
        for n in steps
    ):
        raise SceneError(
            f"steps must be a non-empty list of integers from 1 to {MAX_STEPS}, got {steps!r}"
        )
    names, opts = _convergence_methods(methods, options, gd_options, include_gd)
    ref = solve(ocp, REFERENCE_METHOD)
    out: dict[str, Any] = {
        "problem": ocp.name,
        "steps": [int(n) for n in steps],
        "methods": names,
        "reference_cost": float(ref.cost),
    }
    continuous = {}
    for name in names:
        if METHODS[name].representation == "continuous":
            continuous[name] = solve(ocp, name, initial=ref, **opts[name])
            out[f"{name}_continuous_cost"] = float(continuous[name].cost)
    costs: dict[str, list[float]] = {name: [] for name in names}
    losses: dict[str, list[float]] = {name: [] for name in names if name not in continuous}
    times: dict[str, list[float]] = {name: [] for name in losses}
    for n in steps:
        sc = ocp.replace(steps=int(n))
        for name in names:
            if name in continuous:  # its control's cell averages on the N-grid, judged
                costs[name].append(float(continuous[name].to_grid(problem=sc).cost))
                continue
            t0 = time.perf_counter()
            g = solve(sc, name, **opts[name])
            times[name].append(time.perf_counter() - t0)
            costs[name].append(float(g.cost))
            losses[name].append(float(g.info.get("loss", float("nan"))))
    J = ref.cost
    for name in names:
        err = [abs(c - J) / J for c in costs[name]]
        out[name] = {"cost": costs[name], "error": err, "order": observed_orders(steps, err)}
        if name in losses:
            out[name]["discrete_loss"] = losses[name]
            out[name]["solve_time_s"] = times[name]
    return out


def _convergence_methods(
    methods: Sequence[str] | None,
    options: Mapping[str, Mapping[str, Any]] | None,
    gd_options: dict[str, Any] | None,
    include_gd: bool,
) -> tuple[list[str], dict[str, dict[str, Any]]]:
    """The methods of a convergence study and their options, with the deprecated
    ``gd_options`` and ``include_gd`` (which named one method) mapped onto them."""
    import warnings

    given = [m for m in BUILTIN if m != REFERENCE_METHOD] if methods is None else list(methods)
    opts = {k: dict(v) for k, v in (options or {}).items()}
    if gd_options is not None or not include_gd:
        warnings.warn(
            "convergence(gd_options=, include_gd=) is deprecated: use options={'gd': ...} and "
            "methods=[...]",
            DeprecationWarning,
            stacklevel=3,
        )
        if gd_options is not None:
            opts["gd"] = {**gd_options, **opts.get("gd", {})}
        if not include_gd:
            given = [m for m in given if m != "gd"]
    names = list(dict.fromkeys(m for m in given if m != REFERENCE_METHOD))
    unknown = [m for m in [*names, *opts] if m not in METHODS]
    if unknown or not names:
        raise OptionError(
            f"convergence needs registered methods other than the reference; got "
            f"{unknown or names}, choose from {', '.join(METHODS)}"
        )
    return names, {name: opts.get(name, {}) for name in names}


def convergence_figure(report: dict[str, Any]) -> Any:
    """Log-log plot of the relative cost errors against N."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.4), layout="constrained")
    ax = fig.subplots()
    steps = np.array(report["steps"], dtype=float)
    names = _report_methods(report)
    for k, name in enumerate(names):
        err = np.array(report[name]["error"], dtype=float)
        ok = err > 0
        label = (
            f"{name}, cell averages on the N-grid"
            if f"{name}_continuous_cost" in report
            else f"{name} at N (true continuous cost)"
        )
        ax.loglog(steps[ok], err[ok], marker="osD^v<>"[k % 7], label=label)
    first = report[names[0]]["error"][0] if names else 0.0
    e0 = first if first > 0 else 1e-6
    ax.loglog(steps, e0 * steps[0] / steps, "k--", lw=0.8, label="slope -1")
    ax.loglog(steps, e0 * steps[0] ** 2 / steps**2, "k:", lw=1, label="slope -2")
    ax.set_xlabel("N (grid cells)")
    ax.set_ylabel("|J_N - J*| / J*")
    ax.set_title(f"{report['problem']}: convergence to the reference optimum")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return fig


def _report_methods(report: Mapping[str, Any]) -> list[str]:
    """The methods of a convergence report (its ``methods``; a report written before it
    had them: its blocks)."""
    if "methods" in report:
        return list(report["methods"])
    return [k for k, v in report.items() if isinstance(v, Mapping) and "error" in v]
