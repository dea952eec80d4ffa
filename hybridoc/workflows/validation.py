"""Validation against the HMP reference: user controls, cross-validation, convergence.

Three reports, each a JSON-ready dict plus figures:

- :func:`validate_controls`: the true continuous cost of a user's piecewise-constant control
  (the judge), its relative gap to the reference optimum, control errors on the grid, and
  whether its events are the reference's.
- :func:`crossval`: registered methods (:data:`hybridoc.methods.METHODS`) on one problem,
  each measured twice: against the reference, and against the best control the method can
  represent (:func:`representable`), within the tolerance the method declares
  (:attr:`~hybridoc.methods.Method.tolerance`). Only the second gap is a disagreement: the
  first also holds the method's discretisation error. Disagreements are findings (``agree``
  false with the reasons); a method that fails is a row that says so.
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
    "representable",
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
        reference = solve(ocp, "reference")
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

    Each method gets two gaps. The gap to the reference, ``(J - J*) / |J*|``, holds the
    method's discretisation error as well as any disagreement; the gap to the best control
    the method can represent (:func:`representable`: the reference's control on the
    method's N-step grid for a piecewise-constant method, the transcription re-solved from
    the reference on its own mesh for ``dt``) holds only the disagreement. A method
    disagrees when that second gap exceeds its tolerance.

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
        ``report``: ``{"problem", "agree", "reasons", "grid_cost", "grid_gap_relative",
        <method>: entry}``. ``grid_cost`` is the judged cost of the reference's control
        averaged over the cells of the problem's N-step grid, the best a piecewise-constant
        method can be expected to reach (``grid_gap_relative`` its gap to ``J*``). Each entry
        is :func:`method_entry` plus the gap to the reference extremal of the method's own
        event sequence (:func:`local_gap`), :func:`representable`'s fields, ``converged``
        (the method's own status is a success), ``tolerance`` and, for a problem with
        terminal constraints, ``terminal_violation``. A method that raised is an entry
        ``{"error", "error_type", "wall_time_s", "converged": False}``; the others still
        run. ``agree`` is false when the reference is beaten by another method's true cost,
        when a method is beyond its tolerance of the best control it can represent, when a
        method (or the reference) failed or did not converge, or when a method's own check
        (:attr:`~hybridoc.methods.Method.crossval_check`) finds a disagreement;
        ``reasons`` says which. ``solutions``: the Solutions of the methods that returned
        one.
    """
    ocp = as_ocp(problem)
    names = ["reference"] + [m for m in methods if m != "reference"]
    unknown = [m for m in names if m not in METHODS]
    if unknown:
        raise SceneError(f"unknown method(s) {unknown}; choose from {', '.join(METHODS)}")
    bad_tol = [k for k in (tolerances or {}) if k not in METHODS]
    if bad_tol:
        raise SceneError(f"tolerance for unknown method(s) {bad_tol}")
    tol = {name: METHODS[name].tolerance for name in names} | {
        k: _checked_tolerance(k, v) for k, v in (tolerances or {}).items()
    }
    opts = _run_options(ocp, names, options)
    with progress_scope(progress, "crossval") as p:
        sols, walls, errors = _run_methods(ocp, names, opts, p)
        ref = sols.get("reference")
        report: dict[str, Any] = {"problem": ocp.name}
        reasons: list[str] = []
        if ref is not None and not ref.success:
            reasons.append(f"the reference reports {ref.status.value}: {ref.message}")
        report.update(_grid_projection(ocp, ref))
        for name in names:
            if name in errors:
                report[name] = {**errors[name], "wall_time_s": walls[name], "converged": False}
                reasons.append(f"{name} failed: {errors[name]['error']}")
                continue
            if ref is None:  # nothing to compare with: the method's own answer only
                report[name] = method_entry(sols[name], None, wall_time_s=walls[name])
                report[name]["converged"] = sols[name].success
                continue
            if name != "reference":
                p.stage(f"comparing {name} with the reference")
            try:
                report[name], why = _judge_method(
                    ocp, name, sols[name], ref, walls[name], tol[name], opts[name], p
                )
            except Exception as exc:  # a comparison that breaks is that method's failure
                report[name] = {**_error_fields(exc), "wall_time_s": walls[name]}
                report[name]["converged"] = sols[name].success
                why = [f"{name} could not be compared: {report[name]['error']}"]
            reasons += why
    report["agree"] = not reasons
    report["reasons"] = reasons
    return report, sols


