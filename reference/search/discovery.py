"""The reference's discovery of event sequences (part of :mod:`hybridoc.reference.search`).

The initial guess's candidates, the candidate sources' proposals, the enumeration and the
sequences of re-simulations (:func:`discover`); the known controls that are cheaper
(:func:`revisit_cheaper`); the second starts of Newton that the proof needs
(:func:`second_start`); and a given sequence's extremal (:func:`solve_given`).
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.errors import ConvergenceError, HybridocError, SceneError
from hybridoc.ocp import HybridOCP
from hybridoc.reference.candidates import guess_candidates, guess_times, lower_bound
from hybridoc.reference.options import MAX_EVENTS
from hybridoc.reference.result import ReferenceResult
from hybridoc.reference.search.book import (
    KNOWN_STARTS,
    MAX_PROOF_DEPTH,
    OPT_RTOL,
    Book,
    Guess,
    Known,
    Run,
    exhaustive_length,
    is_convex,
    is_feasible,
    judge_adjoint,
    lacks_reason,
    n_events,
    note_source,
    source_lacks,
)
from hybridoc.reference.search.claims import PROOF_STARTS, check_simultaneous, touch_reason
from hybridoc.reference.search.enumeration import run_enumeration, start_screens
from hybridoc.reference.shooting import has_closed_form_phases
from hybridoc.reference.sources import Proposal, SourceContext

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.reference.search.enumeration import _EarlyScreens


def solve_given(ocp: HybridOCP, run: Run, book: Book, guess: Guess) -> ReferenceResult:
    """The extremal of the given sequence, verified unless ``verify=False``."""
    seq = run.seq
    assert seq is not None
    ev = guess.evaluation
    book.attempt(
        seq, guess_times(ocp, seq, ev), guess.controls, "given", estimate=guess.estimate,
        grad=guess.grad, guess_ev=ev,
    )  # fmt: skip
    key = tuple(seq)
    best = book.results.get(key)
    touch = touch_reason(book.reasons.get(key))
    if best is None and touch:
        raise ConvergenceError(f"no HMP extremal with the sequence {seq}: {touch}; use method 'dt'")
    if best is None or (run.verify and not book.verify(key)):
        found, tried = None, _discovery_may_find(ocp, seq, book.reasons.get(key))
        if tried:
            found = _given_by_discovery(ocp, run, book, guess)
        nor = "; nor did the discovery without the sequence find one" if tried else ""
        if found is not None:
            best = found
        elif best is None:
            why = str(book.reasons.get(key)).removeprefix("pruned: ")
            raise ConvergenceError(
                f"no HMP extremal with the sequence {seq}: {why}{nor}. "
                "hint: start from a control with these events (--controls) or check that the "
                "sequence is feasible"
            )
        else:
            raise ConvergenceError(
                f"the extremal of {seq} does not re-simulate to its own events: "
                f"{book.verdicts[key][1]}{nor + ' that does' if nor else ''}"
            )
    # the only optimality claim of a given sequence is within it: a cheaper control with the
    # same events means Newton stopped at a worse stationary point
    check_simultaneous(book, best)
    return best


def _discovery_may_find(ocp: HybridOCP, seq: list[str], why: str | None) -> bool:
    """Whether the discovery may find the extremal of a given sequence that Newton from the
    guess did not: not on a disc scene (its sequences start from the NLP over the sequence
    as well), not for a sequence no control has (an infinite lower bound), nor where Newton
    converged and the integration could not reach ``rtol`` (refine's reasons name it;
    every other start meets the same limit)."""
    if has_closed_form_phases(ocp) or math.isinf(lower_bound(ocp, seq)):
        return False
    return why is None or ("(rtol " not in why and "for rtol " not in why)


def _given_by_discovery(
    ocp: HybridOCP, run: Run, book: Book, guess: Guess
) -> ReferenceResult | None:
    """The given sequence's extremal as the discovery finds it, where Newton from the guess
    (and the known controls) found none or one that does not re-simulate to its own events:
    coulomb-block's ``['reverse']`` from the guess converges to a worse extremal (cost 1.41)
    whose re-simulation chatters between the two friction guards, while the multi-start's
    control starts the optimum (0.639); friction-patch-free-time's ``['enter-rough']`` is
    found only from the costates of the no-event extremal cut at its re-simulated event.

    The discovery (the sources, the enumeration, the sequences of re-simulations) runs on a
    book of its own, so that the given sequence's answer stays about that sequence (an
    ill-posed cheaper sequence met on the way does not turn it into an error); its verified
    extremal of the sequence, if any, moves into ``book``, and so do the controls it met
    (the rivals that can make the answer ``not-optimal``) and the sources it ran."""
    key = tuple(run.seq or ())
    book.say(f"{list(key)}: not found from the guess; the discovery without the sequence")
    book.progress.stage("the discovery without the given sequence")
    sub = Book(
        ocp, run.tol, run.verbose, book.starters, run.rtol, progress=book.progress,
        deadline=book.deadline, hard_deadline=book.hard_deadline,
    )  # fmt: skip
    sub.known = list(book.known)
    discover(ocp, run, sub, guess)
    book.verify_time += sub.verify_time
    book.known = sub.known
    book.sources += sub.sources
    res = sub.results.get(key)
    if res is None or not sub.verify(key):
        return None
    book.results[key] = sub.results[key]
    book.verdicts[key] = sub.verdicts[key]
    book.reasons.pop(key, None)
    book.origins[key] = f"the discovery ({sub.origins.get(key, '')})"
    book.times[key] = book.times.get(key, 0.0) + sub.times.get(key, 0.0)
    return book.results[key]


def discover(ocp: HybridOCP, run: Run, book: Book, guess: Guess) -> None:
    """The discovery: the guess's candidates, the sources' proposals, the one-event
    sequences (or the ``search``), and the sequences of re-simulations."""
    ev = guess.evaluation
    t0 = time.perf_counter()
    if len(ev.events) > MAX_EVENTS + 1:
        # all its neighbours are too long as well: only the empty sequence is left, and
        # building them would cost O(K^2) for nothing
        book.skip_long(tuple(ev.sequence), "initial guess")
        cands = [[]]
    else:
        cands = guess_candidates(ocp, ev)
    early = start_screens(ocp, run, book, guess, cands)
    try:
        _discover_with(ocp, run, book, guess, cands, t0, early)
    finally:
        if early is not None:
            early.close()


def _discover_with(
    ocp: HybridOCP,
    run: Run,
    book: Book,
    guess: Guess,
    cands: list[list[tuple[str, float]]],
    t0: float,
    early: _EarlyScreens | None,
) -> None:
    """:func:`discover` once the guess's candidates are known (and the search's screens
    started, ``early``)."""
    ev = guess.evaluation
    book.progress.stage(
        f"discovering sequences: {len(cands)} from the initial guess ({n_events(len(ev.events))})"
    )
    for i, cand in enumerate(cands):
        if i and book.left() <= 0:
            book.budget_stopped = True
            book.say(f"initial guess: {len(cands) - i} candidate(s) left, the budget is spent")
            break
        key = [n for n, _ in cand]
        book.attempt(
            key, np.array([t for _, t in cand]), guess.controls, "initial guess",
            estimate=guess.estimate and key == ev.sequence, grad=guess.grad, guess_ev=ev,
        )  # fmt: skip
    note_source(book, "initial guess", "reference", len(cands), t0)
    for source in run.proposers:
        lacking = source_lacks(ocp, source)
        if lacking:
            book.say(f"source {source.name!r}: not run, {lacks_reason(lacking)}")
            note_source(
                book, source.name, run.kind, 0, time.perf_counter(),
                skipped=f"not run: {lacks_reason(lacking)}",
            )  # fmt: skip
            continue
        if book.left() <= 0:
            book.budget_stopped = True
            book.say(f"source {source.name!r}: not run, the budget of {run.budget:g} s is spent")
            note_source(book, source.name, run.kind, 0, time.perf_counter(), skipped=True)
            continue
        _run_source(ocp, run, book, guess, source)
    # every sequence of up to the scene's depth (or the search's) too, by lower bound: a
    # guess that never comes near a guard (a cart at rest before a wall) proposes no event
    # at all, and neither may the sources reach a sequence that starts with a bounce
    run_enumeration(ocp, run, book, guess, early)
    book.best_verified()
    book.follow_resimulations()
    best = book.best_verified()
    if (
        best is not None
        and len(best.sequence) + 1 > book.depth
        and book.depth < MAX_PROOF_DEPTH
        and exhaustive_length(book) == book.depth
        and not book.budget_stopped
    ):
        # a re-simulation found a best as long as the enumeration: the proof needs one
        # length more (friction-patch-free-time's optimum comes from the no-event extremal)
        run_enumeration(ocp, run, book, guess)
        book.best_verified()
        book.follow_resimulations()


def _run_source(ocp: HybridOCP, run: Run, book: Book, guess: Guess, source: Any) -> None:
    """Ask one candidate source for proposals and take them, in order."""
    t0 = time.perf_counter()
    context = SourceContext(
        controls=guess.controls, evaluation=guess.evaluation, progress=book.progress,
        multistart=run.multistart, max_events=MAX_EVENTS,
        best_cost=min((k.cost for k in book.rivals()), default=math.inf), say=book.say,
        budget_s=book.left(),
    )  # fmt: skip
    try:
        proposals = list(source.propose(ocp, context))
    except HybridocError as exc:
        book.say(f"source {source.name!r} failed: {exc}")
        note_source(book, source.name, run.kind, 0, t0, failed=str(exc))
        return
    for p in proposals:
        _take(ocp, book, guess, p)
    note_source(book, source.name, run.kind, len(proposals), t0)


def _take(ocp: HybridOCP, book: Book, guess: Guess, p: Proposal) -> None:
    """One proposal: a known control (with its cost) and/or a sequence to solve."""
    if not isinstance(p, Proposal):
        raise SceneError(f"a candidate source returned {type(p).__name__}, not a Proposal")
    seq = None
    if p.sequence is not None:
        seq = ocp.check_sequence(list(p.sequence))
    elif p.evaluation is not None:
        seq = list(p.evaluation.sequence)
    cost = p.known_cost()
    if p.known and p.controls is not None and cost is not None and seq is not None:
        label = p.label or f"the source {p.source!r}"
        controls = np.asarray(p.controls, dtype=float)
        feasible = is_feasible(ocp, p.evaluation)
        if (
            feasible
            and ocp.path is not None
            and p.evaluation is not None
            and cost != float(p.evaluation.cost)
        ):
            # the cost is another control's than the one judged (the transcription's
            # continuous u(t), judged as its grid control): between its nodes it may break
            # the path constraints, so it bounds nothing
            feasible = False
        book.known.append(Known(label, cost, seq, controls, p.evaluation, feasible))
    if not p.solve or seq is None:
        return
    if not ocp.sequence_admissible(seq):
        # a source's sequence that leaves a mode by a transition of another mode, or ends
        # outside the required final mode (its control is still a known control above; its
        # sequence has no admissible extremal)
        why = (
            "is not mode-feasible"
            if not ocp.sequence_feasible(seq)
            else f"does not end in the final mode {ocp.final_mode!r}"
        )
        book.say(f"{p.source}: the sequence {seq} {why}: not solved")
        return
    key = tuple(seq)
    own = p.controls is not None  # the proposal's own control starts Newton
    ev = p.evaluation if p.evaluation is not None else guess.evaluation
    times = None if p.event_times is None else np.asarray(p.event_times, dtype=float).ravel()
    if times is not None and times.size != len(seq):
        # event times of another sequence (a source's slip): the times must match the
        # sequence, or the shooting's unknowns do not fit
        book.say(
            f"{p.source}: {times.size} event times for the {len(seq)}-event sequence {seq}: "
            "guessed from its evaluation instead"
        )
        times = None
    if times is None:
        times = guess_times(ocp, seq, ev)
    # a sequence that failed before gets another try from the proposal's own control, and
    # so does one whose extremal costs more than the proposal's control with its events
    # (Newton stopped at a worse stationary point)
    old = book.results.get(key)
    cheaper = old is not None and own and cost is not None and cost < old.cost * (1 - OPT_RTOL)
    retry = (key in book.reasons and (p.retry or own) and key not in book.pruned) or cheaper
    if (key in book.results or key in book.reasons) and not retry:
        return  # solved or failed before: nothing new to try
    book.attempt(
        seq, times, np.asarray(p.controls, dtype=float) if own else guess.controls, p.source,
        estimate=own, grad=judge_adjoint(ocp, p.controls) if own else None, guess_ev=ev,
        retry=retry, warm_start=p.warm_start,
    )  # fmt: skip


def best_of(book: Book) -> ReferenceResult:
    """The cheapest verified extremal; an error when there is none."""
    best = book.best_verified()
    check_simultaneous(book, best)
    if best is None:
        lines = [f"{list(k)}: {v}" for k, v in book.reasons.items()]
        lines += [f"{list(k)}: {msg}" for k, (ok, msg) in book.verdicts.items() if not ok]
        # path constraints that no control met satisfies: say so first, not only that
        # Newton failed
        infeasible = (
            "infeasible as far as the reference can tell: no control it met satisfies the "
            "path constraints and no HMP extremal that meets them was found; "
            if book.ocp.path is not None and not book.rivals()
            else ""
        )
        raise ConvergenceError(
            infeasible
            + "no event sequence satisfies the HMP conditions and re-simulates to its own events"
            + (" (" + "; ".join(lines) + ")" if lines else "")
            + ". hint: start from another initial guess (e.g. a solver's solution) or give "
            "an explicit --sequence"
        )
    return best


def revisit_cheaper(
    ocp: HybridOCP, book: Book, best: ReferenceResult
) -> tuple[ReferenceResult, list[Known]]:
    """Trust: no known control may be cheaper. The sequences of cheaper ones are solved
    again from them; returns the best extremal and the known controls still cheaper."""
    for k in sorted(book.rivals(), key=lambda k: k.cost):
        if k.cost >= best.cost * (1 - OPT_RTOL) - 1e-15:
            break
        if k.evaluation is None:
            continue
        book.attempt(
            k.sequence, guess_times(ocp, k.sequence, k.evaluation), k.controls,
            f"cheaper {k.source}", estimate=True, grad=judge_adjoint(ocp, k.controls),
            guess_ev=k.evaluation, retry=True,
        )  # fmt: skip
        best = book.best_verified() or best
    cheaper = [k for k in book.rivals() if k.cost < best.cost * (1 - OPT_RTOL) - 1e-15]
    return best, cheaper


def second_start(
    ocp: HybridOCP, book: Book, guess: Guess, best: ReferenceResult
) -> ReferenceResult:
    """The best sequence solved from other starts until :data:`PROOF_STARTS` of them reach
    its extremal (each start once): the known controls with its events (their costate
    estimates), then on a disc scene the NLP from evenly spread event times and no control,
    elsewhere the warm starts and the zero costate from the guess (unless the enumeration's
    screen already started it so). A disc scene's no-event extremal needs none
    (:func:`is_convex`). Returns the cheapest verified extremal then (a start may find a
    cheaper one)."""
    key = tuple(best.sequence)
    if book.agreeing_starts(key) >= PROOF_STARTS or is_convex(ocp, key):
        return best
    same = [k for k in book.known if tuple(k.sequence) == key and k.evaluation is not None]
    tries: list[tuple[Any, ...]] = [
        (guess_times(ocp, key, k.evaluation), k.controls, f"second start ({k.source})", True,
         judge_adjoint(ocp, k.controls), k.evaluation)
        for k in sorted(same, key=lambda k: k.cost)[:KNOWN_STARTS]
    ]  # fmt: skip
    if has_closed_form_phases(ocp):
        tries.append(
            (guess_times(ocp, key, None), np.zeros_like(guess.controls),
             "second start (the NLP from evenly spread event times)", False, None, None)
        )  # fmt: skip
    elif key not in book.screened:
        # (the enumeration's screen started it so already)
        tries.append(
            (guess_times(ocp, key, guess.evaluation), guess.controls,
             "second start (the warm starts from the guess)", False, None, guess.evaluation)
        )  # fmt: skip
    for times, u, origin, estimate, grad, ev in tries:
        if book.agreeing_starts(key) >= PROOF_STARTS:
            break
        book.attempt(
            key, times, u, origin, estimate=estimate, grad=grad, guess_ev=ev, retry=True,
            fallback=False,
        )  # fmt: skip
    found = book.best_verified()
    return found if found is not None and found.cost < best.cost else best
