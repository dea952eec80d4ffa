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
    (:func:`_proof`): every feasible sequence of up to one event more than the answer's
    own was solved or excluded by a valid lower bound (the enumeration extends to that
    length while the shorter ones are covered, at most :data:`MAX_PROOF_DEPTH`, within the
    budget), no cheaper extremal of those lengths fails its re-simulation (that sequence's
    optimum, with the extra contacts avoided, would be unknown), and the answer's extremal
    was reached from :data:`PROOF_STARTS` distinct starts of Newton that agree (a second
    start is run where needed). Anything less is ``best-found``: the best verified
    extremal, nothing cheaper known, with ``info["coverage"]["why_not_proven"]``.
    ``time_limit`` (and a KeyboardInterrupt) stops everything and returns the best verified
    extremal so far as ``not-converged``.

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
import sys
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hybridoc import tolerances
from hybridoc.cores import usable_cores
from hybridoc.errors import (
    ConvergenceError,
    EvaluationError,
    HybridocError,
    SceneError,
    SimultaneousEventError,
)
from hybridoc.evaluation import Evaluation
from hybridoc.evaluator import evaluate, gradient
from hybridoc.methods import FEATURES, Method, problem_features
from hybridoc.ocp import HybridOCP
from hybridoc.problem import ControlsLike, ProblemLike, as_ocp
from hybridoc.progress import NullProgress, Progress, ProgressLike, progress_scope
from hybridoc.reference.candidates import (
    default_depth,
    enumerate_sequences,
    guess_candidates,
    guess_times,
    lower_bound,
)
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
from hybridoc.reference.result import ReferenceResult, make_result, reference_control
from hybridoc.reference.sequence import (
    COST_RTOL,
    SCREEN_NLP_ITER,
    TERMINAL_TOL,
    judged_reference,
    judged_violation,
    solve_sequence,
)
from hybridoc.reference.shooting import (
    hamiltonian_check,
    is_disc_scene,
    newton,
    path_check,
    prepare,
    refine,
    reset_control_check,
    saturation_check,
    shooting_system,
)
from hybridoc.reference.sources import (
    CandidateSource,
    PhaseCostates,
    Proposal,
    SequenceStarter,
    SourceContext,
    registered_sources,
)
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

_OPT_RTOL = tolerances.CHEAPER  # a known control cheaper by more than this: not optimal
MAX_WORKERS = 8
"""Worker processes of the search over sequences, at most (one per usable core)."""
FAILED_SHOWN = 4
"""The failed sequences ``info["coverage"]["failed"]`` lists (all are counted)."""
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
_IMPOSSIBLE = (
    "pruned: no control has these events (two bodies that cannot move themselves never meet)"
)
PROOF_STARTS = 2
"""Distinct starts of Newton that must reach the optimum's extremal (the same cost, to
:data:`START_RTOL`) for a ``success``: one start can land on a worse stationary point of
the right sequence."""
START_RTOL = 1e-6
"""Two starts reached the same extremal when their costs agree to this much relative (the
integration's refinement moves a cost by about ``rtol``; distinct stationary points of one
sequence differ by far more)."""
MAX_PROOF_DEPTH = MAX_SEARCH
"""The longest sequences the default enumeration extends to so that it covers every
sequence of up to one event more than the best extremal found (the budget stops it)."""


class _Stopped(Exception):
    """The time limit or a KeyboardInterrupt stopped the search (``reason``)."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def _events(k: int) -> str:
    """``"1 event"``, ``"3 events"``: for messages."""
    return f"{k} event{'' if k == 1 else 's'}"


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


def coverage_line(coverage: dict[str, Any] | None) -> str:
    """One line of what the reference covered (``info["coverage"]``): the sources, the
    sequences proposed and solved, the exhaustive length and whether the budget stopped it."""
    if not coverage:
        return "(none recorded)"
    ex = coverage.get("exhaustive_length")
    failed = coverage.get("failed") or {}
    if ex is not None:
        reach = f"every sequence of up to {_events(ex)}"
    elif "enumeration" in coverage.get("sources", ()):
        reach = "no length covered exhaustively"
    else:
        reach = "no enumeration"
    text = (
        f"{coverage['proposed']} sequence(s) proposed, {coverage['solved']} solved, "
        f"{coverage['pruned']} pruned by bounds"
        + (
            f", {failed['count']} failed ("
            + "; ".join(",".join(q) or "no event" for q in failed.get("sequences", []))
            + (", ..." if failed["count"] > len(failed.get("sequences", [])) else "")
            + ")"
            if failed.get("count")
            else ""
        )
        + f"; {reach}; sources: {', '.join(coverage['sources']) or 'none'}"
    )
    if coverage.get("budget_stopped"):
        text += f"; stopped by the budget of {coverage['budget_s']:g} s"
    if coverage.get("stopped"):
        text += f"; stopped: {coverage['stopped']}"
    if "proven" in coverage:
        text += "; optimum proven" if coverage["proven"] else "; not proven"
    unsupported = [
        f"{row['name']} ({row['reason'].removeprefix('not run: ')})"
        for row in coverage.get("skipped_sources") or []
        if "budget" not in row["reason"]
    ]
    if unsupported:
        text += "; not run: " + ", ".join(unsupported)
    return text


def families_line(coverage: dict[str, Any] | None) -> str:
    """The best cost of each sequence family (the sequences of one number of events) that
    the reference solved, cheapest marked: ``"0 events 1.64; 2 events 0.16107 (best)"``."""
    families = (coverage or {}).get("families") or []
    if not families:
        return "(none solved)"
    best = min(f["best_cost"] for f in families)
    return "; ".join(
        f"{_events(f['events'])} {f['best_cost']:.6g}"
        + (" (best)" if f["best_cost"] == best else "")
        for f in families
    )


def _summary_lines(sol: Solution) -> list[tuple[str, str]]:
    """What ``hybridoc solve`` prints about a reference solution: the HMP residual, the
    coverage and the settings."""
    lines = []
    if "residual" in sol.info:
        lines.append(("residual", f"{sol.info['residual']:.2e} (HMP, max norm)"))
    if "coverage" in sol.info:
        lines.append(("coverage", coverage_line(sol.info["coverage"])))
        lines.append(("families", families_line(sol.info["coverage"])))
    settings = ", ".join(f"{k} {v}" for k, v in sol.settings.items() if v is not None)
    if settings:
        lines.append(("settings", settings))
    return lines


@dataclass
class _Known:
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


def _feasible(ocp: HybridOCP, ev: Evaluation | None) -> bool:
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
    fits its phase controls instead, :func:`_adjoint` gives ``None``)."""
    return not is_disc_scene(ocp)


