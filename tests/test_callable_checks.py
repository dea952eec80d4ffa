"""``evaluate_callable``'s check of each value ``u(t)`` the integrator asks for (issue #18): a
float64 array of ``nu`` finite numbers is taken as it is, anything else is converted and
checked as before; the same trajectory either way, the same errors."""

from __future__ import annotations

import numpy as np
import pytest

from hybridoc.callable_eval import evaluate_callable
from hybridoc.errors import ControlsError
from hybridoc.problem import as_ocp
from hybridoc.problems import load_problem


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return a.shape == b.shape and np.array_equal(a.view(np.int64), b.view(np.int64))


def _ocp():
    return as_ocp(load_problem("bouncing-ball"))


def _push(t: float) -> float:
    # smooth, with bounces: the events and the integrator's steps depend on every value
    return 2.0 * np.sin(3.0 * t) - 1.0


@pytest.mark.parametrize(
    "form",
    [
        lambda v: [v],  # a list: the converted path
        lambda v: (v,),
        lambda v: np.array([[v]]),  # float64 of another shape: taken, flattened
        lambda v: np.array([v]).view(np.matrix),  # a subclass: the converted path
    ],
)
def test_every_form_of_a_value_gives_the_same_trajectory(form) -> None:
    ocp = _ocp()
    fast = evaluate_callable(ocp, lambda t: np.array([_push(t)]))
    other = evaluate_callable(ocp, lambda t: form(_push(t)))
    assert fast.events
    assert _same_bits(fast.times, other.times)
    assert _same_bits(fast.states, other.states)
    assert fast.cost == other.cost


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_a_value_that_is_not_finite_mid_horizon_is_an_error(bad: float) -> None:
    ocp = _ocp()
    mid = 0.5 * ocp.horizon

    def u(t: float) -> np.ndarray:
        return np.array([bad if abs(t - mid) < 0.1 * ocp.horizon else 0.0])

    with pytest.raises(ControlsError, match=r"must be 1 finite numbers"):
        evaluate_callable(ocp, u)


def test_a_float64_array_of_the_wrong_size_is_an_error() -> None:
    ocp = _ocp()
    with pytest.raises(ControlsError, match=r"must be 1 finite numbers"):
        evaluate_callable(ocp, lambda t: np.zeros(2))
    with pytest.raises(ControlsError, match=r"must be 1 finite numbers"):
        evaluate_callable(ocp, lambda t: np.zeros(0))
