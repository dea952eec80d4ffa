"""The solvers' candidate sources for the reference (:mod:`hybridoc.reference.sources`).

* :class:`MultiStartSource` (``"multi-start"``), asked first: a batched multi-start of the
  differentiable simulator on a coarse grid proposes every distinct event sequence it
  reaches (each judged result also as a known control). On an ordinary problem it is cheap
  (``context.multistart`` starts, :data:`MULTISTART_ITERS` iterations); on a
  :func:`rich_scene` (a disc scene with walls, several actuated discs or passive discs
  already moving) it is gradient descent's multi-start with diverse starts
  (:func:`~hybridoc.solvers.multistart.diverse_starts`: aimed at each body and each wall,
  bounce-first, every actuated disc and pairs of them), :data:`DIVERSE_FACTOR` times as
  many starts.
* :class:`TranscriptionSource` (``"transcription"``): the direct transcription from the
  initial guess (within :data:`DT_BUDGET_SHARE` of the budget) and, on a
  :func:`rich_scene` with several actuated discs or passive discs already moving, from the
  two cheapest aimed starts of :func:`diverse_controls
  <hybridoc.solvers.multistart.diverse_controls>`, proposes its event sequences, each with
  its own event times (the modelled sequence with the NLP's, the re-simulated one with the
  judge's), and two known controls (its continuous ``u(t)`` and its grid control); with a
  sequence fixed it gives the shooting a warm start (its multipliers as
  :class:`~hybridoc.reference.sources.PhaseCostates`).

Both honour ``context.budget_s``: the descent stops where it is and fewer results are judged
(a partial result is still proposals); the transcription's further guesses are skipped.

:func:`register_builtin_sources` registers both; importing :mod:`hybridoc.solvers` calls it,
so ``hybridoc.solve(problem, "reference")``, the command line and ``hybridoc.solve_reference``
use them. The solvers themselves are imported when a source first runs.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from hybridoc.reference.sources import PhaseCostates, Proposal, SourceContext, register_source

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np

    from hybridoc.evaluation import Evaluation
    from hybridoc.ocp import HybridOCP

__all__ = [
    "DIVERSE_FACTOR",
    "DT_BUDGET_SHARE",
    "GD_BUDGET_SHARE",
    "GD_FACTOR",
    "MULTISTART_ITERS",
    "MULTISTART_REPEATS",
    "MULTISTART_STEPS",
    "MultiStartSource",
    "TranscriptionSource",
    "gd_multistart",
    "phase_costates",
    "register_builtin_sources",
    "rich_scene",
]

# the multi-start's coarse grid: at 40 steps two impacts 0.1 T apart fell into one or two
# cells and its descent never separated them (the two-impact optimum of the juggling paddle
# with mass ratio 0.5 was missed, 74% cheaper than the one-impact extremal returned)
MULTISTART_STEPS = 80
"""Grid steps of the multi-start's coarse problem (at most the problem's)."""
MULTISTART_ITERS = 20
"""Descent iterations of each start."""
MULTISTART_JUDGED = 4
"""Distinct results of the multi-start judged at the problem's resolution."""

# measured on the scenes of tests/scenes (issue #21, 2 cores): 16 diverse starts, 60 steps
# and 40 iterations reached the optimum's sequence on all four (channel, two strikers, bank
# shot, corner pocket) in 0.2-0.5 s each; 24 starts leave a margin
MULTISTART_REPEATS = 1
"""The multi-start (not the diverse one) stops judging after this many results in a row,
in the order of their coarse loss, repeated an event sequence it had judged
(:func:`~hybridoc.solvers.multistart.explore`'s ``repeats``): measured on pendulum-wall,
the hopper, bouncing-ball-2 and the juggling paddle, the four results judged before were
one sequence each time (within 0.4% of each other), and one evaluation of pendulum-wall
costs about 90 ms."""

