"""The public solver: :func:`solve_dt` and :func:`run_dt`, the ``"dt"`` :class:`Method`, and the
Solution assembled from the chosen candidate.
"""

from __future__ import annotations

import math
import signal
import sys
import time
from typing import Any

import numpy as np

from hybridoc.errors import ConvergenceError
from hybridoc.evaluation import Evaluation
from hybridoc.methods import Method, options_from_keywords, options_signature, settings_lines
from hybridoc.ocp import HybridOCP
from hybridoc.problem import ControlsLike, ProblemLike, as_ocp
from hybridoc.progress import Progress, ProgressLike, progress_scope
from hybridoc.solution import Solution, Status
from hybridoc.solvers.threads import flag_interrupts
from hybridoc.solvers.transcription.claims import cheaper_known, choose, claim
from hybridoc.solvers.transcription.guess import (
    admissible_candidates,
    candidate_sequences,
    evaluate_guess,
    initial_controls,
    initial_point,
)
from hybridoc.solvers.transcription.ipopt import solve_nlp
from hybridoc.solvers.transcription.judging import Judged
from hybridoc.solvers.transcription.monitor import MONITOR, Monitor, Stopped, short_sequence
from hybridoc.solvers.transcription.nlp import nlp_for, nlp_size
from hybridoc.solvers.transcription.options import (
    DEFAULT_MESH,
    DTOptions,
    checked_mesh,
)
from hybridoc.solvers.transcription.refine import jsonable_estimate, judge_or_refine
from hybridoc.solvers.transcription.result import (
    DTResult,
    problem_at,
    resimulated_names,
    sequence_matches,
)

__all__ = ["METHOD", "run_dt", "solve_dt"]


