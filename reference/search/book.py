"""The reference's search bookkeeping (part of :mod:`hybridoc.reference.search`).

What one :func:`~hybridoc.reference.solve_reference` call tried and knows (:class:`Book`),
its checked arguments (:class:`Run`), the initial guess as it uses it (:class:`Guess`), the
controls met (:class:`Known`) and whether they are feasible (:func:`is_feasible`,
:func:`path_violation`), and the limits the search is held to.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hybridoc import tolerances
from hybridoc.errors import ConvergenceError, EvaluationError, HybridocError
from hybridoc.evaluation import Evaluation
from hybridoc.evaluator import evaluate, gradient
from hybridoc.methods import FEATURES, problem_features
from hybridoc.ocp import HybridOCP
from hybridoc.progress import NullProgress, Progress
from hybridoc.reference.candidates import guess_times, lower_bound
from hybridoc.reference.options import MAX_EVENTS, MAX_SEARCH
from hybridoc.reference.result import ReferenceResult
from hybridoc.reference.sequence import (
    COST_RTOL,
    TERMINAL_TOL,
    judged_reference,
    judged_violation,
    solve_sequence,
)
from hybridoc.reference.shooting import has_closed_form_phases
from hybridoc.reference.sources import PhaseCostates
from hybridoc.reference.units import cost_shown as _J

OPT_RTOL = tolerances.CHEAPER
"""A known control cheaper than an extremal by more than this (relative) makes the extremal
not optimal (the table's ``cheaper``)."""
KNOWN_STARTS = 2
"""A sequence whose solve failed is started again from at most this many known controls
with its events (the cheapest)."""
PATH_TOL = tolerances.FEASIBILITY
"""The largest violation of the path constraints a control may show and still count as
feasible (the judge's :attr:`~hybridoc.Evaluation.feasible`): a known control beyond it
bounds nothing, an extremal beyond it is ``infeasible``."""
PATH_SAMPLES = 8
"""Times per grid cell at which :func:`path_violation` checks the path constraints besides
the judge's own."""
# why a sequence with an infinite lower bound (candidates.lower_bound) is not solved,
# wherever it comes from
IMPOSSIBLE = (
    "pruned: no control has these events (two bodies that cannot move themselves never meet)"
)


START_RTOL = 1e-6
"""Two starts reached the same extremal when their costs agree to this much relative (the
integration's refinement moves a cost by about ``rtol``; distinct stationary points of one
sequence differ by far more)."""
MAX_PROOF_DEPTH = MAX_SEARCH
"""The longest sequences the default enumeration extends to so that it covers every
sequence of up to one event more than the best extremal found (the budget stops it)."""


class Stopped(Exception):
    """The time limit or a KeyboardInterrupt stopped the search (``reason``)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def n_events(k: int) -> str:
    """``"1 event"``, ``"3 events"``: for messages."""
    return f"{k} event{'' if k == 1 else 's'}"


@dataclass
class Known:
    """A control met during the search, with its true (judged) cost. Only a ``feasible``
    one (terminal constraints met, a final time within its bounds) bounds the optimum; any
    may start Newton on its events."""

    source: str
    cost: float
    sequence: list[str]
    controls: np.ndarray
    evaluation: Evaluation | None = None
    feasible: bool = True


def path_violation(
    ocp: HybridOCP, ev: Evaluation, control: Any = None, samples: int = PATH_SAMPLES
) -> float:
    """The largest violation of ``ocp``'s path constraints along a judged trajectory: the
    judge's own (grid and event times) and ``samples`` more times inside every grid cell
    (0 without path constraints).

    Parameters
    ----------
    ocp
        The problem.
    ev
        The judge's evaluation of the control (its trajectory is sampled,
        :meth:`~hybridoc.Evaluation.sample`).
    control
        ``u(t)`` of a continuous control; ``None``: ``ev``'s grid controls, constant over
        each cell (a control that meets the constraints at the grid times only may break
        them in between, and its cost then bounds nothing).
    samples
        Times per grid cell, at ``(i + 1/2) / samples`` of it.
    """
    if ocp.path is None:
        return 0.0
    grid = ev.ocp.time_grid()
    frac = (np.arange(samples) + 0.5) / samples
    cells = np.repeat(np.arange(grid.size - 1), samples)
    t = grid[cells] + np.tile(frac, grid.size - 1) * np.diff(grid)[cells]
    states = ev.sample(t)
    if control is None:
        U = np.asarray(ev.controls, dtype=float)[cells]
    else:
        U = np.array([np.asarray(control(float(tt)), dtype=float).ravel() for tt in t])
    c = np.asarray(ocp.path.map(t.size)(states.T, U.T), dtype=float)
    return max(float(ev.path_violation), float(np.max(-c, initial=0.0)))


def is_feasible(ocp: HybridOCP, ev: Evaluation | None) -> bool:
    """Whether a judged control is feasible for ``ocp``'s path constraints (between the grid
    times too, :func:`path_violation`), required final mode, terminal constraints and
    final-time bounds (always, without them): an infeasible control's cost bounds
    nothing."""
    if ocp.path is not None:
        if ev is None:
            return False
        try:
            if path_violation(ocp, ev) > PATH_TOL:
                return False
        except HybridocError:
            return False
    if ocp.final_mode is not None:
        if ev is None or ev.final_mode != ocp.final_mode:
            return False
    if not (ocp.has_terminal_constraints or ocp.free_horizon):
        return True
    if ev is None:
        return False
    if ocp.free_horizon:
        lo, hi = ocp.horizon_bounds  # type: ignore[misc]
        T = float(ev.ocp.horizon)
        if not lo <= T <= hi:
            return False
    return judged_violation(ocp, ev) <= TERMINAL_TOL


@dataclass(frozen=True)
class _Start:
    """What :func:`~hybridoc.reference.sequence.solve_sequence` starts a sequence from,
    besides what a book holds fixed (the problem, ``tol``, ``rtol``, the warm-start
    sources): the control's and the event times' bits, whether Newton starts from the
    control's adjoint costate (which the judge computes from the control, so its presence
    is all that counts), and the trajectory and warm start passed (by identity: kept alive
    here, so that an identity is never reused)."""

    controls: bytes
    times: bytes
    estimate: bool
    adjoint: bool
    evaluation: Any
    warm_start: Any

    @staticmethod
    def of(
        controls: Any, times: Any, estimate: bool, grad: Any, evaluation: Any, warm_start: Any
    ) -> _Start:
        return _Start(
            np.ascontiguousarray(controls, dtype=float).tobytes(),
            np.ascontiguousarray(times, dtype=float).tobytes(),
            bool(estimate), grad is not None and grad is not False, evaluation, warm_start,
        )  # fmt: skip

    def same(self, other: _Start) -> bool:
        return (
            self.controls == other.controls
            and self.times == other.times
            and self.estimate == other.estimate
            and self.adjoint == other.adjoint
            and self.evaluation is other.evaluation
            and self.warm_start is other.warm_start
        )


def _adjoint_used(ocp: HybridOCP) -> bool:
    """Whether a costate estimate reads the judge's adjoint (generic problems; a disc scene
    fits its phase controls instead, :func:`judge_adjoint` gives ``None``)."""
    return not has_closed_form_phases(ocp)


@dataclass
class Book:
    """Everything one reference solve tried."""

    ocp: HybridOCP
    tol: float
    verbose: bool
    starters: tuple[Any, ...] = ()
    rtol: float = COST_RTOL
    results: dict[tuple[str, ...], ReferenceResult] = field(default_factory=dict)
    reasons: dict[tuple[str, ...], str] = field(default_factory=dict)
    verdicts: dict[tuple[str, ...], tuple[bool, str]] = field(default_factory=dict)
    times: dict[tuple[str, ...], float] = field(default_factory=dict)
    origins: dict[tuple[str, ...], str] = field(default_factory=dict)
    known: list[Known] = field(default_factory=list)
    resimulated: dict[tuple[str, ...], Evaluation] = field(default_factory=dict)
    verify_time: float = 0.0
    progress: Progress = field(default_factory=NullProgress)
    sources: list[dict[str, Any]] = field(default_factory=list)
    deadline: float = math.inf  # perf_counter() time at which the budget is spent
    pruned: set[tuple[str, ...]] = field(default_factory=set)
    proposed: set[tuple[str, ...]] = field(default_factory=set)
    depth: int = 0  # the enumeration's target length
    exhaustive: int | None = None  # the longest length the enumeration went through
    # the feasible sequences of each length the enumeration went through
    enumerated: list[list[tuple[str, ...]]] = field(default_factory=list)
    budget_stopped: bool = False
    # the known controls (by id) a failed sequence was started from (from_known)
    known_tried: dict[tuple[str, ...], set[int]] = field(default_factory=dict)
    # (extremal, re-simulated sequence) pairs whose neighbour start was tried
    neighbours_tried: set[tuple[tuple[str, ...], tuple[str, ...]]] = field(default_factory=set)
    # the starts each sequence was solved from (_Start): the same start again gives the
    # same outcome
    starts: dict[tuple[str, ...], list[_Start]] = field(default_factory=dict)
    # the cost of the extremal every converged start of a sequence reached
    start_costs: dict[tuple[str, ...], list[float]] = field(default_factory=dict)
    # perf_counter() time of the hard time limit (time_limit), and what stopped the search
    hard_deadline: float = math.inf
    stopped: str = ""
    # the sequences the enumeration screened from the guess (_search_one)
    screened: set[tuple[str, ...]] = field(default_factory=set)
    # the given sequence (sequence=), whose verification error is the answer
    seq_given: tuple[str, ...] | None = None

    def check_limit(self) -> None:
        """Raise :class:`Stopped` once the hard time limit is reached."""
        if time.perf_counter() >= self.hard_deadline:
            raise Stopped("the time limit")

    def agreeing_starts(self, key: tuple[str, ...]) -> int:
        """How many converged starts of ``key`` reached its extremal (the same cost, to
        :data:`START_RTOL`)."""
        res = self.results.get(key)
        if res is None:
            return 0
        tol = START_RTOL * max(abs(res.cost), 1e-300)
        return sum(abs(c - res.cost) <= tol for c in self.start_costs.get(key, ()))

    def tried(self, key: tuple[str, ...], start: _Start) -> bool:
        """Whether ``key`` was already solved from ``start``."""
        return any(start.same(s) for s in self.starts.get(key, ()))

    def left(self) -> float:
        """Seconds of the budget left (0 when spent)."""
        return max(0.0, self.deadline - time.perf_counter())

    def best_bound(self) -> float:
        """The cheapest verified extremal or known control: a sequence whose lower bound
        is not below it cannot hold a cheaper optimum."""
        verified = [r.cost for k, r in self.results.items() if self.verdicts.get(k, (False,))[0]]
        return min([*verified, *(k.cost for k in self.rivals())], default=math.inf)

    def rivals(self) -> list[Known]:
        """The known controls that bound the optimum (the feasible ones)."""
        return [k for k in self.known if k.feasible]

    def say(self, text: str) -> None:
        if self.verbose:
            print(f"reference: {text}", file=sys.stderr)

    def skip_long(self, key: tuple[str, ...], origin: str) -> bool:
        """Record a sequence beyond :data:`MAX_EVENTS` as not attempted."""
        if len(key) <= MAX_EVENTS:
            return False
        if key not in self.reasons:
            self.reasons[key] = too_long(len(key))
            self.origins.setdefault(key, origin)
            self.times.setdefault(key, 0.0)
            self.say(f"a {len(key)}-event sequence ({origin}): not attempted (MAX_EVENTS)")
        return True

    def attempt(
        self,
        sequence: Sequence[str],
        gamma0: np.ndarray,
        u_guess: np.ndarray,
        origin: str,
        *,
        estimate: bool,
        grad: Any = None,
        guess_ev: Evaluation | None = None,
        retry: bool = False,
        warm_start: PhaseCostates | None = None,
        fallback: bool = True,
    ) -> ReferenceResult | None:
        """Solve one sequence (once; again with ``retry`` when it failed before or a better
        start is at hand) and keep the cheaper result; where it fails (and ``fallback``),
        start it again from the known controls with these events (:meth:`from_known`)."""
        key = tuple(sequence)
        self.proposed.add(key)
        if key in self.results and not retry:
            return self.results[key]
        if self.skip_long(key, origin) or (key in self.reasons and not retry):
            return None
        if key not in self.results and math.isinf(lower_bound(self.ocp, key)):
            # no control has these events (the guess's candidates drop events, so a passive
            # body may be asked to move first): Newton, the NLP and the transcription's
            # start would only fail, at up to a second each
            self.reasons[key] = IMPOSSIBLE
            self.pruned.add(key)
            self.origins.setdefault(key, origin)
            self.times.setdefault(key, 0.0)
            self.say(f"{list(key)} ({origin}): {IMPOSSIBLE}")
            return None
        if np.size(gamma0) != len(key):
            self.say(f"{list(key)} ({origin}): event times of another length, guessed anew")
            gamma0 = guess_times(self.ocp, key, guess_ev)
        start = _Start.of(u_guess, gamma0, estimate, grad, guess_ev, warm_start)
        self.check_limit()
        if self.tried(key, start):
            # solve_sequence is a function of its start: the known control of the guess is
            # the guess (friction-patch-free-time: its failed starts, 0.4 s, were repeated)
            self.say(f"{list(key)} ({origin}): the same start as before, not solved again")
            return self.results.get(key)
        self.starts.setdefault(key, []).append(start)
        self.progress.stage(f"shooting on a {len(key)}-event sequence ({origin})")
        t0 = time.perf_counter()
        try:
            res, why = solve_sequence(
                self.ocp, list(key), gamma0, u_guess, estimate=estimate, grad=grad,
                guess_ev=guess_ev, starters=self.starters, tol=self.tol, verbose=self.verbose,
                warm_start=warm_start, rtol=self.rtol,
            )  # fmt: skip
        except (ConvergenceError, EvaluationError, np.linalg.LinAlgError) as exc:
            res, why = None, str(exc)
        self.times[key] = self.times.get(key, 0.0) + time.perf_counter() - t0
        self.origins.setdefault(key, origin)
        if res is not None:
            self.start_costs.setdefault(key, []).extend(res.start_costs or (float(res.cost),))
        old = self.results.get(key)
        if res is not None and (old is None or res.cost < old.cost - 1e-12 * abs(old.cost)):
            self.results[key] = res
            self.verdicts.pop(key, None)
            self.reasons.pop(key, None)
        elif res is None and old is None:
            self.reasons[key] = why
        self.say(f"{list(key)} ({origin}): " + (f"cost {_J(res.cost):.12g}" if res else why))
        if key not in self.results and fallback:
            return self.from_known(key)
        return self.results.get(key)

    def from_known(self, key: tuple[str, ...]) -> ReferenceResult | None:
        """A sequence whose solve failed, started again from the known controls whose
        judged events are that sequence (the multi-start's, the transcription's), cheapest
        first, at most :data:`KNOWN_STARTS` of them, each once."""
        tried = self.known_tried.setdefault(key, set())
        same = [k for k in self.known if tuple(k.sequence) == key and k.evaluation is not None]
        for k in sorted(same, key=lambda k: k.cost)[:KNOWN_STARTS]:
            if id(k) in tried:
                continue
            tried.add(id(k))
            times = guess_times(self.ocp, key, k.evaluation)
            if _adjoint_used(self.ocp) and self.tried(
                key, _Start.of(k.controls, times, True, True, k.evaluation, None)
            ):
                continue  # its adjoint, then the same solve: nothing new
            res = self.attempt(
                key, times, k.controls, f"the known control of {k.source}", estimate=True,
                grad=judge_adjoint(self.ocp, k.controls), guess_ev=k.evaluation, retry=True,
                fallback=False,
            )  # fmt: skip
            if res is not None:
                return res
        return self.results.get(key)

    def verify(self, key: tuple[str, ...]) -> bool:
        if key not in self.verdicts:
            self.progress.stage(f"re-simulating the {len(key)}-event extremal with the judge")
            t0 = time.perf_counter()
            try:
                res, ok, sim, msg = judged_reference(
                    self.results[key], rtol=self.rtol, tol=self.tol, verbose=self.verbose
                )
            except ConvergenceError as exc:
                if self.seq_given == key:
                    raise  # the given sequence's own answer: the error is the answer
                # an extremal the judge cannot confirm is no answer; the search goes on
                res, ok, sim, msg = self.results[key], False, None, str(exc)
            self.results[key] = res  # refined where the judge asked for it
            self.verify_time += time.perf_counter() - t0
            self.verdicts[key] = (ok, msg)
            if not ok and sim is not None:
                self.resimulated[key] = sim
            self.say(f"verify {list(key)}: {'ok' if ok else msg}")
        return self.verdicts[key][0]

    def follow_resimulations(self, rounds: int = 3) -> None:
        """A re-simulation with other events proposes its own sequence (started from the
        extremal's control, whose trajectory has those events)."""
        # terminal constraints or a free final time: the extremal's own costates, cut at
        # the re-simulated events, start the new sequence (the control's adjoint knows
        # nothing of the terminal multipliers), also where it failed from other starts
        neighbour = self.ocp.has_terminal_constraints or self.ocp.free_horizon
        for _ in range(rounds):
            new = False
            for key, sim in list(self.resimulated.items()):
                seq = sim.sequence
                if tuple(seq) in self.results:
                    continue
                pair = (key, tuple(seq))
                failed_before = tuple(seq) in self.reasons
                if failed_before and (not neighbour or pair in self.neighbours_tried):
                    continue
                self.neighbours_tried.add(pair)
                res = self.results[key]
                u = res.cell_averages()
                try:
                    ev = evaluate(res.ocp, u)
                except HybridocError:
                    continue
                origin = f"re-simulation of {list(key)}"
                times = guess_times(self.ocp, ev.sequence, ev)
                warm = None
                if neighbour:
                    own = np.array([e.time for e in sim.events])
                    warm = res.phase_costates_at(own)
                self.attempt(
                    ev.sequence, times, u, origin, estimate=True, guess_ev=ev,
                    warm_start=warm, retry=failed_before,
                )  # fmt: skip
                new = True
            self.best_verified()
            if not new:
                return

    def best_verified(self) -> ReferenceResult | None:
        for res in sorted(self.results.values(), key=lambda r: r.cost):
            if self.verify(tuple(res.sequence)):
                return res
        return None

    def landscape(self) -> list[dict[str, Any]]:
        rows = []
        keys = list(dict.fromkeys([*self.results, *self.reasons]))
        for key in keys:
            res = self.results.get(key)
            if res is None:
                why = self.reasons.get(key, "")
                verdict = why if key in self.pruned else "failed: " + why
            elif key in self.verdicts:
                ok, msg = self.verdicts[key]
                verdict = "verified" if ok else f"not verified: {msg}"
            else:
                verdict = "not verified (not needed)"
            rows.append(
                {
                    "sequence": list(key),
                    "cost": None if res is None else float(res.cost),
                    "verdict": verdict,
                    "origin": self.origins.get(key, ""),
                    "time_s": float(self.times.get(key, 0.0)),
                }
            )
        rows.sort(key=lambda r: (r["cost"] is None, r["cost"] or 0.0, len(r["sequence"])))
        return rows


@dataclass(frozen=True)
class Run:
    """The checked arguments of one :func:`solve_reference` call."""

    seq: list[str] | None
    initial: Any
    search: int | None
    budget: float
    verbose: bool
    tol: float
    rtol: float
    verify: bool
    transcription: bool
    multistart: int
    sources: Sequence[Any] | None
    proposers: tuple[Any, ...]
    starters: tuple[Any, ...]
    kind: str
    t_start: float
    time_limit: float | None = None

    def options(self) -> dict[str, Any]:
        """The options of a second run of the same problem (the search without a given
        sequence)."""
        return dict(
            initial=self.initial, verbose=self.verbose, tol=self.tol, rtol=self.rtol,
            budget=self.budget,
            # what is left of the limit: the second run is part of this one
            time_limit=None if self.time_limit is None else max(
                1e-3, self.t_start + self.time_limit - time.perf_counter()
            ),
            transcription=self.transcription, multistart=self.multistart, sources=self.sources,
        )  # fmt: skip


def source_lacks(ocp: HybridOCP, source: Any) -> str:
    """The words for the features of ``ocp`` (:data:`hybridoc.methods.FEATURES`) that a
    candidate source does not declare in its ``features`` attribute (none declared: none
    honoured), or ``""``. Such a source is not run on ``ocp`` (its proposals would answer a
    simpler problem) and its warm starts are not asked for."""
    have = frozenset(getattr(source, "features", frozenset()) or ())
    missing = [FEATURES[f] for f in problem_features(ocp) if f not in have]
    return " or ".join(missing)


LACKS = "its features do not declare"


def lacks_reason(lacking: str) -> str:
    """Why a source or warm start that lacks features of the problem (:func:`source_lacks`)
    is not used: what the source declares, not what the solver behind it can do (dt solves
    a free final time, while the transcription source's proposals do not carry it yet)."""
    return f"{LACKS} {lacking} (the source would answer a simpler problem)"


def too_long(k: int) -> str:
    """Why a sequence of ``k`` events is not solved."""
    return (
        f"a sequence of {k} events is more than the reference solves (MAX_EVENTS = "
        f"{MAX_EVENTS}: its shooting NLP grows as K^3 in time and K^2.7 in memory, 63 events "
        "took 22 s and 1.4 GB, 126 took 220 s and 8.8 GB); for long horizons use 'hybridoc "
        "evaluate' to judge a control, 'hybridoc solve --method gd' (or --method dt, within "
        "its MAX_NLP_SIZE), or a shorter horizon"
    )


@dataclass
class Guess:
    """The initial guess as the reference uses it."""

    controls: np.ndarray
    evaluation: Evaluation
    grad: Any
    estimate: bool  # start Newton from its costate


def note_source(
    book: Book,
    name: str,
    kind: str,
    proposals: int,
    t0: float,
    failed: str = "",
    *,
    skipped: bool | str = False,
    **extra: Any,
) -> None:
    """Record a source used (or, ``skipped``, not started: the budget was spent) in
    ``info["sources"]``."""
    row: dict[str, Any] = {
        "name": name,
        "kind": kind,
        "proposals": int(proposals),
        "time_s": time.perf_counter() - t0,
        **extra,
    }
    if failed:
        row["failed"] = failed
    if skipped:
        row["skipped"] = skipped if isinstance(skipped, str) else "not run: the budget was spent"
    old = next((r for r in book.sources if r["name"] == name == "enumeration"), None)
    if old is not None:
        # the enumeration extended after the re-simulations: one row
        old["proposals"] += row["proposals"]
        old["time_s"] += row["time_s"]
        old.update(extra)
        return
    book.sources.append(row)


def is_convex(ocp: HybridOCP, key: tuple[str, ...]) -> bool:
    """Whether the sequence's problem has one extremal, its minimum, whatever the start: a
    disc scene without events (double integrators, a quadratic cost, linear control bounds:
    a strictly convex problem)."""
    return not key and has_closed_form_phases(ocp) and ocp.path is None


def exhaustive_length(book: Book) -> int | None:
    """The largest ``L`` such that every feasible sequence of up to ``L`` events was solved
    (an extremal found, verified or not) or pruned by a valid bound; ``None`` when not even
    the empty sequence is covered (or there was no enumeration). A sequence whose solve
    failed leaves its length uncovered."""
    if book.exhaustive is None:
        return None
    covered = None
    for length, keys in enumerate(book.enumerated[: book.exhaustive + 1]):
        if any(k not in book.results and k not in book.pruned for k in keys):
            break
        covered = length
    return covered


def judge_adjoint(ocp: HybridOCP, controls: Any) -> Any:
    """The judge's adjoint of a control (generic problems' costate estimate), else None."""
    if has_closed_form_phases(ocp):
        return None
    try:
        return gradient(ocp, np.asarray(controls, dtype=float))
    except HybridocError:
        return None