@dataclass
class _Book:
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
    known: list[_Known] = field(default_factory=list)
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
        """Raise :class:`_Stopped` once the hard time limit is reached."""
        if time.perf_counter() >= self.hard_deadline:
            raise _Stopped("the time limit")

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

    def rivals(self) -> list[_Known]:
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
            self.reasons[key] = _too_long(len(key))
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
            self.reasons[key] = _IMPOSSIBLE
            self.pruned.add(key)
            self.origins.setdefault(key, origin)
            self.times.setdefault(key, 0.0)
            self.say(f"{list(key)} ({origin}): {_IMPOSSIBLE}")
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
                grad=_adjoint(self.ocp, k.controls), guess_ev=k.evaluation, retry=True,
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
    run = _Run(
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


@dataclass(frozen=True)
class _Run:
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


def _check_arguments(ocp: HybridOCP, sequence: Sequence[str] | str | None) -> list[str] | None:
    """The checked sequence (or ``None``); a :class:`SceneError` for a problem the reference
    cannot solve or a sequence it does not have (the options themselves are checked by
    :class:`ReferenceOptions`)."""
    reason = reference_supports(ocp)
    if reason:
        raise SceneError(f"{ocp.name!r}: {reason}")
    seq = None if sequence is None else ocp.admissible_sequence(sequence)
    if seq is not None and len(seq) > MAX_EVENTS:
        raise SceneError(_too_long(len(seq)))
    return seq


def source_lacks(ocp: HybridOCP, source: Any) -> str:
    """The words for the features of ``ocp`` (:data:`hybridoc.methods.FEATURES`) that a
    candidate source does not declare in its ``features`` attribute (none declared: none
    honoured), or ``""``. Such a source is not run on ``ocp`` (its proposals would answer a
    simpler problem) and its warm starts are not asked for."""
    have = frozenset(getattr(source, "features", frozenset()) or ())
    missing = [FEATURES[f] for f in problem_features(ocp) if f not in have]
    return " or ".join(missing)


_LACKS = "its features do not declare"


def _lacks_reason(lacking: str) -> str:
    """Why a source or warm start that lacks features of the problem (:func:`source_lacks`)
    is not used: what the source declares, not what the solver behind it can do (dt solves
    a free final time, while the transcription source's proposals do not carry it yet)."""
    return f"{_LACKS} {lacking} (the source would answer a simpler problem)"


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


def _too_long(k: int) -> str:
    """Why a sequence of ``k`` events is not solved."""
    return (
        f"a sequence of {k} events is more than the reference solves (MAX_EVENTS = "
        f"{MAX_EVENTS}: its shooting NLP grows as K^3 in time and K^2.7 in memory, 63 events "
        "took 22 s and 1.4 GB, 126 took 220 s and 8.8 GB); for long horizons use 'hybridoc "
        "evaluate' to judge a control, 'hybridoc solve --method gd' (or --method dt, within "
        "its MAX_NLP_SIZE), or a shorter horizon"
    )


@dataclass
class _Guess:
    """The initial guess as the reference uses it."""

    controls: np.ndarray
    evaluation: Evaluation
    grad: Any
    estimate: bool  # start Newton from its costate


def _solve(ocp: HybridOCP, run: _Run, progress: Progress) -> Solution:
    """:func:`solve_reference` after its arguments are checked."""
    progress.stage("simulating the initial guess")
    u0, given = _initial_controls(ocp, run.initial)
    ev, grad, u_used = _robust_guess(ocp, u0, want_adjoint=not is_disc_scene(ocp))
    guess = _Guess(u_used, ev, grad, given or grad is not None)
    starters = tuple(s for s in run.starters if not source_lacks(ocp, s))
    hard = math.inf if run.time_limit is None else run.t_start + run.time_limit
    book = _Book(
        ocp, run.tol, run.verbose, starters, run.rtol, progress=progress,
        deadline=min(run.t_start + run.budget, hard), hard_deadline=hard,
    )  # fmt: skip
    book.seq_given = None if run.seq is None else tuple(run.seq)
    for s in run.starters:
        if s not in starters:
            book.say(f"warm start {s.name!r}: not used, {_lacks_reason(source_lacks(ocp, s))}")
    book.known.append(
        _Known("the initial guess", ev.cost, ev.sequence, u_used, ev, _feasible(ocp, ev))
    )
    try:
        if run.seq is not None:
            best = _solve_given(ocp, run, book, guess)
            same = [k for k in book.rivals() if k.sequence == run.seq]
            cheaper = [k for k in same if k.cost < best.cost * (1 - _OPT_RTOL) - 1e-15]
        else:
            _discover(ocp, run, book, guess)
            best = _best_of(book)
            best, cheaper = _revisit_cheaper(ocp, book, best)
            if not cheaper:
                book.check_limit()
                best = _second_start(ocp, book, guess, best)
        book.check_limit()
    except _Stopped as stop:
        return _stopped(ocp, run, book, stop.reason)
    except KeyboardInterrupt:
        return _stopped(ocp, run, book, "interrupted")
    status, message, cheapest, landscape = _verdict(ocp, run, book, best, cheaper)
    return _finish(ocp, run, book, best, status, message, cheapest, landscape)


def _stopped(ocp: HybridOCP, run: _Run, book: _Book, reason: str) -> Solution:
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
    cheaper = [k for k in book.rivals() if k.cost < best.cost * (1 - _OPT_RTOL) - 1e-15]
    cheapest = None
    if cheaper:
        c = min(cheaper, key=lambda k: k.cost)
        message += f"; {c.source} costs less, {_J(c.cost):.10g} (events {c.sequence})"
        cheapest = {"source": c.source, "cost": c.cost, "sequence": c.sequence}
    return _finish(ocp, run, book, best, Status.NOT_CONVERGED, message, cheapest, None)


def _solve_given(ocp: HybridOCP, run: _Run, book: _Book, guess: _Guess) -> ReferenceResult:
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
    touch = _touch_reason(book.reasons.get(key))
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
                "hint: start from a control with these events (--initial) or check that the "
                "sequence is feasible"
            )
        else:
            raise ConvergenceError(
                f"the extremal of {seq} does not re-simulate to its own events: "
                f"{book.verdicts[key][1]}{nor + ' that does' if nor else ''}"
            )
    # the only optimality claim of a given sequence is within it: a cheaper control with the
    # same events means Newton stopped at a worse stationary point
    _check_simultaneous(book, best)
    return best


def _discovery_may_find(ocp: HybridOCP, seq: list[str], why: str | None) -> bool:
    """Whether the discovery may find the extremal of a given sequence that Newton from the
    guess did not: not on a disc scene (its sequences start from the NLP over the sequence
    as well), not for a sequence no control has (an infinite lower bound), nor where Newton
    converged and the integration could not reach ``rtol`` (refine's reasons name it;
    every other start meets the same limit)."""
    if is_disc_scene(ocp) or math.isinf(lower_bound(ocp, seq)):
        return False
    return why is None or ("(rtol " not in why and "for rtol " not in why)


