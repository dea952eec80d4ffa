"""Issue #15's time-dependent flows and costs, lowered to a time state (HybridOCP notes).

The closed form: ``x' = u + sin t``, ``x(0) = 0``, ``J = int_0^T u^2 dt + w (x(T) - x_T)^2``.
The costate is constant, ``lambda = 2 w (x(T) - x_T)``, so the optimal control is the
constant ``u = -lambda / 2``; with ``x(T) = c T + 1 - cos T`` for ``u = c``,
``dJ/dc = 2 c T + 2 w T (c T + 1 - cos T - x_T) = 0`` gives
``c* = w (x_T - 1 + cos T) / (1 + w T)``. A constant is piecewise constant, so ``c*`` is also
the optimum on any grid: the judge's cost there is ``J*``, its gradient vanishes, and dt
(whose control may be any polynomial) finds it too.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest

import hybridoc
from hybridoc.errors import SceneError
from hybridoc.ocp import Guard, HybridOCP
from hybridoc.solution import Status
from hybridoc.solvers.transcription import solve_dt

T, W, X_T, N = 2.0, 10.0, 2.0, 20
C_STAR = W * (X_T - 1.0 + math.cos(T)) / (1.0 + W * T)
J_STAR = C_STAR**2 * T + W * (C_STAR * T + 1.0 - math.cos(T) - X_T) ** 2


def forced(L_extra: bool = False) -> HybridOCP:
    s, u, t = ca.SX.sym("x"), ca.SX.sym("u"), ca.SX.sym("t")
    L = u**2 + ((s - ca.sin(t)) ** 2 if L_extra else 0)
    return HybridOCP.from_expressions(
        s, u, f=u + ca.sin(t), L=L, phi=W * (s - X_T) ** 2, guards=[], x0=[0.0],
        horizon=T, steps=N, t=t, state_labels=["x"],
    )  # fmt: skip


def test_lowering_adds_the_time_state() -> None:
    ocp = forced()
    assert ocp.nx == 2 and ocp.state_labels == ["x", "t"]
    np.testing.assert_array_equal(ocp.x0, [0.0, 0.0])
    np.testing.assert_allclose(ocp.f([0.3, 1.1], [0.5]).full().ravel(), [0.5 + math.sin(1.1), 1])


def test_judge_closed_form_and_zero_gradient_at_the_optimum() -> None:
    ocp = forced()
    ev = hybridoc.evaluate(ocp, np.full((N, 1), C_STAR))
    x_end = C_STAR * T + 1.0 - math.cos(T)
    # CVODES at 1e-13 per cell
    np.testing.assert_allclose(ev.final_state, [x_end, T], rtol=1e-10)
    assert ev.cost == pytest.approx(J_STAR, rel=1e-10)
    g = hybridoc.gradient(ocp, np.full((N, 1), C_STAR))
    assert np.abs(g.d_controls).max() < 1e-9


@pytest.mark.parametrize("L_extra", [False, True])
def test_gradient_against_central_differences(L_extra: bool) -> None:
    # with L_extra the running cost (x - sin t)^2 depends on the state through the time
    ocp = forced(L_extra)
    U = np.random.default_rng(3).normal(size=(N, 1))
    g = hybridoc.gradient(ocp, U)
    # a step well above CVODES's jitter (its steps change with the control: ~1e-11 in x)
    d = 1e-4
    for n in (0, 9, 19):
        Up, Um = U.copy(), U.copy()
        Up[n] += d
        Um[n] -= d
        fd = (hybridoc.evaluate(ocp, Up).cost - hybridoc.evaluate(ocp, Um).cost) / (2 * d)
        assert g.d_controls[n, 0] == pytest.approx(fd, rel=1e-6)


def test_dt_finds_the_closed_form_optimum() -> None:
    ocp = forced()
    sol = solve_dt(ocp)
    assert sol.status is Status.SUCCESS, sol.message
    assert sol.cost == pytest.approx(J_STAR, rel=1e-9)
    np.testing.assert_allclose(sol.controls.ravel(), C_STAR, atol=1e-6)


def test_time_dependent_modes_switch_at_the_closed_form_time() -> None:
    # mode "rise": x' = cos t + u; at x = 1/2 (t = pi / 6 for u = 0) into "hold": x' = u
    s, u, t = ca.SX.sym("x"), ca.SX.sym("u"), ca.SX.sym("t")
    ocp = HybridOCP.from_modes(
        s, u, modes={"rise": (ca.cos(t) + u, u**2), "hold": (u, u**2 + t)},
        transitions=[Guard.from_expressions("top", s, 0.5 - s, s, source="rise", target="hold")],
        initial_mode="rise", phi=ca.SX(0.0), x0=[0.0], horizon=1.0, steps=10, t=t,
        state_labels=["x"], terminal_eq=s - 0.5,
    )  # fmt: skip
    assert ocp.state_labels == ["x", "t", "mode"]
    ev = hybridoc.evaluate(ocp, np.zeros((10, 1)))
    assert ev.sequence == ["top"]
    assert ev.events[0].time == pytest.approx(math.pi / 6, abs=1e-10)
    # the reset keeps the time; in "hold" the running cost is t: int_{pi/6}^1 t dt
    np.testing.assert_allclose(ev.final_state, [0.5, 1.0, 1.0], atol=1e-10)
    assert ev.cost == pytest.approx((1 - (math.pi / 6) ** 2) / 2, rel=1e-10)
    assert ev.terminal_violation < 1e-10


def test_lowering_errors_are_scene_errors() -> None:
    s, u, t = ca.SX.sym("x"), ca.SX.sym("u"), ca.SX.sym("t")
    other = ca.SX.sym("p")
    common = {"guards": [], "x0": [0.0], "horizon": 1.0, "steps": 4, "phi": s}
    with pytest.raises(SceneError, match="t must be one scalar CasADi symbol"):
        HybridOCP.from_expressions(s, u, f=u, L=u**2, t=2 * t, **common)
    with pytest.raises(SceneError, match="L must be an expression in"):
        HybridOCP.from_expressions(s, u, f=u, L=u**2 + other, t=t, **common)
    with pytest.raises(SceneError, match="a flow_map cannot be given"):
        HybridOCP.from_expressions(s, u, f=u, L=u**2, t=t, flow_map=None, **common)
