"""Result types of the judge: :class:`Evaluation` and :class:`Gradient`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from hybridoc.events import Event
from hybridoc.ocp import HybridOCP

__all__ = ["Evaluation", "Gradient", "Segment"]


class Segment(NamedTuple):
    """A piece of the trajectory under one constant control (cheap to build in bulk)."""

    t0: float
    s0: np.ndarray
    interval: int
    h: float
    event: int | None  # guard fired at the segment's end


@dataclass
class Evaluation:
    """Result of :func:`hybridoc.evaluate`.

    Attributes
    ----------
    cost, terminal_cost, running_cost
        ``J = phi(s(T)) + integral L``, and its two parts.
    times, states
        Grid times and event times with the states there; an event appears twice, with the
        state before and after the jump.
    events
        The events in time order.
    controls
        The ``(N, nu)`` controls that were evaluated (for a feedback policy: the values it
        returned; for a continuous-time control: its values at the cell midpoints).
    final_state
        ``s(T)``.
    bound_violation
        Largest violation of the problem's control bounds (0 when none).
    path_violation
        Largest violation of the problem's path constraints at the recorded times (0 when
        none or when the problem has none).
    """

    cost: float
    terminal_cost: float
    running_cost: float
    times: np.ndarray
    states: np.ndarray
    events: list[Event]
    controls: np.ndarray
    final_state: np.ndarray
    ocp: HybridOCP = field(repr=False)
    segments: list[Segment] = field(repr=False, default_factory=list)
    bound_violation: float = 0.0
    path_violation: float = 0.0

    @property
    def sequence(self) -> list[str]:
        """The guard names of the events, in time order."""
        return [e.name for e in self.events]

    @property
    def feasible(self) -> bool:
        """Whether the control respects the bounds and the path constraints (to 1e-9)."""
        return self.bound_violation <= 1e-9 and self.path_violation <= 1e-9

    def sample(self, times: Sequence[float] | np.ndarray) -> np.ndarray:
        """States at arbitrary times (after any jump at exactly that time)."""
        from hybridoc.kernels import kernels

        if not self.segments:
            raise ValueError("dense sampling needs piecewise-constant controls")
        t = np.atleast_1d(np.asarray(times, dtype=float))
        starts = np.array([seg.t0 for seg in self.segments])
        out = np.empty((t.size, self.ocp.nx))
        flow = kernels(self.ocp).numeric().flow
        last = len(self.segments) - 1
        for k, tk in enumerate(t):
            i = max(int(np.searchsorted(starts, tk, side="right")) - 1, 0)
            seg = self.segments[i]
            tau = min(max(tk - seg.t0, 0.0), seg.h) if i < last else tk - seg.t0
            out[k] = flow(seg.s0, self.controls[seg.interval], tau)[0]
        return out

    def event_dicts(self) -> list[dict[str, Any]]:
        """Events as JSON-ready dicts."""
        return [e.to_dict() for e in self.events]


@dataclass
class Gradient:
    """Result of :func:`hybridoc.gradient`.

    Attributes
    ----------
    cost
        The continuous cost ``J``.
    d_initial_state
        ``dJ/ds(0)``, equal to the costate ``lambda(0)``.
    d_controls
        ``dJ/du``, shape ``(N, nu)``: derivative with respect to each piecewise-constant value.
    costate_times, costates
        The costate at the start and end of every segment (events appear twice: after and
        before the jump), in time order.
    evaluation
        The forward :class:`Evaluation`.
    """

    cost: float
    d_initial_state: np.ndarray
    d_controls: np.ndarray
    costate_times: np.ndarray
    costates: np.ndarray
    evaluation: Evaluation