def _given_by_discovery(
    ocp: HybridOCP, run: _Run, book: _Book, guess: _Guess
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
    sub = _Book(
        ocp, run.tol, run.verbose, book.starters, run.rtol, progress=book.progress,
        deadline=book.deadline, hard_deadline=book.hard_deadline,
    )  # fmt: skip
    sub.known = list(book.known)
    _discover(ocp, run, sub, guess)
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


def _discover(ocp: HybridOCP, run: _Run, book: _Book, guess: _Guess) -> None:
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
    early = _EarlyScreens.start(ocp, run, book, guess, cands)
    try:
        _discover_with(ocp, run, book, guess, cands, t0, early)
    finally:
        if early is not None:
            early.close()


def _discover_with(
    ocp: HybridOCP,
    run: _Run,
    book: _Book,
    guess: _Guess,
    cands: list[list[tuple[str, float]]],
    t0: float,
    early: _EarlyScreens | None,
) -> None:
    """:func:`_discover` once the guess's candidates are known (and the search's screens
    started, ``early``)."""
    ev = guess.evaluation
    book.progress.stage(
        f"discovering sequences: {len(cands)} from the initial guess ({_events(len(ev.events))})"
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
    _note_source(book, "initial guess", "reference", len(cands), t0)
    for source in run.proposers:
        lacking = source_lacks(ocp, source)
        if lacking:
            book.say(f"source {source.name!r}: not run, {_lacks_reason(lacking)}")
            _note_source(
                book, source.name, run.kind, 0, time.perf_counter(),
                skipped=f"not run: {_lacks_reason(lacking)}",
            )  # fmt: skip
            continue
        if book.left() <= 0:
            book.budget_stopped = True
            book.say(f"source {source.name!r}: not run, the budget of {run.budget:g} s is spent")
            _note_source(book, source.name, run.kind, 0, time.perf_counter(), skipped=True)
            continue
        _run_source(ocp, run, book, guess, source)
    # every sequence of up to the scene's depth (or the search's) too, by lower bound: a
    # guess that never comes near a guard (a cart at rest before a wall) proposes no event
    # at all, and neither may the sources reach a sequence that starts with a bounce
    _enumerate(ocp, run, book, guess, early)
    book.best_verified()
    book.follow_resimulations()
    best = book.best_verified()
    if (
        best is not None
        and len(best.sequence) + 1 > book.depth
        and book.depth < MAX_PROOF_DEPTH
        and _exhaustive(book) == book.depth
        and not book.budget_stopped
    ):
        # a re-simulation found a best as long as the enumeration: the proof needs one
        # length more (friction-patch-free-time's optimum comes from the no-event extremal)
        _enumerate(ocp, run, book, guess)
        book.best_verified()
        book.follow_resimulations()


def _note_source(
    book: _Book,
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


def _run_source(ocp: HybridOCP, run: _Run, book: _Book, guess: _Guess, source: Any) -> None:
    """Ask one candidate source for proposals and take them, in order."""
    t0 = time.perf_counter()
    context = SourceContext(
        controls=guess.controls, evaluation=guess.evaluation, progress=book.progress,
        multistart=int(run.multistart), max_events=MAX_EVENTS,
        best_cost=min((k.cost for k in book.rivals()), default=math.inf), say=book.say,
        budget_s=book.left(),
    )  # fmt: skip
    try:
        proposals = list(source.propose(ocp, context))
    except HybridocError as exc:
        book.say(f"source {source.name!r} failed: {exc}")
        _note_source(book, source.name, run.kind, 0, t0, failed=str(exc))
        return
    for p in proposals:
        _take(ocp, book, guess, p)
    _note_source(book, source.name, run.kind, len(proposals), t0)


def _take(ocp: HybridOCP, book: _Book, guess: _Guess, p: Proposal) -> None:
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
        feasible = _feasible(ocp, p.evaluation)
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
        book.known.append(_Known(label, cost, seq, controls, p.evaluation, feasible))
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
    cheaper = old is not None and own and cost is not None and cost < old.cost * (1 - _OPT_RTOL)
    retry = (key in book.reasons and (p.retry or own) and key not in book.pruned) or cheaper
    if (key in book.results or key in book.reasons) and not retry:
        return  # solved or failed before: nothing new to try
    book.attempt(
        seq, times, np.asarray(p.controls, dtype=float) if own else guess.controls, p.source,
        estimate=own, grad=_adjoint(ocp, p.controls) if own else None, guess_ev=ev,
        retry=retry, warm_start=p.warm_start,
    )  # fmt: skip


def _best_of(book: _Book) -> ReferenceResult:
    """The cheapest verified extremal; an error when there is none."""
    best = book.best_verified()
    _check_simultaneous(book, best)
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


def _revisit_cheaper(
    ocp: HybridOCP, book: _Book, best: ReferenceResult
) -> tuple[ReferenceResult, list[_Known]]:
    """Trust: no known control may be cheaper. The sequences of cheaper ones are solved
    again from them; returns the best extremal and the known controls still cheaper."""
    for k in sorted(book.rivals(), key=lambda k: k.cost):
        if k.cost >= best.cost * (1 - _OPT_RTOL) - 1e-15:
            break
        if k.evaluation is None:
            continue
        book.attempt(
            k.sequence, guess_times(ocp, k.sequence, k.evaluation), k.controls,
            f"cheaper {k.source}", estimate=True, grad=_adjoint(ocp, k.controls),
            guess_ev=k.evaluation, retry=True,
        )  # fmt: skip
        best = book.best_verified() or best
    cheaper = [k for k in book.rivals() if k.cost < best.cost * (1 - _OPT_RTOL) - 1e-15]
    return best, cheaper


def _verdict(
    ocp: HybridOCP, run: _Run, book: _Book, best: ReferenceResult, cheaper: list[_Known]
) -> tuple[Status, str, dict[str, Any] | None, list[dict[str, Any]] | None]:
    """``(status, message, cheaper, landscape)`` of the best extremal (module notes)."""
    seq = run.seq
    # a given sequence's extremal claims nothing beyond its sequence: only the discovery (or
    # the search, below) can make it the optimum
    status, message = (
        (Status.SUCCESS, "")
        if seq is None
        else (Status.EXTREMAL, _extremal_message(seq, run.verify, run.search))
    )
    cheapest: dict[str, Any] | None = None
    landscape = book.landscape() if run.search is not None else None
    if cheaper:
        c = min(cheaper, key=lambda k: k.cost)
        _check_coalescing(ocp, c, best)
        status = Status.NOT_OPTIMAL
        message = (
            f"the extremal found costs {_J(best.cost):.10g}, but {c.source} costs "
            f"{_J(c.cost):.10g} (events {c.sequence}): this is not the optimum; try --initial "
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
        proven, text = _proof(run, book, best)
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
    violation = _extremal_path_violation(ocp, best)
    if violation > PATH_TOL:
        status = Status.INFEASIBLE
        message = (
            f"the best HMP extremal found violates the path constraints by {violation:.3g} "
            f"(> {PATH_TOL:g}) along the judge's re-simulation: no extremal that meets them "
            "was found (the constraints may be infeasible from x0, or active on arcs the "
            "reference did not find); use method 'dt'"
        )
    touch = _touch_note(book) if status in (Status.NOT_OPTIMAL, Status.INFEASIBLE) else ""
    if touch:
        # the extremal that would have answered lies outside what the reference models:
        # say so instead of returning a worse one
        raise ConvergenceError(f"{touch}; the reference's best answer otherwise: {message}")
    return status, message, cheapest, landscape


def _proof(run: _Run, book: _Book, best: ReferenceResult) -> tuple[bool, str]:
    """``(proven, text)``: whether the coverage proves ``best`` the global optimum, and
    the words that say how, or what is missing.

    Proven means all of: every feasible sequence of up to ``len(best) + 1`` events was
    solved (an extremal found) or excluded by a valid lower bound (``exhaustive_length``);
    no extremal of those lengths that is cheaper than ``best`` fails to re-simulate to its
    own events (that sequence's optimum, with the extra contacts avoided, would be unknown);
    every longer sequence that a control met has (a feasible known control, a
    re-simulation) has an extremal or is excluded by a bound; and the optimum's extremal
    was reached from at least :data:`PROOF_STARTS` distinct
    starts of Newton that agree (:data:`START_RTOL`). Sequences longer than
    ``len(best) + 1`` are not covered: the proof is of the search's claim, not of an
    infinite enumeration (docs/reference.rst, "What success means")."""
    k = len(best.sequence)
    need = k + 1
    ex = _exhaustive(book)
    why: list[str] = []
    if ex is not None and ex >= need:
        covered = (
            f"every feasible sequence of up to {_events(ex)} solved or excluded by a bound "
            f"(the optimum has {_events(k)})"
        )
    else:
        reach = (
            "no length covered" if ex is None else f"every sequence of up to {_events(ex)} covered"
        )
        nxt = 0 if ex is None else ex + 1
        why.append(f"{reach}; the best has {_events(k)}; {_uncovered(run, book, nxt)}")
        covered = ""
    bound = best.cost * (1 - _OPT_RTOL) - 1e-15
    for key, res in sorted(book.results.items(), key=lambda kv: kv[1].cost):
        if res.cost >= bound:
            break
        if len(key) <= need and not book.verify(key):
            why.append(
                f"the extremal of {list(key) or 'no event'} costs {_J(res.cost):.10g}, less, but "
                "does not re-simulate to its own events: that sequence's optimum with the other "
                "contacts avoided is not known"
            )
            break
    # a control met (known, or an extremal's re-simulation) with a longer sequence shows
    # that sequence reachable: one whose extremal was not found leaves the claim open (a
    # break whose relaxed one-strike extremal re-simulates to the cascade)
    met = {tuple(k.sequence) for k in book.rivals()}
    met |= {tuple(sim.sequence) for sim in book.resimulated.values()}
    open_ = sorted(
        (
            q
            for q in met
            if need < len(q) <= MAX_EVENTS and q not in book.results and q not in book.pruned
        ),
        key=lambda q: (len(q), q),
    )
    if open_:
        why.append(
            f"{len(open_)} longer sequence(s) that a control met has, without an extremal "
            f"(the first: {','.join(open_[0])})"
        )
    key = tuple(best.sequence)
    n = book.agreeing_starts(key)
    if _convex(book.ocp, key) and n >= 1:
        n = max(n, PROOF_STARTS)  # one extremal: the unique minimum
    if n < PROOF_STARTS:
        others = sorted(
            {f"{_J(c):.10g}" for c in book.start_costs.get(key, ()) if c != best.cost}
            - {f"{_J(best.cost):.10g}"}
        )
        why.append(
            f"its extremal was reached from {n} start(s) of Newton, {PROOF_STARTS} needed"
            + (f" (other starts reached {', '.join(others)})" if others else "")
        )
    if why:
        return False, "; ".join(why)
    if _convex(book.ocp, key):
        return True, f"{covered}; its extremal is the unique minimum (no event: a convex problem)"
    return True, f"{covered}; its extremal reached from {n} starts of Newton"


def _convex(ocp: HybridOCP, key: tuple[str, ...]) -> bool:
    """Whether the sequence's problem has one extremal, its minimum, whatever the start: a
    disc scene without events (double integrators, a quadratic cost, linear control bounds:
    a strictly convex problem)."""
    return not key and is_disc_scene(ocp) and ocp.path is None


def _uncovered(run: _Run, book: _Book, length: int) -> str:
    """Why the sequences of ``length`` events are not all covered (for :func:`_proof`)."""
    if length > book.depth or length >= len(book.enumerated):
        if book.depth >= MAX_PROOF_DEPTH:
            return f"sequences of {_events(length)} are beyond the enumeration (MAX_PROOF_DEPTH)"
        return f"sequences of {_events(length)} were not enumerated"
    keys = book.enumerated[length]
    left = [k for k in keys if k not in book.results and k not in book.pruned]
    failed = [k for k in left if k in book.reasons]
    untried = len(left) - len(failed)
    parts = []
    if failed:
        first = ",".join(failed[0]) or "no event"
        parts.append(f"{len(failed)} failed (the first: {first})")
    if untried:
        stop = f"the budget of {run.budget:g} s was spent" if book.budget_stopped else "not reached"
        parts.append(f"{untried} not solved ({stop})")
    return f"sequences of {_events(length)} not all solved: " + ", ".join(parts)


def _second_start(
    ocp: HybridOCP, book: _Book, guess: _Guess, best: ReferenceResult
) -> ReferenceResult:
    """The best sequence solved from other starts until :data:`PROOF_STARTS` of them reach
    its extremal (each start once): the known controls with its events (their costate
    estimates), then on a disc scene the NLP from evenly spread event times and no control,
    elsewhere the warm starts and the zero costate from the guess (unless the enumeration's
    screen already started it so). A disc scene's no-event extremal needs none
    (:func:`_convex`). Returns the cheapest verified extremal then (a start may find a
    cheaper one)."""
    key = tuple(best.sequence)
    if book.agreeing_starts(key) >= PROOF_STARTS or _convex(ocp, key):
        return best
    same = [k for k in book.known if tuple(k.sequence) == key and k.evaluation is not None]
    tries: list[tuple[Any, ...]] = [
        (guess_times(ocp, key, k.evaluation), k.controls, f"second start ({k.source})", True,
         _adjoint(ocp, k.controls), k.evaluation)
        for k in sorted(same, key=lambda k: k.cost)[:KNOWN_STARTS]
    ]  # fmt: skip
    if is_disc_scene(ocp):
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


def _touch_note(book: _Book) -> str:
    """Where a sequence failed at a touch point of a pure state constraint (the constraint
    met at one instant, which the reference does not model): the words that say so; else
    empty."""
    for key, why in book.reasons.items():
        text = _touch_reason(why)
        if text:
            return f"{text} (with the events {list(key)}); use method 'dt'"
    return ""


def _touch_reason(why: str | None) -> str:
    """The touch point a sequence's failure reasons name (its first), without the advice
    to use dt; else empty."""
    at = -1 if why is None else why.find("pure state constraint row")
    if why is None or at < 0 or "touch point" not in why:
        return ""
    end = why.find("use method 'dt'", at)
    return why[at : end if end >= 0 else len(why)].rstrip("; ")


def _extremal_path_violation(ocp: HybridOCP, best: ReferenceResult) -> float:
    """The path constraints' largest violation along the judge's re-simulation of the
    extremal's ``u(t)`` (:func:`path_violation`; 0 without path constraints)."""
    if ocp.path is None:
        return 0.0
    from hybridoc.callable_eval import evaluate_callable

    u, breakpoints = reference_control(best)
    try:
        ev = evaluate_callable(
            best.ocp, u, breakpoints=breakpoints, event_controls=best.event_controls
        )
    except HybridocError:
        return math.inf
    return path_violation(ocp, ev, u)


EVENT_CONTROL_PROBE = 1e-3
"""How far, relative to ``1 + |v|``, :func:`event_control_rival` moves a reset's own
control on each side (besides trying its bounds)."""


def event_control_rival(ocp: HybridOCP, best: ReferenceResult) -> dict[str, Any] | None:
    """A control cheaper than the extremal ``best`` found by moving one reset control
    ``v_k`` (``u(t)`` kept), or ``None``.

    The shooting's conditions on ``v_k`` are first order (stationary inside the bounds, the
    right sign at a bound), which a maximum meets too; the judge is the arbiter: each
    component ``v_k,i`` a reset reads is moved by :data:`EVENT_CONTROL_PROBE` ``(1 +
    |v|)`` either way and to each finite bound, and a feasible move (:func:`_feasible`) with
    the same events that the judge finds cheaper by more than ``1e-9`` relative is
    returned: ``{"source", "cost", "sequence", "event", "component", "value"}``.
    """
    V0 = best.event_controls
    if V0 is None:
        return None
    from hybridoc.callable_eval import evaluate_callable

    u, breakpoints = reference_control(best)

    def judge(V: np.ndarray) -> Evaluation | None:
        try:
            return evaluate_callable(best.ocp, u, breakpoints=breakpoints, event_controls=V)
        except HybridocError:
            return None

    base = judge(V0)
    if base is None:
        return None
    lo, hi = best.system.core.v_bounds
    for k, comps in enumerate(best.system.core.v_comps):
        for i in comps:
            v = float(V0[k, i])
            step = EVENT_CONTROL_PROBE * (1.0 + abs(v))
            trials = {v - step, v + step, float(lo[i]), float(hi[i])}
            for w in sorted(x for x in trials if math.isfinite(x) and x != v):
                if not lo[i] <= w <= hi[i]:
                    continue
                V = np.array(V0, dtype=float)
                V[k, i] = w
                ev = judge(V)
                if (
                    ev is not None
                    and ev.sequence == base.sequence
                    and ev.cost < base.cost - _OPT_RTOL * abs(base.cost)
                    and _feasible(ocp, ev)
                ):
                    return {
                        "source": f"the extremal with the control of event {k + 1}'s reset "
                        f"u[{i}] = {w:.6g} instead of {v:.6g}",
                        "cost": float(ev.cost),
                        "sequence": list(ev.sequence),
                        "event": k,
                        "component": i,
                        "value": w,
                    }
    return None


def _check_coalescing(ocp: HybridOCP, c: _Known, best: ReferenceResult) -> None:
    """A cheaper known control whose impacts nearly coincide without commuting: the
    optimum lies at a simultaneous impact, an error."""
    pair = _coalescing(ocp, c)
    if pair is None:
        return
    a, b, gap = pair
    raise ConvergenceError(
        f"no optimal control exists within the impulsive model: the cheapest control "
        f"found ({c.source}, cost {_J(c.cost):.10g}) has the impacts {a!r} and {b!r} only "
        f"{gap:.2g} apart, and no extremal with them in order exists: the optimum lies "
        "at a simultaneous impact whose jumps do not commute, which the model does not "
        "define. Perturb the scene slightly so that the contacts happen one after the "
        f"other (the best well-defined extremal found costs {_J(best.cost):.10g})"
    )


def _finish(
    ocp: HybridOCP,
    run: _Run,
    book: _Book,
    best: ReferenceResult,
    status: Status,
    message: str,
    cheapest: dict[str, Any] | None,
    landscape: list[dict[str, Any]] | None,
) -> Solution:
    """The Solution: the best extremal with what was tried, known and used."""
    candidates = [
        {"sequence": row["sequence"], "result": row["verdict"] if row["cost"] is None else
         f"cost {row['cost']:.12g} ({row['verdict']})", "origin": row["origin"]}
        for row in book.landscape()
    ]  # fmt: skip
    info: dict[str, Any] = {
        "verified": bool(run.verify or run.seq is None),
        "candidates": candidates,
        "known_controls": [
            {"source": k.source, "cost": k.cost, "sequence": k.sequence}
            # only where feasibility is in question (terminal or path constraints, a free
            # final time)
            | ({"feasible": k.feasible} if problem_features(ocp) or ocp.path is not None else {})
            for k in book.known
        ],
        "sources": list(book.sources),
        "warm_starts": [s.name for s in book.starters],
    }
    unused = [s for s in run.starters if s not in book.starters]
    if unused:
        info["warm_starts_skipped"] = [
            {"name": s.name, "reason": _lacks_reason(source_lacks(ocp, s))} for s in unused
        ]
    if cheapest is not None:
        info["cheaper"] = cheapest
    if landscape is not None:
        info["landscape"] = landscape
    best.coverage = _coverage(run, book, best)
    if best.coverage.get("proven") and status is not Status.SUCCESS:
        # the coverage would prove it, but the answer is beaten or infeasible
        best.coverage["proven"] = False
        best.coverage.pop("proof", None)
        best.coverage["why_not_proven"] = f"the answer is {status.value}"
    if best.coverage["budget_stopped"] and status is Status.SUCCESS and not message:
        ex = best.coverage["exhaustive_length"]
        message = (
            f"the optimum: the budget of {run.budget:g} s stopped the enumeration after it "
            f"had covered every sequence of up to {ex} events, as the proof needs"
        )
    elif status is Status.BEST_FOUND and best.coverage["budget_stopped"]:
        message += "; --budget gives it more time"
    sol = best.to_solution(timings={"verify_time_s": book.verify_time}, info=info)
    sol.settings = {
        "tol": run.tol, "rtol": run.rtol, "sequence": run.seq, "search": run.search,
        "multistart": run.multistart, "budget": run.budget,
    }  # fmt: skip
    sol.timings = {"solve_time_s": time.perf_counter() - run.t_start, **sol.timings}
    return sol.set_status(status, message)


def _coverage(run: _Run, book: _Book, best: ReferenceResult | None = None) -> dict[str, Any]:
    """``info["coverage"]``: what the search covered (:func:`solve_reference`), and whether
    it proves ``best`` the optimum (:func:`_proof`)."""
    # the cheapest extremal of each length that re-simulates to its own events
    families: dict[int, tuple[float, tuple[str, ...]]] = {}
    for key, res in sorted(book.results.items(), key=lambda kv: kv[1].cost):
        if len(key) not in families and book.verify(key):
            families[len(key)] = (float(res.cost), key)
    attempted = {k for k in [*book.results, *book.reasons] if k not in book.pruned}
    attempted -= {k for k, why in book.reasons.items() if why == _too_long(len(k))}
    failed = sorted((k for k in attempted if k not in book.results), key=lambda k: (len(k), k))
    return {
        "sources": [row["name"] for row in book.sources if "skipped" not in row],
        "proposed": len(book.proposed | set(book.results) | set(book.reasons)),
        "attempted": len(attempted),
        "solved": len(book.results),
        "pruned": len(book.pruned),
        "depth": book.depth,
        "exhaustive_length": _exhaustive(book),
        "failed": {"count": len(failed), "sequences": [list(k) for k in failed[:FAILED_SHOWN]]},
        "budget_s": run.budget,
        "budget_stopped": bool(book.budget_stopped),
        "time_limit_s": run.time_limit,
        "stopped": book.stopped or None,
        **_proof_fields(run, book, best),
        "family": "the number of events",
        "families": [
            {"events": k, "best_cost": c, "sequence": list(key)}
            for k, (c, key) in sorted(families.items())
        ],
        **_skipped_sources(book),
    }


def _proof_fields(run: _Run, book: _Book, best: ReferenceResult | None) -> dict[str, Any]:
    """``proven`` and ``proof`` (how) or ``why_not_proven`` for ``info["coverage"]``."""
    if best is None:
        return {"proven": False, "why_not_proven": "no answer"}
    if run.seq is not None:
        return {
            "proven": False,
            "why_not_proven": "a given sequence: its extremal, not compared with every other "
            "sequence" + (" (the search without it decides the status)" if run.search else ""),
        }
    if book.stopped:
        return {"proven": False, "why_not_proven": f"the search was stopped ({book.stopped})"}
    proven, text = _proof(run, book, best)
    return {"proven": True, "proof": text} if proven else {"proven": False, "why_not_proven": text}


def _skipped_sources(book: _Book) -> dict[str, Any]:
    """``{"skipped_sources": [{"name", "reason"}]}``: the sources not run because they do not
    honour the problem's features (:func:`source_lacks`), or ``{}`` (a source the budget
    stopped is only in ``info["sources"]``)."""
    rows = [
        {"name": r["name"], "reason": r["skipped"]}
        for r in book.sources
        if "skipped" in r and _LACKS in r["skipped"]
    ]
    return {"skipped_sources": rows} if rows else {}


def _exhaustive(book: _Book) -> int | None:
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


def _extremal_message(seq: list[str], verify: bool, search: int | None) -> str:
    """The message of an ``extremal``: what it is and what it is not."""
    checked = "" if verify else " (not re-simulated by the judge: verify=False)"
    if search is not None:
        return f"the HMP extremal of the given sequence {seq}{checked}"
    return (
        f"the HMP extremal of the given sequence {seq}{checked}, not compared with other "
        "sequences (without --sequence, or with --search K, the reference looks for the "
        "optimum)"
    )


def _judge_given_sequence(
    ocp: HybridOCP,
    seq: list[str],
    best: ReferenceResult,
    book: _Book,
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
    bound = best.cost * (1 - _OPT_RTOL) - 1e-15
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


def _coalescing(ocp: HybridOCP, k: _Known) -> tuple[str, str, float] | None:
    """Two consecutive events of a known control that nearly coincide and whose jumps do
    not commute: ``(guard a, guard b, time apart)``, else ``None``."""
    ev = k.evaluation
    if ev is None or len(ev.events) < 2:
        return None
    from hybridoc.events import commute_defect
    from hybridoc.kernels import kernels

    num = kernels(ocp).numeric()
    for e1, e2 in zip(ev.events[:-1], ev.events[1:], strict=True):
        gap = e2.time - e1.time
        if gap > 1e-4 * ocp.horizon or e1.guard == e2.guard:
            continue
        s = np.asarray(e1.state_before, dtype=float)
        ra, rb = num.reset(e1.guard), num.reset(e2.guard)
        ga, gb = np.asarray(ra(s)[0], dtype=float), np.asarray(rb(s)[0], dtype=float)
        ab = np.asarray(ra(gb)[0], dtype=float)
        ba = np.asarray(rb(ga)[0], dtype=float)
        # the judge's test: only the components the jumps change, each at its own scale (a
        # far body must not lend its size to the tolerance)
        defect = commute_defect(ab, ba, s, ga, gb, floor=ocp.scales.state_array)
        if defect > tolerances.value("commute"):
            return e1.name, e2.name, gap
    return None


def _check_simultaneous(book: _Book, best: ReferenceResult | None) -> None:
    """An extremal cheaper than every verified one whose events coincide without an order
    means the problem has no optimum within the impulsive model: a clear error."""
    bound = math.inf if best is None else best.cost * (1 - _OPT_RTOL)
    for key, (ok, msg) in sorted(book.verdicts.items(), key=lambda kv: book.results[kv[0]].cost):
        res = book.results[key]
        if ok or res.cost >= bound or "same instant" not in msg:
            continue
        raise ConvergenceError(
            f"the cheapest extremal ({_J(res.cost):.10g}, events {list(key)}) has events that "
            "coincide in time without commuting jumps: the optimum of this problem lies at a "
            "simultaneous impact, which the impulsive model does not define (controls that "
            "separate the impacts by a little come arbitrarily close to that cost). Perturb the "
            "scene so that the contacts happen one after the other"
            + (
                ""
                if best is None
                else f"; the best well-defined extremal found costs {_J(best.cost):.10g}"
            )
        )


def _adjoint(ocp: HybridOCP, controls: Any) -> Any:
    """The judge's adjoint of a control (generic problems' costate estimate), else None."""
    if is_disc_scene(ocp):
        return None
    try:
        return gradient(ocp, np.asarray(controls, dtype=float))
    except HybridocError:
        return None


_SEARCH_STATE: dict[str, Any] = {}

SCREEN_WAIT = 60.0
"""Seconds the search waits for a worker's screen with nothing else to do before it runs the
screen itself (a screen takes well under a second; a worker process forked from threads
could hang)."""
# a screen's claim (one signed byte per screen, shared with the worker processes): free,
# this process's, or the number of the worker that runs it (1, 2, ...)
_FREE, _PARENT = 0, -1


def _screen_worker(
    number: int, tasks: list[list[str]], claims: Any, lock: Any, results: Any
) -> None:
    """Worker ``number`` of :class:`_EarlyScreens`: the first screen nobody has claimed,
    until none is left; each outcome goes to ``results`` as ``(index, outcome)``, ``(index,
    None)`` where :func:`_search_one` raised (the parent runs it again and meets the error
    itself)."""
    from hybridoc.children import die_with_parent

    die_with_parent()  # a SIGKILLed search must not leave its screens running
    # the screening NLPs built here, while the parent solves the guess's candidates (it
    # builds those of the lengths it screens itself when it joins)
    prepare(_SEARCH_STATE["ocp"], {len(seq) for seq in tasks}, max_iter=SCREEN_NLP_ITER)
    first = 0  # claims only ever leave _FREE: the first free screen moves forward
    while True:
        with lock:
            while first < len(tasks) and claims[first] != _FREE:
                first += 1
            if first == len(tasks):
                break
            i = first
            claims[i] = number
        try:
            out: _Outcome | None = _search_one(tasks[i])
        except Exception:
            out = None
        results.put((i, out))


class _EarlyScreens:
    """The screens of an explicit ``search`` on a disc scene, started before the guess's
    candidates and the sources in worker processes (one per usable core but this one's, at
    most :data:`MAX_WORKERS` - 1), and shared with this process once the enumeration needs
    their outcomes: on two cores the worker screens while the sources run here, then both
    screen (multiple-collision, ``--search 5``: about 3 s of CPU here for the guess's
    candidates and the sources, 5.5 s of screens).

    A screen's outcome (:func:`_search_one`) depends on the problem, the guess, ``tol``,
    ``rtol`` and the warm-start sources alone, never on what the discovery has found or on
    the process that runs it, so :func:`_enumerate` takes it as it is, in its own order and
    with its own pruning and skipping: the landscape is the one the screens run in order
    would give. Screened: every sequence of up to ``search`` events the enumeration lists
    whose lower bound is below the best cost known at the start (the bound it prunes with
    only falls), in the enumeration's order, the guess's candidates last (solved here
    first, they need no screen unless they fail). Each screen is claimed once, by a worker
    or by this process (:meth:`outcomes`); a screen the enumeration skips is wasted (on
    multiple-collision a few of 146: the sequences the sources solve first)."""

    def __init__(
        self,
        tasks: list[list[str]],
        claims: Any,
        lock: Any,
        results: Any,
        workers: list[Any],
    ) -> None:
        self.tasks = tasks
        self.index = {tuple(seq): i for i, seq in enumerate(tasks)}
        self.claims, self.lock, self.results, self.workers = claims, lock, results, workers
        self.done: dict[int, _Outcome] = {}
        self.by_worker = 0  # outcomes the workers gave

    @classmethod
    def start(
        cls,
        ocp: HybridOCP,
        run: _Run,
        book: _Book,
        guess: _Guess,
        cands: Sequence[Sequence[tuple[str, float]]] = (),
    ) -> _EarlyScreens | None:
        """Start the workers (or ``None``: no explicit search, not a disc scene, one usable
        core, no ``fork``, or only a handful of sequences)."""
        import multiprocessing as mp

        workers = min(usable_cores(), MAX_WORKERS) - 1
        if (
            not run.search
            or not is_disc_scene(ocp)
            or workers < 1
            or "fork" not in mp.get_all_start_methods()
        ):
            return None
        best = book.best_bound()
        later = {tuple(n for n, _ in c) for c in cands}
        by_length: list[list[tuple[float, list[str]]]] = [[] for _ in range(run.search + 1)]
        for seq in enumerate_sequences(ocp, run.search):
            lb = lower_bound(ocp, seq)
            if lb < best:  # the enumeration prunes the others (an infinite bound too)
                by_length[len(seq)].append((lb, seq))
        # the enumeration's order: length by length, by lower bound within one
        order = [seq for rows in by_length for _, seq in sorted(rows, key=lambda r: r[0])]
        # the guess's candidates last (stable: the order kept otherwise)
        tasks = sorted(order, key=lambda q: tuple(q) in later)
        if len(tasks) <= 4:
            return None
        ctx = mp.get_context("fork")
        claims = ctx.RawArray("b", len(tasks))
        lock = ctx.Lock()
        results = ctx.Queue()
        _SEARCH_STATE.update(
            ocp=ocp, u0=guess.controls, ev=guess.evaluation, tol=book.tol, rtol=book.rtol,
            starters=book.starters,
        )  # fmt: skip
        procs = []
        try:
            for number in range(1, workers + 1):
                p = ctx.Process(
                    target=_screen_worker,
                    args=(number, tasks, claims, lock, results),
                    daemon=True,
                )
                p.start()  # forks with the state above
                procs.append(p)
        finally:
            _SEARCH_STATE.clear()
        book.say(f"enumeration: {len(tasks)} screens started before the sources")
        return cls(tasks, claims, lock, results, procs)

    def withdraw(self, keys: Any) -> None:
        """The screens of these sequences are not wanted (solved before the enumeration):
        no worker starts them."""
        with self.lock:
            for key in keys:
                i = self.index.get(tuple(key))
                if i is not None and self.claims[i] == _FREE:
                    self.claims[i] = _PARENT

    def _claim(self, i: int) -> bool:
        with self.lock:
            if self.claims[i] != _FREE:
                return False
            self.claims[i] = _PARENT
            return True

    def _receive(self, timeout: float | None) -> bool:
        """Take one outcome from the workers (waiting at most ``timeout`` seconds; ``None``:
        do not wait); ``False`` when none came."""
        import queue

        try:
            if timeout is None:
                i, out = self.results.get_nowait()
            else:
                i, out = self.results.get(timeout=timeout)
        except queue.Empty:
            return False
        if out is None:
            # _search_one raised in the worker: run here when wanted (_get), where the error
            # surfaces
            with self.lock:
                self.claims[i] = _PARENT
        else:
            self.by_worker += 1
            self.done[i] = out
        return True

    def _lost(self) -> None:
        """The screens of a worker that died without giving their outcomes: run here (one
        that ran out of screens has given all of its own and exited with code 0)."""
        dead = {n for n, p in enumerate(self.workers, 1) if p.exitcode not in (None, 0)}
        if not dead:
            return
        while self._receive(None):
            pass
        for i in range(len(self.tasks)):
            if self.claims[i] in dead and i not in self.done:
                self.claims[i] = _PARENT  # run here when wanted (_get)

    def _get(self, i: int, ahead: list[int]) -> _Outcome:
        """Screen ``i``'s outcome: a worker's, or run here when no worker has started it;
        while a worker runs it, this process runs the free screens of ``ahead`` (the
        enumeration's next ones), then of the others in order. A worker that gives no
        outcome for :data:`SCREEN_WAIT` seconds while nothing else is left to do here is
        taken for stuck: the screen is run here (the same outcome)."""
        waited = 0.0
        while i not in self.done:
            if waited >= SCREEN_WAIT:
                with self.lock:
                    self.claims[i] = _PARENT
            while self._receive(None):
                pass
            if i in self.done:
                break
            # claimed here and not done: withdrawn, or lost by a worker
            if self._claim(i) or self.claims[i] == _PARENT:
                self.done[i] = _search_one(self.tasks[i])
                break
            nxt = next((j for j in [*ahead, *range(len(self.tasks))] if self._claim(j)), None)
            if nxt is not None:
                self.done[nxt] = _search_one(self.tasks[nxt])
            elif not self._receive(1.0):
                waited += 1.0
                self._lost()
        return self.done.pop(i)

    def outcomes(
        self,
        ocp: HybridOCP,
        book: _Book,
        guess: _Guess,
        todo: list[list[str]],
        deadline: float | None = None,
    ) -> list[_Outcome]:
        """:func:`_search_one` of each sequence of ``todo``, in its order (:meth:`_get`);
        none after ``deadline`` (``time.perf_counter()``, the time limit): the outcomes
        then stop short of ``todo``."""
        _SEARCH_STATE.update(
            ocp=ocp, u0=guess.controls, ev=guess.evaluation, tol=book.tol, rtol=book.rtol,
            starters=book.starters,
        )  # fmt: skip
        idx = [self.index.get(tuple(seq)) for seq in todo]
        out: list[_Outcome] = []
        try:
            for pos, (seq, i) in enumerate(zip(todo, idx, strict=True)):
                if deadline is not None and time.perf_counter() >= deadline:
                    break
                if i is None:
                    out.append(_search_one(seq))
                else:
                    ahead = [j for j in idx[pos + 1 :] if j is not None]
                    out.append(self._get(i, ahead))
                book.progress.count(len(out), len(todo), "sequences")
        finally:
            _SEARCH_STATE.clear()
        return out

    def close(self) -> None:
        """Withdraw the screens nobody has claimed and end the workers (a screen one of them
        still runs is not wanted)."""
        with self.lock:
            for i in range(len(self.tasks)):
                if self.claims[i] == _FREE:
                    self.claims[i] = _PARENT
        for p in self.workers:
            if p.is_alive():
                p.terminate()
            p.join()
        self.results.close()
        self.results.cancel_join_thread()


# (sequence, point, (steps per arc, arcs) of its system, reason, seconds, final time)
_Outcome = tuple[list[str], np.ndarray | None, tuple[Any, Any] | None, str, float, float]


def _search_one(seq: list[str]) -> _Outcome:
    """A worker: Newton from the disc NLP (or the transcription) for one sequence."""
    ocp, u0, ev, tol, rtol, starters = (
        _SEARCH_STATE[k] for k in ("ocp", "u0", "ev", "tol", "rtol", "starters")
    )
    t0 = time.perf_counter()
    try:
        res, why = solve_sequence(
            ocp, seq, guess_times(ocp, seq, ev), u0, estimate=False,
            guess_ev=None if is_disc_scene(ocp) else ev, starters=starters, tol=tol, screen=True,
            rtol=rtol,
        )  # fmt: skip
    except (ConvergenceError, EvaluationError, np.linalg.LinAlgError) as exc:
        res, why = None, str(exc)
    if res is None:
        return seq, None, None, why, time.perf_counter() - t0, ocp.horizon
    # the steps per phase (and a free final time) travel with the point: a worker's cache is
    # not the parent's
    return seq, res.z, res.system.spec, why, time.perf_counter() - t0, res.horizon


def _enumerate(
    ocp: HybridOCP, run: _Run, book: _Book, guess: _Guess, early: _EarlyScreens | None = None
) -> None:
    """Every feasible sequence, length by length, up to the scene's depth
    (:func:`~hybridoc.reference.candidates.default_depth`) or ``search`` if longer: within
    one length in the order of the lower bound, each skipped where the bound is not below
    the cheapest verified extremal or known control, solved in worker processes (one per
    core, at most :data:`MAX_WORKERS`) where the platform can fork. Lengths beyond
    ``search`` stop when the budget is spent; ``book.exhaustive`` is the longest length
    completed.

    A ``success`` needs every sequence of up to one event more than the optimum's own
    covered (:func:`_proof`): while the lengths so far are covered and the best verified
    extremal has ``depth`` events or more, the enumeration goes on to its length plus one
    (at most :data:`MAX_PROOF_DEPTH`; the budget stops these lengths too)."""
    t0 = time.perf_counter()
    if early is not None:
        early.withdraw(book.results)
    explicit = run.search or 0
    depth = max(explicit, default_depth(ocp))
    by_length = _by_length(ocp, book, depth)
    book.best_verified()  # the cheapest verified extremal so far bounds the enumeration
    solved = 0
    length = -1
    while True:
        length += 1
        if length > depth and depth < MAX_PROOF_DEPTH:
            # the proof needs one length beyond the optimum's: go on while it can succeed
            # (every length so far covered)
            best_res = book.best_verified()
            need = 0 if best_res is None else len(best_res.sequence) + 1
            if need > depth and _exhaustive(book) == depth:
                depth = min(need, MAX_PROOF_DEPTH)
                book.say(f"enumeration: extended to {_events(depth)} (the best has {need - 1})")
                by_length = _by_length(ocp, book, depth)
        if length > depth:
            break
        seqs = by_length[length]
        book.check_limit()
        bounded = length > explicit  # the budget may stop this length
        if bounded and book.left() <= 0:
            book.budget_stopped = True
            break
        best = book.best_bound()
        todo: list[tuple[float, list[str]]] = []
        for seq in seqs:
            key = tuple(seq)
            book.proposed.add(key)
            if key in book.results:
                continue  # proposed and solved before
            lb = lower_bound(ocp, seq)
            if key in book.reasons:
                # failed before (a source's start): a valid bound still covers it; else the
                # enumeration's own start gets a try
                if lb >= best and book.reasons[key] != _too_long(len(key)):
                    book.pruned.add(key)
                    book.reasons[key] = f"pruned: its cost is at least {lb:.6g} >= {best:.6g}"
                    continue
                if key in book.pruned or book.reasons[key] == _too_long(len(key)):
                    continue
            if lb >= best:
                book.pruned.add(key)
                book.reasons[key] = (
                    _IMPOSSIBLE
                    if math.isinf(lb)
                    else f"pruned: its cost is at least {lb:.6g} >= {best:.6g}"
                )
                book.origins[key] = "enumeration"
                book.times[key] = 0.0
                continue
            todo.append((lb, seq))
        todo.sort(key=lambda item: item[0])
        if not todo:
            book.exhaustive = length  # every sequence of this length solved or pruned before
            continue
        book.progress.stage(f"enumeration of {_events(length)}: {len(todo)} to solve")
        seqs_todo = [seq for _, seq in todo]
        hard = None if math.isinf(book.hard_deadline) else book.hard_deadline
        if early is not None and not bounded:
            outcomes = early.outcomes(ocp, book, guess, seqs_todo, deadline=hard)
        else:
            outcomes = _search_outcomes(
                ocp, book, seqs_todo, guess.controls, guess.evaluation,
                deadline=book.deadline if bounded else hard,
            )  # fmt: skip
        solved += len(outcomes)
        for seq, z, levels, why, took, horizon in outcomes:
            _record(ocp, book, seq, z, levels, why, took, horizon)
        if len(outcomes) == len(todo):
            _retry_failed(ocp, run, book, guess, [tuple(q) for q in seqs_todo], bounded)
        if len(outcomes) < len(todo):
            book.check_limit()
            book.budget_stopped = True
            book.say(
                f"enumeration: the budget of {run.budget:g} s is spent after {len(outcomes)} "
                f"of {len(todo)} sequences of {length} events"
            )
            break
        book.exhaustive = length
        if run.search is not None:
            for key in list(book.results):
                book.verify(key)  # the landscape's verdicts
        else:
            book.best_verified()
    _note_source(book, "enumeration", "reference", solved, t0, depth=depth)


def _retry_failed(
    ocp: HybridOCP,
    run: _Run,
    book: _Book,
    guess: _Guess,
    keys: list[tuple[str, ...]],
    bounded: bool,
) -> None:
    """A second start for the enumerated sequences of a disc scene whose screen found no
    extremal, while the proof may still need them (no longer than the best verified
    extremal plus one): the full solve (:func:`~hybridoc.reference.sequence.solve_sequence` without
    ``screen``: the disc NLP to convergence, then the warm starts from the guess, such as
    the transcription with the sequence fixed). Multiple-collision's ``ball1|ball2`` has no
    screened extremal, and one from the full solve. Stops when the budget is spent (a
    length beyond ``search``) or at the time limit."""
    if not is_disc_scene(ocp):
        return  # a generic problem's screen already ran the warm starts from the guess
    best = book.best_verified()
    if best is None:
        return
    need = len(best.sequence) + 1
    ev = guess.evaluation
    for key in keys:
        if key in book.results or key in book.pruned or len(key) > need:
            continue
        if bounded and book.left() <= 0:
            book.budget_stopped = True
            return
        lb, bound = lower_bound(ocp, key), book.best_bound()
        if lb >= bound:  # excluded by what was found since its screen
            book.pruned.add(key)
            book.reasons[key] = f"pruned: its cost is at least {lb:.6g} >= {bound:.6g}"
            continue
        book.attempt(
            key, guess_times(ocp, key, ev), guess.controls, "enumeration (full solve)",
            estimate=False, guess_ev=ev, retry=True,
        )  # fmt: skip


def _by_length(ocp: HybridOCP, book: _Book, depth: int) -> list[list[list[str]]]:
    """The feasible sequences of up to ``depth`` events, by length (kept in ``book``)."""
    book.depth = depth
    by_length: list[list[list[str]]] = [[] for _ in range(depth + 1)]
    for seq in enumerate_sequences(ocp, depth):
        by_length[len(seq)].append(seq)
    book.enumerated = [[tuple(q) for q in seqs] for seqs in by_length]
    return by_length


def _record(
    ocp: HybridOCP,
    book: _Book,
    seq: list[str],
    z: np.ndarray | None,
    levels: tuple[Any, Any] | None,
    why: str,
    took: float,
    horizon: float,
) -> None:
    """One enumerated sequence's outcome: its extremal (Newton polishes the worker's point
    here, in one step, at the worker's steps per phase and final time) or the reason it has
    none."""
    key = tuple(seq)
    book.screened.add(key)
    book.origins.setdefault(key, "enumeration")
    book.times[key] = book.times.get(key, 0.0) + took
    if z is None:
        book.reasons[key] = why
        book.say(f"{seq} (enumeration): {why}")
        book.from_known(key)
        return
    # a free final time comes back fixed at the value found (result.make_result)
    at = ocp.replace(horizon=horizon) if ocp.free_horizon else ocp
    steps, arcs = levels if levels is not None else (None, None)
    S = shooting_system(at, seq, steps, free=False, arcs=arcs)
    nr = newton(S, z, tol=book.tol)
    if not nr.converged:
        book.reasons[key] = f"Newton from the enumeration's point: residual {nr.residual:.2e}"
        book.from_known(key)
        return
    ref = refine(S, nr, rtol=book.rtol, tol=book.tol, verbose=book.verbose)
    if not ref.ok:
        book.reasons[key] = ref.reason
        book.from_known(key)
        return
    res = make_result(ref.system, ref.newton, "search", ref.error)
    book.start_costs.setdefault(key, []).append(float(res.cost))
    old = book.results.get(key)
    if old is None or res.cost < old.cost - 1e-12 * abs(old.cost):
        book.results[key] = res
        book.verdicts.pop(key, None)
    book.say(f"{seq} (enumeration): cost {_J(res.cost):.12g}")


def _search_outcomes(
    ocp: HybridOCP,
    book: _Book,
    todo: list[list[str]],
    u0: np.ndarray,
    ev: Evaluation,
    *,
    deadline: float | None = None,
) -> list[_Outcome]:
    """:func:`_search_one` on the sequences of ``todo`` in order, counted on
    ``book.progress``; with a ``deadline`` (``time.perf_counter()``), no sequence starts
    after it (the outcomes then stop short of ``todo``)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from hybridoc.children import die_with_parent

    def spent() -> bool:
        return deadline is not None and time.perf_counter() >= deadline

    _SEARCH_STATE.update(
        ocp=ocp, u0=u0, ev=ev, tol=book.tol, rtol=book.rtol, starters=book.starters
    )
    workers = min(usable_cores(), MAX_WORKERS)
    outcomes: list[_Outcome] = []
    # the screening NLP of each length once, before the workers fork (each would compile it)
    prepare(ocp, {len(seq) for seq in todo}, max_iter=SCREEN_NLP_ITER)
    try:
        if workers > 1 and len(todo) > 4 and "fork" in mp.get_all_start_methods():
            with ProcessPoolExecutor(
                workers, mp_context=mp.get_context("fork"), initializer=die_with_parent
            ) as pool:
                # a few sequences ahead of the workers, so that the deadline stops soon
                pending = [pool.submit(_search_one, seq) for seq in todo[: 2 * workers]]
                nxt = len(pending)
                while pending:
                    outcomes.append(pending.pop(0).result())
                    book.progress.count(len(outcomes), len(todo), "sequences")
                    if spent():
                        for f in pending:
                            f.cancel()
                        # what already ran still counts, in order
                        outcomes += [f.result() for f in pending if not f.cancelled()]
                        break
                    if nxt < len(todo):
                        pending.append(pool.submit(_search_one, todo[nxt]))
                        nxt += 1
        else:
            for seq in todo:
                if spent():
                    break
                outcomes.append(_search_one(seq))
                book.progress.count(len(outcomes), len(todo), "sequences")
    finally:
        _SEARCH_STATE.clear()
    return outcomes


METHOD = Method(
    "reference",
    "optimal control by shooting on the hybrid minimum principle (the ground truth)",
    run=solve_reference,
    options=ReferenceOptions,
    tolerance=1e-9,
    supports=reference_supports,
    summary_lines=_summary_lines,
    features=frozenset({"terminal", "free_horizon"}),
)
"""The method ``"reference"`` (:mod:`hybridoc.methods`)."""
