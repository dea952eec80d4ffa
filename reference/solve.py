"""The reference solution: HMP shooting, a search over event sequences, and trust checks.

:func:`solve_reference` returns a :class:`~hybridoc.solution.Solution` whose control is the
exact optimal control ``u(t)`` of the continuous problem for the event sequence it reports.

What it tries
    Without ``sequence``: the events of the initial guess (and that sequence with one event
    dropped, or with one near-touch added, and no event at all); the proposals of the
    candidate sources (:mod:`hybridoc.reference.sources`; by default the registered ones:
    the event sequence of the direct transcription started from the same guess, and those
    of a cheap batched multi-start of the differentiable simulator on a coarse grid), each
    given what is left of the ``budget``; then the enumeration: every feasible sequence,
    length by length up to the scene's depth
    (:func:`~hybridoc.reference.candidates.default_depth`) or ``search=K`` if longer,
    within a length by lower bound, skipping those whose bound
    (:func:`~hybridoc.reference.candidates.lower_bound`: the passive-disc terminal bound
    and the reachability bound) is not below the best cost met, and stopping when the
    budget is spent (lengths beyond ``search`` only). Each sequence is solved by
    :func:`~hybridoc.reference.sequence.solve_sequence` (Newton from a costate estimate,
    the disc NLP, or the warm start of a source such as the transcription with the
    sequence fixed). ``info["sources"]`` lists the sources used, ``info["coverage"]`` what
    the search covered.

What it claims
    ``success`` means the global optimum, and only where the coverage proves it
    (:func:`~hybridoc.reference.search.claims.proof`): every feasible sequence of up to one event
    more than the answer's own was solved or excluded by a valid lower bound (the
    enumeration extends to that length while the shorter ones are covered, at most
    :data:`MAX_PROOF_DEPTH`, within the budget), no cheaper extremal of those lengths fails
    its re-simulation (that sequence's optimum, with the extra contacts avoided, would be
    unknown), and the answer's extremal was reached from :data:`PROOF_STARTS` distinct
    starts of Newton that agree (a second start is run where needed). Anything less is
    ``best-found``: the best verified extremal, nothing cheaper known, with
    ``info["coverage"]["why_not_proven"]``. ``time_limit`` (and a KeyboardInterrupt) stops
    everything and returns the best verified extremal so far as ``not-converged``.

What it checks before it answers
    1. The HMP residual (transversality, guards, costate jumps, Hamiltonian continuity) is
       below ``tol`` after Newton with exact Jacobians.
    2. ``u(t)`` re-simulated by the judge produces exactly the modelled events, no extra and
       none missing, and the same cost.
    3. No control it has met is cheaper: not the initial guess, not those the sources
       proposed (the transcription's, the multi-start's). Where one is, its event sequence
       is solved again from that control; if the extremal is still more expensive, the
       result is reported with status ``not-optimal`` and the cheaper cost named, never as
       the optimum.

    With ``sequence`` given, only that sequence is solved, and the answer is its extremal
    (status ``extremal``), not a claim of optimality: ``not-optimal`` when a known control
    (of the same or other events) is cheaper; with ``search`` too, the discovery and search
    run without the sequence and their optimum confirms it (``success``) or beats it.

    Control bounds enter the minimum condition as saturation, ``u* = clip(argmin H)``, with
    a switch time per saturation switch (:func:`~hybridoc.reference.shooting.saturate`);
    an answer whose control still violates them has status ``infeasible``. Mixed path
    constraints ``c(s, u) >= 0`` (every row depending on ``u``, affinely) enter with their
    multipliers on arcs where rows are active, found by the same loop; a known control
    counts against the answer only when it meets them between the grid times too
    (:func:`path_violation`), and an answer that violates them is ``infeasible``. Pure
    state constraints are refused (:func:`reference_supports`).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

from hybridoc import tolerances
from hybridoc.errors import (
    ConvergenceError,
    EvaluationError,
    HybridocError,
    SceneError,
    SimultaneousEventError,
)
from hybridoc.evaluator import evaluate, gradient
from hybridoc.methods import Method
from hybridoc.ocp import HybridOCP
from hybridoc.problem import ControlsLike, ProblemLike, as_ocp
from hybridoc.progress import Progress, ProgressLike, progress_scope
from hybridoc.reference.options import (
    DEFAULT_BUDGET,
    MAX_EVENTS,
    MAX_SEARCH,
    MULTISTART,
    ReferenceOptions,
    option_keywords,
    parse_budget,
    parse_search,
)
from hybridoc.reference.result import ReferenceResult
from hybridoc.reference.search.book import (
    MAX_PROOF_DEPTH,
    OPT_RTOL,
    PATH_SAMPLES,
    PATH_TOL,
    START_RTOL,
    Book,
    Guess,
    Known,
    Run,
    Stopped,
    is_feasible,
    lacks_reason,
    path_violation,
    source_lacks,
    too_long,
)
from hybridoc.reference.search.claims import (
    EVENT_CONTROL_PROBE,
    PROOF_STARTS,
    check_coalescing,
    coverage_line,
    event_control_rival,
    extremal_message,
    extremal_path_violation,
    families_line,
    finish,
    proof,
    summary_lines,
    touch_note,
)
from hybridoc.reference.search.discovery import (
    best_of,
    discover,
    revisit_cheaper,
    second_start,
    solve_given,
)
from hybridoc.reference.shooting import (
    hamiltonian_check,
    has_closed_form_phases,
    path_check,
    reset_control_check,
    saturation_check,
)
from hybridoc.reference.sources import CandidateSource, SequenceStarter, registered_sources
from hybridoc.reference.units import canonical, in_problem_units
from hybridoc.reference.units import cost_shown as _J
from hybridoc.solution import Solution, Status

__all__ = [
    "DEFAULT_BUDGET",
    "EVENT_CONTROL_PROBE",
    "MAX_EVENTS",
    "MAX_PROOF_DEPTH",
    "MAX_SEARCH",
    "METHOD",
    "MULTISTART",
    "PATH_SAMPLES",
    "PATH_TOL",
    "PROOF_STARTS",
    "START_RTOL",
    "ReferenceOptions",
    "coverage_line",
    "event_control_rival",
    "families_line",
    "parse_budget",
    "parse_search",
    "path_violation",
    "reference_supports",
    "solve_reference",
]


def reference_supports(ocp: HybridOCP) -> str | None:
    """``None`` when the reference can solve ``ocp``, else the one-line reason (pure state
    constraints of order 2 or more, path constraints not affine in ``u``, a Hamiltonian not
    quadratic in ``u``, bounds with a coupled control weight, a reset affine in an unbounded
    control)."""
    return (
        reset_control_check(ocp)
        or hamiltonian_check(ocp)
        or path_check(ocp)
        or saturation_check(ocp)
    )


def _robust_guess(
    ocp: HybridOCP, u0: np.ndarray, *, want_adjoint: bool
) -> tuple[Any, Any, np.ndarray]:
    """The judge's evaluation (and adjoint) of the guess. A guess whose events fire at the
    same instant without an order (a symmetric scene) is perturbed slightly, so that its
    trajectory can still propose sequences and start the searches."""
    rng = np.random.default_rng(12345)
    u = u0
    scale = max(1.0, float(np.abs(u0).max(initial=0.0)))
    for attempt in range(4):
        try:
            if want_adjoint:
                g = gradient(ocp, u)
                return g.evaluation, g, u
            return evaluate(ocp, u), None, u
        except SimultaneousEventError:
            if attempt == 3:
                raise
            u = u0 + 1e-6 * scale * (attempt + 1) * rng.standard_normal(u0.shape)
        except EvaluationError as exc:
            raise ConvergenceError(f"cannot simulate the initial guess: {exc}") from None
    raise AssertionError("unreachable")  # pragma: no cover


def _initial_controls(ocp: HybridOCP, initial: Any) -> tuple[np.ndarray, bool]:
    if initial is None:
        return np.asarray(ocp.u_guess, dtype=float), False
    controls = getattr(initial, "controls", initial)
    return ocp.check_controls(controls, what="initial"), True


@option_keywords(ReferenceOptions)
def solve_reference(
    problem: ProblemLike,
    options: ReferenceOptions | None = None,
    *,
    initial: ControlsLike | None = None,
    progress: ProgressLike = False,
    **overrides: Any,
) -> Solution:
    """The optimal control by shooting on the hybrid minimum principle.

    Parameters
    ----------
    problem
        Any problem (:func:`hybridoc.problem.as_ocp`) whose Hamiltonian is quadratic in
        ``u``, whose path constraints (if any) each depend on ``u``, affinely
        (:func:`reference_supports`). A disc scene far from its own units (its
        :attr:`~hybridoc.ocp.HybridOCP.scales` beyond a factor 4, or moved from the origin)
        is solved in them and the answer stated in the scene's
        (:mod:`hybridoc.reference.units`), so that the same physical scene in any units, or
        moved, gets the same answer.
    options
        A :class:`ReferenceOptions`; the keywords below replace its fields (default: the
        defaults). ``solve_reference(problem, search=2)`` and
        ``solve_reference(problem, ReferenceOptions(search=2))`` are the same solve.
    sequence
        Guard names in event order (e.g. ``["ball1|ball2", "ball2|wall"]`` or the string
        ``"ball1|ball2,ball2|wall"``; ``[]`` for no event): the extremal of that sequence.
        ``None`` (default): search (module notes).
    initial
        ``None`` (the problem's initial guess), ``(N, nu)`` controls or a Solution: its
        events and adjoint costate start Newton, and it is one of the controls the result
        must not be worse than.
    search
        Also solve every feasible sequence of up to this many events (at most
        :data:`MAX_SEARCH`) and report the landscape of extremals (``info["landscape"]``).
        The sequences of up to ``search`` events are enumerated whatever the budget.
    budget
        Seconds (default :data:`DEFAULT_BUDGET`) the search for the optimum may take: each
        candidate source is given what is left of it
        (:attr:`~hybridoc.reference.sources.SourceContext.budget_s`; one not started when
        nothing is left), and the default enumeration stops when it is spent
        (``info["coverage"]["budget_stopped"]``). What follows (the verification, the
        sequences of cheaper controls met) is not cut short. The budget is the search's soft
        limit: a search it stops short of the proof returns ``best-found``.
    time_limit
        A hard wall-clock limit in seconds over the whole solve (default none): checked
        before each sequence's solve, between the stages and in the enumeration, and given
        to the sources as their ``budget_s`` when it is nearer than the budget's end. When
        it is reached the best verified extremal found so far is returned with status
        ``not-converged`` and a message that says so; a :class:`ConvergenceError` when none
        was found. A KeyboardInterrupt during the search does the same (message
        ``"interrupted"``). One sequence's solve, a source that does not keep to its
        ``budget_s`` and the final verification are not cut short.
    verbose
        Print Newton's iterations and the candidates to stderr.
    rtol
        Relative accuracy of the cost (from 1e-11 to 1e-6; default 1e-9): on a generic
        problem the integration of each phase is refined until its error estimate is within
        it (:func:`~hybridoc.reference.shooting.refine`), and the judge's re-simulation of
        the extremal's ``u(t)`` must agree with the shooting cost to it (where it does not,
        the integration is refined further, at most
        :data:`~hybridoc.reference.sequence.JUDGE_RETRIES` times, before a
        :class:`~hybridoc.errors.ConvergenceError` names ``rtol``).
    tol
        Max-norm of the HMP residual required.
    verify
        Re-simulate the result with the judge. Only an explicit ``sequence`` may skip it
        (for timing).
    transcription
        Use the candidate source called ``"transcription"`` (the direct transcription from
        the same guess, a competitor and the fallback start of Newton).
    multistart
        Starts of the candidate source called ``"multi-start"`` (0 to skip it).
    sources
        The candidate sources (:class:`~hybridoc.reference.sources.CandidateSource`,
        :class:`~hybridoc.reference.sources.SequenceStarter`), in order; ``None``: the
        registered ones (:func:`~hybridoc.reference.sources.register_source`: the
        transcription and the multi-start unless unregistered; a warning says when none
        is).
    progress
        ``True``, ``False``/``None`` or a :class:`~hybridoc.progress.Progress`: stage lines
        (which sequence is being solved, the sources, the verification) and the count of
        the search over sequences.

    Returns
    -------
    hybridoc.solution.Solution
        Method ``"reference"``; ``status`` ``success`` (the global optimum as the coverage
        proves it: the answer satisfies the HMP conditions, re-simulates to its own events,
        no control met is cheaper, every feasible sequence of up to one event more than its
        own was solved or excluded by a valid bound with no cheaper extremal among them
        failing its re-simulation, and its extremal was reached from :data:`PROOF_STARTS`
        agreeing starts of Newton; ``coverage["proven"]`` and ``coverage["proof"]``),
        ``best-found`` (the best verified extremal of a search whose coverage proves less:
        ``coverage["why_not_proven"]`` and the message say what is missing; exit code 1),
        ``not-converged`` (``time_limit`` or a KeyboardInterrupt stopped the search: the
        best verified extremal so far, ``coverage["stopped"]``), ``extremal`` (the
        extremal of a given ``sequence``, not compared with other sequences; with ``search``
        as well, the search runs without the sequence and makes it ``success`` when it finds
        nothing cheaper and proves its own answer), ``not-optimal`` (a cheaper control is
        known: named in ``message`` and ``info["cheaper"]``) or ``infeasible`` (the extremal
        violates the control bounds or the path constraints); ``info`` holds ``residual``,
        ``sequence``, ``newton_iterations``, ``grazing``, ``event_times``, ``candidates``
        (every sequence tried and its outcome), ``sources`` (each source used: ``name``,
        ``kind`` ``"reference"``, ``"registered"`` or ``"given"``, ``proposals``,
        ``time_s``, and ``failed`` where it raised), ``warm_starts`` (the sources that may
        start Newton on a sequence), ``coverage`` (what the search covered: ``sources``, the
        numbers of distinct sequences ``proposed``, ``attempted``, ``solved`` (an extremal
        found) and ``pruned`` (skipped by a lower bound), ``depth`` (the enumeration's
        target length), ``exhaustive_length`` (every feasible sequence of up to this many
        events was solved, an extremal found, or pruned by a valid bound: a sequence whose
        solve failed leaves its length uncovered; ``None`` without an enumeration, or when
        not even the empty sequence is covered), ``failed`` (the sequences attempted whose
        solve failed and that no bound prunes: ``count`` and the first few ``sequences``),
        ``budget_s``, ``budget_stopped``, ``time_limit_s``, ``stopped`` (``None``, ``"the
        time limit"`` or ``"interrupted"``), ``proven`` with ``proof`` or
        ``why_not_proven``, and ``families``: the best extremal of each
        sequence family, a family being the sequences of one number of events) and with
        ``search`` the ``landscape``.

    Raises
    ------
    OptionError
        A bad option (``tol``, ``search``, ``rtol``, ``budget``, ``time_limit``, a source),
        from :class:`ReferenceOptions`.
    TypeError
        A keyword that is not an option.
    SceneError
        A bad ``sequence``, a ``sequence`` of more than :data:`MAX_EVENTS` events, or a
        problem the reference cannot handle. Without
        ``sequence``, candidates longer than :data:`MAX_EVENTS` are not attempted (listed in
        ``info["candidates"]`` with the reason).
    ConvergenceError
        No candidate sequence satisfies the conditions and re-simulates to its own events,
        or the time limit (or an interrupt) came before any did.
    """
    t_start = time.perf_counter()
    opts = ReferenceOptions.of(options, overrides)
    ocp = as_ocp(problem)
    seq = _check_arguments(ocp, opts.sequence)
    proposers, starters, kind = _active_sources(opts.sources, opts.transcription, opts.multistart)
    run = Run(
        seq=seq, initial=initial, search=opts.search, budget=opts.budget, verbose=opts.verbose,
        tol=opts.tol, rtol=opts.rtol, time_limit=opts.time_limit, verify=opts.verify,
        transcription=opts.transcription, multistart=opts.multistart, sources=opts.sources,
        proposers=proposers, starters=starters, kind=kind, t_start=t_start,
    )  # fmt: skip
    units = canonical(ocp)
    if units is None:
        with progress_scope(progress, "reference") as meter:
            return _solve(ocp, run, meter)
    # a disc scene in other units, or moved: solved in its scaled units (reference.units)
    run = dataclasses.replace(run, initial=units.initial_in(initial))
    with progress_scope(progress, "reference") as meter, in_problem_units(units):
        sol = _solve(units.ocp, run, meter)
    return units.to_problem(sol, ocp, opts.rtol)


def _check_arguments(ocp: HybridOCP, sequence: Sequence[str] | str | None) -> list[str] | None:
    """The checked sequence (or ``None``); a :class:`SceneError` for a problem the reference
    cannot solve or a sequence it does not have (the options themselves are checked by
    :class:`ReferenceOptions`)."""
    reason = reference_supports(ocp)
    if reason:
        raise SceneError(f"{ocp.name!r}: {reason}")
    seq = None if sequence is None else ocp.admissible_sequence(sequence)
    if seq is not None and len(seq) > MAX_EVENTS:
        raise SceneError(too_long(len(seq)))
    return seq


def _active_sources(
    sources: Sequence[Any] | None, transcription: bool, multistart: int
) -> tuple[tuple[Any, ...], tuple[Any, ...], str]:
    """``(proposers, starters, kind)``: the given or registered sources that propose and
    those that start Newton on a sequence, less those switched off by ``transcription`` and
    ``multistart``; ``kind`` is ``"given"`` or ``"registered"``."""
    if sources is None:
        chosen, kind = registered_sources(), "registered"
        if not chosen:
            warnings.warn(
                "no candidate sources are registered (all were unregistered): the "
                "reference proposes sequences from the initial guess and the one-event "
                "sequences only",
                stacklevel=3,
            )
    else:  # a list of sources, checked by ReferenceOptions
        chosen, kind = tuple(sources), "given"
    off = {"transcription"} if not transcription else set()
    off |= {"multi-start"} if not multistart else set()
    kept = [s for s in chosen if s.name not in off]
    proposers = tuple(s for s in kept if isinstance(s, CandidateSource))
    starters = tuple(s for s in kept if isinstance(s, SequenceStarter))
    return proposers, starters, kind


def _solve(ocp: HybridOCP, run: Run, progress: Progress) -> Solution:
    """:func:`solve_reference` after its arguments are checked."""
    progress.stage("simulating the initial guess")
    u0, given = _initial_controls(ocp, run.initial)
    ev, grad, u_used = _robust_guess(ocp, u0, want_adjoint=not has_closed_form_phases(ocp))
    guess = Guess(u_used, ev, grad, given or grad is not None)
    starters = tuple(s for s in run.starters if not source_lacks(ocp, s))
    hard = math.inf if run.time_limit is None else run.t_start + run.time_limit
    book = Book(
        ocp, run.tol, run.verbose, starters, run.rtol, progress=progress,
        deadline=min(run.t_start + run.budget, hard), hard_deadline=hard,
    )  # fmt: skip
    book.seq_given = None if run.seq is None else tuple(run.seq)
    for s in run.starters:
        if s not in starters:
            book.say(f"warm start {s.name!r}: not used, {lacks_reason(source_lacks(ocp, s))}")
    book.known.append(
        Known("the initial guess", ev.cost, ev.sequence, u_used, ev, is_feasible(ocp, ev))
    )
    try:
        if run.seq is not None:
            best = solve_given(ocp, run, book, guess)
            same = [k for k in book.rivals() if k.sequence == run.seq]
            cheaper = [k for k in same if k.cost < best.cost * (1 - OPT_RTOL) - 1e-15]
        else:
            discover(ocp, run, book, guess)
            best = best_of(book)
            best, cheaper = revisit_cheaper(ocp, book, best)
            if not cheaper:
                book.check_limit()
                best = second_start(ocp, book, guess, best)
        book.check_limit()
    except Stopped as stop:
        return _stopped(ocp, run, book, stop.reason)
    except KeyboardInterrupt:
        return _stopped(ocp, run, book, "interrupted")
    status, message, cheapest, landscape = _verdict(ocp, run, book, best, cheaper)
    return finish(ocp, run, book, best, status, message, cheapest, landscape)


def _stopped(ocp: HybridOCP, run: Run, book: Book, reason: str) -> Solution:
    """The answer when the time limit or a KeyboardInterrupt stopped the search
    (``reason``): the best verified extremal found so far (of the given sequence, with
    ``sequence``), status ``not-converged``; a :class:`ConvergenceError` when there is
    none."""
    book.stopped = reason
    what = (
        f"stopped by the time limit of {run.time_limit:g} s"
        if reason == "the time limit"
        else "interrupted"
    )
    book.say(f"{what}: the best verified extremal so far")
    if run.seq is not None:
        key = tuple(run.seq)
        best = book.results.get(key) if key in book.results and book.verify(key) else None
    else:
        best = book.best_verified()
    if best is None:
        raise ConvergenceError(
            f"{what} before any extremal was found and verified"
            + (f" for the sequence {run.seq}" if run.seq is not None else "")
            + ("; --time-limit gives it more time" if reason == "the time limit" else "")
        )
    message = (
        f"{what}: the best verified extremal found so far (cost {_J(best.cost):.10g}, events "
        f"{best.sequence}); the search did not finish, so it claims nothing more"
    )
    cheaper = [k for k in book.rivals() if k.cost < best.cost * (1 - OPT_RTOL) - 1e-15]
    cheapest = None
    if cheaper:
        c = min(cheaper, key=lambda k: k.cost)
        message += f"; {c.source} costs less, {_J(c.cost):.10g} (events {c.sequence})"
        cheapest = {"source": c.source, "cost": c.cost, "sequence": c.sequence}
    return finish(ocp, run, book, best, Status.NOT_CONVERGED, message, cheapest, None)


def _verdict(
    ocp: HybridOCP, run: Run, book: Book, best: ReferenceResult, cheaper: list[Known]
) -> tuple[Status, str, dict[str, Any] | None, list[dict[str, Any]] | None]:
    """``(status, message, cheaper, landscape)`` of the best extremal (module notes)."""
    seq = run.seq
    # a given sequence's extremal claims nothing beyond its sequence: only the discovery (or
    # the search, below) can make it the optimum
    status, message = (
        (Status.SUCCESS, "")
        if seq is None
        else (Status.EXTREMAL, extremal_message(seq, run.verify, run.search))
    )
    cheapest: dict[str, Any] | None = None
    landscape = book.landscape() if run.search is not None else None
    if cheaper:
        c = min(cheaper, key=lambda k: k.cost)
        check_coalescing(ocp, c, best)
        status = Status.NOT_OPTIMAL
        message = (
            f"the extremal found costs {_J(best.cost):.10g}, but {c.source} costs "
            f"{_J(c.cost):.10g} (events {c.sequence}): this is not the optimum; try --controls "
            "with that control or --search"
        )
        cheapest = {"source": c.source, "cost": c.cost, "sequence": c.sequence}
    elif seq is not None:
        status, message, cheapest, found = _judge_given_sequence(
            ocp, seq, best, book, status, message, search=run.search, options=run.options()
        )
        if found is not None:
            landscape = found
    skipped = [k for k in book.reasons if len(k) > MAX_EVENTS]
    if skipped and status is Status.SUCCESS:
        # the discovery reached less far than usual: say so
        message = (
            f"the optimum among sequences of up to {MAX_EVENTS} events; {len(skipped)} longer "
            f"candidate(s), of up to {max(map(len, skipped))} events, were not solved "
            "(MAX_EVENTS)"
        )
    if status is Status.SUCCESS and seq is None:
        proven, text = proof(run, book, best)
        if not proven:
            status, message = Status.BEST_FOUND, f"best found, not proven: {text}"
            if skipped:  # what the search could not reach at all, said as with success
                message += (
                    f"; {len(skipped)} longer candidate(s), of up to {max(map(len, skipped))} "
                    f"events, were not solved (MAX_EVENTS = {MAX_EVENTS})"
                )
    if status in (Status.SUCCESS, Status.EXTREMAL, Status.BEST_FOUND):
        rival = event_control_rival(ocp, best)
        if rival is not None:
            status = Status.NOT_OPTIMAL
            message = (
                f"the extremal found costs {_J(best.cost):.10g}, but {rival['source']} costs "
                f"{_J(rival['cost']):.10g}: the reset's control meets its first-order conditions "
                "without being a minimum; this is not the optimum"
            )
            cheapest = rival
    bounds_violation = ocp.bound_violation(best.cell_averages()) if ocp.has_bounds else 0.0
    if bounds_violation > tolerances.FEASIBILITY:
        status = Status.INFEASIBLE
        message = (
            f"the HMP extremal violates the control bounds by {bounds_violation:.3g} (its "
            "saturated arcs do not hold); use method 'dt'"
        )
    violation = extremal_path_violation(ocp, best)
    if violation > PATH_TOL:
        status = Status.INFEASIBLE
        message = (
            f"the best HMP extremal found violates the path constraints by {violation:.3g} "
            f"(> {PATH_TOL:g}) along the judge's re-simulation: no extremal that meets them "
            "was found (the constraints may be infeasible from x0, or active on arcs the "
            "reference did not find); use method 'dt'"
        )
    touch = touch_note(book) if status in (Status.NOT_OPTIMAL, Status.INFEASIBLE) else ""
    if touch:
        # the extremal that would have answered lies outside what the reference models:
        # say so instead of returning a worse one
        raise ConvergenceError(f"{touch}; the reference's best answer otherwise: {message}")
    return status, message, cheapest, landscape


def _judge_given_sequence(
    ocp: HybridOCP,
    seq: list[str],
    best: ReferenceResult,
    book: Book,
    status: Status,
    message: str,
    *,
    search: int | None,
    options: dict[str, Any],
) -> tuple[Status, str, dict[str, Any] | None, list[dict[str, Any]] | None]:
    """The status of the extremal of a given sequence against everything else known.

    A known control with other events that is cheaper beats it (``not-optimal``). With
    ``search``, the full discovery and search run without the sequence: their optimum
    confirms it (``success``, and their landscape is returned), beats it (``not-optimal``),
    or leaves it an ``extremal`` (they found nothing they could confirm).

    Returns
    -------
    status, message, cheaper, landscape
        ``cheaper`` for ``info["cheaper"]`` (or None); ``landscape`` of the search (or None).
    """
    bound = best.cost * (1 - OPT_RTOL) - 1e-15
    if search is None:
        beaten = [k for k in book.rivals() if k.sequence != seq and k.cost < bound]
        if not beaten:
            return status, message, None, None
        c = min(beaten, key=lambda k: k.cost)
        return (
            Status.NOT_OPTIMAL,
            f"the extremal of the given sequence {seq} costs {_J(best.cost):.10g}, but {c.source} "
            f"costs {_J(c.cost):.10g} with the events {c.sequence}: a cheaper control is known "
            "(without --sequence, or with --search K, the reference looks for the optimum)",
            {"source": c.source, "cost": c.cost, "sequence": c.sequence},
            None,
        )
    book.say(f"search: the discovery and the search of up to {search} events, for {seq}")
    book.progress.stage(f"the discovery and search of up to {search} events, without the sequence")
    try:
        full = solve_reference(ocp, search=search, **options)
    except HybridocError as exc:
        note = f"; the search without it failed: {' '.join(str(exc).split())}"
        return status, message + note, None, None
    landscape = full.info.get("landscape")
    # the cheapest the search met: its extremal, or a control cheaper still (not-optimal)
    low = {"source": "the search", "cost": full.cost, "sequence": full.sequence}
    other = full.info.get("cheaper")
    if other is not None and other["cost"] < low["cost"]:
        low = dict(other)
    if low["cost"] < bound:
        return (
            Status.NOT_OPTIMAL,
            f"the extremal of the given sequence {seq} costs {_J(best.cost):.10g}, but the "
            f"discovery and search found {low['cost']:.10g} with the events "
            f"{low['sequence']} ({low['source']})",
            low,
            landscape,
        )
    if full.status is Status.SUCCESS:
        return (
            Status.SUCCESS,
            f"nothing cheaper in the discovery and the search of up to {search} events: the "
            "optimum as far as they reach",
            None,
            landscape,
        )
    note = f"; the search found nothing cheaper but could not confirm it ({full.status.value})"
    return status, message + note, None, landscape


METHOD = Method(
    "reference",
    "optimal control by shooting on the hybrid minimum principle (the ground truth)",
    run=solve_reference,
    options=ReferenceOptions,
    tolerance=1e-9,
    supports=reference_supports,
    summary_lines=summary_lines,
    features=frozenset({"terminal", "free_horizon"}),
    representation="continuous",
)
"""The method ``"reference"`` (:mod:`hybridoc.methods`)."""
