"""Solution.sample's costates of the reference: rebuilt exactly between the stored samples
(state and costate integrated from the phase start under the Solution's control), against
closed forms."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import hybridoc
from hybridoc.ocp import HybridOCP

C, W, EPS = 2.0, 5.0, 0.05


def _damped() -> HybridOCP:
    """x' = v, v' = u - c v, no events; J = w (x(T) - 1)^2 + w v(T)^2 + eps int u^2."""
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u", 1)
    return HybridOCP(
        f=ca.Function("f", [s, u], [ca.vertcat(s[1], u - C * s[1])]),
        L=ca.Function("L", [s, u], [EPS * u[0] ** 2]),
        phi=ca.Function("phi", [s], [W * (s[0] - 1) ** 2 + W * s[1] ** 2]),
        guards=[], x0=np.array([0.0, 0.0]), horizon=1.0, steps=50, name="damped",
    )  # fmt: skip


def test_the_costate_of_a_damped_mass_is_its_closed_form_between_samples() -> None:
    """lambda_x' = 0, lambda_v' = c lambda_v - lambda_x with lambda(T) = grad phi(s(T)):
    lambda_x = a and lambda_v(t) = a / c + (lambda_v(T) - a / c) exp(c (t - T)). Linear
    interpolation of the stored samples misses the exponential by 2e-4; the rebuilt
    costate is the closed form to the reference's accuracy."""
    sol = hybridoc.solve(_damped(), "reference")
    assert sol.success and sol.control_kind == "hmp" and not sol.events
    ts = np.linspace(0.0, 1.0, 23) + 0.37 / 50  # between the stored samples (grid times)
    ts[-1] = 1.0
    got = sol.sample(ts)
    x_T, v_T = got.states[-1]
    a, lv_T = 2 * W * (x_T - 1), 2 * W * v_T
    exact = np.c_[np.full(ts.size, a), a / C + (lv_T - a / C) * np.exp(C * (ts - 1.0))]
    assert got.costates is not None
    np.testing.assert_allclose(got.costates, exact, rtol=0, atol=1e-9)
    linear = np.array([np.interp(ts, sol.costate_times, sol.costates[:, i]) for i in (0, 1)]).T
    assert np.max(np.abs(linear - exact)) > 1e-5  # what sample returned before
    # the HMP control u = -lambda_v / (2 eps) of the rebuilt costate is the Solution's own
    np.testing.assert_allclose(got.controls[:, 0], -got.costates[:, 1] / (2 * EPS), atol=1e-9)


@pytest.fixture(scope="module")
def ball_reference() -> hybridoc.Solution:
    return hybridoc.solve("bouncing-ball", "reference")


def test_the_bouncing_balls_costate_is_linear_on_each_arc(
    ball_reference: hybridoc.Solution,
) -> None:
    """h' = v, v' = u - g, L = eps u^2: lambda_h is constant and lambda_v' = -lambda_h on
    each arc, from the phase's start (after the jump); at the bounce lambda_v(gamma-) =
    -e lambda_v(gamma+) (the jump relation of the reset v+ = -e v-)."""
    sol = ball_reference
    starts = sol.arrays["phase_starts"]
    L0 = sol.arrays["phase_costates"]
    (event,) = sol.events
    gamma = event["time"]
    grid = sol.time_grid
    ts = np.r_[0.5 * (grid[:-1] + grid[1:])[::7], gamma, sol.horizon]
    got = sol.sample(ts)
    k = np.searchsorted(starts, ts, side="right") - 1
    exact = np.c_[L0[k, 0], L0[k, 1] - L0[k, 0] * (ts - starts[k])]
    np.testing.assert_allclose(got.costates, exact, rtol=0, atol=1e-13)
    # the stored samples are the same costate
    at_grid = sol.sample(grid[::25])
    stored = dict(zip(sol.costate_times.tolist(), sol.costates, strict=False))
    want = np.array([stored[t] for t in grid[::25].tolist()])
    np.testing.assert_allclose(at_grid.costates, want, rtol=0, atol=1e-13)
    # across the bounce
    before = sol.sample([gamma - 1e-9]).costates[0]
    after = sol.sample([gamma]).costates[0]
    e = 0.8
    assert before[1] == pytest.approx(-e * after[1], abs=1e-9)
    # the terminal condition lambda(T) = grad phi(s(T))
    h_T, v_T = got.states[-1]
    p = sol.problem.meta["params"]
    grad = [2 * p["weight_height"] * (h_T - p["target_height"]),
            2 * p["weight_velocity"] * (v_T - p["target_velocity"])]  # fmt: skip
    np.testing.assert_allclose(got.costates[-1], grad, rtol=0, atol=1e-9)


def test_the_costate_on_an_active_path_arc_carries_the_multiplier() -> None:
    """The ceiling integrator of test_reference_path (x' = u, c = 1 - x - u >= 0): lambda =
    -k before the junction t1 and -k cosh(t - t1) on the boundary arc, where lambda' =
    -(H_x - nu c_x) = -nu is not -H_x = 0 (the rebuild adds c_s^T nu of the active rows)."""
    from test_reference_path import ceiling, ceiling_closed_form

    cf = ceiling_closed_form()
    sol = hybridoc.solve(ceiling(), "reference")
    assert sol.success, sol.message
    ts = np.linspace(0.0, 2.0, 29) + 0.013
    ts[-1] = 2.0
    got = sol.sample(ts).costates[:, 0]
    tau = np.maximum(ts - cf["t1"], 0.0)
    np.testing.assert_allclose(got, -cf["k"] * np.cosh(tau), rtol=0, atol=1e-8)


def test_the_costate_jumps_at_a_state_constraints_entry() -> None:
    """The plateau of test_reference_state_constraints (x' = u, min int u^2/2 - x, x(T) = 0,
    x <= a): lambda' = 1 everywhere (the boundary arc holds c1 = -u = 0, whose c1_x = 0), so
    lambda = t - t1 before the entry, where u = -lambda reaches 0, and t - t2 after it: the
    entry jump lambda(t1+) - lambda(t1-) = eta grad c = -(t2 - t1)."""
    from test_reference_state_constraints import plateau, plateau_closed_form

    cf = plateau_closed_form()
    sol = hybridoc.solve(plateau(), "reference")
    assert sol.success, sol.message
    ts = np.linspace(0.0, 2.0, 31) + 0.011
    ts[-1] = 2.0
    got = sol.sample(ts).costates[:, 0]
    exact = np.where(ts < cf["t1"], ts - cf["t1"], ts - cf["t2"])
    np.testing.assert_allclose(got, exact, rtol=0, atol=1e-8)
