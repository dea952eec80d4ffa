"""The event-exact evaluator: the judge of any control.

:func:`evaluate` simulates the continuous hybrid system of a :class:`~hybridoc.HybridOCP`
under a control that is piecewise constant on the N-grid and returns the trajectory, every
event and the cost. :func:`gradient` returns the exact gradient of that continuous cost with
respect to the initial state and to every control value, by the adjoint with the hybrid
minimum principle's jump relation (the saltation-matrix adjoint).

How events are located
    On each grid interval the control is constant. Each guard's detector is sampled along the
    exact flow at ``degree + 1`` Chebyshev-Lobatto points; for the polynomial flows and guards
    of disc scenes (degree 4 for disc-disc, 2 for disc-wall) the Chebyshev interpolant *is*
    the detector, so its roots are exact up to rounding; they are then polished by Newton's
    method on the guard itself. Guards of unknown degree use a degree-16 interpolant.

Which crossings jump
    A guard fires when it crosses zero from above with approach speed
    ``d psi/dt < -graze_tol``. A grazing contact (approach speed within ``graze_tol`` of zero)
    does not jump.

Simultaneous events
    Crossings within ``1e-13 * T`` of the earliest one are simultaneous. They are resolved at
    one time, one reset at a time, always taking the lowest-index guard (the scene's order:
    disc pairs, then disc-wall) that is still in contact and still approaching after the
    previous resets, until none is. The result is deterministic; the gradient at such a point
    is the one-sided derivative for that order.

Not modelled
    Sustained contact (e.g. restitution 0 with a force pushing into the contact) and Zeno
    accumulations of events raise :class:`~hybridoc.errors.EvaluationError` instead of
    returning a wrong number.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np
from numpy.polynomial import chebyshev as cheb

from hybridoc.errors import ControlsError, EvaluationError
from hybridoc.ocp import HybridOCP

__all__ = ["Event", "Evaluation", "Gradient", "evaluate", "gradient", "as_ocp"]

_UNKNOWN_DEGREE = 16
_MAX_EVENTS_PER_INTERVAL = 200


@dataclass(frozen=True)
class Event:
    """One state jump.

    Attributes
    ----------
    time
        Event time.
    kind
        Guard kind, e.g. ``"disc-disc"`` or ``"disc-wall"``.
    bodies
        Names of the bodies involved.
    guard
        Index of the guard in ``ocp.guards``.
    approach_speed
        ``d psi/dt`` just before the jump (negative).
    state_before, state_after
        ``s(gamma-)`` and ``s(gamma+)``.
    """

    time: float
    kind: str
    bodies: tuple[str, ...]
    guard: int
    approach_speed: float
    state_before: np.ndarray = field(repr=False)
    state_after: np.ndarray = field(repr=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready ``{"time", "kind", "bodies"}``."""
        return {"time": float(self.time), "kind": self.kind, "bodies": list(self.bodies)}


@dataclass(frozen=True)
class _Segment:
    t0: float
    s0: np.ndarray
    interval: int
    h: float
    event: int | None  # guard fired at the segment's end


@dataclass
class Evaluation:
    """Result of :func:`evaluate`.

    Attributes
    ----------
    cost, terminal_cost, running_cost
        ``J = phi(s(T)) + integral L``, and its two parts.
    times, states
        Grid times and event times with the states there; an event appears twice, with the
        state before and after the jump.
    events
        The events in time order.
    controls
        The ``(N, nu)`` controls that were evaluated.
    final_state
        ``s(T)``.
    """

    cost: float
    terminal_cost: float
    running_cost: float
    times: np.ndarray
    states: np.ndarray
    events: list[Event]
    controls: np.ndarray
    final_state: np.ndarray
    ocp: HybridOCP = field(repr=False)
    segments: list[_Segment] = field(repr=False, default_factory=list)

    def sample(self, times: Sequence[float] | np.ndarray) -> np.ndarray:
        """States at arbitrary times (after any jump at exactly that time)."""
        if not self.segments:
            raise ValueError("dense sampling needs piecewise-constant controls")
        t = np.atleast_1d(np.asarray(times, dtype=float))
        starts = np.array([seg.t0 for seg in self.segments])
        out = np.empty((t.size, self.ocp.nx))
        fm = self.ocp.flow_map
        for k, tk in enumerate(t):
            i = max(int(np.searchsorted(starts, tk, side="right")) - 1, 0)
            seg = self.segments[i]
            tau = min(max(tk - seg.t0, 0.0), seg.h) if i < len(self.segments) - 1 else tk - seg.t0
            s_end, _ = fm(seg.s0, self.controls[seg.interval], tau)
            out[k] = np.asarray(s_end).ravel()
        return out

    def event_dicts(self) -> list[dict[str, Any]]:
        """Events as JSON-ready dicts."""
        return [e.to_dict() for e in self.events]


