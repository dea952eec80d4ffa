"""gd on terminal constraints and a free final time (issue #15): the augmented Lagrangian
against the exact piecewise-constant optimum on the same grid, computed here independently
(a KKT system of the discrete double integrator; an IPOPT NLP with the bounce time as a
variable), and dJ/dT against central differences of the judged cost."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest
from scipy.optimize import minimize_scalar

import hybridoc
from hybridoc.errors import SceneError
from hybridoc.ocp import Guard, HybridOCP
from hybridoc.solution import Status
from hybridoc.solvers.compiled import TerminalLoss
from hybridoc.solvers.gd import METHOD, solve_gd

RTOL = 5e-4  # gd's usual agreement with an independent optimum
TOL = 1e-8  # the terminal constraints
D = 2.0  # the double integrator travels from x = -1 to x = 1


# ---------------------------------------------------------------------- the problems
def _flow(s: ca.SX, u: ca.SX, L: ca.SX) -> ca.Function:
    """Exact flow of x' = v, v' = u with running cost L (constant in time) over h."""
    h = ca.SX.sym("h")
    x, v = s[0], s[1]
    return ca.Function("fm", [s, u, h], [ca.vertcat(x + v * h + u * h**2 / 2, v + u * h), L * h])


def double_integrator(
    N: int = 40,
    T: float = 2.0,
    *,
    v_min: float | None = None,
    free: tuple[float, float] | None = None,
) -> HybridOCP:
    """x(0) = -1, v(0) = 0; x(T) = 1 and v(T) = 0 (or v(T) >= v_min); J = int u^2
    (int 1 + u^2 with a free final time)."""
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u", 1)
    x, v = s[0], s[1]
    L = u[0] ** 2 + (1.0 if free else 0.0)
    eq = ca.vertcat(x - 1, v) if v_min is None else x - 1
    return HybridOCP.from_expressions(
        s, u, f=ca.vertcat(v, u), L=L, phi=ca.SX(0), guards=[], x0=[-1.0, 0.0],
        horizon=T, steps=N, flow_map=_flow(s, u, L), terminal_eq=eq,
        terminal_ineq=None if v_min is None else v - v_min, horizon_bounds=free,
    )  # fmt: skip


E = 0.8  # the wall's restitution


def wall(
    N: int = 30, T: float = 1.5, *, terminal: bool = True, free: tuple[float, float] | None = None
) -> HybridOCP:
    """A ball at x = 0 thrown at 2 m/s towards a wall at x = 1 (restitution E), pushed by
    u, that must end at x(T) = 0 with v(T) = -1 (or pay (x^2 + (v + 1)^2) without
    ``terminal``); J = int u^2 (int 1 + u^2 with a free final time)."""
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u", 1)
    x, v = s[0], s[1]
    L = u[0] ** 2 + (1.0 if free else 0.0)
    guard = Guard(
        "wall", ca.Function("psi", [s], [1 - x]),
        ca.Function("reset", [s], [ca.vertcat(x, -E * v)]), degree=2,
    )  # fmt: skip
    end = ca.vertcat(x, v + 1)
    return HybridOCP.from_expressions(
        s, u, f=ca.vertcat(v, u), L=L, phi=ca.SX(0) if terminal else ca.sumsqr(end),
        guards=[guard], x0=[0.0, 2.0], horizon=T, steps=N, flow_map=_flow(s, u, L),
        terminal_eq=end if terminal else None, horizon_bounds=free,
    )  # fmt: skip


# ---------------------------------------------------------------------- independent optima
def pwc_double_integrator(N: int, T: float, v_end: float | None) -> tuple[float, np.ndarray]:
    """Exact optimum of the double integrator over N piecewise-constant controls (cells
    T / N) with x_N = 1 and, unless ``v_end`` is None, v_N = v_end: min h |u|^2 subject to
    linear constraints, by its KKT system."""
    h = T / N
    # x_N = -1 + sum u_n h^2 (N - n - 1/2), v_N = sum u_n h
    a = h * h * (N - np.arange(N) - 0.5)
    rows, rhs = [a], [D]
    if v_end is not None:
        rows.append(np.full(N, h))
        rhs.append(v_end)
    A = np.array(rows)
    m = len(rows)
    K = np.block([[2 * h * np.eye(N), A.T], [A, np.zeros((m, m))]])
    sol = np.linalg.solve(K, np.concatenate([np.zeros(N), rhs]))
    u = sol[:N]
    return float(h * u @ u), u


def pwc_wall(N: int, T: float | None, u0: np.ndarray, tau0: float, T0: float) -> dict:
    """The exact optimum over N piecewise-constant controls of the wall problem with one
    bounce in the cell where ``tau0`` lies: an IPOPT NLP in the controls, the bounce time
    (``x(tau) = 1``) and, for a free final time (``T`` None), T; the states are the exact
    polynomials of each piece, written here from scratch."""
    free = T is None
    u = ca.MX.sym("u", N)
    th = ca.MX.sym("theta")  # where in its cell the bounce is, in [0, 1]
    Tv = ca.MX.sym("T") if free else ca.MX(T)
    h = Tv / N
    j = int(tau0 / (T0 / N))
    x, v = ca.MX(0.0), ca.MX(2.0)
    before = []  # the wall's distance at the grid times before the bounce
    for n in range(N):
        if n == j:
            d1 = th * h
            x, v = x + v * d1 + u[n] * d1**2 / 2, v + u[n] * d1
            x_hit = x
            v = -E * v
            d2 = (1 - th) * h
            x, v = x + v * d2 + u[n] * d2**2 / 2, v + u[n] * d2
        else:
            x, v = x + v * h + u[n] * h**2 / 2, v + u[n] * h
            before.append(1 - x)
    J = h * ca.sumsqr(u) + (Tv if free else 0)
    z = ca.vertcat(u, th, Tv) if free else ca.vertcat(u, th)
    g = ca.vertcat(x_hit - 1, x, v + 1)
    solver = ca.nlpsol(
        "wall", "ipopt", {"x": z, "f": J, "g": g},
        {"print_time": 0, "ipopt": {"print_level": 0, "tol": 1e-12, "sb": "yes"}},
    )  # fmt: skip
    guess = np.concatenate([u0, [(tau0 - j * T0 / N) / (T0 / N)], [T0] if free else []])
    lbx = np.concatenate([-np.inf * np.ones(N), [0.0], [0.5] if free else []])
    ubx = np.concatenate([np.inf * np.ones(N), [1.0], [5.0] if free else []])
    res = solver(x0=guess, lbx=lbx, ubx=ubx, lbg=0, ubg=0)
    assert solver.stats()["success"]
    zs = np.asarray(res["x"]).ravel()
    return {
        "cost": float(res["f"]),
        "u": zs[:N],
        "tau": (j + zs[N]) * (zs[N + 1] if free else T) / N,
        "T": float(zs[N + 1]) if free else T,
    }


def _judged(ocp: HybridOCP, sol: hybridoc.Solution) -> hybridoc.Evaluation:
    T = sol.info.get("horizon", ocp.horizon)
    return hybridoc.evaluate(ocp.replace(horizon=T), sol.controls)


def _check_met(ocp: HybridOCP, sol: hybridoc.Solution) -> None:
    assert sol.status == Status.SUCCESS, sol.message
    ev = _judged(ocp, sol)
    assert ocp.terminal_violation(ev.final_state) <= TOL
    assert sol.info["terminal_violation"] <= TOL
    assert sol.cost == pytest.approx(ev.cost, rel=1e-12)


# ---------------------------------------------------------------------- the tests
def test_independent_optimum_matches_the_closed_form() -> None:
    # the KKT system of the test itself, against the continuous closed form 12 d^2 / T^3 = 6
    # with its O(1/N^2) gap (piecewise-constant controls cost more)
    J, u = pwc_double_integrator(400, 2.0, 0.0)
    assert J == pytest.approx(12 * D**2 / 2.0**3, rel=1e-5) and J > 6
    t = (np.arange(400) + 0.5) * 2.0 / 400
    np.testing.assert_allclose(u, 6 * D / 4.0 * (1 - t), atol=1e-2)


def test_terminal_equalities_double_integrator() -> None:
    ocp = double_integrator()
    sol = solve_gd(ocp)
    J, u = pwc_double_integrator(40, 2.0, 0.0)
    _check_met(ocp, sol)
    assert sol.cost == pytest.approx(J, rel=RTOL)
    np.testing.assert_allclose(sol.controls.ravel(), u, atol=1e-3 * np.abs(u).max())
    assert "horizon" not in sol.info  # a fixed final time


@pytest.mark.parametrize(("v_min", "active"), [(2.0, True), (-5.0, False)])
def test_terminal_inequality(v_min: float, active: bool) -> None:
    # x(T) = 1 with v(T) free ends at v = 3 d / (2 T) = 1.5: v >= 2 is active, v >= -5 not
    ocp = double_integrator(v_min=v_min)
    J_free, u_free = pwc_double_integrator(40, 2.0, None)
    v_free = float(u_free.sum() * 2.0 / 40)
    assert (v_free < v_min) == active
    J, _ = pwc_double_integrator(40, 2.0, v_min) if active else (J_free, u_free)
    sol = solve_gd(ocp)
    _check_met(ocp, sol)
    assert sol.cost == pytest.approx(J, rel=RTOL)
    mu = sol.info["terminal_multipliers"]["ineq"][0]
    assert (mu > 1e-3) if active else (mu == 0.0)
    v_end = _judged(ocp, sol).final_state[1]
    assert v_end == pytest.approx(v_min if active else v_free, abs=1e-6)


def test_free_final_time_double_integrator() -> None:
    ocp = double_integrator(T=3.0, free=(0.5, 5.0))
    # the piecewise-constant optimum: min over T of T + J_N(T), beside the continuous
    # T* = (36 d^2)^(1/4) = 2 sqrt(3)
    res = minimize_scalar(
        lambda T: T + pwc_double_integrator(40, T, 0.0)[0], bounds=(0.5, 5.0),
        method="bounded", options={"xatol": 1e-10},
    )  # fmt: skip
    assert res.x == pytest.approx(2 * math.sqrt(3), rel=1e-2)
    sol = solve_gd(ocp)
    _check_met(ocp, sol)
    assert sol.info["horizon"] == pytest.approx(res.x, abs=1e-3)
    assert sol.cost == pytest.approx(res.fun, rel=RTOL)
    assert sol.time_grid[-1] == pytest.approx(sol.info["horizon"], rel=1e-14)
    # the judge takes a free final time's Solution at its info["horizon"]
    ev = hybridoc.evaluate(ocp, sol)
    assert ev.cost == sol.cost and ev.terminal_violation == sol.info["terminal_violation"]
    lines = dict(METHOD.summary_lines(sol))
    assert lines["final time"].startswith(f"{sol.info['horizon']:.12g}")
    assert "terminal violation" in lines["constraints"]


def test_wall_bounce_against_an_independent_nlp() -> None:
    ocp = wall()
    sol = solve_gd(ocp)
    _check_met(ocp, sol)
    assert [e["guard"] for e in sol.events] == ["wall"]
    ref = pwc_wall(30, 1.5, sol.controls.ravel(), sol.events[0]["time"], 1.5)
    assert sol.cost == pytest.approx(ref["cost"], rel=RTOL)
    assert sol.events[0]["time"] == pytest.approx(ref["tau"], abs=1e-3)
    # the coast (u = 0) bounces and ends at x = -0.6: the constraints did the work
    coast = hybridoc.evaluate(ocp, np.zeros((30, 1)))
    assert ocp.terminal_violation(coast.final_state) > 0.5


def test_wall_bounce_free_final_time() -> None:
    ocp = wall(free=(1.0, 3.0))
    sol = solve_gd(ocp)
    _check_met(ocp, sol)
    assert [e["guard"] for e in sol.events] == ["wall"]
    ref = pwc_wall(30, None, sol.controls.ravel(), sol.events[0]["time"], sol.info["horizon"])
    assert sol.info["horizon"] == pytest.approx(ref["T"], abs=1e-3)
    assert sol.cost == pytest.approx(ref["cost"], rel=RTOL)


def test_horizon_gradient_against_the_judge() -> None:
    # dJ/dT of the compiled rollout (through an event) against central differences of the
    # judged cost, the N cells stretching with T
    ocp = wall(terminal=False, free=(1.0, 3.0))
    loss = TerminalLoss(ocp)
    t = (np.arange(30) + 0.5) * 1.5 / 30
    u = (0.3 * np.sin(3 * t) - 0.2)[:, None]
    for T in (1.3, 1.7):
        J, A, _, _, gT = loss.evaluate(u, T)
        assert A == 0.0
        assert J == pytest.approx(hybridoc.evaluate(ocp.replace(horizon=T), u).cost, rel=1e-12)
        d = 1e-5
        plus = hybridoc.evaluate(ocp.replace(horizon=T + d), u).cost
        minus = hybridoc.evaluate(ocp.replace(horizon=T - d), u).cost
        assert gT == pytest.approx((plus - minus) / (2 * d), rel=1e-6)
        # and the judge's own adjoint dJ/dT
        assert gT == pytest.approx(hybridoc.gradient(ocp.replace(horizon=T), u).d_horizon, rel=1e-9)


def test_violation_above_the_tolerance_is_not_success() -> None:
    ocp = double_integrator()
    sol = solve_gd(ocp, terminal_iters=1)
    assert sol.status == Status.INFEASIBLE
    assert sol.info["terminal_violation"] > TOL
    assert "terminal constraints violated by" in sol.message
    assert sol.info["terminal_violation"] == pytest.approx(
        ocp.terminal_violation(hybridoc.evaluate(ocp, sol.controls).final_state), rel=1e-9
    )


def test_features_declared_and_refusals() -> None:
    assert {"terminal", "free_horizon"} <= METHOD.features
    ocp = double_integrator(N=10)
    for kw, words in [
        ({"starts": 2}, "multi-start"),
        ({"hops": 1}, "multi-start and the hops"),
        ({"optimizer": "adam"}, "L-BFGS-B"),
        ({"max_step": 0.1}, "max_step"),
    ]:
        with pytest.raises(SceneError, match=words):
            solve_gd(ocp, **kw)
    with pytest.raises(SceneError, match="terminal_tol"):
        solve_gd(ocp, terminal_tol=0.0)
    # through hybridoc.solve too: gd declares both features
    sol = hybridoc.solve(double_integrator(N=10, T=3.0, free=(0.5, 5.0)), "gd")
    assert sol.status == Status.SUCCESS and "horizon" in sol.info


# ---------------------------------------------------------------------- friction patch
SMOOTH, ROUGH = 0.2, 3.0  # viscous friction for x < 0 and x > 0


def friction_patch(free: bool = False) -> HybridOCP:
    """Issue #15's ``friction-patch`` (``-free-time`` with ``free``), written here from its
    definition: x' = v, v' = u - c v with c = 0.2 for x < 0 and 3 for x > 0; x(0) = -1,
    v(0) = 0; x(T) = 1, v(T) = 0; T = 2 (free in [0.5, 5]), N = 200; J = int u^2 (+ T)."""
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u", 1)
    x, v = s[0], s[1]
    L = u[0] ** 2 + (1.0 if free else 0.0)
    modes = {
        "smooth": (ca.vertcat(v, u - SMOOTH * v), L),
        "rough": (ca.vertcat(v, u - ROUGH * v), L),
    }
    transitions = [
        Guard.from_expressions("enter", s, -x, s, source="smooth", target="rough"),
        Guard.from_expressions("leave", s, x, s, source="rough", target="smooth"),
    ]
    return HybridOCP.from_modes(
        s, u, modes=modes, transitions=transitions, initial_mode="smooth", phi=ca.SX(0),
        x0=[-1.0, 0.0], horizon=2.0, steps=200, terminal_eq=ca.vertcat(x - 1, v),
        horizon_bounds=(0.5, 5.0) if free else None, name="friction-patch",
    )  # fmt: skip


def pwc_friction_patch(N: int, T: float | None, u0: np.ndarray, tau0: float, T0: float) -> dict:
    """The exact optimum over N piecewise-constant controls of the friction patch entering
    the rough part once, in the cell of ``tau0``: an IPOPT NLP in the controls, the crossing
    time (``x(tau) = 0``) and, when free (``T`` None), T, on the closed-form flow of
    v' = u - c v written here."""
    free = T is None

    def flow(x: ca.MX, v: ca.MX, w: ca.MX, c: float, d: ca.MX) -> tuple[ca.MX, ca.MX]:
        e = ca.exp(-c * d)
        return x + v * (1 - e) / c + w / c * (d - (1 - e) / c), v * e + w / c * (1 - e)

    u = ca.MX.sym("u", N)
    th = ca.MX.sym("theta")
    Tv = ca.MX.sym("T") if free else ca.MX(T)
    h = Tv / N
    j = int(tau0 / (T0 / N))
    x, v = ca.MX(-1.0), ca.MX(0.0)
    for n in range(N):
        if n < j:
            x, v = flow(x, v, u[n], SMOOTH, h)
        elif n == j:
            x, v = flow(x, v, u[n], SMOOTH, th * h)
            x_hit = x
            x, v = flow(x, v, u[n], ROUGH, (1 - th) * h)
        else:
            x, v = flow(x, v, u[n], ROUGH, h)
    J = h * ca.sumsqr(u) + (Tv if free else 0)
    z = ca.vertcat(u, th, Tv) if free else ca.vertcat(u, th)
    solver = ca.nlpsol(
        "fp", "ipopt", {"x": z, "f": J, "g": ca.vertcat(x_hit, x - 1, v)},
        {"print_time": 0, "ipopt": {"print_level": 0, "tol": 1e-12, "sb": "yes"}},
    )  # fmt: skip
    guess = np.concatenate([u0, [(tau0 - j * T0 / N) / (T0 / N)], [T0] if free else []])
    lbx = np.concatenate([-np.inf * np.ones(N), [0.0], [0.5] if free else []])
    ubx = np.concatenate([np.inf * np.ones(N), [1.0], [5.0] if free else []])
    res = solver(x0=guess, lbx=lbx, ubx=ubx, lbg=0, ubg=0)
    assert solver.stats()["success"]
    zs = np.asarray(res["x"]).ravel()
    return {"cost": float(res["f"]), "T": float(zs[N + 1]) if free else T}


