"""A hybrid system that is not made of discs: HybridOCP.from_expressions without a flow map
(CasADi's CVODES integrates the flow), checked against closed forms and finite differences."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest
from scipy.special import ellipk

import hybridoc
from hybridoc import Guard, HybridOCP

G_EARTH, E_BALL, THRUST = 9.81, 0.9, 2.0


def bouncing_ball(degree: int | None, steps: int = 100) -> HybridOCP:
    """Height h, velocity v; thrust u; the ground h = 0 reverses v with restitution 0.9."""
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u")
    ground = Guard.from_expressions(
        "ground", s, s[0], ca.vertcat(s[0], -E_BALL * s[1]), kind="bounce", degree=degree
    )
    return HybridOCP.from_expressions(
        s, u, f=ca.vertcat(s[1], u - G_EARTH), L=0.01 * u**2, phi=(s[0] - 1.0) ** 2,
        guards=[ground], x0=[1.0, 0.0], horizon=2.5, steps=steps,
        u_guess=np.full((steps, 1), THRUST), name="ball",
    )  # fmt: skip


def bounce_times(h0: float, g: float, e: float, horizon: float) -> list[float]:
    """Drop from rest at h0 under gravity g: first impact at sqrt(2 h0 / g) with speed
    v1 = g t1; then flights of 2 e^k v1 / g."""
    t, v = math.sqrt(2 * h0 / g), math.sqrt(2 * h0 * g)
    out = []
    while t < horizon:
        out.append(t)
        v *= e
        t += 2 * v / g
    return out


@pytest.fixture(scope="module", params=[2, None], ids=["degree2", "degree-unknown"])
def ball(request) -> HybridOCP:
    return bouncing_ball(request.param)


def test_ball_uses_the_integrator_flow(ball):
    assert ball.flow_map is not None and ball.flow_map.is_a("MXFunction")
    assert ball.guards[0].degree in (2, None)


def test_ball_bounce_times_and_energy(ball):
    ev = hybridoc.evaluate(ball)
    g = G_EARTH - THRUST
    expected = bounce_times(1.0, g, E_BALL, ball.horizon)
    assert len(expected) == 3
    assert [e.bodies for e in ev.events] == [()] * 3 and ev.events[0].kind == "bounce"
    np.testing.assert_allclose([e.time for e in ev.events], expected, rtol=0, atol=1e-9)

    def energy(s: np.ndarray) -> float:
        return 0.5 * s[1] ** 2 + g * s[0]

    e_before = [energy(e.state_before) for e in ev.events]
    e_after = [energy(e.state_after) for e in ev.events]
    assert e_before[0] == pytest.approx(g * 1.0, rel=1e-11)
    for k in range(len(ev.events)):
        assert e_after[k] == pytest.approx(E_BALL**2 * e_before[k], rel=1e-12)
        if k + 1 < len(ev.events):  # conserved in flight, so e^2 per bounce
            assert e_before[k + 1] / e_before[k] == pytest.approx(E_BALL**2, rel=1e-9)
    assert ev.running_cost == pytest.approx(0.01 * THRUST**2 * ball.horizon, rel=1e-11)
    # closed form of h(T): after the last bounce the ball rises at e^3 v1 minus g t
    t3 = expected[-1]
    v3 = E_BALL**3 * math.sqrt(2 * g)
    tau = ball.horizon - t3
    h_T = v3 * tau - 0.5 * g * tau**2
    assert ev.final_state == pytest.approx([h_T, v3 - g * tau], abs=1e-9)
    assert ev.terminal_cost == pytest.approx((h_T - 1) ** 2, abs=1e-9)


def test_ball_degrees_agree():
    a, b = (hybridoc.evaluate(bouncing_ball(d)) for d in (2, None))
    assert a.cost == pytest.approx(b.cost, rel=1e-11)
    np.testing.assert_allclose([e.time for e in a.events], [e.time for e in b.events], atol=1e-11)


def test_ball_gradient_matches_finite_differences(ball):
    rng = np.random.default_rng(4)
    u = ball.u_guess + 0.5 * rng.standard_normal(ball.u_guess.shape)
    gr = hybridoc.gradient(ball, u)
    ev = gr.evaluation
    assert len(ev.events) == 3
    sig = [seg.interval for seg in ev.segments if seg.event is not None]

    def cost(x0: np.ndarray, uu: np.ndarray) -> float:
        probe = ball.replace(x0=x0)  # same structure: the compiled functions are shared
        e = hybridoc.evaluate(probe, uu)
        assert [seg.interval for seg in e.segments if seg.event is not None] == sig
        return e.cost

    step = 1e-5
    for k in range(2):
        d = np.zeros(2)
        d[k] = step
        fd = (cost(ball.x0 + d, u) - cost(ball.x0 - d, u)) / (2 * step)
        assert gr.d_initial_state[k] == pytest.approx(fd, rel=1e-6, abs=1e-7)
    rows = sorted({0, 37, ball.steps - 1, *sig})
    for n in rows:
        up, um = u.copy(), u.copy()
        up[n, 0] += 1e-3
        um[n, 0] -= 1e-3
        fd = (cost(ball.x0, up) - cost(ball.x0, um)) / 2e-3
        assert gr.d_controls[n, 0] == pytest.approx(fd, rel=1e-6, abs=1e-9)
    np.testing.assert_array_equal(gr.d_initial_state, gr.costates[0])


def test_pendulum_against_elliptic_integral():
    """A non-polynomial flow with degree=None: a pendulum released at theta0 hits a wall at
    theta = 0 after the quarter period K(sin^2(theta0 / 2)) (g / l = 1) with speed
    2 sin(theta0 / 2), and after a bounce with restitution e rises to theta1 with
    1 - cos(theta1) = (e * speed)^2 / 2, coming back after 2 K(sin^2(theta1 / 2))."""
    th0, e = 1.2, 0.8
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u")
    wall = Guard.from_expressions("wall", s, s[0], ca.vertcat(s[0], -e * s[1]))
    ocp = HybridOCP.from_expressions(
        s, u, f=ca.vertcat(s[1], -ca.sin(s[0]) + u), L=u**2, phi=s[0] ** 2,
        guards=[wall], x0=[th0, 0.0], horizon=6.0, steps=40,
    )  # fmt: skip
    ev = hybridoc.evaluate(ocp)
    t1 = ellipk(math.sin(th0 / 2) ** 2)
    speed = 2 * math.sin(th0 / 2)
    th1 = math.acos(1 - 0.5 * (e * speed) ** 2)
    t2 = t1 + 2 * ellipk(math.sin(th1 / 2) ** 2)
    times = [x.time for x in ev.events]
    assert times[:2] == pytest.approx([t1, t2], abs=1e-10)
    assert ev.events[0].approach_speed == pytest.approx(-speed, rel=1e-10)
