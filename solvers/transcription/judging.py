"""A candidate judged: its control re-simulated by the judge, whether it is feasible, and the
nudge of its controls past events it misses by a hair.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridoc import tolerances
from hybridoc.errors import EvaluationError
from hybridoc.evaluation import Evaluation
from hybridoc.ocp import HybridOCP
from hybridoc.solvers.transcription.collocation import lagrange_basis
from hybridoc.solvers.transcription.monitor import MONITOR
from hybridoc.solvers.transcription.options import TERMINAL_TOL
from hybridoc.solvers.transcription.result import DTResult, resimulate, sequence_matches

__all__ = ["Judged", "PATH_TOL", "bound_tol", "judge", "try_nudges"]


_BOUND_TOL = tolerances.FEASIBILITY  # judged control-bound violation: INFEASIBLE above it


PATH_TOL = tolerances.PATH  # judged path-constraint violation: INFEASIBLE above it


_NUDGES = (1e-9, 1e-7)
"""Extensions (relative to ``T``) of each phase's last control piece past its event that
:func:`_nudged` tries, in order, on a candidate whose re-simulation misses its events."""


def bound_tol(ocp: HybridOCP) -> float:
    """:data:`_BOUND_TOL` in the controls' units (the smallest control scale)."""
    return _BOUND_TOL * float(np.min(ocp.scales.control_array, initial=1.0))


@dataclass
class Judged:
    """A converged candidate with its re-simulation by the judge."""

    result: DTResult
    ev: Evaluation | None
    error: str = ""
    terminal_tol: float = TERMINAL_TOL
    nudge: float = 0.0  # the extension of :func:`_nudged` that made it reproduce its events
    estimate: dict[str, Any] | None = None  # :func:`error_estimate`, where computed

    @property
    def feasible(self) -> bool:
        assert self.ev is not None
        return (
            self.ev.bound_violation <= bound_tol(self.result._nlp.ocp)
            and self.ev.path_violation <= PATH_TOL
            and self.ev.terminal_violation <= self.terminal_tol
        )


def judge(ocp: HybridOCP, r: DTResult, terminal_tol: float) -> Judged:
    """``r`` with the judge's re-simulation of its control (or the reason it failed); the
    run in progress keeps it (what a stopped run returns)."""
    try:
        j = Judged(r, resimulate(ocp, r), terminal_tol=terminal_tol)
    except EvaluationError as exc:
        j = Judged(r, None, str(exc), terminal_tol=terminal_tol)
    monitor = MONITOR.get()
    if monitor is not None:
        monitor.judged.append(j)
    return j


def _nudged(r: DTResult, delta: float) -> DTResult | None:
    """``r`` with each phase's last control polynomial extended ``delta`` past its event.

    The NLP puts each event exactly at a phase end: the guard is zero there and the next
    phase's control starts. Re-simulated, the control reaches the guard to within the
    integrator's and the collocation's errors; where the next phase's control stops the
    approach (a clock driven before a switch and frozen after it), a state that stopped
    ``1e-12`` short of the guard never crosses it. Extending the approaching phase's
    control polynomial over ``[gamma, gamma + delta]`` (one more element) and starting the
    next phase's at ``gamma + delta`` (its first element shrunk, the same polynomial in time)
    lets the trajectory cross the guard transversally, as the NLP's approach condition says
    it does. What this control does is judged like any other: it must reproduce the
    modelled events, and its cost is the judge's. ``None`` when ``delta`` is not below half
    of every phase's first element.
    """
    nlp = r._nlp
    if not r.sequence:
        return None
    rad, d, nu = nlp.rad, nlp.d, nlp.ocp.nu
    eb = np.asarray(r.element_bounds, dtype=float)
    vals = np.concatenate(r.controls, axis=1).reshape(nu, -1, d)
    nodes = rad.tau[1:]
    # the index of each phase's last element in the global element list
    ends = np.cumsum([c.shape[1] // d for c in r.controls])
    bounds, per_phase = [eb[0]], []
    for k in range(len(r.controls)):
        first = 0 if k == 0 else int(ends[k - 1])
        last = int(ends[k])
        phase_bounds, phase_vals = [], []
        for e in range(first, last):
            a, b, v = eb[e], eb[e + 1], vals[:, e, :]
            if k > 0 and e == first:
                # the extension of the previous phase's last piece, then this piece shrunk
                pa, pb, pv = eb[e - 1], eb[e], vals[:, e - 1, :]
                if not delta < 0.5 * (b - a):
                    return None
                t_ext = a + delta * nodes
                ext = pv @ lagrange_basis(nodes, (t_ext - pa) / (pb - pa)).T
                phase_bounds.append(a + delta)
                phase_vals.append(ext)
                t_new = a + delta + (b - a - delta) * nodes
                v = v @ lagrange_basis(nodes, (t_new - a) / (b - a)).T
            phase_bounds.append(b)
            phase_vals.append(v)
        bounds += phase_bounds
        per_phase.append(np.concatenate(phase_vals, axis=1))
    controls = [nlp.clip_controls(c) for c in per_phase]
    element_bounds = np.array(bounds)
    control_times = []
    i = 0
    for c in controls:
        n = c.shape[1] // d
        loc = element_bounds[i : i + n]
        he = element_bounds[i + 1 : i + n + 1] - loc
        control_times.append((loc[:, None] + he[:, None] * nodes[None, :]).ravel())
        i += n
    return dataclasses.replace(
        r, controls=controls, control_times=control_times, element_bounds=element_bounds
    )


def try_nudges(ocp: HybridOCP, r: DTResult, terminal_tol: float) -> tuple[Judged, float] | None:
    """The first of :data:`_NUDGES` whose :func:`_nudged` control reproduces ``r``'s events
    (judged), with the extension used; ``None`` if none does."""
    for rel in _NUDGES:
        rn = _nudged(r, rel * r.horizon)
        if rn is None:
            return None
        jn = judge(ocp, rn, terminal_tol)
        if jn.ev is not None and sequence_matches(ocp, rn, jn.ev):
            jn.nudge = rel * r.horizon
            return jn, jn.nudge
    return None