def solve_dt(
    problem: ProblemLike,
    *,
    initial: ControlsLike | None = None,
    progress: ProgressLike = None,
    **options: Any,
) -> Solution:
    """Solve a hybrid OCP by multi-phase direct transcription (LGR collocation + IPOPT).

    The options are the fields of :class:`DTOptions`, with its defaults (where they are
    written, once); ``solve_dt(problem, **options)`` is
    ``run_dt(problem, DTOptions(**options))`` (:func:`run_dt`).

    Terminal constraints ``h(s(T)) = 0`` / ``>= 0`` are constraints of the NLP at the last
    phase's final node; a free final time (``horizon_bounds``) makes the sum of the phase
    durations a decision variable within its bounds.

    Parameters
    ----------
    problem
        A :class:`~hybridoc.HybridOCP`, a :class:`~hybridoc.problems.Scene` or a built-in
        scene name.
    initial
        Initial guess: ``None`` (the problem's ``u_guess``), an ``(N, nu)`` control array, or
        a :class:`~hybridoc.solution.Solution` (its controls and its events). The phases are
        initialised from the guess's simulated trajectory. A guess whose simulation has two
        events at the same instant that do not commute (a symmetric scene) is perturbed by
        about ``1e-6`` so that they happen one after the other.
    progress
        ``True``: stage lines on stderr once the run has lasted a few seconds (a
        :class:`~hybridoc.progress.ProgressMeter`): the candidate, its NLP's size and
        IPOPT's iteration; ``False``/``None``: silent; or a caller's
        :class:`~hybridoc.progress.Progress`.
    sequence
        Event sequence as guard names, e.g. ``["ball1|ball2", "ball2|wall"]`` or the string
        ``"ball1|ball2,ball2|wall"`` (``[]``: no event). Default:
        discovered from ``initial``: its simulated events and every sequence with one of them
        dropped are solved, and the lowest-cost one whose control, re-simulated by the
        event-exact evaluator, produces exactly the modelled events is kept.
    degree
        Collocation degree, 1 to :data:`MAX_DEGREE` (``>= 3`` recommended; disc optima are
        cubic, so 3 is exact).
    mesh
        Collocation elements per phase (one int, or one per phase), 1 to :data:`MAX_MESH`
        each; default 4, refined: a candidate whose re-simulated events are the modelled
        ones at times off by a little (more than ``1e-6 T``, at most ``1e-3 T``) is solved
        once more with twice the elements, and a candidate that reproduces its events is
        refined until its error estimate is within the tolerances (:data:`REFINE_RTOL`,
        :data:`DEFECT_TOL`: the judged cost against the NLP objective and against the
        previous mesh, the collocation defects between the collocation points), the
        elements with too large defects halved, up to :data:`MAX_ADAPTIVE_MESH` elements
        per phase.
        A mesh given here is kept (its estimate is reported in ``info["error_estimate"]``;
        above the tolerances the result is ``not-converged``).
    time_limit
        Seconds of wall time: past them IPOPT (or the refinement) is stopped and the best
        candidate judged so far is returned as ``not-converged``; before any candidate is
        judged a :class:`~hybridoc.errors.HybridocError` names the limit (``None``: no
        limit; the work is at most one NLP of at most 500 IPOPT iterations per candidate,
        and the refinements). An interrupt (``KeyboardInterrupt``, SIGINT) returns the same
        way once a candidate has been judged.
    terminal_tol
        The judged terminal-constraint violation (of the re-simulated control) above which
        the result is :attr:`~hybridoc.solution.Status.INFEASIBLE`. The NLP meets the
        constraints at its collocated final state; the re-simulation misses them by the
        collocation's error, so at the default mesh a candidate above the tolerance is
        solved again with twice the elements, up to 4 times (mesh 64).
    verbose
        Print IPOPT's log and the candidates to stderr.

    Returns
    -------
    Solution
        Method ``"dt"``. ``cost`` and its parts are the continuous cost of the returned
        control ``u(t)`` re-simulated by :func:`hybridoc.evaluate_callable`; ``controls`` are
        cell averages of ``u(t)`` on the N-grid; ``costates`` are the multiplier estimates
        (events appear twice). ``info`` holds ``sequence``, ``event_times``, ``nlp_cost``,
        ``lambda0`` (``lambda(0)``, a warm start for the HMP reference), the candidates
        tried and IPOPT's counters, ``horizon`` (the final time: for a free final time the
        one found, at which :func:`hybridoc.evaluate` judges the solution and on which the
        grid of ``controls`` lies) and ``terminal_violation`` (the judge's). The callable
        control is available through :func:`control_function` on the solution.

        The NLP honours the control bounds at its Radau points (``u(t)`` is the Radau
        polynomial clipped into the bounds) and the path constraints at the Radau points and
        phase starts. When the re-simulation reproduces the modelled events and is
        feasible, ``status`` says what was compared (docs/solvers.rst, "dt: what its status
        claims"): :attr:`~hybridoc.solution.Status.EXTREMAL` for a given ``sequence`` (its
        optimum, not compared with other sequences);
        :attr:`~hybridoc.solution.Status.BEST_FOUND` for the default discovery on a problem
        with guards (the best of the guess's sequence and those with one event dropped,
        nothing more); :attr:`~hybridoc.solution.Status.SUCCESS` on a problem without
        guards (one sequence); :attr:`~hybridoc.solution.Status.NOT_OPTIMAL` instead of any
        of these when a cheaper feasible control is known (``info["cheaper"]``: the initial
        guess, an initial Solution's control, a candidate that re-simulated to other
        events); :attr:`~hybridoc.solution.Status.NOT_CONVERGED` when the default mesh's
        error estimate is still above the tolerances where the refinement stopped, or the
        time limit or an interrupt stopped the run (``info["stopped"]``). A candidate that
        misses its events by a hair is judged again with each phase's control extended
        ``1e-9 T`` (then ``1e-7 T``) past its event (``info["nudge"]``). Otherwise
        :attr:`~hybridoc.solution.Status.INFEASIBLE` when it reproduces them but violates
        the bounds (by more than ``1e-9``), the path constraints (by more than ``1e-6``) or
        the terminal constraints (by more than ``terminal_tol``) (a feasible candidate is
        preferred; ``message`` says by how much); :attr:`~hybridoc.solution.Status.EVENTS_DIFFER`
        when no converged candidate reproduces its events (the one with the lowest judged
        cost is returned; ``message`` names both sequences).

    Raises
    ------
    TypeError
        A keyword that is not an option of :class:`DTOptions`.
    OptionError
        ``degree``, ``mesh``, ``time_limit`` or ``terminal_tol`` is out of range, or a
        ``mesh`` per phase does not match the given ``sequence`` (a
        :class:`~hybridoc.errors.SceneError`).
    SceneError
        ``sequence`` names an event that is not a guard of the problem, or a candidate's
        NLP would have more than :data:`MAX_NLP_SIZE` variables and constraints
        (:func:`nlp_size`).
    HybridocError
        The run passed ``time_limit`` before any candidate was judged.
    ConvergenceError
        No candidate sequence's NLP converged (the message names IPOPT's status for each,
        e.g. ``Infeasible_Problem_Detected`` for terminal constraints it cannot meet).
    EvaluationError
        The judge cannot simulate the initial guess, or the control of any converged
        candidate (e.g. sustained contact).
    """
    opts = options_from_keywords(DTOptions, options, "solve_dt")
    return run_dt(problem, opts, initial=initial, progress=progress)


