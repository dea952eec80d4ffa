"""``evaluate_callable``'s report of a time control at the cell midpoints (issue #18): one
pass over the times for a control that returns float64 arrays, the checked call per point
otherwise; the same values either way, the same errors."""

from __future__ import annotations

import numpy as np
import pytest

from hybridoc.callable_eval import evaluate_callable
from hybridoc.errors import ControlsError
from hybridoc.problem import as_ocp
from hybridoc.problems import load_problem


def test_the_one_pass_report_equals_the_checked_calls() -> None:
    ocp = as_ocp(load_problem("bouncing-ball"))
    mids = (np.arange(ocp.steps) + 0.5) * ocp.dt
    # piecewise constant with jumps exactly at two cell midpoints: the clamping of the time
    # into its integration piece decides which side such a midpoint reads
    a, b = float(mids[50]), float(mids[120])

    def steps(t: float) -> float:
        return 1.0 if t < a else (-2.0 if t < b else 0.5)

    fast = evaluate_callable(ocp, lambda t: np.array([steps(t)]), breakpoints=[a, b])
    # a list is no float64 array: every value goes through the checked call
    slow = evaluate_callable(ocp, lambda t: [steps(t)], breakpoints=[a, b])
    assert np.array_equal(fast.controls, slow.controls)
    assert fast.cost == slow.cost
    assert {-2.0, 0.5, 1.0} <= set(fast.controls[:, 0].tolist())


def test_a_bad_value_is_reported_as_before() -> None:
    ocp = as_ocp(load_problem("bouncing-ball"))
    late = ocp.horizon - 0.5 * ocp.dt  # only the last midpoint: the report meets it first

    def nan_late(t: float) -> np.ndarray:
        return np.array([np.nan if t >= late else 0.0])

    with pytest.raises(ControlsError, match=r"must be 1 finite numbers"):
        evaluate_callable(ocp, nan_late)

    def two_late(t: float) -> np.ndarray:
        return np.zeros(2 if t >= late else 1)

    with pytest.raises(ControlsError, match=r"must be 1 finite numbers"):
        evaluate_callable(ocp, two_late)
