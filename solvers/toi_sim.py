"""A differentiable time-of-impact simulation of any :class:`~hybridoc.HybridOCP`.

The paper's method (DESIGN.md section 3) written for a general hybrid system. One step of
length ``dt`` under a constant control ``u``:

1. **Flow** the state over the whole step, ``s^ = Phi(s, u, dt)``: the problem's closed-form
   flow map when it has one (an SX function), otherwise ``substeps`` classical Runge-Kutta
   steps of ``f`` (with the running cost as an extra state).
2. **Detect** each guard that ends the step penetrated and approaching:
   ``psi(s^) < 0`` and ``d psi/dt (s^) < 0``.
3. **Locate** its event time: the paper's velocity-level linear estimate
   ``tau_0 = dt - psi(s^) / (d psi/dt)(s^)`` (Eq. 3), refined by Newton's method on the flow,
   ``tau <- tau - det(Phi(s, u, tau)) / (d det/dt)``, on the guard's detector (its polynomial
   form where it has one).
4. **Jump** at the earliest located event, ``s+ = g(Phi(s, u, tau))`` (``g(., u)`` for a
   reset that depends on the control: the step's control), and integrate the rest of the
   step, ``Phi(s+, u, dt - tau)``; then look again (up to ``max_events`` events per step).

Everything is one CasADi SX expression with ``if_else`` branches, so its derivative goes
through the event time: the gradient carries the saltation term of the jump. With an exact
flow map and converged Newton iterations the step is the exact flow of the
piecewise-constant control up to the events it resolves, and the discrete loss is the
continuous cost (to rounding). On disc scenes it agrees with the disc simulator's ``exact``
integrator (:mod:`hybridoc.solvers.simulator`).

A problem whose flow map is an MX function (the multi-start's switch over modes,
:func:`hybridoc.solvers.multistart.mode_switch`) gets an MX step: the same parts, each an SX
function (a guard's estimate, one Newton iteration, the choice of the earliest event), called
between the flow's calls, so that each flow evaluation runs only the current mode's branch;
an SX step inlines the same parts (the same expression as before they were parts, bit for
bit).
"""

from __future__ import annotations

from typing import Any

import casadi as ca

from hybridoc.errors import SceneError
from hybridoc.ocp import HybridOCP

__all__ = ["toi_step", "NEWTON_ITERATIONS", "RK4_SUBSTEPS"]

NEWTON_ITERATIONS = 6
"""Newton iterations on the event time (quadratic convergence from the linear estimate)."""
RK4_SUBSTEPS = 4
"""Runge-Kutta sub-steps per step when the problem has no closed-form flow map."""


def _sx_flow(ocp: HybridOCP, substeps: int) -> ca.Function:
    """``(s, u, h) -> (s(h), integral of L)``: the closed-form flow map or RK4 sub-steps.

    A closed-form flow map that is an MX function (a switch over the modes,
    :func:`hybridoc.solvers.multistart.mode_switch`) is returned as it is: the step is then
    built in MX around its calls."""
    nx, nu = ocp.nx, ocp.nu
    fm = ocp.flow_map
    if ocp.has_closed_form_flow and fm is not None and fm.is_a("SXFunction"):
        return fm
    if ocp.has_closed_form_flow and fm is not None and fm.is_a("MXFunction"):
        return fm
    for fn in (ocp.f, ocp.L):
        if not fn.is_a("SXFunction"):
            raise SceneError(
                "the TOI simulation needs f and L as SX functions (or an SX flow map); "
                f"{fn.name()!r} is an MX function"
            )
    s, u, h = ca.SX.sym("s", nx), ca.SX.sym("u", nu), ca.SX.sym("h")
    z = ca.vertcat(s, 0)

    def rhs(zz: Any) -> Any:
        return ca.vertcat(ocp.f(zz[:nx], u), ocp.L(zz[:nx], u))

    dh = h / substeps
    for _ in range(substeps):
        k1 = rhs(z)
        k2 = rhs(z + 0.5 * dh * k1)
        k3 = rhs(z + 0.5 * dh * k2)
        k4 = rhs(z + dh * k3)
        z = z + dh / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return ca.Function("rk4_flow", [s, u, h], [z[:nx], z[nx]])