solve_dt.__signature__ = options_signature(solve_dt, DTOptions)  # type: ignore[attr-defined]


def run_dt(
    problem: ProblemLike,
    options: DTOptions | None = None,
    *,
    initial: ControlsLike | None = None,
    progress: ProgressLike = None,
) -> Solution:
    """:func:`solve_dt` with its options as one :class:`DTOptions` (checked when it was
    made; ``None``: the defaults).

    Parameters
    ----------
    problem
        A :class:`~hybridoc.HybridOCP`, a :class:`~hybridoc.problems.Scene` or a built-in
        scene name.
    options
        The options (:class:`DTOptions`).
    initial, progress
        As :func:`solve_dt`'s.

    Returns
    -------
    Solution
        As :func:`solve_dt`'s.
    """
    opts = DTOptions() if options is None else options
    ocp = as_ocp(problem)
    t_start = time.perf_counter()
    sequence = opts.sequence
    if sequence is not None:
        sequence = ocp.admissible_sequence(sequence)
        checked_mesh(opts.mesh, len(sequence) + 1)  # one per phase of this sequence
    degree, mesh, verbose = opts.degree, opts.mesh, opts.verbose
    time_limit, terminal_tol = opts.time_limit, opts.terminal_tol
    with progress_scope(progress, "dt") as meter:
        monitor = Monitor(meter, time_limit)
        token = MONITOR.set(monitor)
        previous = flag_interrupts(monitor)
        try:
            return _solve_dt(
                ocp,
                sequence,
                initial,
                degree,
                mesh,
                verbose,
                monitor,
                t_start,
                float(terminal_tol),
            )
        except (Stopped, KeyboardInterrupt) as exc:
            stopped = _stopped_solution(ocp, monitor, exc, degree, mesh, sequence, t_start)
            if stopped is None:
                raise
            return stopped
        finally:
            if previous is not None:
                signal.signal(signal.SIGINT, previous)
            MONITOR.reset(token)


