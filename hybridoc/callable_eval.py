"""Evaluation of a control given as a function of continuous time, ``u(t)``.

Used to judge controls that are not piecewise constant on the grid, such as the reference's
optimal control. The flow is integrated by SciPy's DOP853 at ``rtol = atol = 1e-12`` with the
guards as terminal events (located by SciPy's root finder on the dense output), the same
jump rule as :func:`hybridoc.evaluate` (approach speed below the grazing threshold,
simultaneous crossings in guard order), and integration restarted after every jump and at
every breakpoint where ``u`` may be discontinuous.

Between two breakpoints ``a < b`` the control is evaluated at times clamped a few ulps inside
``[a, b]``, so that a piecewise-constant ``u`` with breakpoints at its jumps is seen as
constant on each piece even by the Runge-Kutta stages that fall exactly on ``a`` or ``b``.

A guard that stops the integration without jumping (a graze) is disarmed until it rises
above ``penetration_tol`` again; while disarmed, falling below ``-penetration_tol`` means
sustained contact and raises :class:`~hybridoc.errors.EvaluationError`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy.integrate import solve_ivp

from hybridoc.errors import ControlsError, EvaluationError
from hybridoc.evaluator import Evaluation, Event, _approaching, _compiled
from hybridoc.ocp import HybridOCP

__all__ = ["evaluate_callable"]

_MAX_STOPS_AT_ONE_TIME = 200


def _inside(a: float, b: float) -> tuple[float, float]:
    """``[a, b]`` shrunk by a few ulps (to its midpoint if it is shorter than that)."""
    lo = a + 4 * np.spacing(abs(a))
    hi = b - 4 * np.spacing(abs(b))
    if lo > hi:
        lo = hi = 0.5 * (a + b)
    return float(lo), float(hi)


def evaluate_callable(
    ocp: HybridOCP,
    control: Callable[[float], Any],
    *,
    breakpoints: Sequence[float] = (),
    graze_tol: float = 1e-10,
    rtol: float = 1e-12,
    atol: float = 1e-12,
    penetration_tol: float = 1e-9,
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
    penetration_tol
        As in :func:`hybridoc.evaluate`: how far a non-jumping (grazing or resting) contact
        may penetrate before the motion counts as sustained contact, an error.

    Returns
    -------
    Evaluation
        ``controls`` holds ``u`` sampled at the grid-interval midpoints (for reports).
    """
    c = _compiled(ocp)
    num = c.numeric()
    nx, G, T = ocp.nx, len(ocp.guards), ocp.horizon

    def u_at(t: float) -> np.ndarray:
        val = np.asarray(control(t), dtype=float).ravel()
        if val.shape != (ocp.nu,) or not np.all(np.isfinite(val)):
            raise ControlsError(f"u({t:.6g}) must be {ocp.nu} finite numbers, got {val}")
        return val

    psi_cache: dict[str, Any] = {"t": None, "y": None, "psi": None}

    def psi_at(t: float, y: np.ndarray) -> np.ndarray:
        # SciPy calls every event function at the same (t, y): evaluate the guards once
        if psi_cache["t"] != t or not np.array_equal(psi_cache["y"], y[:nx]):
            psi_cache["t"], psi_cache["y"] = t, y[:nx].copy()
            psi_cache["psi"] = num.guards_psi(y[:nx])[0]
        return psi_cache["psi"]

    def crossing(j: int) -> Callable[[float, np.ndarray], float]:
        def ev(t: float, z: np.ndarray) -> float:
            return float(psi_at(t, z)[j])

        ev.terminal = True  # type: ignore[attr-defined]
        ev.direction = -1  # type: ignore[attr-defined]
        return ev

    def rearm(j: int) -> Callable[[float, np.ndarray], float]:
        def ev(t: float, z: np.ndarray) -> float:
            return float(psi_at(t, z)[j]) - penetration_tol

        ev.terminal = True  # type: ignore[attr-defined]
        ev.direction = 1  # type: ignore[attr-defined]
        return ev

    def penetration(j: int) -> Callable[[float, np.ndarray], float]:
        def ev(t: float, z: np.ndarray) -> float:
            return float(psi_at(t, z)[j]) + penetration_tol

        ev.terminal = True  # type: ignore[attr-defined]
        ev.direction = -1  # type: ignore[attr-defined]
        return ev

    crossings = [crossing(j) for j in range(G)]
    rearms = [rearm(j) for j in range(G)]
    penetrations = [penetration(j) for j in range(G)]

    stops = sorted({float(b) for b in breakpoints if 0 < b < T} | {T})
    z = np.concatenate([ocp.x0, [0.0]])
    t = 0.0
    times, states, events = [0.0], [ocp.x0.copy()], []
    disarmed: set[int] = set()
    a = 0.0
    for b in stops:
        lo, hi = _inside(a, b)

        def u_piece(tt: float, lo: float = lo, hi: float = hi) -> np.ndarray:
            return u_at(min(max(tt, lo), hi))

        def rhs(tt: float, zz: np.ndarray, u_piece: Any = u_piece) -> np.ndarray:
            fs, Ls = num.fL(zz[:nx], u_piece(tt))
            return np.concatenate([fs, Ls])

        stalls = 0
        while t < b:
            # (kind, guard) of each event function passed to the integrator
            kinds = [("cross", j) for j in range(G) if j not in disarmed]
            kinds += [(k, j) for j in sorted(disarmed) for k in ("rearm", "penetrate")]
            table = {"cross": crossings, "rearm": rearms, "penetrate": penetrations}
            fns = [table[k][j] for k, j in kinds]
            sol = solve_ivp(rhs, (t, b), z, method="DOP853", rtol=rtol, atol=atol, events=fns)
            if sol.status == -1:
                raise EvaluationError(f"integration failed at t = {t:.6g}: {sol.message}")
            times.extend(sol.t[1:].tolist())
            states.extend(sol.y[:nx, 1:].T)
            z = sol.y[:, -1].copy()
            t_new = float(sol.t[-1])
            stalls = stalls + 1 if t_new == t else 0
            if stalls > _MAX_STOPS_AT_ONE_TIME:
                raise EvaluationError(
                    f"the integration stops again and again at t = {t:.6g}: an accumulation "
                    "of events (Zeno behaviour) that the impulsive model does not resolve"
                )
            t = t_new
            if sol.status != 1:
                break
            hit = [kinds[k] for k, te in enumerate(sol.t_events) if te.size]
            for kind, j in hit:
                if kind == "penetrate":
                    g = ocp.guards[j]
                    raise EvaluationError(
                        f"guard {g.name!r} is violated by more than {penetration_tol:.3g} at "
                        f"t = {t:.6g} without an impact: the bodies stay in contact (e.g. "
                        "restitution 0 with a force pushing into the contact), which the "
                        "impulsive model does not represent"
                    )
                if kind == "rearm":
                    disarmed.discard(j)
            crossed = {j for kind, j in hit if kind == "cross"}
            if not crossed:
                continue
            s = z[:nx]
            u = u_piece(t)
            fired: set[int] = set()
            n_fired = 0
            while True:
                psi, rate, accel = num.contact(s, u)
                appr = _approaching(rate, accel, s, graze_tol)
                cand = [j for j in range(G) if appr[j] and (j in crossed or abs(psi[j]) <= 1e-9)]
                if not cand:
                    break
                j = min(cand)
                crossed.discard(j)
                s_new = num.reset(j)(s)[0]
                g = ocp.guards[j]
                events.append(Event(t, g.kind, g.bodies, j, float(rate[j]), s.copy(), s_new))
                fired.add(j)
                s = s_new
                n_fired += 1
                if n_fired > _MAX_STOPS_AT_ONE_TIME:
                    raise EvaluationError(f"accumulation of events near t = {t:.6g}")
            disarmed |= crossed - fired  # grazes: no jump, and no second stop right here
            z[:nx] = s
            times.append(t)
            states.append(s.copy())
        a = b
    s = z[:nx]
    terminal = float(num.phi_grad(s)[0][0])
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