@dataclass
class Gradient:
    """Result of :func:`gradient`.

    Attributes
    ----------
    cost
        The continuous cost ``J``.
    d_initial_state
        ``dJ/ds(0)``, equal to the costate ``lambda(0)``.
    d_controls
        ``dJ/du``, shape ``(N, nu)``: derivative with respect to each piecewise-constant value.
    costate_times, costates
        The costate at the start and end of every segment (events appear twice: after and
        before the jump), in time order.
    evaluation
        The forward :class:`Evaluation`.
    """

    cost: float
    d_initial_state: np.ndarray
    d_controls: np.ndarray
    costate_times: np.ndarray
    costates: np.ndarray
    evaluation: Evaluation


def as_ocp(problem: Any) -> HybridOCP:
    """Accept a :class:`HybridOCP` or anything with ``to_ocp()`` (a Scene)."""
    if isinstance(problem, HybridOCP):
        return problem
    to_ocp = getattr(problem, "to_ocp", None)
    if to_ocp is None:
        raise TypeError(f"expected a HybridOCP or a Scene, got {type(problem).__name__}")
    return to_ocp()


class _Compiled:
    """CasADi functions an evaluator needs, built once per OCP."""

    def __init__(self, ocp: HybridOCP) -> None:
        nx, nu, G = ocp.nx, ocp.nu, len(ocp.guards)
        s = ca.SX.sym("s", nx) if _is_sx(ocp) else ca.MX.sym("s", nx)
        u = type(s).sym("u", nu)
        h = type(s).sym("h")
        degrees = [g.degree for g in ocp.guards]
        if G and all(d is not None for d in degrees):
            D = max(max(int(d) for d in degrees if d is not None), 1)
        else:
            D = _UNKNOWN_DEGREE
        self.D = D
        # Chebyshev-Lobatto nodes on [-1, 1], ascending, and the interpolation matrix
        self.x_nodes = -np.cos(np.pi * np.arange(D + 1) / D)
        self.interp = np.linalg.inv(cheb.chebvander(self.x_nodes, D))
        fm = ocp.flow_map
        assert fm is not None
        s_end, cost = fm(s, u, h)
        dets = [g.detector if g.detector is not None else g.psi for g in ocp.guards]
        if G:
            cols = []
            for xk in self.x_nodes:
                sk = fm(s, u, h * (xk + 1) / 2)[0]
                cols.append(ca.vertcat(*[d(sk) for d in dets]))
            samples = ca.horzcat(*cols)
        else:
            samples = type(s)(0, D + 1)
        self.interval = ca.Function("interval", [s, u, h], [s_end, cost, samples])
        # detector, its time derivative, guard and guard rate at s(h)
        det_v = ca.vertcat(*[d(s_end) for d in dets]) if G else type(s)(0, 1)
        det_r = ca.jacobian(det_v, h) if G else type(s)(0, 1)
        self.point = ca.Function("point", [s, u, h], [s_end, det_v, det_r])
        sp = type(s).sym("sp", nx)
        psi = ca.vertcat(*[g.psi(sp) for g in ocp.guards]) if G else type(s)(0, 1)
        rate = ca.jtimes(psi, sp, ocp.f(sp, u)) if G else type(s)(0, 1)
        self.contact = ca.Function("contact", [sp, u], [psi, rate])
        self.resets = [g.reset for g in ocp.guards]
        # adjoint pieces
        self.seg_jac = ca.Function(
            "seg_jac",
            [s, u, h],
            [ca.jacobian(s_end, s), ca.jacobian(s_end, u), ca.gradient(cost, s), ca.gradient(cost, u)],
        )
        self.event_jac = []
        for g in ocp.guards:
            gs = g.reset(sp)
            self.event_jac.append(
                ca.Function(
                    "event_jac",
                    [sp, u],
                    [ca.gradient(g.psi(sp), sp), ca.jacobian(gs, sp), gs],
                )
            )
        self.fL = ca.Function("fL", [sp, u], [ocp.f(sp, u), ocp.L(sp, u)])
        sf = type(s).sym("sf", nx)
        self.phi_grad = ca.Function("phi_grad", [sf], [ocp.phi(sf), ca.gradient(ocp.phi(sf), sf)])


