"""Evaluation of a control given as a function of continuous time, ``u(t)``.

Used to judge controls that are not piecewise constant on the grid, such as the reference's
optimal control. The flow is integrated by SciPy's DOP853 at ``rtol = atol = 1e-12`` with the
guards as terminal events (located by SciPy's root finder on the dense output), the same
jump rule as :func:`hybridoc.evaluate` (approach speed below ``-graze_tol``, simultaneous
crossings in guard order), and integration restarted after every jump and at every
breakpoint where ``u`` may be discontinuous.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy.integrate import solve_ivp

from hybridoc.errors import ControlsError, EvaluationError
from hybridoc.evaluator import Evaluation, Event, _compiled, _vec
from hybridoc.ocp import HybridOCP

__all__ = ["evaluate_callable"]


def evaluate_callable(
    ocp: HybridOCP,
    control: Callable[[float], Any],
    *,
    breakpoints: Sequence[float] = (),
    graze_tol: float = 1e-10,
    rtol: float = 1e-12,
    atol: float = 1e-12,
) -> Evaluation:
    """Simulate under a control ``u(t)`` given as a callable.

    Parameters
    ----------
    ocp
        The problem.
    control
        ``u(t) -> array of shape (nu,)``, smooth between ``breakpoints`` and events.
    breakpoints
        Times where ``u`` may jump or kink; integration restarts there.
    graze_tol
        As in :func:`hybridoc.evaluate`.
    rtol, atol
        Integrator tolerances.

    Returns
    -------
    Evaluation
        ``controls`` holds ``u`` sampled at the grid-interval midpoints (for reports).
    """
    c = _compiled(ocp)
    nx, G, T = ocp.nx, len(ocp.guards), ocp.horizon

    def u_at(t: float) -> np.ndarray:
        val = np.asarray(control(t), dtype=float).ravel()
        if val.shape != (ocp.nu,) or not np.all(np.isfinite(val)):
            raise ControlsError(f"u({t:.6g}) must be {ocp.nu} finite numbers, got {val}")
        return val

    def rhs(t: float, z: np.ndarray) -> np.ndarray:
        fs, Ls = c.fL(z[:nx], u_at(t))
        return np.concatenate([_vec(fs), _vec(Ls)])

    def make_event(j: int) -> Callable[[float, np.ndarray], float]:
        def ev(t: float, z: np.ndarray) -> float:
            return float(_vec(c.contact(z[:nx], u_at(t))[0])[j])

        ev.terminal = True  # type: ignore[attr-defined]
        ev.direction = -1  # type: ignore[attr-defined]
        return ev

    event_fns = [make_event(j) for j in range(G)]
    stops = sorted({float(b) for b in breakpoints if 0 < b < T} | {T})
    z = np.concatenate([ocp.x0, [0.0]])
    t = 0.0
    times, states, events = [0.0], [ocp.x0.copy()], []
    for t_stop in stops:
        while t < t_stop:
            sol = solve_ivp(
                rhs, (t, t_stop), z, method="DOP853", rtol=rtol, atol=atol, events=event_fns
            )
            if sol.status == -1:
                raise EvaluationError(f"integration failed at t = {t:.6g}: {sol.message}")
            times.extend(sol.t[1:].tolist())
            states.extend(sol.y[:nx, 1:].T)
            z = sol.y[:, -1].copy()
            t = float(sol.t[-1])
            if sol.status != 1:
                break
            s = z[:nx]
            u = u_at(t)
            fired = 0
            while True:
                psi, rate = (_vec(x) for x in c.contact(s, u))
                cand = [j for j in range(G) if rate[j] < -graze_tol and abs(psi[j]) <= 1e-9]
                if not cand:
                    break
                j = min(cand)
                s_new = _vec(c.resets[j](s))
                g = ocp.guards[j]
                events.append(Event(t, g.kind, g.bodies, j, float(rate[j]), s.copy(), s_new))
                s = s_new
                fired += 1
                if fired > 200:
                    raise EvaluationError(f"accumulation of events near t = {t:.6g}")
            z[:nx] = s
            times.append(t)
            states.append(s.copy())
    s = z[:nx]
    terminal = float(c.phi_grad(s)[0])
    mids = (np.arange(ocp.steps) + 0.5) * ocp.dt
    return Evaluation(
        cost=terminal + float(z[nx]),
        terminal_cost=terminal,
        running_cost=float(z[nx]),
        times=np.array(times),
        states=np.array(states),
        events=events,
        controls=np.array([u_at(tm) for tm in mids]),
        final_state=s.copy(),
        ocp=ocp,
    )