def _stopped_solution(
    ocp: HybridOCP,
    monitor: Monitor,
    exc: BaseException,
    degree: int,
    mesh: Any,
    sequence: list[str] | None,
    t_start: float,
) -> Solution | None:
    """The best candidate judged before the time limit or an interrupt (SIGINT), as a
    ``not-converged`` Solution whose message says why it stopped; ``None`` when nothing
    was judged yet (the error or the interrupt then goes on)."""
    best = monitor.best()
    if best is None:
        return None
    assert best.ev is not None
    why = (
        "interrupted (SIGINT)"
        if isinstance(exc, KeyboardInterrupt)
        else " ".join(str(exc).split()).removeprefix("dt: ")
    )
    ok = sequence_matches(ocp, best.result, best.ev)
    if ok and best.feasible:
        what = "reproduces its events and is feasible"
    elif ok:
        what = "reproduces its events but violates a constraint"
    else:
        what = f"re-simulates to other events ({resimulated_names(ocp, best.ev)})"
    message = (
        f"{why}: the best candidate judged so far is returned (sequence "
        f"{short_sequence(best.result.sequence)}, mesh {list(best.result._nlp.mesh)}; it "
        f"{what}), without the comparison or refinement the run had left"
    )
    sol = _assemble(
        ocp,
        best,
        degree,
        mesh,
        sequence,
        monitor.tried,
        monitor.perturbation,
        time.perf_counter() - t_start,
    )
    sol.info["stopped"] = why
    return sol.set_status(Status.NOT_CONVERGED, message)


def _summary_lines(sol: Solution) -> list[tuple[str, str]]:
    """What ``hybridoc solve`` prints about a dt solution besides status, cost and events."""
    lines = []
    if "iterations" in sol.info:
        lines.append(("iterations", str(sol.info["iterations"])))
    if "nlp_cost" in sol.info:
        x = sol.info["nlp_cost"]
        text = "-" if x is None or math.isnan(float(x)) else f"{float(x):.12g}"
        lines.append(("nlp cost", f"{text} (the transcription's)"))
    if sol.info.get("free_horizon"):
        lines.append(("final time", f"{float(sol.info['horizon']):.12g} (free)"))
    if sol.info.get("terminal_constraints"):
        lines.append(
            (
                "constraints",
                f"terminal violated by {float(sol.info['terminal_violation']):.2e} (judged)",
            )
        )
        lines.append(("final mesh", " ".join(map(str, sol.info.get("mesh", [])))))
    return lines + settings_lines(sol)


METHOD = Method(
    "dt",
    "multi-phase direct transcription (Radau collocation, IPOPT)",
    run=solve_dt,
    options=DTOptions,
    tolerance=1e-6,
    summary_lines=_summary_lines,
    features=frozenset({"terminal", "free_horizon"}),
    representation="continuous",
    resolution_option="mesh",
    projection_options=("mesh", "degree"),
)
"""The ``"dt"`` method (:data:`hybridoc.methods.METHODS`): the transcription is exact for
polynomial optima, so crossval expects it within ``1e-6`` of the reference."""


def _solve_dt(
    ocp: HybridOCP,
    sequence: list[str] | None,
    initial: Any,
    degree: int,
    mesh: Any,
    verbose: bool,
    monitor: Monitor,
    t_start: float,
    terminal_tol: float,
) -> Solution:
    """:func:`solve_dt` after its arguments are checked: candidate sequences from the guess,
    their NLPs solved, the results judged, the best one assembled into a Solution."""
    monitor.progress.stage("simulating the initial guess")
    u0, seq_from_initial = initial_controls(ocp, initial)
    guess, u0, perturbation = evaluate_guess(ocp, u0)
    skipped: list[dict[str, Any]] = []
    if sequence is not None:
        cands = [list(sequence)]
    else:
        observed = seq_from_initial or [ocp.guards[e.guard].name for e in guess.events]
        cands, skipped = admissible_candidates(ocp, candidate_sequences(observed))
    monitor.perturbation = perturbation
    results, tried = _solve_candidates(ocp, cands, guess, u0, degree, mesh, verbose, monitor)
    tried += skipped
    matched, differ = _judge_candidates(
        ocp, results, tried, mesh, verbose, monitor.progress, terminal_tol
    )
    best_j, status, message = choose(ocp, matched, differ, tried)
    status, message = claim(ocp, best_j, status, message, sequence, cands, mesh)
    cheaper = cheaper_known(ocp, best_j, guess, initial, differ)
    if cheaper is not None:
        what = (
            f"{cheaper['source']} costs {cheaper['cost']:.10g} (judged; events "
            f"{cheaper['sequence']}), less than this result's {best_j.ev.cost:.10g}"  # type: ignore[union-attr]
        )
        if status in (Status.SUCCESS, Status.EXTREMAL, Status.BEST_FOUND):
            status = Status.NOT_OPTIMAL
            message = (
                f"{what}: a cheaper control is known, so this is not the optimum; try "
                "--controls with that control, another --sequence, or --method reference"
            )
        else:
            message = f"{message}; {what}" if message else what
    solve_time = time.perf_counter() - t_start
    sol = _assemble(ocp, best_j, degree, mesh, sequence, tried, perturbation, solve_time)
    if best_j.estimate is not None:
        sol.info["error_estimate"] = jsonable_estimate(best_j.estimate)
    sol.info["nudge"] = float(best_j.nudge)
    sol.info["cheaper"] = cheaper
    return sol.set_status(status, message)


