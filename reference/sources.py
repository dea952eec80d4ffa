"""Candidate sources: whatever proposes controls or event sequences to the reference.

The reference solves the HMP system of event sequences; which sequences to try comes from
its own proposals (the initial guess and its neighbours, every one-event sequence, the
``search`` enumeration: :mod:`hybridoc.reference.candidates`) and from **candidate
sources**, objects behind a small protocol, so that the reference imports no solver:

* :class:`CandidateSource`: a ``name`` and ``propose(ocp, context) -> [Proposal, ...]``,
  called once per solve with what the reference knows so far (:class:`SourceContext`);
* :class:`SequenceStarter`: a ``name`` and ``start(ocp, sequence, guess, controls) ->
  Proposal | None``, asked for a warm start of the shooting (:class:`PhaseCostates`) when
  Newton failed on a sequence from the reference's own starts.

One object may be both. A :class:`Proposal` names a sequence to solve (with event-time
guesses and a control to start Newton from), a known control the result must not be worse
than, or both.

Sources are passed in (``solve_reference(problem, sources=[...])``) or registered
(:func:`register_source`). The sources that ship with hybridoc (the direct transcription,
the batched multi-start of the simulator, in :mod:`hybridoc.solvers.candidates`) are
registered on the registry's first use through :data:`hybridoc.methods.BUILTIN_SOURCES`, as
the built-in methods are, so every entry point runs with them while this package imports no
solver; the result says which sources were used (``info["sources"]``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from hybridoc.methods import load_builtin_sources

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np

    from hybridoc.evaluation import Evaluation
    from hybridoc.ocp import HybridOCP
    from hybridoc.progress import Progress

__all__ = [
    "CandidateSource",
    "PhaseCostates",
    "Proposal",
    "SequenceStarter",
    "SourceContext",
    "register_source",
    "registered_sources",
    "unregister_source",
]


@dataclass(frozen=True)
class PhaseCostates:
    """A warm start of the shooting of one sequence: costates and states per phase.

    A direct transcription with the sequence fixed gives them (its multipliers); the
    reference turns them into Newton's unknowns (the costate jumps follow from them).

    Attributes
    ----------
    event_times
        ``(K,)`` event times.
    costate_start, costate_end
        ``K + 1`` costates ``(nx,)``: at the start and at the end of each phase.
    state_end
        ``K + 1`` states ``(nx,)`` at the end of each phase (before each event's jump).
    horizon
        The final time of these phases, for a problem with a free final time (``None``: the
        problem's ``horizon``, its guess). The terminal constraints' multipliers are
        estimated from the last costate.
    """

    event_times: np.ndarray
    costate_start: Sequence[np.ndarray]
    costate_end: Sequence[np.ndarray]
    state_end: Sequence[np.ndarray]
    horizon: float | None = None


@dataclass
class Proposal:
    """What a source proposes: a sequence to solve, a known control, or both.

    Attributes
    ----------
    source
        The proposing source's name (the origin of the sequence in ``info["candidates"]``).
    sequence
        Guard names in event order: the sequence to solve, and the events of ``controls``
        as a known control.
    controls
        ``(N, nu)`` controls on the problem's grid: Newton's start (its adjoint costate) and,
        with ``known``, a control the result must not be worse than.
    evaluation
        The judge's evaluation of ``controls`` (its trajectory starts the searches).
    event_times
        Guesses of the event times; default: from ``evaluation``.
    cost
        The true cost of the known control; default ``evaluation.cost``.
    label
        How messages name the known control ("the direct transcription"); default the
        source's name.
    solve
        Solve the HMP system of ``sequence``.
    known
        Count ``controls`` as a control the result must not be worse than (it needs a cost).
    retry
        Solve ``sequence`` again from this start when it failed before.
    warm_start
        Costates that start Newton on ``sequence`` (:class:`PhaseCostates`).
    """

    source: str
    sequence: Sequence[str] | None = None
    controls: np.ndarray | None = None
    evaluation: Evaluation | None = None
    event_times: np.ndarray | None = None
    cost: float | None = None
    label: str = ""
    solve: bool = True
    known: bool = True
    retry: bool = False
    warm_start: PhaseCostates | None = None

    def known_cost(self) -> float | None:
        """The known control's cost (``cost``, else the evaluation's), or ``None``."""
        if self.cost is not None:
            return float(self.cost)
        return None if self.evaluation is None else float(self.evaluation.cost)


@dataclass
class SourceContext:
    """What the reference knows when it asks a source for proposals.

    Attributes
    ----------
    controls, evaluation
        The initial guess's controls and the judge's evaluation of them.
    budget_s
        Seconds the source may take (``None``: no limit).
    progress
        Where to report stages (:mod:`hybridoc.progress`).
    multistart
        Starts a multi-start source should run (the reference's ``multistart`` option).
    max_events
        The longest sequence the reference solves: longer proposals are not attempted.
    best_cost
        The cheapest known control so far (``inf``: none).
    say
        Writes one line of the reference's ``verbose`` log.
    """

    controls: np.ndarray
    evaluation: Evaluation
    progress: Progress
    budget_s: float | None = None
    multistart: int = 0
    max_events: int = 40
    best_cost: float = math.inf
    say: Callable[[str], None] = field(default=lambda text: None)


@runtime_checkable
class CandidateSource(Protocol):
    """Proposes event sequences and known controls to the reference (module notes)."""

    name: str

    def propose(self, ocp: HybridOCP, context: SourceContext) -> Sequence[Proposal]:
        """The proposals for ``ocp``, in the order the reference should take them.

        Raise :class:`~hybridoc.errors.HybridocError` (or return ``[]``) when there are
        none; the reference notes the failure and goes on.
        """
        ...


@runtime_checkable
class SequenceStarter(Protocol):
    """Starts the shooting of one given sequence (module notes)."""

    name: str

    def start(
        self, ocp: HybridOCP, sequence: Sequence[str], guess: Evaluation, controls: np.ndarray
    ) -> Proposal | None:
        """A proposal for ``sequence`` with a ``warm_start`` (or ``None``), from a simulated
        ``guess`` trajectory and its ``controls``. May raise
        :class:`~hybridoc.errors.ConvergenceError`, :class:`~hybridoc.errors.EvaluationError`
        or ``ValueError``: the reference records the reason."""
        ...


_REGISTRY: dict[str, Any] = {}


def register_source(source: Any) -> Any:
    """Register a :class:`CandidateSource` and/or :class:`SequenceStarter` (replacing one of
    the same name); the reference uses the registered sources, in registration order, when
    it is given none. Returns ``source``."""
    if not isinstance(source, CandidateSource | SequenceStarter):
        raise TypeError(
            "a candidate source needs a name and a propose(ocp, context) or "
            f"start(ocp, sequence, guess, controls) method, got {type(source).__name__}"
        )
    _REGISTRY.pop(source.name, None)
    _REGISTRY[source.name] = source
    return source


def unregister_source(name: str) -> None:
    """Remove the registered source called ``name`` (nothing when there is none)."""
    _REGISTRY.pop(name, None)


def registered_sources() -> tuple[Any, ...]:
    """The registered sources, in registration order: the built-in ones
    (:data:`hybridoc.methods.BUILTIN_SOURCES`, registered on first use) and any registered
    since."""
    load_builtin_sources()
    return tuple(_REGISTRY.values())
