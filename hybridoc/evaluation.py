"""Result types of the judge: :class:`Evaluation` and :class:`Gradient`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from hybridoc import tolerances
from hybridoc.errors import HybridocError
from hybridoc.events import Event
from hybridoc.ocp import HybridOCP

__all__ = ["TERMINAL_TOL", "Evaluation", "Gradient", "Segment", "checked_times"]

TERMINAL_TOL = tolerances.TERMINAL
"""The terminal-constraint violation up to which a result meets its terminal constraints
(unless a method is given another tolerance): the table's ``"terminal"``
(:mod:`hybridoc.tolerances`)."""


def checked_times(times: Any, horizon: float, name: str = "times") -> np.ndarray:
    """``times`` as a 1-D float array in ``[0, T]``, or an error naming the argument.

    Times within rounding of the ends (``64 eps T``: a sum of phase durations that
    lands an ulp past ``T``) are clamped onto them; anything further out raises, as nothing
    is extrapolated.

    Raises
    ------
    hybridoc.errors.HybridocError
        For a time outside ``[0, T]``, not a number, or not 0-D/1-D.
    """
    try:
        t = np.atleast_1d(np.asarray(times, dtype=float))
    except (TypeError, ValueError):
        raise HybridocError(f"{name} must be numbers, got {times!r}") from None
    if t.ndim != 1:
        raise HybridocError(f"{name} must be a number or a 1-D array, got shape {t.shape}")
    slack = 64 * np.finfo(float).eps * abs(horizon)  # relative: horizons of 1e-6 s are fine
    bad = ~np.isfinite(t) | (t < -slack) | (t > horizon + slack)
    if bad.any():
        raise HybridocError(
            f"{name}: {float(t[bad][0])!r} lies outside [0, T] = [0, {horizon!r}] "
            "(no extrapolation)"
        )
    return np.clip(t, 0.0, horizon)


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
    terminal_violation
        Largest violation of the problem's terminal constraints at ``s(T)``:
        ``max(|h_eq|, max(-h_ineq, 0))`` (0 when it has none); ``inf`` when ``s(T)`` is
        not in the problem's required ``final_mode``.
    terminal_eq_values, terminal_ineq_values
        The terminal constraints at ``s(T)``, one value per constraint (``h_eq`` must be 0,
        ``h_ineq`` at least 0); empty arrays when the problem has none.
    segments, dense_pieces
        What :meth:`sample` reads: the constant-control segments of a grid or ZOH
        evaluation, or the integrator's dense output per step ``(t0, t1, dense)`` of a
        continuous-time one (:func:`hybridoc.evaluate_callable`).
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
    dense_pieces: list[tuple[float, float, Any]] = field(repr=False, default_factory=list)
    bound_violation: float = 0.0
    path_violation: float = 0.0
    terminal_violation: float = field(init=False, default=0.0)
    terminal_eq_values: np.ndarray = field(init=False, repr=False)
    terminal_ineq_values: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        # every evaluation (grid controls, a policy, a callable u(t)) reports its terminal
        # constraints from the same final state, whichever path built it
        s_end = np.asarray(self.final_state, dtype=float).ravel()
        eq, ineq = self.ocp.terminal_eq, self.ocp.terminal_ineq
        self.terminal_eq_values = (
            np.zeros(0) if eq is None else np.asarray(eq(s_end).full(), dtype=float).ravel()
        )
        self.terminal_ineq_values = (
            np.zeros(0) if ineq is None else np.asarray(ineq(s_end).full(), dtype=float).ravel()
        )
        self.terminal_violation = max(
            float(np.max(np.abs(self.terminal_eq_values), initial=0.0)),
            float(np.max(-self.terminal_ineq_values, initial=0.0)),
        )
        if self.ocp.final_mode is not None and self.final_mode != self.ocp.final_mode:
            self.terminal_violation = math.inf

    @property
    def final_mode(self) -> str | None:
        """The mode of ``s(T)`` (a problem with modes), else ``None``."""
        if self.ocp.modes is None:
            return None
        return self.ocp.mode_of(self.final_state)

    @property
    def horizon(self) -> float:
        """The final time ``T`` of the evaluation (for a free final time: the one judged)."""
        return float(self.ocp.horizon)

    @property
    def sequence(self) -> list[str]:
        """The guard names of the events, in time order."""
        return [e.name for e in self.events]

    @property
    def feasible(self) -> bool:
        """Whether the control respects the bounds and the path constraints (to
        :data:`hybridoc.tolerances.FEASIBILITY`, 1e-9) and the terminal constraints (to
        :data:`TERMINAL_TOL`)."""
        return (
            self.bound_violation <= tolerances.FEASIBILITY
            and self.path_violation <= tolerances.FEASIBILITY
            and self.terminal_violation <= TERMINAL_TOL
        )

    def infeasibility(self) -> str:
        """What the control violates, in words (``""`` when :attr:`feasible`): the bounds,
        the path constraints, the terminal constraints or the required final mode, each
        with its largest violation."""
        parts = []
        if self.bound_violation > tolerances.FEASIBILITY:
            parts.append(f"the control bounds by {self.bound_violation:.3g}")
        if self.path_violation > tolerances.FEASIBILITY:
            parts.append(f"the path constraints by {self.path_violation:.3g}")
        if self.terminal_violation > TERMINAL_TOL:
            required = self.ocp.final_mode
            if required is not None and self.final_mode != required:
                parts.append(
                    f"the required final mode {required!r} (it ends in {self.final_mode!r})"
                )
            else:
                parts.append(f"the terminal constraints by {self.terminal_violation:.3g}")
        return "" if not parts else "the controls violate " + " and ".join(parts)

    def sample(self, times: Sequence[float] | np.ndarray) -> np.ndarray:
        """States at any times in ``[0, T]``, after any jump at exactly that time.

        Exact between events: for piecewise-constant controls the flow of the segment that
        holds the time, from its start; for a continuous control (:func:`~hybridoc.
        evaluate_callable`) the integrator's own dense output on the step that holds it
        (the judge's trajectory, to its tolerances).

        Parameters
        ----------
        times
            One time or a 1-D array of times in ``[0, T]``.

        Returns
        -------
        numpy.ndarray
            ``(len(times), nx)``.

        Raises
        ------
        hybridoc.errors.HybridocError
            For a time outside ``[0, T]`` (no extrapolation) or not a number.
        """
        from hybridoc.kernels import kernels

        t = checked_times(times, self.horizon)
        if not self.segments:
            return self._sample_dense(t)
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

    def _sample_dense(self, t: np.ndarray) -> np.ndarray:
        nx = self.ocp.nx
        if not self.dense_pieces:
            if np.all(t == 0.0):  # nothing was integrated (no step): only s(0)
                return np.tile(np.asarray(self.states[0], dtype=float), (t.size, 1))
            raise HybridocError("this evaluation kept no trajectory between its states")
        starts = np.array([p[0] for p in self.dense_pieces])
        out = np.empty((t.size, nx))
        for k, tk in enumerate(t):
            # the last piece starting at or before t: after a jump at t, the one from t
            i = max(int(np.searchsorted(starts, tk, side="right")) - 1, 0)
            t0, t1, dense = self.dense_pieces[i]
            out[k] = np.asarray(dense(min(max(tk, t0), t1)), dtype=float)[:nx]
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
    d_horizon
        ``dJ/dT`` with the controls held per cell and the cells ``T / N`` long (the grid
        stretches with ``T``): the mean over the cells of the Hamiltonian
        ``L + lambda^T f``, which is constant on each cell (events included). It is the
        gradient with respect to a free final time; ``nan`` for the closed-loop gradient.
    terminal_d_controls, terminal_d_initial_state, terminal_d_horizon
        The same derivatives of each terminal constraint value (``terminal_eq`` first, then
        ``terminal_ineq``, as in :attr:`Evaluation.terminal_eq_values` and
        :attr:`Evaluation.terminal_ineq_values`): shapes ``(m, N, nu)``, ``(m, nx)`` and
        ``(m,)``; ``m = 0`` without terminal constraints (or for the closed-loop gradient).
    """

    cost: float
    d_initial_state: np.ndarray
    d_controls: np.ndarray
    costate_times: np.ndarray
    costates: np.ndarray
    evaluation: Evaluation
    d_horizon: float = float("nan")
    terminal_d_controls: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0)))
    terminal_d_initial_state: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    terminal_d_horizon: np.ndarray = field(default_factory=lambda: np.zeros(0))
