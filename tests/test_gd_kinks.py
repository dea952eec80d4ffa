"""gd at kinks of its loss (issue #29): an event pinned to a grid time.

The loss of piecewise-constant controls is not smooth where an event time crosses a grid
time, and L-BFGS stalled there and said ``success``: on the lifeguard problem (Snell
refraction, :func:`tests.kink_problems.snell`) 0.96% above the optimum of its own grid at 10
steps, 0.28% at 20. gd now goes on past such a kink (a nonsmooth BFGS with a gradient
sampling certificate) and reaches that optimum, computed here by numpy/scipy alone
(:func:`tests.kink_problems.snell_grid_optimum`), or says that it stalled.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from kink_problems import (
    SNELL_T_MIN,
    ball_2d,
    snell,
    snell_grid_optimum,
    snell_t_min,
    thermostat,
)

import hybridoc.solvers.gd as gd
from hybridoc import evaluate
from hybridoc.solvers.optimizers import min_norm_element, nonsmooth_bfgs


def test_snell_least_time_is_the_closed_form():
    assert snell_t_min() == pytest.approx(SNELL_T_MIN, rel=1e-12, abs=0)


@pytest.mark.parametrize("steps", [10, 20])
def test_the_grid_optimum_is_what_the_judge_measures(steps):
    """The closed-form cell costs are the judge's cost of their own controls, with the
    shore crossed where they say (an independent check of the independent optimum)."""
    T = SNELL_T_MIN
    cost, _, j, theta, u = snell_grid_optimum(steps, T, 100.0)
    ev = evaluate(snell(steps, horizon=T, weight=100.0), u)
    assert ev.cost == pytest.approx(cost, rel=1e-12)
    assert [e.name for e in ev.events] == ["shore"]
    assert ev.events[0].time == pytest.approx((j + theta) * T / steps, abs=1e-9)


@pytest.mark.parametrize(("steps", "before"), [(10, 9.6e-3), (20, 2.8e-3)])
def test_gd_reaches_the_optimum_of_its_grid_past_a_kink(steps, before):
    """Fixed final time, the target as a terminal cost. Before: success at +0.96% (10
    steps) and +0.28% (20), the crossing stalled 0.7% and 1.4% of a step short of t_4 and
    t_7, where the grid's optimum has it."""
    T = SNELL_T_MIN
    ocp = snell(steps, horizon=T, weight=100.0)
    best, _, j, theta, _ = snell_grid_optimum(steps, T, 100.0)
    sol = gd.solve_gd(ocp)
    assert sol.success, sol.message
    gap = sol.cost / best - 1
    assert -1e-12 < gap < 1e-5, gap
    kinks = sol.info["kinks"]
    assert kinks["loss_before"] / best - 1 > before / 2  # it was stalled, far above
    assert not kinks["stalled"] and kinks["stationarity"] <= gd.KINK_GTOL
    # the optimum of the grid has the crossing on a grid time, and so has gd's
    assert theta in (0.0, 1.0)
    assert sol.events[0]["time"] == pytest.approx((j + theta) * T / steps, abs=1e-9)


def test_free_final_time_snell_reaches_its_grid_optimum():
    """The free-final-time encoding (terminal constraints, augmented Lagrangian): its
    optimum is 2 T_min in the continuum, and on 10 steps gd's T and cost are the grid's."""
    best, T, _, _, _ = snell_grid_optimum(10)
    assert best > 2 * SNELL_T_MIN
    sol = gd.solve_gd(snell(10))
    assert sol.success, sol.message
    assert sol.info["horizon"] == pytest.approx(T, rel=1e-4)  # the cost is flat in T
    assert abs(sol.cost / best - 1) < 1e-5


def test_a_stall_at_a_kink_is_not_a_success(monkeypatch):
    """Without the iterations past the kink, the stalled descent is reported as such, with
    the event and the grid time (it was ``success`` at +0.96%)."""
    monkeypatch.setattr(gd.kinks, "KINK_ITERS", 0)
    ocp = snell(10, horizon=SNELL_T_MIN, weight=100.0)
    sol = gd.solve_gd(ocp)
    assert sol.status.value == "not-converged"
    assert sol.message.startswith("stalled at a kink: event 1 ('shore', t = 1.08")
    assert "pinned at grid time t_4 = 1.09018" in sol.message
    kinks = sol.info["kinks"]
    assert kinks["stalled"] and kinks["stationarity"] > 1e-3
    assert kinks["before"][0]["grid_index"] == 4 and abs(kinks["before"][0]["offset"]) < 0.01
    assert not sol.info["converged"]


@pytest.mark.parametrize(("make", "gain"), [(lambda: thermostat(40), 4e-5),
                                            (lambda: ball_2d(20), 6e-4)])  # fmt: skip
def test_user_problems_go_past_their_kinks(make, gain):
    """A thermostat (a heater switching at temperature thresholds) and a 2-D bouncing
    ball: the descent stalled with an event on a grid time (t_14; t_16) and said success;
    going past the kink lowers the loss (measured: 4.75e-5 and 6.7e-4 relative) to a
    certified stationary point."""
    sol = gd.solve_gd(make())
    kinks = sol.info["kinks"]
    assert sol.success and not kinks["stalled"], sol.message
    assert kinks["loss"] < kinks["loss_before"] * (1 - gain)
    assert kinks["stationarity"] <= gd.KINK_GTOL


def test_pinned_events_finds_events_near_inner_grid_times():
    ocp = snell(10, horizon=SNELL_T_MIN, weight=100.0)
    _, _, j, theta, u = snell_grid_optimum(10, SNELL_T_MIN, 100.0)
    (pin,) = gd.pinned_events(ocp, evaluate(ocp, u))
    assert pin["grid_index"] == j + theta and abs(pin["offset"]) < 1e-9
    assert pin["name"] == "shore" and pin["event"] == 1


# ---------------------------------------------------------------------- the optimiser
def test_min_norm_element_of_two_vectors_is_the_closed_form():
    a, b = np.array([3.0, 1.0]), np.array([-1.0, 2.0])
    t = float((b - a) @ b / ((b - a) @ (b - a)))  # argmin |t a + (1 - t) b|
    d, lam = min_norm_element(np.array([a, b]))
    assert np.allclose(d, t * a + (1 - t) * b, atol=1e-12)
    assert np.allclose(lam, [t, 1 - t], atol=1e-12)
    d0, _ = min_norm_element(np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0]]))
    assert np.allclose(d0, 0.0, atol=1e-12)


def test_nonsmooth_bfgs_converges_onto_a_kink():
    """f = |x_0 - 1| + 2 max(x_1, -x_1 / 2) + (x_0^2 + x_1^2 + x_2^2) / 2, minimised at
    (1, 0, 0) (the subgradient 1 - [-1, 1] in x_0 contains 0; in x_1, [-1, 2] contains 0)
    with f = 1/2; L-BFGS-style smooth methods stall on either kink."""

    def fun(x):
        f = abs(x[0] - 1) + 2 * max(x[1], -x[1] / 2) + 0.5 * float(x @ x)
        g = x.copy()
        g[0] += math.copysign(1.0, x[0] - 1)
        g[1] += 2.0 if x[1] > -x[1] / 2 else -1.0
        return f, g

    res = nonsmooth_bfgs(fun, np.array([3.0, -2.0, 1.0]), gtol=1e-9)
    assert res.message.startswith("stationary"), res.message
    assert np.allclose(res.x, [1.0, 0.0, 0.0], atol=1e-7)
    assert res.f == pytest.approx(0.5, abs=1e-10)
    assert res.stationarity <= 1e-9
