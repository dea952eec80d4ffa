"""The HMP reference on resets that depend on the control, ``s+ = g(s-, u)`` (issue #15).

At each event whose reset reads the control, the reference has an unknown of its own, the
reset's control ``v_k`` in the control bounds, with the first-order conditions of the
minimum of ``lambda(gamma+)^T g(s(gamma-), v)``; the costate jump and the Hamiltonian
condition use ``g(., v_k)``. The balls of ``tests/test_control_resets.py`` bounce once on a
floor; a second control ``r`` (``u[1]``) sets the restitution:

* ``restitution_ball``: ``e = 0.8 + 0.1 r``, ``r`` in ``[-1, 1]``: the optimum at the bound
  ``r = 1`` (``e = 0.9``);
* ``sin_ball``: ``e = 0.8 + 0.1 sin(r)``, ``r`` in ``[-2, 2]``: the optimum at the interior
  ``r = pi / 2``, where ``e`` is largest (``e = 0.9`` again), a stationary point of
  ``lambda+^T g`` (``-r = pi / 2`` is one too, of the largest cost);
* ``quad_ball``: ``e = 0.7 + 0.2 r^2``: ``r = 0`` is a stationary point of the cost in
  ``r``, a maximum.

On the flow ``r`` does nothing, so each continuous optimum is the bouncing ball's with the
restitution fixed at 0.9, which ``tests/library_optima.py`` computes by its own
sequence-fixed QP (no hybridoc solver): 0.0190400769878.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest
from test_control_resets import (
    E_HI,
    EPS,
    H_TARGET,
    T_R,
    G,
    _flow_map,
    fixed_restitution_optimum,
    restitution_ball,
    tanh_ball,
)

import hybridoc
from hybridoc import Guard, HybridOCP
from hybridoc.reference.result import make_result
from hybridoc.reference.shooting import newton, shooting_system
from hybridoc.reference.solve import event_control_rival
from hybridoc.solution import Solution, Status


def _ball(restitution: ca.SX, r_bound: float, u: ca.SX, s: ca.SX) -> HybridOCP:
    reset = ca.vertcat(s[0], -restitution * s[1])
    floor = Guard.from_expressions("floor", s, s[0], reset, u=u, degree=2)
    L = EPS * u[0] ** 2 + EPS * u[1] ** 2
    return HybridOCP.from_expressions(
        s, u, f=ca.vertcat(s[1], u[0] - G), L=L, phi=(s[0] - H_TARGET) ** 2 + s[1] ** 2,
        guards=[floor], x0=[1.0, 0.0], horizon=T_R, steps=40, flow_map=_flow_map(s, u, L),
        u_min=[-np.inf, -r_bound], u_max=[np.inf, r_bound],
    )  # fmt: skip


def sin_ball() -> HybridOCP:
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u", 2)
    return _ball(0.8 + 0.1 * ca.sin(u[1]), 2.0, u, s)


def quad_ball() -> HybridOCP:
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u", 2)
    return _ball(0.7 + 0.2 * u[1] ** 2, 1.0, u, s)


@pytest.fixture(scope="module")
def best() -> float:
    return fixed_restitution_optimum(E_HI)


@pytest.fixture(scope="module")
def restitution() -> tuple[HybridOCP, Solution, Solution]:
    ocp = restitution_ball()
    return ocp, hybridoc.solve(ocp, "reference"), hybridoc.solve(ocp, "dt")


@pytest.fixture(scope="module")
def sine() -> tuple[HybridOCP, Solution, Solution]:
    ocp = sin_ball()
    return ocp, hybridoc.solve(ocp, "reference"), hybridoc.solve(ocp, "dt")


def test_restitution_at_its_bound_reaches_the_independent_optimum(
    restitution: tuple[HybridOCP, Solution, Solution], best: float, tmp_path
) -> None:
    ocp, sol, dt = restitution
    assert sol.status is Status.SUCCESS, sol.message
    assert abs(sol.cost - best) <= 1e-9 * best
    assert abs(sol.cost - dt.cost) <= 1e-9 * best
    V = sol.event_controls
    assert V is not None and V.shape == (1, 2)
    assert V[0, 1] == 1.0  # r at its upper bound: the box minimum of lambda+^T g
    residuals = sol.reference.hmp_residuals()
    assert residuals["event_control"] <= 1e-12
    assert max(residuals.values()) <= 1e-10
    # the derivative of lambda+^T g in r has the sign of a minimum at the upper bound
    ref = sol.reference
    lam_plus, v_minus = ref.phase_costates[1], ref.states_minus[0, 1]
    assert lam_plus[1] * (-0.1 * v_minus) < 0
    # the judge applies v_k: its cost is sol.cost bit for bit, also after a save and a load
    assert hybridoc.evaluate(ocp, sol).cost == sol.cost
    sol.save(tmp_path / "ref")
    back = Solution.load(tmp_path / "ref")
    np.testing.assert_array_equal(back.event_controls, V)
    assert hybridoc.evaluate(ocp, back).cost == sol.cost
    # without v_k (the reset reading u(t) at the bounce, r = 0 on the flow) the cost is that
    # of e = 0.8
    u, bps = hybridoc.reference.reference_control(back, ocp)
    plain = hybridoc.evaluate_callable(ocp, u, breakpoints=bps)
    assert plain.cost > sol.cost + 1e-3


def test_interior_reset_control_is_the_stationary_minimum(
    sine: tuple[HybridOCP, Solution, Solution], best: float
) -> None:
    ocp, sol, dt = sine
    assert sol.status is Status.SUCCESS, sol.message
    # r = pi / 2 inside |r| <= 2: sin(r) = 1, e = 0.9, the same optimum as above
    assert sol.event_controls[0, 1] == pytest.approx(math.pi / 2, abs=1e-9)
    assert dt.event_controls[0, 1] == pytest.approx(math.pi / 2, abs=1e-6)
    assert abs(sol.cost - best) <= 1e-9 * best
    assert abs(sol.cost - dt.cost) <= 1e-9 * best
    assert hybridoc.evaluate(ocp, sol).cost == sol.cost


def test_jump_and_hamiltonian_use_the_reset_at_its_own_control(
    sine: tuple[HybridOCP, Solution, Solution],
) -> None:
    """The HMP conditions at the bounce recomputed by hand from the extremal's numbers:
    ``lambda- = Dg(s-, v)^T lambda+ + pi grad psi`` with ``Dg`` by central differences of
    the reset at ``v``, and ``H(gamma-) = H(gamma+)`` with ``s+ = g(s-, v)`` and ``u*`` in
    closed form (``u0 = -lambda_v / (2 eps)``, ``r = 0`` on the flow)."""
    ocp, sol, _ = sine
    ref = sol.reference
    v = sol.event_controls[0]
    reset = ocp.guards[0].reset

    def g(s: np.ndarray) -> np.ndarray:
        return np.asarray(reset(s, v), dtype=float).ravel()

    sm, lm, lp = ref.states_minus[0], ref.costates_minus[0], ref.phase_costates[1]
    Dg = np.column_stack([(g(sm + h) - g(sm - h)) / 2e-6 for h in np.eye(2) * 1e-6])
    grad_psi = np.array([1.0, 0.0])
    np.testing.assert_allclose(lm, Dg.T @ lp + ref.multipliers[0] * grad_psi, atol=1e-8)
    sp = g(sm)
    np.testing.assert_allclose(ref.phase_states[1], sp, atol=1e-14)
    assert sp[1] == pytest.approx(-(0.8 + 0.1 * math.sin(v[1])) * sm[1], abs=1e-14)

    def H(s: np.ndarray, lam: np.ndarray) -> float:
        u0 = -lam[1] / (2 * EPS)
        return EPS * u0**2 + lam[0] * s[1] + lam[1] * (u0 - G)

    assert abs(H(sm, lm) - H(sp, lp)) <= 1e-9 * max(1.0, abs(H(sm, lm)))
    # at the other stationary point (r = -pi / 2, e = 0.7) neither condition holds: they
    # really are taken at v
    v_bad = np.array([v[0], -math.pi / 2])

    def g_bad(s: np.ndarray) -> np.ndarray:
        return np.asarray(reset(s, v_bad), dtype=float).ravel()

    Dg_bad = np.column_stack([(g_bad(sm + h) - g_bad(sm - h)) / 2e-6 for h in np.eye(2) * 1e-6])
    assert np.max(np.abs(lm - Dg_bad.T @ lp - ref.multipliers[0] * grad_psi)) > 1e-3
    assert abs(H(sm, lm) - H(g_bad(sm), lp)) > 1e-3


def test_unbounded_nonlinear_reset_control_against_dt() -> None:
    """``v+ = -(0.8 + 0.15 tanh(u)) v- + 0.3 u`` with ``u`` unbounded (the thrust): the
    reset's control is a root of ``d/dv lambda+^T g = 0`` alone."""
    ocp = tanh_ball()
    # the one-bounce extremal (issue #29: the search now also covers two bounces, whose free
    # reset controls bring the cost to zero, 5e-31, confirmed by the judge: the one-bounce
    # extremal was a success it had not earned)
    sol = hybridoc.solve(ocp, "reference", multistart=0, sequence=["floor"])
    dt = hybridoc.solve(ocp, "dt")
    assert sol.status is Status.EXTREMAL, sol.message
    assert abs(sol.cost - dt.cost) <= 1e-9 * abs(dt.cost)
    np.testing.assert_allclose(sol.event_controls, dt.event_controls, atol=1e-6)
    ref = sol.reference
    lam_v, v_minus, w = ref.phase_costates[1][1], ref.states_minus[0, 1], sol.event_controls[0, 0]
    # the stationarity by hand: lambda_v+ (-0.15 sech^2(w) v- + 0.3) = 0
    assert abs(lam_v * (-0.15 / math.cosh(w) ** 2 * v_minus + 0.3)) <= 1e-10
    assert hybridoc.evaluate(ocp, sol).cost == sol.cost


