"""Resets that depend on the control, ``s+ = g(s-, u)`` (issue #15), through every method.

The problems are balls bouncing on a floor with a closed-form flow (``h' = v``,
``v' = thrust - g``), whose reset the control changes:

* ``tanh_ball``: one control, the thrust, also sets the restitution and adds an impulse,
  ``v+ = -(E0 + A tanh(u)) v- + B u``. The judge is checked against an independent event-exact
  simulation written here from the closed form (quadratic impact times), and its adjoint
  against central differences, with the bounce in one grid cell and then in the next.
* ``restitution_ball``: a second control ``r`` in ``[-1, 1]`` sets the restitution,
  ``v+ = -(0.8 + 0.1 r) v-``, and costs ``eps_r r^2``. On the flow ``r`` does nothing, so the
  continuous optimum is that of the library's bouncing ball with the restitution fixed at
  the best ``e`` in ``[0.7, 0.9]``, which ``tests/library_optima.py`` computes by its own
  sequence-fixed QP (no hybridoc solver).
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from library_optima import LinearModel, minimise_over_times

import hybridoc
from hybridoc import Guard, HybridOCP
from hybridoc.callable_eval import evaluate_callable
from hybridoc.errors import SceneError
from hybridoc.solution import Solution

G = 9.81
E0, A, B = 0.8, 0.15, 0.3  # tanh_ball's reset
EPS = 0.01
T_TANH = 0.9

# restitution_ball: the library's one-bounce ball (bouncing_ball(1, 0.8)'s T and target)
T_R, H_TARGET, E_LO, E_HI = 0.812743, 0.94, 0.7, 0.9


def _flow_map(s: ca.SX, u: ca.SX, L: ca.SX) -> ca.Function:
    h = ca.SX.sym("h")
    a = u[0] - G
    end = ca.vertcat(s[0] + s[1] * h + a * h**2 / 2, s[1] + a * h)
    return ca.Function("fm", [s, u, h], [end, L * h])


def tanh_ball(N: int = 20, *, terminal: bool = False) -> HybridOCP:
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u")
    reset = ca.vertcat(s[0], -(E0 + A * ca.tanh(u)) * s[1] + B * u)
    floor = Guard.from_expressions("floor", s, s[0], reset, u=u, degree=2)
    L = EPS * u**2
    return HybridOCP.from_expressions(
        s, u, f=ca.vertcat(s[1], u - G), L=L, phi=(s[0] - 0.7) ** 2 + 0.5 * (s[1] - 0.5) ** 2,
        guards=[floor], x0=[1.0, 0.0], horizon=T_TANH, steps=N, flow_map=_flow_map(s, u, L),
        terminal_eq=s[1] - 0.5 if terminal else None,
    )  # fmt: skip


def hand_simulation(u: np.ndarray, N: int = 20) -> tuple[float, list[tuple[float, int]], tuple]:
    """tanh_ball under piecewise-constant ``u``: ``(cost, [(event time, cell)], s(T))`` from
    the closed form, each impact time the first root of ``h + v t + a t^2 / 2`` with the
    ball approaching, the reset reading the cell's control."""
    dt = T_TANH / N
    h, v = 1.0, 0.0
    events = []
    for n in range(N):
        un = float(u[n])
        a, left, t = un - G, dt, n * dt
        while True:
            roots = [r.real for r in np.roots([a / 2, v, h]) if abs(r.imag) < 1e-12]
            hits = sorted(r for r in roots if 1e-12 < r <= left and v + a * r < 0)
            if not hits:
                h, v = h + v * left + a * left**2 / 2, v + a * left
                break
            tau = hits[0]
            v = -(E0 + A * np.tanh(un)) * (v + a * tau) + B * un
            h, left, t = 0.0, left - tau, t + tau
            events.append((t, n))
    cost = EPS * dt * float(np.sum(np.square(u))) + (h - 0.7) ** 2 + 0.5 * (v - 0.5) ** 2
    return cost, events, (h, v)


def restitution_ball(N: int = 40) -> HybridOCP:
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u", 2)
    reset = ca.vertcat(s[0], -(0.8 + 0.1 * u[1]) * s[1])
    floor = Guard.from_expressions("floor", s, s[0], reset, u=u, degree=2)
    L = EPS * u[0] ** 2 + EPS * u[1] ** 2
    return HybridOCP.from_expressions(
        s, u, f=ca.vertcat(s[1], u[0] - G), L=L, phi=(s[0] - H_TARGET) ** 2 + s[1] ** 2,
        guards=[floor], x0=[1.0, 0.0], horizon=T_R, steps=N, flow_map=_flow_map(s, u, L),
        u_min=[-np.inf, -1.0], u_max=[np.inf, 1.0],
    )  # fmt: skip


