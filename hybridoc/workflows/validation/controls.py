"""A user's controls judged against the reference optimum (:func:`validate_controls`) and
their overlay figures."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.evaluator import evaluate
from hybridoc.methods import REFERENCE_METHOD, solve
from hybridoc.problem import ControlsLike, ProblemLike, as_ocp
from hybridoc.solution import Solution
from hybridoc.workflows.validation.measures import (
    control_errors,
    event_comparison,
)

if TYPE_CHECKING:  # pragma: no cover
    pass

__all__ = [
    "validate_controls",
    "validation_figures",
]


def validate_controls(
    problem: ProblemLike,
    controls: ControlsLike,
    *,
    reference: Solution | None = None,
    substeps: int = 1,
) -> dict[str, Any]:
    """Judge a user's piecewise-constant control against the reference optimum.

    Parameters
    ----------
    problem
        Any problem.
    controls
        ``(N, nu)`` array or a Solution (validated: shape, finiteness); ``(N * K, nu)``
        with ``substeps=K``. A Solution is judged by its own control
        (:meth:`~hybridoc.Solution.control`), so ``cost`` is its ``cost`` bit for bit.
    reference
        The reference Solution of ``problem`` (on its own grid); solved when not given.
    substeps
        ``K``: the controls hold ``K`` values per grid interval (a simulator's log at ``K``
        substeps) and are judged exactly on the ``K`` times finer grid
        (:func:`hybridoc.io.substep_problem`); the gap is to the reference of ``problem``,
        and the control error compares them with the reference's values held over the
        ``K`` substeps.

    Returns
    -------
    dict
        ``cost``, ``terminal_cost``, ``running_cost``, ``reference_cost``,
        ``cost_gap_relative`` (``(J - J*) / J*``), ``control_error`` (``l2``, ``max``),
        ``events``, ``reference_events``, ``sequence_matches``, ``event_time_errors``,
        ``reference_status``, ``feasible``, ``bound_violation``, ``path_violation``,
        ``terminal_violation`` (the judge's), ``substeps``.
    """
    from hybridoc.io import substep_problem

    ocp = as_ocp(problem)
    fine = substep_problem(ocp, substeps)
    u = fine.check_controls(getattr(controls, "controls", controls))
    if reference is None:
        reference = solve(ocp, REFERENCE_METHOD)
    # a Solution is judged by its own control (so its cost comes back bit for bit)
    own = substeps == 1 and hasattr(controls, "control_kind")
    ev = evaluate(fine, controls if own else u)
    events = ev.event_dicts()
    cmp = event_comparison(events, reference.events)
    return {
        "problem": ocp.name,
        "cost": float(ev.cost),
        "terminal_cost": float(ev.terminal_cost),
        "running_cost": float(ev.running_cost),
        "reference_cost": float(reference.cost),
        "reference_status": reference.status.value,
        "cost_gap_relative": float((ev.cost - reference.cost) / abs(reference.cost)),
        "control_error": control_errors(
            u, np.repeat(np.asarray(reference.controls), fine.steps // ocp.steps, axis=0), fine.dt
        ),
        "events": events,
        "reference_events": list(reference.events),
        "sequence_matches": cmp["sequence_matches"],
        "event_time_errors": cmp["time_errors"],
        "feasible": ev.feasible,
        "bound_violation": float(ev.bound_violation),
        "path_violation": float(ev.path_violation),
        "terminal_violation": float(ev.terminal_violation),
        "substeps": fine.steps // ocp.steps,
    }


def validation_figures(
    problem: ProblemLike, controls: np.ndarray, reference: Solution, *, label: str = "user"
) -> dict[str, Any]:
    """Figures ``controls`` (user vs reference) and ``trajectories`` (overlaid)."""
    from hybridoc.plotting import plot_controls, plot_trajectories

    ocp = as_ocp(problem)
    ev_user = evaluate(ocp, controls)
    fig_u = plot_controls(
        ocp.time_grid(),
        {REFERENCE_METHOD: reference.controls, label: controls},
        list(ocp.control_labels or []),
        title=f"{ocp.name}: {label} control vs reference",
        event_times={
            REFERENCE_METHOD: [e["time"] for e in reference.events],
            label: [e.time for e in ev_user.events],
        },
    )
    fig_x = plot_trajectories(
        ocp,
        {REFERENCE_METHOD: evaluate(ocp, reference.controls), label: ev_user},
        title=f"{ocp.name}: {label} trajectory vs reference",
    )
    return {"controls": fig_u, "trajectories": fig_x}
