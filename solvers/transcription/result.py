"""The raw result of one transcribed NLP (:class:`DTResult`), and how it compares with the
judge's re-simulation of its control.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from hybridoc.evaluation import Evaluation
from hybridoc.judging import lagrange_pieces
from hybridoc.ocp import HybridOCP
from hybridoc.solvers.transcription.collocation import average_on_cells, pieces_at_one_time

if TYPE_CHECKING:
    from hybridoc.solvers.transcription.nlp import PhaseNLP

__all__ = [
    "DTResult",
    "event_time_gap",
    "problem_at",
    "resimulate",
    "resimulated_names",
    "sequence_matches",
]


@dataclass
class DTResult:
    """The raw solution of the transcribed NLP for one sequence.

    Attributes
    ----------
    sequence
        Guard names of the events.
    nlp_cost
        The NLP objective.
    event_times
        ``gamma_1 .. gamma_K``.
    node_times, states
        Per phase: the state node times ``(M d + 1,)`` and states ``(nx, M d + 1)``.
    control_times, controls
        Per phase: Radau-point times and controls ``(nu, M d)``.
    costate_times, costates
        Costate estimates in time order (phase start from the link multiplier, then the
        Radau points); event times appear twice (after and before the jump).
    jump_multipliers
        Multipliers of the guard equations (``pi_k`` of the HMP jump condition, up to sign).
    lambda0
        ``lambda(0) = dJ/ds(0)``.
    horizon
        The final time, the sum of the phase durations (a decision variable for a free
        final time, clipped into its bounds).
    iterations, status
        IPOPT's counters.
    active_path
        Largest multiplier of the non-penetration constraints (non-zero: a guard outside the
        sequence is touched, a grazing contact).
    """

    sequence: list[str]
    nlp_cost: float
    event_times: np.ndarray
    node_times: list[np.ndarray]
    states: list[np.ndarray]
    control_times: list[np.ndarray]
    controls: list[np.ndarray]
    costate_times: np.ndarray
    costates: np.ndarray
    jump_multipliers: np.ndarray
    lambda0: np.ndarray
    horizon: float
    iterations: int
    status: str
    active_path: float
    element_bounds: np.ndarray
    _nlp: PhaseNLP
    _w: np.ndarray

    event_controls: np.ndarray | None = None
    """``(K, nu)`` the control each event's reset reads (``v_k`` for a reset that depends on
    the control, the control at the phase's end for the others); ``None`` when no reset of
    the sequence depends on the control."""

    def control_function(self) -> Callable[[float], np.ndarray]:
        """The continuous-time control: per element, the polynomial through the Radau points
        (:meth:`control_at` at one time, bit for bit, for the judge's calls one at a time)."""
        nlp = self._nlp
        U_all = np.concatenate(self.controls, axis=1)
        vals = U_all.reshape(nlp.ocp.nu, -1, nlp.d)
        return pieces_at_one_time(
            self.element_bounds, nlp.rad.tau[1:], vals, nlp.ocp.u_min, nlp.ocp.u_max
        )

    def control_at(self, t: np.ndarray) -> np.ndarray:
        """The control at the times ``t`` (vectorised), shape ``(len(t), nu)``."""
        nlp = self._nlp
        U_all = np.concatenate(self.controls, axis=1)  # (nu, total elements * d)
        vals = U_all.reshape(nlp.ocp.nu, -1, nlp.d)  # (nu, elements, d)
        # the Solution's own u(t) is this function of the arrays it saves, so the judged
        # cost of a saved dt Solution is this one bit for bit; the clip: the interpolating
        # polynomial may overshoot a bound between Radau points
        return lagrange_pieces(
            t, self.element_bounds, nlp.rad.tau[1:], vals, nlp.ocp.u_min, nlp.ocp.u_max
        )

    def cell_averages(self, grid: np.ndarray) -> np.ndarray:
        """Averages of the control over the cells of ``grid`` (exact for polynomial pieces)."""
        return average_on_cells(self.control_at, self.element_bounds, np.asarray(grid, dtype=float))


def problem_at(ocp: HybridOCP, r: DTResult) -> HybridOCP:
    """The problem at ``r``'s final time (itself for a fixed final time)."""
    if ocp.horizon_bounds is None or r.horizon == ocp.horizon:
        return ocp
    return ocp.replace(horizon=r.horizon)


def resimulate(ocp: HybridOCP, r: DTResult) -> Evaluation:
    from hybridoc.callable_eval import evaluate_callable

    return evaluate_callable(
        problem_at(ocp, r),
        r.control_function(),
        breakpoints=r.element_bounds[1:-1],
        event_controls=r.event_controls,
    )


def resimulated_names(ocp: HybridOCP, ev: Evaluation) -> list[str]:
    return [ocp.guards[e.guard].name for e in ev.events]


def event_time_gap(ocp: HybridOCP, r: DTResult, ev: Evaluation) -> float | None:
    """Largest gap between modelled and re-simulated event times (``None``: other events)."""
    if resimulated_names(ocp, ev) != r.sequence:
        return None
    times = np.array([e.time for e in ev.events])
    return float(np.max(np.abs(times - r.event_times), initial=0.0))


def sequence_matches(ocp: HybridOCP, r: DTResult, ev: Evaluation, tol: float = 1e-6) -> bool:
    gap = event_time_gap(ocp, r, ev)
    return gap is not None and gap <= tol * ocp.horizon
