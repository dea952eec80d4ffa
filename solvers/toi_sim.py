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
    """``(s, u, h) -> (s(h), integral of L)``: the closed-form flow map or RK4 sub-steps."""
    nx, nu = ocp.nx, ocp.nu
    fm = ocp.flow_map
    if ocp.has_closed_form_flow and fm is not None and fm.is_a("SXFunction"):
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
    s = ca.SX.sym("s", nx)
    u = ca.SX.sym("u", nu)
    sp = ca.SX.sym("sp", nx)
    guards = ocp.guards
    psi_fns, det_fns, rate_fns, det_rate_fns = [], [], [], []
    for g in guards:
        psi = g.psi(sp)
        det = g.detector(sp) if g.detector is not None else psi
        psi_fns.append(ca.Function("psi", [sp], [psi]))
        det_fns.append(ca.Function("det", [sp], [det]))
        rate_fns.append(ca.Function("rate", [sp, u], [ca.jtimes(psi, sp, ocp.f(sp, u))]))
        det_rate_fns.append(ca.Function("det_rate", [sp, u], [ca.jtimes(det, sp, ocp.f(sp, u))]))

    state = s
    cost = ca.SX(0)
    remaining = ca.SX(dt)
    for _ in range(max_events if guards else 0):
        s_hat, c_hat = flow(state, u, remaining)
        best_tau = remaining
        best_state = s_hat
        best_cost = c_hat
        best_after = s_hat
        fired = ca.SX(0)
        for j in range(len(guards)):
            psi_hat = psi_fns[j](s_hat)
            rate_hat = rate_fns[j](s_hat, u)
            hit = ca.logic_and(psi_hat < 0, rate_hat < 0)
            safe_rate = ca.if_else(hit, rate_hat, -1.0)
            # the paper's estimate: the guard was crossed psi / rate before the end
            tau = ca.fmin(ca.fmax(remaining - psi_hat / safe_rate, 0.0), remaining)
            for _k in range(newton_iterations):
                s_tau = flow(state, u, tau)[0]
                d = det_fns[j](s_tau)
                dd = det_rate_fns[j](s_tau, u)
                ok = ca.logic_and(hit, dd < 0)
                dd = ca.if_else(ok, dd, -1.0)
                tau = ca.if_else(ok, ca.fmin(ca.fmax(tau - d / dd, 0.0), remaining), tau)
            s_ev, c_ev = flow(state, u, tau)
            earlier = ca.logic_and(hit, tau < best_tau)
            best_tau = ca.if_else(earlier, tau, best_tau)
            best_state = ca.if_else(earlier, s_ev, best_state)
            best_cost = ca.if_else(earlier, c_ev, best_cost)
            # a reset that depends on the control reads the step's own (the cell's) control
            best_after = ca.if_else(earlier, guards[j].reset_at(s_ev, u), best_after)
            fired = ca.if_else(earlier, 1.0, fired)
        # no event: the flow to the end; an event: the state just after its jump
        cost = cost + best_cost
        state = ca.if_else(fired > 0.5, best_after, best_state)
        remaining = ca.if_else(fired > 0.5, remaining - best_tau, 0.0)
    s_end, c_end = flow(state, u, remaining)
    cost = cost + c_end
    if isinstance(dt, ca.SX):
        return ca.Function(
            "toi_step_h", [s, u, dt], [s_end, cost], ["s", "u", "h"], ["s_next", "cost"]
        )
    return ca.Function("toi_step", [s, u], [s_end, cost], ["s", "u"], ["s_next", "cost"])