def test_a_stationary_maximum_is_not_optimal_and_the_search_leaves_it(best: float) -> None:
    """``e = 0.7 + 0.2 r^2``: Newton from ``r = 0`` meets the first-order conditions there
    (``d/dr lambda+^T g = 0``), the least restitution, a maximum of the cost in ``r``;
    the judge moves ``r`` and finds it cheaper, so such an extremal is no optimum. The
    reference itself starts again from the extremes of ``lambda+^T g`` and ends at a bound
    (``|r| = 1``, ``e = 0.9``)."""
    ocp = quad_ball()
    S = shooting_system(ocp, ["floor"])
    ev = hybridoc.evaluate(ocp, ocp.u_guess)
    z0 = S.pack(np.zeros(2), [ev.events[0].time], [0.0], [np.array([0.0, -0.1])])
    nr = newton(S, z0)
    assert nr.converged
    res = make_result(S, nr, "test")
    assert res.event_controls[0, 1] == 0.0
    assert res.cost == pytest.approx(fixed_restitution_optimum(0.7), rel=1e-9)
    rival = event_control_rival(ocp, res)
    assert rival is not None and rival["component"] == 1 and rival["cost"] < res.cost
    sol = hybridoc.solve(ocp, "reference", multistart=0)
    # issue #29: best-found, not success: starts of Newton reach different extremals of the
    # sequence (the stationary maximum among them), and floor twice has none
    assert sol.status is Status.BEST_FOUND, sol.message
    assert "other starts reached" in sol.info["coverage"]["why_not_proven"]
    assert abs(sol.event_controls[0, 1]) == 1.0
    assert abs(sol.cost - best) <= 1e-9 * best
    assert event_control_rival(ocp, sol.reference) is None