def fixed_restitution_optimum(e: float) -> float:
    """The continuous one-bounce optimum with restitution ``e`` (library_optima's QP)."""
    mod = LinearModel(
        A=np.array([[0.0, 1.0], [0.0, 0.0]]), B=np.array([[0.0], [1.0]]),
        c=np.array([0.0, -G]), eps=EPS, W=np.eye(2), xt=np.array([H_TARGET, 0.0]),
        x0=np.array([1.0, 0.0]), T=T_R, guards={"floor": np.array([1.0, 0.0])},
        resets={"floor": np.diag([1.0, -e])},
    )  # fmt: skip
    return float(minimise_over_times(mod, ["floor"])[0])


def _central_differences(ocp: HybridOCP, u: np.ndarray, out: str = "cost") -> np.ndarray:
    fd = np.zeros(u.shape)
    for idx in np.ndindex(*u.shape):
        d = np.zeros(u.shape)
        d[idx] = 1e-6
        hi, lo = hybridoc.evaluate(ocp, u + d), hybridoc.evaluate(ocp, u - d)
        if out == "cost":
            fd[idx] = (hi.cost - lo.cost) / 2e-6
        else:  # the terminal constraint v(T) - 0.5
            fd[idx] = (hi.final_state[1] - lo.final_state[1]) / 2e-6
    return fd


# ------------------------------------------------------------------------------ the model
def test_guard_forms_and_signature_errors() -> None:
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u")
    with_u = Guard.from_expressions("g", s, s[0], ca.vertcat(s[0], -s[1] + u), u=u)
    without = Guard.from_expressions("g", s, s[0], ca.vertcat(s[0], -s[1]), u=u)
    assert with_u.uses_control and with_u.reset.n_in() == 2
    assert not without.uses_control and without.reset.n_in() == 1
    np.testing.assert_array_equal(np.ravel(with_u.reset_at([0.0, -2.0], 0.5)), [0.0, 2.5])
    np.testing.assert_array_equal(np.ravel(without.reset_at([0.0, -2.0], 0.5)), [0.0, 2.0])
    with pytest.raises(SceneError, match=r"guard 'g': the reset .* \(pass u= .*it uses u"):
        Guard.from_expressions("g", s, s[0], ca.vertcat(s[0], -s[1] + u))
    with pytest.raises(SceneError, match=r"s -> s or \(s, u\) -> s, got 3 inputs"):
        Guard("g", ca.Function("p", [s], [s[0]]), ca.Function("r", [s, u, ca.SX.sym("w")], [s]))

    def problem(guard: Guard) -> HybridOCP:
        return HybridOCP.from_expressions(
            s, u, f=ca.vertcat(s[1], u), L=u**2, phi=s[0] ** 2, guards=[guard], x0=[1.0, 0.0],
            horizon=1.0, steps=4,
        )  # fmt: skip

    swapped = Guard("g", ca.Function("p", [s], [s[0]]), ca.Function("r", [u, s], [s]))
    with pytest.raises(SceneError, match=r"\(s, u\) -> s with s of size 2 and u of size 1 .*"
                       r"takes the state first\), got inputs \(1x1, 2x1\) -> 2x1"):  # fmt: skip
        problem(swapped)
    short = Guard("g", ca.Function("p", [s], [s[0]]), ca.Function("r", [s, u], [s[0]]))
    with pytest.raises(SceneError, match=r"got inputs \(2x1, 1x1\) -> 1x1"):
        problem(short)
    assert problem(with_u).guards[0].uses_control