DIVERSE_FACTOR = 3
"""On a :func:`rich_scene`, the multi-start runs this many times ``context.multistart``
diverse starts."""
DIVERSE_STEPS = 60
"""Grid steps of the diverse multi-start (gradient descent's multi-start grid)."""
DIVERSE_ITERS = 40
"""Descent iterations of each diverse start."""
DIVERSE_JUDGED = 6
"""Distinct results of the diverse multi-start judged at the problem's resolution."""
GD_FACTOR = 4
"""Starts of gradient descent's multi-start per ``context.multistart`` (0 skips it).

On a problem with a geometry (a disc scene) the multi-start source first runs gradient
descent's multi-start (:func:`gd_multistart`) from this many times ``context.multistart``
starts: 32 by default, as ``solve_gd(starts=32)`` runs it in cross-validation
(:data:`hybridoc.solvers.gd.GD_STARTS`)."""
GD_BUDGET_SHARE = 0.5
"""The share of ``context.budget_s`` gradient descent's multi-start may take."""
DT_GUESSES = 2
"""Further guesses of the transcription on a scene with several actuated discs or passive
discs already moving (:class:`TranscriptionSource`)."""
DT_BUDGET_SHARE = 0.6
"""The share of ``context.budget_s`` the transcription from the initial guess may take: the
rest solves the sequences proposed (its own and the enumeration's)."""
DT_GUESS_LIMIT_S = 5.0
"""No further guess when the transcription from the initial guess took longer than this
(the channel's took 19 s on 2 busy cores; the multi-start covers it); each further guess
gets at most twice that first run's time (at least 1 s)."""


def rich_scene(ocp: HybridOCP) -> str:
    """Why ``ocp`` gets the diverse multi-start, or an empty string.

    A disc scene with walls (bounce-first sequences), several actuated discs, or passive
    discs already moving (sequences that add a strike to a body's own events): read off the
    problem's :attr:`~hybridoc.capabilities.Capabilities.geometry` and initial state."""
    geo = ocp.capabilities.geometry
    if geo is None:
        return ""
    act = set(geo.actuated_indices)
    why = []
    if len(act) > 1:
        why.append("several actuated discs")
    if any(
        i not in act and any(abs(float(x)) > 0 for x in geo.velocity(ocp.x0, i))
        for i in range(geo.n_bodies)
    ):
        why.append("passive discs in motion")
    if geo.planes:
        why.append("walls")
    return ", ".join(why)


def _deadline(context: SourceContext, t0: float) -> float | None:
    return None if context.budget_s is None else t0 + float(context.budget_s)


def _spent(deadline: float | None, share: float = 0.0, t0: float = 0.0) -> bool:
    """The budget is spent (or, with ``share``, that share of it since ``t0``)."""
    if deadline is None:
        return False
    now = time.perf_counter()
    return now > deadline if not share else now - t0 > share * (deadline - t0)


def phase_costates(r: Any) -> PhaseCostates:
    """The warm start of a transcription of one sequence
    (:class:`~hybridoc.solvers.transcription.DTResult`): its costates come in one block per
    phase, the phase's start (the link multiplier) then its ``M d`` Radau points, the last of
    which is the phase's end."""
    starts, ends, states = [], [], []
    i = 0
    for nodes, X in zip(r.node_times, r.states, strict=True):
        n = len(nodes)  # M d + 1 nodes: the start and the Radau points
        starts.append(r.costates[i])
        ends.append(r.costates[i + n - 1])
        states.append(X[:, -1])
        i += n
    return PhaseCostates(r.event_times, starts, ends, states)


