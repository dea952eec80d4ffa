"""The solvers' candidate sources for the reference (:mod:`hybridoc.reference.sources`).

* :class:`TranscriptionSource` (``"transcription"``): the direct transcription from the
  initial guess proposes its event sequence and two known controls (its continuous ``u(t)``
  and its grid control); with a sequence fixed it gives the shooting a warm start (its
  multipliers as :class:`~hybridoc.reference.sources.PhaseCostates`).
* :class:`MultiStartSource` (``"multi-start"``): a cheap batched multi-start of the
  differentiable simulator on a coarse grid proposes the event sequences it reaches.

:func:`register_builtin_sources` registers both; importing :mod:`hybridoc.solvers` calls it,
so ``hybridoc.solve(problem, "reference")``, the command line and ``hybridoc.solve_reference``
use them. The solvers themselves are imported when a source first runs.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from hybridoc.reference.sources import PhaseCostates, Proposal, SourceContext, register_source

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np

    from hybridoc.evaluation import Evaluation
    from hybridoc.ocp import HybridOCP

__all__ = [
    "MULTISTART_ITERS",
    "MULTISTART_STEPS",
    "MultiStartSource",
    "TranscriptionSource",
    "phase_costates",
    "register_builtin_sources",
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
    """The direct transcription: a competitor from the initial guess, and a warm start of the
    shooting of a given sequence (module notes)."""

    name = "transcription"

    def propose(self, ocp: HybridOCP, context: SourceContext) -> list[Proposal]:
        """The transcription's sequence and its two controls, from the initial guess."""
        from hybridoc.errors import HybridocError
        from hybridoc.evaluator import evaluate
        from hybridoc.solvers.transcription import solve_dt

        ev = context.evaluation
        if len(ev.events) > context.max_events:
            context.say("transcription from the guess: not run, its events are too many")
            return []
        context.progress.stage(
            f"direct transcription from the initial guess ({len(ev.events)} events)"
        )
        t0 = time.perf_counter()
        try:
            dt = solve_dt(ocp, initial=context.controls)
        except HybridocError as exc:
            context.say(f"transcription from the guess failed: {exc}")
            return []
        took = time.perf_counter() - t0
        context.say(f"transcription: cost {dt.cost:.12g}, events {dt.sequence} ({took:.2f} s)")
        try:
            dt_ev = evaluate(ocp, dt.controls)
        except HybridocError:
            dt_ev = None
        out = []
        if dt.success:
            # the transcription's control itself (continuous u(t)): its judged cost
            out.append(
                Proposal(self.name, dt.sequence, dt.controls, dt_ev, cost=dt.cost,
                         label="the direct transcription", solve=False)
            )  # fmt: skip
        if dt_ev is not None:
            out.append(
                Proposal(self.name, dt_ev.sequence, dt.controls, dt_ev,
                         label="the transcription's grid control", solve=False)
            )  # fmt: skip
            out.append(
                Proposal(self.name, dt.sequence, dt.controls, dt_ev, known=False, retry=True,
                         event_times=dt.info.get("event_times"))
            )  # fmt: skip
        return out

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


class MultiStartSource:
    """A batched multi-start of the differentiable simulator on a coarse grid
    (:func:`hybridoc.solvers.multistart.explore`) from ``context.multistart`` starts."""

    name = "multi-start"

    def propose(self, ocp: HybridOCP, context: SourceContext) -> list[Proposal]:
        """Every judged result as a known control; each distinct sequence to solve."""
        from hybridoc.errors import HybridocError
        from hybridoc.solvers.contacts import contact_model
        from hybridoc.solvers.gd import make_loss
        from hybridoc.solvers.multistart import explore

        model = contact_model("direct", toi="both")

        count = context.multistart
        if not count:
            return []
        context.progress.stage(f"multi-start of the simulator ({count} starts)")
        t0 = time.perf_counter()
        try:
            found = explore(
                ocp, count, steps=min(ocp.steps, MULTISTART_STEPS), iters=MULTISTART_ITERS,
                judge=MULTISTART_JUDGED,
                # gd's cached loss (the default's function): built once per problem
                # structure, not once per call (datasets call the reference per draw)
                loss_for=lambda coarse: make_loss(coarse, model, "exact")[0],
            )  # fmt: skip
        except HybridocError as exc:
            context.say(f"multi-start failed: {exc}")
            return []
        context.say(f"multi-start: {len(found)} results in {time.perf_counter() - t0:.2f} s")
        out, seen = [], set()
        for r in found:
            key = tuple(r["sequence"])
            out.append(
                Proposal(self.name, list(key), r["controls"], r["evaluation"], cost=r["cost"],
                         label="a multi-start of the simulator", solve=key not in seen)
            )  # fmt: skip
            seen.add(key)
        return out


def register_builtin_sources() -> None:
    """Register :class:`TranscriptionSource` and :class:`MultiStartSource` (in this order,
    the order the reference takes their proposals in)."""
    register_source(TranscriptionSource())
    register_source(MultiStartSource())