def test_modes_and_time_lift_carry_the_control_into_the_reset() -> None:
    s, u, t = ca.SX.sym("s", 2), ca.SX.sym("u"), ca.SX.sym("t")
    kick = ca.vertcat(s[0], -s[1] + 2 * u)
    go = Guard.from_expressions("go", s, s[0], kick, u=u, source="a", target="b")
    back = Guard.from_expressions("back", s, -s[0], s, source="b", target="a")
    ocp = HybridOCP.from_modes(
        s, u, modes={"a": (ca.vertcat(s[1], u), u**2), "b": (ca.vertcat(s[1], -u), u**2)},
        transitions=[go, back], initial_mode="a", phi=s[0] ** 2, x0=[1.0, 0.0], horizon=1.0,
        steps=4,
    )  # fmt: skip
    g_go, g_back = ocp.guards
    assert g_go.uses_control and not g_back.uses_control
    # (s, q = a) -> (g(s, u), q = b); the mode index is set, the control read
    np.testing.assert_array_equal(np.ravel(g_go.reset([0.0, -1.0, 0.0], 0.25)), [0.0, 1.5, 1.0])
    lifted = HybridOCP.from_expressions(
        s, u, f=ca.vertcat(s[1], u), L=u**2, phi=s[0] ** 2 + t, guards=[go.__class__(
            "go", go.psi, go.reset)], x0=[1.0, 0.0], horizon=1.0, steps=4, t=t,
    )  # fmt: skip
    g = lifted.guards[0]
    assert g.uses_control
    # the time (third coordinate) is kept by the reset
    np.testing.assert_array_equal(np.ravel(g.reset([0.0, -1.0, 0.3], 0.25)), [0.0, 1.5, 0.3])


# ------------------------------------------------------------------------------ the judge
def _controls_with_bounce_in(cell: int, N: int = 20) -> np.ndarray:
    """Controls (a ramp plus a distinct value per cell) whose bounce falls in ``cell``,
    found by shifting a constant early thrust."""
    base = 0.3 * np.sin(np.arange(N)) + 0.05 * np.arange(N)
    for c in np.linspace(-3.0, 3.0, 241):
        u = base.copy()
        u[:5] += c
        _, events, _ = hand_simulation(u, N)
        if events and events[0][1] == cell:
            t = events[0][0] / (T_TANH / N) - cell
            if 0.2 < t < 0.8:  # well inside the cell: central differences stay in it
                return u
    raise AssertionError(f"no control bounces in cell {cell}")