class TranscriptionSource:
    """The direct transcription: a competitor from the initial guess (and aimed guesses),
    and a warm start of the shooting of a given sequence (module notes)."""

    name = "transcription"
    # dt meets terminal constraints (its warm start then carries the terminal multipliers'
    # costates); a free final time is not yet passed through its proposals
    features = frozenset({"terminal"})

    def propose(self, ocp: HybridOCP, context: SourceContext) -> list[Proposal]:
        """The transcription's sequences and its two controls, from each guess."""
        import numpy as np

        t0 = time.perf_counter()
        deadline = _deadline(context, t0)
        ev = context.evaluation
        out: list[Proposal] = []
        first_deadline = None if deadline is None else t0 + DT_BUDGET_SHARE * (deadline - t0)
        if len(ev.events) > context.max_events:
            context.say("transcription from the guess: not run, its events are too many")
        elif _spent(deadline):
            context.say("transcription from the guess: not run, the time budget is spent")
            return []
        else:
            context.progress.stage(
                f"direct transcription from the initial guess "
                f"({len(ev.events)} event{'' if len(ev.events) == 1 else 's'})"
            )
            out += self._from(ocp, context, context.controls, "the initial guess", first_deadline)
        first = time.perf_counter() - t0
        why = rich_scene(ocp)
        if not why or why == "walls" or not DT_GUESSES or first > DT_GUESS_LIMIT_S:
            return out
        for label, u in _dt_guesses(ocp, context, DT_GUESSES):
            if _spent(deadline, 0.5, t0):
                context.say(f"transcription from {label}: not run, the time budget is spent")
                break
            context.progress.stage(f"direct transcription from {label}")
            limit = time.perf_counter() + max(2 * first, 1.0)
            cap = limit if deadline is None else min(deadline, limit)
            out += self._from(ocp, context, np.asarray(u), label, cap)
        return out

    def _from(
        self,
        ocp: HybridOCP,
        context: SourceContext,
        guess: np.ndarray,
        label: str,
        deadline: float | None,
    ) -> list[Proposal]:
        """The proposals of one transcription from ``guess`` (module notes): each
        sequence with its own event times."""
        import numpy as np

        from hybridoc.errors import HybridocError
        from hybridoc.evaluator import evaluate
        from hybridoc.solvers.transcription import solve_dt

        t0 = time.perf_counter()
        limit = None if deadline is None else max(deadline - t0, 1e-3)
        try:
            dt = solve_dt(ocp, initial=guess, time_limit=limit)
        except HybridocError as exc:
            context.say(f"transcription from {label} failed: {exc}")
            return []
        took = time.perf_counter() - t0
        context.say(
            f"transcription from {label}: cost {dt.cost:.12g}, events {dt.sequence} ({took:.2f} s)"
        )
        try:
            dt_ev = evaluate(ocp, dt.controls)
        except HybridocError:
            dt_ev = None
        which = "the direct transcription"
        if label != "the initial guess":
            which += f" from {label}"
        out = []
        # the judge's events of the continuous u(t): dt.sequence, at the judge's times
        judged = list(dt.sequence)
        judged_times = np.array([float(e["time"]) for e in dt.events])
        if dt.status.value in ("success", "best-found", "extremal"):
            # the transcription's control itself (continuous u(t)): its judged cost (dt's
            # default says best-found where it compared few sequences: the control is as
            # good a known control as with success)
            out.append(
                Proposal(self.name, judged, dt.controls, dt_ev, cost=dt.cost, label=which,
                         solve=False, event_times=judged_times)
            )  # fmt: skip
        if dt_ev is not None:
            out.append(
                Proposal(self.name, dt_ev.sequence, dt.controls, dt_ev,
                         label=f"the grid control of {which}", solve=False)
            )  # fmt: skip
            # the modelled sequence (the NLP's) with the NLP's event times; the judged one,
            # when it differs, with the judge's (issue #21: pairing the judged sequence
            # with the modelled times crashed the shooting)
            modelled = dt.info.get("sequence")
            times = dt.info.get("event_times")
            if modelled is not None and times is not None and len(times) == len(modelled):
                out.append(
                    Proposal(self.name, list(modelled), dt.controls, dt_ev, known=False,
                             retry=True, event_times=np.asarray(times, dtype=float))
                )  # fmt: skip
            if modelled is None or list(modelled) != judged:
                out.append(
                    Proposal(self.name, judged, dt.controls, dt_ev, known=False, retry=True,
                             event_times=judged_times)
                )  # fmt: skip
            if list(dt_ev.sequence) not in (judged, list(modelled or [])):
                out.append(
                    Proposal(self.name, dt_ev.sequence, dt.controls, dt_ev, known=False)
                )  # fmt: skip
        return [p for p in out if len(p.sequence or ()) <= context.max_events or not p.solve]

    def start(
        self, ocp: HybridOCP, sequence: Sequence[str], guess: Evaluation, controls: np.ndarray
    ) -> Proposal:
        """The transcription with ``sequence`` fixed, from ``guess``: its multipliers."""
        from hybridoc.solvers.transcription import solve_dt_sequence

        r = solve_dt_sequence(ocp, list(sequence), guess=guess, guess_controls=controls)
        return Proposal(
            self.name, list(sequence), event_times=r.event_times, known=False,
            warm_start=phase_costates(r),
        )  # fmt: skip