def _guard_blocks(ocp: HybridOCP, g: Any) -> tuple[ca.Function, ca.Function, ca.Function]:
    """One guard's parts of the step (module notes, 2-4) as SX functions.

    ``start(s^, u, remaining) -> (hit, tau_0)``, ``newton(Phi(s, u, tau), u, tau, hit,
    remaining) -> tau`` (one iteration) and ``pick(s_ev, c_ev, u, tau, hit, *best) -> best``
    (the earlier event wins; ``best = (tau, state, cost, state after, fired)``). In an SX
    step their calls are inlined (the same expression as written out); in an MX step (a
    flow that switches over modes) each stays one call between the flow's calls.
    """
    nx, nu = ocp.nx, ocp.nu
    sp, u = ca.SX.sym("sp", nx), ca.SX.sym("u", nu)
    psi = g.psi(sp)
    det = g.detector(sp) if g.detector is not None else psi
    rate = ca.jtimes(psi, sp, ocp.f(sp, u))
    det_rate = ca.jtimes(det, sp, ocp.f(sp, u))
    remaining, tau, hit = ca.SX.sym("remaining"), ca.SX.sym("tau"), ca.SX.sym("hit")

    found = ca.logic_and(psi < 0, rate < 0)
    safe_rate = ca.if_else(found, rate, -1.0)
    # the paper's estimate: the guard was crossed psi / rate before the end
    tau0 = ca.fmin(ca.fmax(remaining - psi / safe_rate, 0.0), remaining)
    start = ca.Function("toi_start", [sp, u, remaining], [found, tau0])

    ok = ca.logic_and(hit, det_rate < 0)
    dd = ca.if_else(ok, det_rate, -1.0)
    step = ca.if_else(ok, ca.fmin(ca.fmax(tau - det / dd, 0.0), remaining), tau)
    newton = ca.Function("toi_newton", [sp, u, tau, hit, remaining], [step])

    c_ev = ca.SX.sym("c_ev")
    b_tau, b_state, b_cost = ca.SX.sym("b_tau"), ca.SX.sym("b_state", nx), ca.SX.sym("b_cost")
    b_after, fired = ca.SX.sym("b_after", nx), ca.SX.sym("fired")
    earlier = ca.logic_and(hit, tau < b_tau)
    # a reset that depends on the control reads the step's own (the cell's) control
    picked = [
        ca.if_else(earlier, tau, b_tau),
        ca.if_else(earlier, sp, b_state),
        ca.if_else(earlier, c_ev, b_cost),
        ca.if_else(earlier, g.reset_at(sp, u), b_after),
        ca.if_else(earlier, 1.0, fired),
    ]
    pick = ca.Function(
        "toi_pick", [sp, c_ev, u, tau, hit, b_tau, b_state, b_cost, b_after, fired], picked
    )
    return start, newton, pick


def _advance_block(nx: int) -> ca.Function:
    """``(cost, remaining, *best) -> (cost, state, remaining)``: after the guards of one
    event, the state just after the earliest event's jump, or the flow to the end."""
    cost, remaining = ca.SX.sym("cost"), ca.SX.sym("remaining")
    b_tau, b_state, b_cost = ca.SX.sym("b_tau"), ca.SX.sym("b_state", nx), ca.SX.sym("b_cost")
    b_after, fired = ca.SX.sym("b_after", nx), ca.SX.sym("fired")
    return ca.Function(
        "toi_advance",
        [cost, remaining, b_tau, b_state, b_cost, b_after, fired],
        [
            cost + b_cost,
            ca.if_else(fired > 0.5, b_after, b_state),
            ca.if_else(fired > 0.5, remaining - b_tau, 0.0),
        ],
    )


def toi_step(
    ocp: HybridOCP,
    dt: float | ca.SX,
    *,
    max_events: int = 2,
    newton_iterations: int = NEWTON_ITERATIONS,
    substeps: int = RK4_SUBSTEPS,
) -> ca.Function:
    """The TOI-corrected step ``(s, u) -> (s_next, running cost)`` of a problem (module notes).

    Parameters
    ----------
    ocp
        The problem; its functions must be SX functions (the closed-form flow map may be
        given; CVODES flows are replaced by RK4 sub-steps).
    dt
        Step length: a number, or a scalar SX symbol, which then becomes the step's third
        input, ``(s, u, h) -> (s_next, cost)`` (a free final time: :mod:`hybridoc.solvers.compiled`
        differentiates the rollout with respect to it).
    max_events
        Events resolved per step (later crossings in the same step are left to the next).
    newton_iterations
        Newton iterations on each event time.
    substeps
        RK4 sub-steps per flow evaluation when there is no closed-form flow map.
    """
    nx, nu = ocp.nx, ocp.nu
    flow = _sx_flow(ocp, substeps)
    # an MX flow (a switch that evaluates only the current mode's branch) keeps the step in
    # MX, so that each of its calls stays one call; SX would inline every branch again
    sym = ca.MX if flow.is_a("MXFunction") and not isinstance(dt, ca.SX) else ca.SX
    if sym is ca.SX and flow.is_a("MXFunction"):
        flow = flow.expand()
    s = sym.sym("s", nx)
    u = sym.sym("u", nu)
    blocks = [_guard_blocks(ocp, g) for g in ocp.guards]
    advance = _advance_block(nx)
    state = s
    cost = sym(0)
    remaining = dt if isinstance(dt, ca.SX) else sym(dt)
    for _ in range(max_events if blocks else 0):
        s_hat, c_hat = flow(state, u, remaining)
        best = [remaining, s_hat, c_hat, s_hat, sym(0)]  # tau, state, cost, after, fired
        for start, newton, pick in blocks:
            hit, tau = start(s_hat, u, remaining)
            for _k in range(newton_iterations):
                tau = newton(flow(state, u, tau)[0], u, tau, hit, remaining)
            s_ev, c_ev = flow(state, u, tau)
            best = pick(s_ev, c_ev, u, tau, hit, *best)
        cost, state, remaining = advance(cost, remaining, *best)
    s_end, c_end = flow(state, u, remaining)
    cost = cost + c_end
    if isinstance(dt, ca.SX):
        return ca.Function(
            "toi_step_h", [s, u, dt], [s_end, cost], ["s", "u", "h"], ["s_next", "cost"]
        )
    return ca.Function("toi_step", [s, u], [s_end, cost], ["s", "u"], ["s_next", "cost"])