def test_judge_matches_an_independent_event_exact_simulation() -> None:
    ocp = tanh_ball()
    rng = np.random.default_rng(3)
    controls = [_controls_with_bounce_in(9), _controls_with_bounce_in(10)]
    controls += [rng.normal(0.0, 2.0, 20) for _ in range(3)]
    cells = set()
    for u in controls:
        ev = hybridoc.evaluate(ocp, u)
        cost, events, final = hand_simulation(u)
        assert len(ev.events) == len(events) >= 1
        for e, (t, n) in zip(ev.events, events, strict=True):
            assert abs(e.time - t) <= 1e-12
            assert int(e.time // ocp.dt) == n
        cells.add(events[0][1])
        assert abs(ev.cost - cost) <= 1e-12 * max(1.0, abs(cost))
        np.testing.assert_allclose(ev.final_state, final, rtol=1e-12, atol=1e-12)
    assert {9, 10} <= cells  # the bounce moved to the next cell and read that cell's control


@pytest.mark.parametrize("cell", [9, 10])
def test_adjoint_matches_central_differences(cell: int) -> None:
    ocp = tanh_ball()
    u = _controls_with_bounce_in(cell)
    grad = hybridoc.gradient(ocp, u)
    fd = _central_differences(ocp, u[:, None])
    np.testing.assert_allclose(grad.d_controls, fd, rtol=1e-6, atol=1e-7)
    # the reset's term lambda+^T dg/du sits in the bounce's cell: without it that cell's
    # derivative would be the flow's alone, far from the differences
    assert abs(fd[cell, 0]) > 10 * np.abs(np.delete(fd[:, 0], cell)).max()


def test_terminal_constraint_gradient_through_a_control_reset() -> None:
    ocp = tanh_ball(terminal=True)
    u = _controls_with_bounce_in(10)
    grad = hybridoc.gradient(ocp, u)
    fd = _central_differences(ocp, u[:, None], out="terminal")
    np.testing.assert_allclose(grad.terminal_d_controls[0], fd, rtol=1e-6, atol=1e-7)


def test_the_judge_applies_a_solutions_event_controls() -> None:
    ocp = tanh_ball()
    u = _controls_with_bounce_in(10)

    def control(t: float) -> np.ndarray:
        return u[min(int(t / ocp.dt), ocp.steps - 1)][None]

    grid = ocp.time_grid()[1:-1]
    same = evaluate_callable(ocp, control, breakpoints=grid)
    assert abs(same.cost - hybridoc.evaluate(ocp, u).cost) < 1e-9  # the cell's control
    own = evaluate_callable(ocp, control, breakpoints=grid, event_controls=np.array([[2.0]]))
    # the same flow to the bounce, whose reset read 2.0 instead of the cell's control
    before, after = own.events[0].state_before, own.events[0].state_after
    np.testing.assert_array_equal(before, same.events[0].state_before)
    np.testing.assert_allclose(after, [0.0, -(E0 + A * np.tanh(2.0)) * before[1] + B * 2.0],
                               rtol=1e-14, atol=1e-14)  # fmt: skip
    assert abs(after[1] - same.events[0].state_after[1]) > 0.1


# ------------------------------------------------------------------------------ the methods
def test_dt_reaches_the_independent_optimum_with_its_own_reset_control(tmp_path) -> None:
    ocp = restitution_ball()
    sol = hybridoc.solve(ocp, "dt")
    best = fixed_restitution_optimum(E_HI)
    # the box minimum of lambda+^T g over r: the restitution at its upper bound is best
    assert best < fixed_restitution_optimum(0.85) < fixed_restitution_optimum(E_LO)
    # the best of the guess's sequences: dt does not claim the global optimum
    assert sol.status is hybridoc.Status.BEST_FOUND, sol.message
    assert abs(sol.cost - best) <= 1e-9 * best
    np.testing.assert_allclose(sol.event_controls[:, 1], [1.0], atol=1e-8)
    assert sol.cost == hybridoc.evaluate(ocp, sol).cost  # the judge applies v_k, bit for bit
    sol.save(tmp_path / "dt")
    back = Solution.load(tmp_path / "dt")
    np.testing.assert_array_equal(back.event_controls, sol.event_controls)
    assert hybridoc.evaluate(ocp, back).cost == sol.cost
    # its cell averages (r about 0 in the bounce's cell) cost more on the grid
    assert sol.to_grid().cost > sol.cost + 1e-3


def test_gd_from_dt_approaches_the_continuous_optimum() -> None:
    ocp = restitution_ball(40)
    best = fixed_restitution_optimum(E_HI)
    sol = hybridoc.solve(ocp, "gd", initial=hybridoc.solve(ocp, "dt"))
    ev = hybridoc.evaluate(ocp, sol)
    assert sol.cost == ev.cost  # the judge's
    cell = int(ev.events[0].time // ocp.dt)
    assert sol.controls[cell, 1] == pytest.approx(1.0, abs=1e-6)  # the event cell's r -> v_k
    # the piecewise-constant optimum is within O(T/N) of the continuous one
    assert best < sol.cost < best + 5e-4


@pytest.mark.slow
def test_gd_gap_to_the_continuous_optimum_shrinks_with_the_grid() -> None:
    best = fixed_restitution_optimum(E_HI)
    gaps = []
    for N in (40, 80, 160):
        ocp = restitution_ball(N)
        sol = hybridoc.solve(ocp, "gd", initial=hybridoc.solve(ocp, "dt"))
        gaps.append(sol.cost - best)
    assert 0 < gaps[2] < gaps[1] < gaps[0] < 5e-4
    assert gaps[2] < 0.35 * gaps[0]  # about O(T / N)


def test_the_reference_refuses_a_reset_affine_in_an_unbounded_control() -> None:
    """``v+ = -0.8 v- + 0.3 u[1]``: ``lambda+^T g`` is linear in the reset's control, with
    no minimum over an unbounded ``u[1]``; the same reset with ``u[1]`` bounded on one side
    is accepted (the minimum at that bound when the slope has the sign for it). The
    reference on the control-dependent resets it accepts: tests/test_reference_control_resets.py."""
    from hybridoc.reference.solve import reference_supports

    s, u = ca.SX.sym("s", 2), ca.SX.sym("u", 2)
    kick = Guard.from_expressions(
        "kick", s, s[0], ca.vertcat(s[0], -0.8 * s[1] + 0.3 * u[1]), u=u, degree=2
    )

    def problem(**bounds: list[float]) -> HybridOCP:
        return HybridOCP.from_expressions(
            s, u, f=ca.vertcat(s[1], u[0] - G), L=EPS * ca.sumsqr(u), phi=(s[0] - 0.9) ** 2,
            guards=[kick], x0=[1.0, 0.0], horizon=0.8, steps=8, **bounds,
        )  # fmt: skip

    with pytest.raises(
        SceneError, match=r"'kick' is affine in the control u\[1\], which has no bounds: .*no "
        r"minimum over it .*bound u\[1\] \(u_min, u_max\)",
    ):  # fmt: skip
        hybridoc.solve(problem(), "reference")
    one_side = problem(u_min=[-np.inf, -1.0], u_max=[np.inf, np.inf])
    assert reference_supports(one_side) is None
    assert reference_supports(restitution_ball()) is None