def _dt_guesses(ocp: HybridOCP, context: SourceContext, count: int) -> list[tuple[str, np.ndarray]]:
    """The transcription's further guesses: of the aimed and bounce-first starts
    (:func:`~hybridoc.solvers.multistart.diverse_controls`), the ``count`` the judge rates
    cheapest, of distinct kinds and with events other than the initial guess's."""
    from hybridoc.errors import HybridocError
    from hybridoc.evaluator import evaluate
    from hybridoc.solvers.multistart import diverse_controls

    rated = []
    for kind, u in diverse_controls(ocp, context.evaluation):
        try:
            ev = evaluate(ocp, u)
        except HybridocError:
            continue
        if ev.sequence == context.evaluation.sequence or len(ev.events) > context.max_events:
            continue
        rated.append((float(ev.cost), kind, u))
    rated.sort(key=lambda r: r[0])
    out: list[tuple[str, np.ndarray]] = []
    kinds: set[str] = set()
    for _, kind, u in rated:
        if kind[0] in kinds:
            continue
        kinds.add(kind[0])
        out.append((f"an aimed start ({kind[0]})", u))
        if len(out) >= count:
            break
    return out


class MultiStartSource:
    """A batched multi-start of the differentiable simulator on a coarse grid
    (:func:`hybridoc.solvers.multistart.explore`) from ``context.multistart`` starts, or
    :data:`DIVERSE_FACTOR` times as many diverse ones on a :func:`rich_scene`; on a disc
    scene first gradient descent's own multi-start (:func:`gd_multistart`) (module
    notes)."""

    name = "multi-start"

    def propose(self, ocp: HybridOCP, context: SourceContext) -> list[Proposal]:
        """Every judged result as a known control; each distinct sequence to solve."""
        if not context.multistart:
            return []
        t0 = time.perf_counter()
        deadline = _deadline(context, t0)
        if _spent(deadline):
            context.say("multi-start: not run, the time budget is spent")
            return []
        out: list[Proposal] = []
        if ocp.capabilities.geometry is not None and GD_FACTOR:
            share = None if deadline is None else t0 + GD_BUDGET_SHARE * (deadline - t0)
            out += gd_multistart(ocp, context, share)
        # each distinct sequence solved once (the first proposal of it: gd's refined control)
        solved: set[tuple[str, ...]] = {tuple(p.sequence or ()) for p in out if p.solve}
        for p in self._explore(ocp, context, deadline):
            key = tuple(p.sequence or ())
            out.append(dataclasses.replace(p, solve=p.solve and key not in solved))
            solved |= {key} if p.solve else set()
        return out

    def _explore(
        self, ocp: HybridOCP, context: SourceContext, deadline: float | None
    ) -> list[Proposal]:
        """The source's own coarse multi-start (diverse starts on a :func:`rich_scene`)."""
        from hybridoc.errors import HybridocError
        from hybridoc.solvers.multistart import cached_exploration_loss, diverse_starts, explore

        count = context.multistart
        t0 = time.perf_counter()
        if _spent(deadline):
            context.say("multi-start: diverse starts not run, the time budget is spent")
            return []
        why = rich_scene(ocp)
        starts = None
        steps, iters, judge = MULTISTART_STEPS, MULTISTART_ITERS, MULTISTART_JUDGED
        repeats: int | None = MULTISTART_REPEATS
        what = f"{count} starts"
        if why:
            # rich scenes: every one of the best distinct results is judged, as before
            count *= DIVERSE_FACTOR
            steps, iters, judge = DIVERSE_STEPS, DIVERSE_ITERS, DIVERSE_JUDGED
            repeats = None
            starts = diverse_starts(ocp, count, evaluation=context.evaluation)
            what = f"{count} diverse starts: {why}"
        context.progress.stage(f"multi-start of the simulator ({what})")
        try:
            found = explore(
                ocp, count, steps=min(ocp.steps, steps), iters=iters, judge=judge,
                starts=starts, deadline=deadline, repeats=repeats,
                # the default's function, built once per problem structure, not once per
                # call (datasets call the reference per draw); a problem with modes through
                # mode slots (the same loss bit for bit, two tanks: 2.3 times faster)
                loss_for=cached_exploration_loss,
            )  # fmt: skip
        except HybridocError as exc:
            context.say(f"multi-start failed: {exc}")
            return []
        context.say(
            f"multi-start ({what}): {len(found)} results in {time.perf_counter() - t0:.2f} s"
        )
        out, seen = [], set()
        for r in found:
            key = tuple(r["sequence"])
            solve = key not in seen and len(key) <= context.max_events
            out.append(
                Proposal(self.name, list(key), r["controls"], r["evaluation"], cost=r["cost"],
                         label="a multi-start of the simulator", solve=solve)
            )  # fmt: skip
            seen.add(key)
        return out


