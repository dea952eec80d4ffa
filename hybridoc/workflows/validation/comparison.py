"""Cross-validation (:func:`crossval`): registered methods on one problem, each measured
against the reference and against the reference projected onto its own representation,
and the checks that may explain a gap; its figures (:func:`crossval_figures`)."""

from __future__ import annotations

import math
import numbers
import time
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.errors import HybridocError, OptionError
from hybridoc.methods import BUILTIN, METHODS, REFERENCE_METHOD, solve
from hybridoc.problem import ProblemLike, as_ocp
from hybridoc.progress import Progress, ProgressLike, progress_scope
from hybridoc.solution import Solution, Status
from hybridoc.workflows.validation.measures import (
    RESULT_STATUSES,
    event_comparison,
    figure_evaluation,
    method_entry,
    relative,
    sequence_text,
)
from hybridoc.workflows.validation.projection import (
    grid_projection,
    local_gap,
    refined_projection,
    representable,
)

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.ocp import HybridOCP

__all__ = [
    "EXPLAINING_CHECKS",
    "REFINE_RATIO",
    "crossval",
    "crossval_figures",
]


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
        report.update(grid_projection(ocp, ref))
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
        gap = relative(float(sol.cost), float(base.cost))
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
                f"{name}'s events ({sequence_text(sol)}) are not {baseline}'s "
                f"({sequence_text(base)}); explained by check 'costs agree': {gap:+.3e}, "
                f"within the tolerance {tol[name]:.0e}"
            )
    return baseline


def _feasible(sol: Solution) -> bool:
    return sol.status is not Status.INFEASIBLE and not (
        float(sol.info.get("terminal_violation", 0.0) or 0.0) > 1e-6
    )


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
    entry["representable_gap_relative"] = None if best is None else relative(sol.cost, best)
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
    theirs, ours = sequence_text(entry), sequence_text(ref)
    local = entry.get("local_reference_cost")
    tie = None if local is None else relative(float(local), float(ref.cost))
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
    evals = {name: figure_evaluation(ocp, s) for name, s in sols.items()}
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