def _checked_tolerance(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise SceneError(f"tolerance of {name} must be a number, got {value!r}")
    if not (math.isfinite(float(value)) and float(value) > 0):
        raise SceneError(f"tolerance of {name} must be a positive number, got {value!r}")
    return float(value)


def _error_fields(exc: BaseException) -> dict[str, Any]:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return {"error": text, "error_type": type(exc).__name__}


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
    """The best control ``method`` can represent, built from the reference, and its cost.

    A method's gap to the reference mixes two things: what its representation of the
    control cannot express (discretisation) and how far it is from the best it could
    express (disagreement: a local optimum, a failure to converge, a wrong gradient). This
    gives the second's yardstick:

    ``dt``
        The transcription re-solved from the reference (its control and its event sequence
        as the initial guess) with ``options`` (the same mesh and degree): the optimum of
        dt's own discretisation near the reference, judged like any dt answer. Holding the
        reference on dt's mesh instead would give a control that dt's NLP never optimises
        (its quadrature and collocation differ from the judge's exact cost), so its cost is
        not a bound on what dt can reach; the discrete optimum is.
    any other method
        The reference's control averaged over the cells of the N-step grid and judged:
        the best piecewise-constant control the method can be expected to reach (not the
        best one exactly: the best piecewise-constant control may be a little cheaper, so
        a negative ``representable_gap_relative`` is not a finding).

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
        ``representable`` (what it is, in words), ``representable_cost`` and
        ``discretisation_gap_relative`` (``(J_best - J*) / |J*|``); ``representable_cost``
        is ``None`` with ``representable_error`` when it could not be built. On a problem
        with terminal constraints or a final mode the grid projection also reports its
        judged ``representable_terminal_violation``: the projection does not keep the
        constraints, so a method that meets them may cost more than it, or less.
    """
    ocp = as_ocp(problem)
    if method == "dt":
        what = "dt re-solved from the reference on its own mesh"
        keep = {k: v for k, v in (options or {}).items() if k in ("mesh", "degree")}
        try:
            best = solve(ocp, "dt", initial=ref, sequence=ref.sequence, progress=progress, **keep)
            cost = float(best.cost)
        except HybridocError as exc:
            return _no_representable(what, str(exc))
    else:
        what = f"the reference's cell averages on the N = {ocp.steps} grid"
        if ocp.free_horizon:
            return _no_representable(what, "a free final time has no fixed grid to project on")
        try:
            grid = ref.to_grid(problem=ocp)
            cost = float(grid.cost)
        except HybridocError as exc:
            return _no_representable(what, str(exc))
        violation = _terminal_violation(ocp, grid)
        if violation is not None:
            return {
                "representable": what,
                "representable_cost": cost,
                "discretisation_gap_relative": _relative(cost, ref.cost),
                "representable_terminal_violation": violation,
            }
    return {
        "representable": what,
        "representable_cost": cost,
        "discretisation_gap_relative": _relative(cost, ref.cost),
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
) -> tuple[dict[str, Any], list[str]]:
    """The report entry of one method and the reasons it disagrees with the reference."""
    entry = method_entry(sol, ref, wall_time_s=wall)
    entry["converged"] = sol.success
    if ocp.has_terminal_constraints:
        v = sol.info.get("terminal_violation")
        entry["terminal_violation"] = None if v is None else float(v)
    entry["tolerance"] = tolerance
    reasons: list[str] = []
    if name == "reference":
        entry.update(local_gap(ocp, sol, ref, progress=progress))
        return entry, reasons
    entry.update(local_gap(ocp, sol, ref, progress=progress))
    entry.update(representable(ocp, name, ref, options=options, progress=progress))
    best = entry["representable_cost"]
    entry["representable_gap_relative"] = None if best is None else _relative(sol.cost, best)
    gap = entry["cost_gap_relative"]
    # the yardstick of a disagreement: the best representable control when there is one
    own = entry["representable_gap_relative"]
    measured, against = (gap, "the reference") if own is None else (own, entry["representable"])
    if sol.cost < ref.cost - max(1e-9 * abs(ref.cost), 1e-15):
        reasons.append(
            f"{name} beats the reference: cost {sol.cost:.10g} < {ref.cost:.10g} "
            f"({gap:+.3e}); the reference is not the optimum"
        )
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
    check = METHODS[name].crossval_check
    if check is not None:
        fields, own_reasons = check(ocp, sol)
        entry.update(fields)
        reasons += own_reasons
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
    evals = {name: evaluate(ocp, s.controls) for name, s in sols.items()}
    figs["trajectories"] = plot_trajectories(
        ocp, evals, title=f"{ocp.name}: trajectories (reference drawn, others dashed)"
    )
    gd = sols.get("gd")
    hist = None if gd is None else gd.arrays.get("loss_history")
    if hist is not None and len(hist) and "reference" in sols:
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
        mark_stages(ax, gd.info.get("history_stages"))
        mark_stages(ax2, gd.info.get("history_stages"))
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