def _solve_candidates(
    ocp: HybridOCP,
    cands: list[list[str]],
    guess: Evaluation,
    u0: np.ndarray,
    degree: int,
    mesh: Any,
    verbose: bool,
    monitor: Monitor,
) -> tuple[list[DTResult], list[dict[str, Any]]]:
    """The NLP of each candidate sequence solved from the guess: the converged results, and
    a record of every candidate tried."""
    results: list[DTResult] = []
    tried: list[dict[str, Any]] = monitor.tried
    names = [g.name for g in ocp.guards]
    for i, cand in enumerate(cands):
        if monitor.expired():
            raise monitor.stop(f"before candidate {i + 1} of {len(cands)}")
        guards = [names.index(c) for c in cand]
        mesh_list = checked_mesh(mesh, len(cand) + 1)
        n_w, n_g = nlp_size(ocp, guards, degree, mesh_list)
        monitor.progress.stage(
            f"candidate {i + 1} of {len(cands)}: a {len(cand)}-event sequence, NLP of {n_w} "
            f"variables and {n_g} constraints"
        )
        try:
            nlp = nlp_for(ocp, guards, degree, mesh_list)
            w0, _ = initial_point(nlp, guess, u0)
            r = solve_nlp(nlp, w0, list(cand), verbose)
        except ConvergenceError as exc:
            tried.append({"sequence": cand, "nlp_cost": None, "status": str(exc)})
            continue
        results.append(r)
        tried.append({"sequence": cand, "nlp_cost": r.nlp_cost, "status": r.status})
    if not results:
        why = "; ".join(f"{t['sequence']}: {t['status']}" for t in tried)
        raise ConvergenceError(
            "direct transcription did not converge for any event sequence (tried "
            f"{[t['sequence'] for t in tried]}); give an explicit sequence or another "
            f"initial guess. Per sequence: {why}"
        )
    return results, tried


def _judge_candidates(
    ocp: HybridOCP,
    results: list[DTResult],
    tried: list[dict[str, Any]],
    mesh: Any,
    verbose: bool,
    progress: Progress,
    terminal_tol: float,
) -> tuple[list[Judged], list[Judged]]:
    """Re-simulate the converged candidates, in order of NLP cost, until one reproduces its
    events and is feasible. Returns those that reproduce their events and those that
    re-simulate to other events (or not at all)."""
    matched: list[Judged] = []
    differ: list[Judged] = []
    for r in sorted(results, key=lambda r: r.nlp_cost):
        progress.stage(f"re-simulating the {len(r.sequence)}-event candidate with the judge")
        j, ok, refined = judge_or_refine(ocp, r, mesh, verbose, progress, terminal_tol)
        _record(ocp, tried, j, ok, refined)
        if verbose:
            print(
                f"dt: {j.result.sequence} cost {j.result.nlp_cost:.12g} valid {ok}"
                + (" (refined mesh)" if refined else ""),
                file=sys.stderr,
            )
        if ok:
            matched.append(j)
            if j.feasible:
                break
        else:
            differ.append(j)
    return matched, differ


