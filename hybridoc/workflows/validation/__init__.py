"""Validation against the HMP reference: user controls, cross-validation, convergence.

Three reports, each a JSON-ready dict plus figures:

- :func:`validate_controls`: the true continuous cost of a user's piecewise-constant control
  (the judge), its relative gap to the reference optimum, control errors on the grid, and
  whether its events are the reference's.
- :func:`crossval`: registered methods (:data:`hybridoc.methods.METHODS`) on one problem,
  each measured twice: against the reference, and against the reference projected onto
  the method's own representation (:func:`representable`), within the tolerance the method
  declares (:attr:`~hybridoc.methods.Method.tolerance`). A gap to the projection beyond the
  tolerance is a disagreement; so is an event sequence other than the reference's, or a
  projection that is itself beyond the tolerance of the reference, unless an independent
  check explains it (:data:`EXPLAINING_CHECKS`). When the reference refuses the problem
  the other methods are compared with each other. Disagreements are findings (``agree``
  false with the reasons, ``status`` ``disagree``); a method that fails is a row that says
  so.
- :func:`convergence`: each method's cost on grids of N cells (a method continuous in time
  averaged on each grid, a method on the grid re-run at each N), errors against the
  reference and observed orders.

What a method is measured against follows from its :class:`~hybridoc.methods.Method`
record (:attr:`~hybridoc.methods.Method.representation`, its resolution option, its loss
history): no method is named here. One module per concern: :mod:`.measures` (gaps, control
errors, event sequences, a method's row), :mod:`.controls` (a user's controls),
:mod:`.projection` (the yardsticks), :mod:`.comparison` (crossval) and
:mod:`.convergence_study`.

Control errors are taken on the N-grid (cell averages for continuous-time controls):
``l2 = sqrt(sum_n |u_n - u*_n|^2 dt)`` (an approximation of the L2(0, T) norm) and
``max = max_n,k |u_nk - u*_nk|``.
"""

from __future__ import annotations

from hybridoc.workflows.validation.comparison import (
    EXPLAINING_CHECKS,
    REFINE_RATIO,
    crossval,
    crossval_figures,
)
from hybridoc.workflows.validation.controls import validate_controls, validation_figures
from hybridoc.workflows.validation.convergence_study import (
    DEFAULT_STEPS,
    convergence,
    convergence_figure,
    observed_orders,
)
from hybridoc.workflows.validation.measures import (
    RESULT_STATUSES,
    control_errors,
    event_comparison,
    figure_evaluation,
    judged_evaluation,
    method_entry,
)
from hybridoc.workflows.validation.projection import (
    local_gap,
    refined_projection,
    representable,
)

__all__ = [
    "DEFAULT_STEPS",
    "EXPLAINING_CHECKS",
    "REFINE_RATIO",
    "RESULT_STATUSES",
    "control_errors",
    "convergence",
    "convergence_figure",
    "crossval",
    "crossval_figures",
    "event_comparison",
    "figure_evaluation",
    "judged_evaluation",
    "local_gap",
    "method_entry",
    "observed_orders",
    "refined_projection",
    "representable",
    "validate_controls",
    "validation_figures",
]