@pytest.mark.slow  # the VM takes over a minute on 2 cores until the compiled loss is cached
@pytest.mark.parametrize("free", [False, True])
def test_friction_patch_against_an_independent_nlp(free: bool) -> None:
    ocp = friction_patch(free)
    sol = solve_gd(ocp)
    _check_met(ocp, sol)
    assert sol.sequence == ["enter"]
    T = sol.info["horizon"] if free else 2.0
    ref = pwc_friction_patch(200, None if free else 2.0, sol.controls.ravel(),
                             sol.events[0]["time"], T)  # fmt: skip
    assert sol.cost == pytest.approx(ref["cost"], rel=RTOL)
    if free:
        assert T == pytest.approx(ref["T"], abs=1e-3)


@pytest.mark.slow  # as above; the library's problems, with their exact flow maps
@pytest.mark.parametrize("name", ["friction-patch", "friction-patch-free-time"])
def test_library_friction_patch(name: str) -> None:
    ocp = hybridoc.as_ocp(name)
    free = ocp.free_horizon
    sol = hybridoc.solve(ocp, "gd")
    _check_met(ocp, sol)
    assert len(sol.events) == 1
    T = sol.info["horizon"] if free else ocp.horizon
    ref = pwc_friction_patch(ocp.steps, None if free else ocp.horizon, sol.controls.ravel(),
                             sol.events[0]["time"], T)  # fmt: skip
    assert sol.cost == pytest.approx(ref["cost"], rel=RTOL)
    if free:
        assert T == pytest.approx(ref["T"], abs=1e-3)