def _record(
    ocp: HybridOCP, tried: list[dict[str, Any]], j: Judged, ok: bool, refined: bool
) -> None:
    """Add the judge's verdict on ``j`` to its entry in ``tried``."""
    for t in tried:
        if t["sequence"] == j.result.sequence:
            t["resimulated"] = ok
            t["refined"] = refined
            if refined:
                t["nlp_cost"] = j.result.nlp_cost
                t["status"] = j.result.status
            if j.ev is None:
                t["resimulation_error"] = j.error
            else:
                t["resimulated_sequence"] = resimulated_names(ocp, j.ev)
                t["judged_cost"] = float(j.ev.cost)
                t["terminal_violation"] = float(j.ev.terminal_violation)
                t["mesh"] = list(j.result._nlp.mesh)
            if j.nudge:
                t["nudge"] = j.nudge
            if j.estimate is not None:
                t["error_estimate"] = jsonable_estimate(j.estimate)


def _assemble(
    ocp: HybridOCP,
    best_j: Judged,
    degree: int,
    mesh: Any,
    sequence: list[str] | None,
    tried: list[dict[str, Any]],
    perturbation: float,
    solve_time: float,
) -> Solution:
    """The Solution of the chosen candidate (its status not yet set)."""
    best, best_ev = best_j.result, best_j.ev
    assert best_ev is not None
    grid = problem_at(ocp, best).time_grid()
    controls = best.cell_averages(grid)
    info = {
        "sequence": best.sequence,
        "event_times": [float(t) for t in best.event_times],
        "nlp_cost": best.nlp_cost,
        "resimulated_cost_gap": float(abs(best_ev.cost - best.nlp_cost)),
        "lambda0": [float(x) for x in best.lambda0],
        "jump_multipliers": [float(x) for x in best.jump_multipliers],
        "iterations": best.iterations,
        "ipopt_status": best.status,
        "active_path_multiplier": best.active_path,
        "mesh": list(best._nlp.mesh),
        "phase_durations": _phase_durations(best),
        "bound_violation": float(best_ev.bound_violation),
        "path_violation": float(best_ev.path_violation),
        "horizon": float(best.horizon),
        "free_horizon": bool(ocp.free_horizon),
        "terminal_constraints": bool(ocp.has_terminal_constraints),
        "terminal_violation": float(best_ev.terminal_violation),
        "guess_perturbation": perturbation,
        "candidates": tried,
    }
    arrays = {
        "event_times": np.array(best.event_times),
        "lambda0": np.array(best.lambda0),
        "element_bounds": best.element_bounds,
        "radau_controls": np.concatenate(best.controls, axis=1),
        "control_nodes": np.array(best._nlp.rad.tau[1:]),  # u(t) rebuilt without casadi
    }
    if ocp.has_bounds:  # u(t) is clipped into them (also after saving and loading)
        arrays["u_min"] = np.array(ocp.u_min, dtype=float)
        arrays["u_max"] = np.array(ocp.u_max, dtype=float)
    if best.event_controls is not None:  # the resets' own controls, which the judge applies
        arrays["event_controls"] = np.array(best.event_controls)
    sol = Solution(
        method="dt",
        scene=ocp.name,
        controls=controls,
        time_grid=grid,
        cost=float(best_ev.cost),
        terminal_cost=float(best_ev.terminal_cost),
        running_cost=float(best_ev.running_cost),
        events=best_ev.event_dicts(),
        state_times=np.array(best_ev.times),
        states=np.array(best_ev.states),
        costate_times=best.costate_times,
        costates=best.costates,
        settings={
            "degree": int(degree),
            "mesh": mesh if mesh is not None else DEFAULT_MESH,
            "sequence": list(sequence) if sequence is not None else None,
        },
        timings={"solve_time_s": solve_time},
        info=info,
        arrays=arrays,
    )
    return sol.bind(ocp).with_evaluation(best_ev)


def _phase_durations(r: DTResult) -> list[float]:
    return [float(x) for x in np.diff(np.concatenate([[0.0], r.event_times, [r.horizon]]))]