def _is_sx(ocp: HybridOCP) -> bool:
    fns = [ocp.f, ocp.L, ocp.phi, ocp.flow_map] + [g.psi for g in ocp.guards]
    return all(fn.is_a("SXFunction") for fn in fns if fn is not None)


def _compiled(ocp: HybridOCP) -> _Compiled:
    c = ocp._cache.get("evaluator")
    if c is None:
        c = _Compiled(ocp)
        ocp._cache["evaluator"] = c
    return c


def _vec(x: Any) -> np.ndarray:
    return np.asarray(x, dtype=float).ravel()


def evaluate(
    problem: Any,
    controls: Any = None,
    *,
    graze_tol: float = 1e-10,
    penetration_tol: float = 1e-9,
) -> Evaluation:
    """Simulate the continuous hybrid system under piecewise-constant controls.

    Parameters
    ----------
    problem
        A :class:`~hybridoc.HybridOCP` or a :class:`~hybridoc.problems.Scene`.
    controls
        ``(N, nu)`` values, constant on each grid interval; default: the problem's initial
        guess. A callable ``u(t)`` is accepted too (see :func:`evaluate_callable`).
    graze_tol
        Approach speeds ``|d psi/dt|`` below this are grazing: no jump.
    penetration_tol
        A guard more negative than this at the end of a grid interval means the impulsive
        model cannot represent the motion (sustained contact): an error, not a number.

    Returns
    -------
    Evaluation
    """
    ocp = as_ocp(problem)
    if callable(controls):
        from hybridoc.callable_eval import evaluate_callable

        return evaluate_callable(ocp, controls, graze_tol=graze_tol)
    u_all = ocp.check_controls(ocp.u_guess if controls is None else controls)
    c = _compiled(ocp)
    G = len(ocp.guards)
    T, N = ocp.horizon, ocp.steps
    grid = ocp.time_grid()
    tol_time = 1e-13 * T
    s = ocp.x0.copy()
    times: list[float] = [0.0]
    states: list[np.ndarray] = [s.copy()]
    events: list[Event] = []
    segments: list[_Segment] = []
    running = 0.0
    for n in range(N):
        u = u_all[n]
        t = grid[n]
        t_end = grid[n + 1]
        n_events = 0
        while True:
            h = t_end - t
            s_end, cost, samples = c.interval(s, u, h)
            s_end = _vec(s_end)
            hit = _first_crossing(c, s, u, h, np.asarray(samples), graze_tol, tol_time) if G else None
            if hit is None:
                segments.append(_Segment(t, s.copy(), n, h, None))
                running += float(cost)
                s = s_end
                break
            tau, first, simultaneous = hit
            s_ev, cost_ev, _ = c.interval(s, u, tau)
            segments.append(_Segment(t, s.copy(), n, tau, None))  # event index set below
            running += float(cost_ev)
            s = _vec(s_ev)
            t = t + tau
            times.append(t)
            states.append(s.copy())
            pending = set(simultaneous) | {first}
            fired_any = False
            while True:
                psi, rate = (_vec(x) for x in c.contact(s, u))
                cand = [
                    j
                    for j in range(G)
                    if rate[j] < -graze_tol and (j in pending or abs(psi[j]) <= 1e-12)
                ]
                if not cand:
                    break
                j = min(cand)
                pending.discard(j)
                s_new = _vec(c.resets[j](s))
                g = ocp.guards[j]
                events.append(Event(t, g.kind, g.bodies, j, float(rate[j]), s.copy(), s_new))
                if fired_any:
                    segments.append(_Segment(t, s.copy(), n, 0.0, j))
                else:
                    last = segments[-1]
                    segments[-1] = _Segment(last.t0, last.s0, last.interval, last.h, j)
                fired_any = True
                s = s_new
                n_events += 1
                if n_events > _MAX_EVENTS_PER_INTERVAL:
                    raise EvaluationError(
                        f"more than {_MAX_EVENTS_PER_INTERVAL} events in grid interval {n} "
                        f"near t = {t:.6g}: an accumulation of impacts (Zeno behaviour) that "
                        "the impulsive model does not resolve"
                    )
            if not fired_any:  # _first_crossing applies the same test: cannot happen
                raise AssertionError(f"event at t = {t} located but not fired")
            times.append(t)
            states.append(s.copy())
        t = t_end
        if G:
            psi, _ = c.contact(s, u)
            psi = _vec(psi)
            worst = int(np.argmin(psi))
            if psi[worst] < -penetration_tol:
                g = ocp.guards[worst]
                raise EvaluationError(
                    f"guard {g.name!r} is violated by {-psi[worst]:.3g} at t = {t:.6g}: the "
                    "bodies stay in contact (e.g. restitution 0 with a force pushing into the "
                    "contact), which the impulsive model does not represent"
                )
        times.append(t)
        states.append(s.copy())
    phi, _ = c.phi_grad(s)
    terminal = float(phi)
    t_arr, s_arr = _dedupe(np.array(times), np.array(states))
    ev = Evaluation(
        cost=terminal + running,
        terminal_cost=terminal,
        running_cost=running,
        times=t_arr,
        states=s_arr,
        events=events,
        controls=u_all,
        final_state=s.copy(),
        ocp=ocp,
        segments=segments,
    )
    if not np.isfinite(ev.cost):
        raise EvaluationError("the cost is not finite: the controls drive the state to overflow")
    return ev