def gd_multistart(ocp: HybridOCP, context: SourceContext, deadline: float | None) -> list[Proposal]:
    """Gradient descent's multi-start as proposals.

    What ``solve_gd(ocp, starts=GD_FACTOR * context.multistart)`` does on a disc scene,
    through gd's and the multi-start's public functions, every result kept: the same
    starting set (:func:`~hybridoc.solvers.multistart.starting_controls`, seed 0), the same
    coarse batched descent (:func:`~hybridoc.solvers.multistart.explore` on gd's
    :data:`~hybridoc.solvers.gd.MULTISTART_STEPS` grid, :data:`~hybridoc.solvers.gd.
    MULTISTART_ITERS` iterations, every distinct result judged), and the refinement of the
    best distinct results (at most :data:`~hybridoc.solvers.gd.MULTISTART_REFINE`, within 2%
    of the best) at full resolution by :func:`~hybridoc.solvers.gd.solve_gd` from each (one
    light smoothing stage, as gd's). Each refined control and each judged coarse result is a
    known control; each distinct sequence is proposed, the refined ones first (with
    ``retry``: a better start than a coarse control). Stops at ``deadline``."""
    from hybridoc.errors import HybridocError
    from hybridoc.evaluator import evaluate
    from hybridoc.solvers import gd
    from hybridoc.solvers.multistart import distinct_basins, explore

    t0 = time.perf_counter()
    count = GD_FACTOR * context.multistart
    coarse = min(ocp.steps, gd.MULTISTART_STEPS)
    context.progress.stage(f"multi-start: gradient descent's {count} starts on {coarse} steps")
    try:
        found = explore(
            ocp, count, seed=0, steps=coarse, iters=gd.MULTISTART_ITERS, deadline=deadline,
            loss_for=gd.exploration_loss,
        )  # fmt: skip
    except HybridocError as exc:
        context.say(f"gd's multi-start failed: {exc}")
        return []
    refined: list[Proposal] = []
    seen: set[tuple[str, ...]] = set()
    for r in distinct_basins(found):  # the basins gd refines
        key = tuple(r["sequence"])
        if _spent(deadline):
            context.say("gd's multi-start: refinement stopped, the time budget is spent")
            break
        seen.add(key)
        context.progress.stage(
            f"multi-start: refining the basin {' '.join(key) or '(no events)'} (gd)"
        )
        stop = None if deadline is None else (lambda k, f, u: time.perf_counter() > deadline)
        try:
            sol = gd.solve_gd(
                ocp, initial=r["controls"], smoothing=gd.MULTISTART_SMOOTHING, callback=stop
            )
            ev = evaluate(ocp, sol.controls)
        except HybridocError as exc:
            context.say(f"gd's refinement of {list(key)} failed: {exc}")
            continue
        refined.append(
            Proposal("multi-start", list(ev.sequence), sol.controls, ev, cost=ev.cost,
                     label="gradient descent's multi-start", retry=True,
                     solve=len(ev.events) <= context.max_events)
        )  # fmt: skip
        if len(seen) >= gd.MULTISTART_REFINE:
            break
    context.say(
        f"gd's multi-start ({count} starts): {len(found)} results, refined "
        + ", ".join(f"{p.cost:.10g} {p.sequence}" for p in refined)
        + f" ({time.perf_counter() - t0:.2f} s)"
    )
    out, done = list(refined), {tuple(p.sequence or ()) for p in refined}
    for r in found:
        key = tuple(r["sequence"])
        out.append(
            Proposal("multi-start", list(key), r["controls"], r["evaluation"], cost=r["cost"],
                     label="gradient descent's multi-start (coarse)",
                     solve=key not in done and len(key) <= context.max_events)
        )  # fmt: skip
        done.add(key)
    return out


def register_builtin_sources() -> None:
    """Register the multi-start and the transcription sources.

    :class:`MultiStartSource` and :class:`TranscriptionSource` (in this order,
    the order the reference takes their proposals in: the multi-start is cheap, a second or
    two, while one transcription can take most of the budget; the channel's took 11 to 21 s
    and, asked first, left the multi-start, which alone reaches the channel's optimum, no
    time)."""
    register_source(MultiStartSource())
    register_source(TranscriptionSource())
