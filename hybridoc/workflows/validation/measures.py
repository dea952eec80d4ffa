"""What every validation report measures: the gap of costs, control errors on the grid,
event sequences compared, one method's row, and the statuses a method's own result may have
without a finding.

Control errors are taken on the N-grid (cell averages for continuous-time controls):
``l2 = sqrt(sum_n |u_n - u*_n|^2 dt)`` (an approximation of the L2(0, T) norm) and
``max = max_n,k |u_nk - u*_nk|``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.solution import Solution, Status

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.evaluation import Evaluation

__all__ = [
    "RESULT_STATUSES",
    "control_errors",
    "event_comparison",
    "event_key",
    "figure_evaluation",
    "judged_evaluation",
    "method_entry",
    "relative",
    "sequence_text",
]


RESULT_STATUSES: frozenset[Status] = frozenset({Status.SUCCESS, Status.EXTREMAL, Status.BEST_FOUND})
"""The statuses of a method's own result that crossval compares without a finding of their
own: ``success``, ``extremal`` (a given sequence's extremal) and ``best-found`` (a search's
best, not proven). The others (``not-optimal``, ``events-differ``, ``infeasible``,
``not-converged``, ``disagree``) are findings the method made about itself."""


def control_errors(controls: np.ndarray, reference: np.ndarray, dt: float) -> dict[str, float]:
    """Grid L2 and max errors of ``(N, nu)`` controls against the reference's.

    Returns
    -------
    dict
        ``{"l2": sqrt(sum |u - u*|^2 dt), "max": max |u - u*|}``.
    """
    diff = np.asarray(controls, dtype=float) - np.asarray(reference, dtype=float)
    return {"l2": float(np.sqrt(np.sum(diff**2) * dt)), "max": float(np.abs(diff).max())}


def event_key(e: Mapping[str, Any]) -> str:
    """The guard of an event record (or its bodies joined by ``|``)."""
    return str(e.get("guard") or "|".join(e.get("bodies", [])))


def event_comparison(
    events: Sequence[Mapping[str, Any]], reference: Sequence[Mapping[str, Any]]
) -> dict[str, Any]:
    """Whether two event lists have the same sequence (guards in time order), and the time
    errors if they do (``None`` when the sequences differ)."""
    same = [event_key(e) for e in events] == [event_key(e) for e in reference]
    errs = (
        [float(e["time"] - r["time"]) for e, r in zip(events, reference, strict=True)]
        if same
        else None
    )
    return {
        "sequence_matches": same,
        "time_errors": errs,
        "max_time_error": max((abs(x) for x in errs), default=0.0) if errs is not None else None,
    }


def method_entry(
    sol: Solution, ref: Solution | None, *, wall_time_s: float | None = None
) -> dict[str, Any]:
    """The cross-validation row of one Solution measured against the reference Solution
    (``None`` when there is none: the comparisons are then ``None``)."""
    dt = float(sol.time_grid[1] - sol.time_grid[0])
    ev = (
        event_comparison(sol.events, ref.events)
        if ref is not None
        else {"sequence_matches": None, "time_errors": None}
    )
    out: dict[str, Any] = {
        "status": sol.status.value,
        "success": sol.success,
        "message": sol.message,
        "cost": float(sol.cost),
        "terminal_cost": float(sol.terminal_cost),
        "running_cost": float(sol.running_cost),
        "cost_gap_relative": None if ref is None else relative(sol.cost, ref.cost),
        "events": list(sol.events),
        "sequence": sol.sequence,
        "event_times": [float(e["time"]) for e in sol.events],
        "sequence_matches": ev["sequence_matches"],
        "event_time_errors": ev["time_errors"],
        "control_error": None if ref is None else control_errors(sol.controls, ref.controls, dt),
        "solve_time_s": float(sol.timings.get("solve_time_s", float("nan"))),
    }
    if wall_time_s is not None:
        out["wall_time_s"] = float(wall_time_s)
    if "loss" in sol.info:
        out["discrete_loss"] = float(sol.info["loss"])
    return out


def relative(cost: float, against: float) -> float:
    """``(cost - against) / |against|``, or the difference when ``against`` is 0."""
    return float((cost - against) / abs(against)) if against else float(cost - against)


def sequence_text(sol: Solution | Mapping[str, Any]) -> str:
    """The guards of a Solution's (or a report entry's) events, in words."""
    events = sol.events if isinstance(sol, Solution) else sol.get("events", [])
    return ", ".join(event_key(e) for e in events) or "no event"


def judged_evaluation(sol: Solution) -> Evaluation | None:
    """The judge's evaluation ``sol``'s cost came from (:attr:`Solution.evaluation`), so
    that a figure need not judge again; ``None`` where the Solution keeps none (a loaded
    file, changed costs)."""
    from hybridoc.evaluation import Evaluation

    ev = getattr(sol, "evaluation", None)
    return ev if isinstance(ev, Evaluation) else None


def figure_evaluation(ocp: Any, sol: Solution) -> Evaluation:
    """The evaluation to draw ``sol`` from: the one its cost came from
    (:func:`judged_evaluation`), or, where it keeps none, the judge's of its grid controls."""
    ev = judged_evaluation(sol)
    if ev is not None:
        return ev
    from hybridoc.evaluator import evaluate

    return evaluate(ocp, sol.controls)