def _dedupe(times: np.ndarray, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop exact repeats (same time and same state) that the loop records."""
    keep = np.ones(times.size, dtype=bool)
    for k in range(1, times.size):
        if times[k] == times[k - 1] and np.array_equal(states[k], states[k - 1]):
            keep[k] = False
    return times[keep], states[keep]


def _first_crossing(
    c: _Compiled,
    s: np.ndarray,
    u: np.ndarray,
    h: float,
    samples: np.ndarray,
    graze_tol: float,
    tol_time: float,
) -> tuple[float, int, list[int]] | None:
    """Earliest downward crossing in [0, h]: (tau, guard, guards crossing within tol_time)."""
    if h <= 0:
        return None
    coeffs = samples @ c.interp.T  # (G, D+1) Chebyshev coefficients on [0, h]
    lower = coeffs[:, 0] - np.abs(coeffs[:, 1:]).sum(axis=1)
    maybe = np.nonzero(lower <= 0)[0]
    found: list[tuple[float, int]] = []
    for j in maybe:
        cj = coeffs[j]
        scale = np.abs(cj).max()
        if scale == 0:
            continue
        cj = cj / scale
        last = np.max(np.nonzero(np.abs(cj) > 1e-14)[0], initial=0)
        if last == 0:
            continue
        roots = cheb.chebroots(cj[: last + 1])
        roots = roots[np.abs(roots.imag) < 1e-6].real
        roots = roots[(roots >= -1 - 1e-9) & (roots <= 1 + 1e-9)]
        cands = [float(np.clip((r + 1) / 2 * h, 0.0, h)) for r in roots]
        if samples[j, 0] <= 0:
            cands.append(0.0)  # numerically at contact already: the approach test decides
        for tau0 in sorted(set(cands)):
            tau = _polish(c, s, u, h, j, tau0)
            if tau is None:
                continue
            s_tau = c.point(s, u, tau)[0]
            rate = float(_vec(c.contact(s_tau, u)[1])[j])
            if rate < -graze_tol:  # the same test the event loop applies
                found.append((tau, int(j)))
                break
    if not found:
        return None
    found.sort()
    tau, first = found[0]
    simultaneous = [j for (tj, j) in found if tj <= tau + tol_time]
    return tau, first, simultaneous


def _point(c: _Compiled, s: np.ndarray, u: np.ndarray, tau: float, j: int) -> tuple[Any, float, float]:
    s_t, det, rate = c.point(s, u, tau)
    return s_t, float(_vec(det)[j]), float(_vec(rate)[j])


def _polish(c: _Compiled, s: np.ndarray, u: np.ndarray, h: float, j: int, tau: float) -> float | None:
    """Newton on the detector from an interpolated root, kept inside [0, h]."""
    for _ in range(30):
        _, d, r = _point(c, s, u, tau, j)
        if d == 0.0:
            return tau
        if r == 0.0:
            break
        step = d / r
        new = min(max(tau - step, 0.0), h)
        if abs(new - tau) <= 4e-16 * max(h, 1.0):
            return new
        tau = new
    _, d, _ = _point(c, s, u, tau, j)
    return tau if abs(d) < 1e-10 else None


def gradient(problem: Any, controls: Any = None, **kwargs: Any) -> Gradient:
    """Exact gradient of the continuous cost (adjoint with the HMP jump relation).

    Between events the costate follows ``d lambda/dt = -dH/ds`` (done exactly by the
    transposed Jacobians of the flow map); at an event
    ``lambda(gamma-) = Dg^T lambda(gamma+) + pi grad psi`` with ``pi`` chosen so that the
    Hamiltonian ``H = L + lambda^T f`` is continuous. Then ``dJ/ds(0) = lambda(0)`` and
    ``dJ/du_n`` is the integral of ``dH/du`` over grid interval ``n``.

    Parameters
    ----------
    problem
        A :class:`~hybridoc.HybridOCP` or a Scene.
    controls
        ``(N, nu)`` piecewise-constant values; default: the initial guess.
    **kwargs
        Passed to :func:`evaluate`.
    """
    ocp = as_ocp(problem)
    if callable(controls):
        raise ControlsError("gradient needs piecewise-constant controls on the N-grid")
    ev = evaluate(ocp, controls, **kwargs)
    c = _compiled(ocp)
    u_all = ev.controls
    _, lam = c.phi_grad(ev.final_state)
    lam = _vec(lam)
    d_u = np.zeros_like(u_all)
    lam_times = [ocp.horizon]
    lam_list = [lam.copy()]
    for seg in reversed(ev.segments):
        u = u_all[seg.interval]
        if seg.event is not None:
            j = seg.event
            b = _vec(c.interval(seg.s0, u, seg.h)[0])
            grad_psi, Dg, gb = (np.asarray(x) for x in c.event_jac[j](b, u))
            grad_psi = grad_psi.ravel()
            gb = gb.ravel()
            f_minus, L_minus = (_vec(x) for x in c.fL(b, u))
            f_plus, L_plus = (_vec(x) for x in c.fL(gb, u))
            H_plus = float(L_plus[0]) + lam @ f_plus
            denom = grad_psi @ f_minus
            pi = (H_plus - float(L_minus[0]) - lam @ (Dg @ f_minus)) / denom
            lam = Dg.T @ lam + pi * grad_psi
            lam_times.append(seg.t0 + seg.h)
            lam_list.append(lam.copy())
        Fs, Fu, Cs, Cu = (np.asarray(x) for x in c.seg_jac(seg.s0, u, seg.h))
        d_u[seg.interval] += Cu.ravel() + Fu.T @ lam
        lam = Cs.ravel() + Fs.T @ lam
        lam_times.append(seg.t0)
        lam_list.append(lam.copy())
    return Gradient(
        cost=ev.cost,
        d_initial_state=lam,
        d_controls=d_u,
        costate_times=np.array(lam_times[::-1]),
        costates=np.array(lam_list[::-1]),
        evaluation=ev,
    )
