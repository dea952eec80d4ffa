"""Evaluation of a control given as a function of continuous time, ``u(t)``, or of a
feedback policy evaluated continuously, ``u = pi(t, s(t))``.

Used to judge controls that are not piecewise constant on the grid, such as the reference's
optimal control or a transcription's polynomial control. The flow is integrated by SciPy's
DOP853 (``rtol = atol = 1e-12``) one step at a time. On every step each guard's detector
is sampled along the step's dense output (a degree-7 polynomial) at 17 Chebyshev-Lobatto
nodes and searched by :class:`hybridoc.rootfind.CrossingSearch`, the judge's search that
bounds the detector over the whole step: a guard that dips below zero and comes back within
one step is found. (For the squared distances of disc scenes the detector along the dense
output is a polynomial of degree 14, so its interpolant is exact.) The jump rule is the
judge's (:mod:`hybridoc.events`), and integration restarts after every jump and at every
breakpoint where ``u`` may be discontinuous.

Between two breakpoints ``a < b`` the control is evaluated at times clamped a few ulps inside
``[a, b]``, so that a piecewise-constant ``u`` with breakpoints at its jumps is seen as
constant on each piece even by the Runge-Kutta stages that fall exactly on ``a`` or ``b``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from hybridoc import tolerances
from hybridoc.errors import ControlsError, EvaluationError
from hybridoc.evaluation import Evaluation
from hybridoc.events import (
    ZENO_RUN,
    Event,
    EventResolver,
    accumulating,
    approaching,
    graze_threshold,
    in_local_frame,
    moved_events,
    penetration_threshold,
)
from hybridoc.kernels import UNKNOWN_DEGREE, kernels
from hybridoc.ocp import HybridOCP, as_float_array
from hybridoc.problem import ProblemLike, as_ocp
from hybridoc.rootfind import Chebyshev, CrossingSearch

__all__ = ["evaluate_callable"]

_CHEB = Chebyshev(UNKNOWN_DEGREE)
_ZENO_WINDOW = 100
_MAX_STEPS = 10**7


def _inside(a: float, b: float) -> tuple[float, float]:
    """``[a, b]`` shrunk by a few ulps (to its midpoint if it is shorter than that)."""
    lo = a + 4 * np.spacing(abs(a))
    hi = b - 4 * np.spacing(abs(b))
    if lo > hi:
        lo = hi = 0.5 * (a + b)
    return float(lo), float(hi)


def evaluate_callable(
    problem: ProblemLike,
    control: Callable[[float], Any] | None = None,
    *,
    breakpoints: Sequence[float] = (),
    state_feedback: Callable[[float, np.ndarray], Any] | None = None,
    graze_tol: float = 1e-10,
    rtol: float = 1e-12,
    atol: float = 1e-12,
    penetration_tol: float = tolerances.value("penetration"),
    max_events: int = 10**6,
    event_controls: np.ndarray | None = None,
) -> Evaluation:
    """Simulate under a control ``u(t)`` (or a continuous feedback ``u = pi(t, s)``).

    Parameters
    ----------
    problem
        The problem (anything :func:`hybridoc.evaluate` accepts).
    control
        ``u(t) -> array of shape (nu,)``, smooth between ``breakpoints`` and events.
    breakpoints
        Times where ``u`` may jump or kink; integration restarts there.
    state_feedback
        Instead of ``control``: ``pi(t, s) -> u``, evaluated on the integrator's stages.
    graze_tol
        As in :func:`hybridoc.evaluate` (in the problem's units).
    rtol, atol
        Integrator tolerances; ``atol`` in the problem's units: times each state
        component's scale and the cost scale (:attr:`HybridOCP.scales
        <hybridoc.ocp.HybridOCP.scales>`).
    penetration_tol
        As in :func:`hybridoc.evaluate`: how far a non-jumping (grazing or resting) contact
        may penetrate before the motion counts as sustained contact, an error.
    max_events
        More events than this raise :class:`~hybridoc.errors.EvaluationError`.
    event_controls
        Optional ``(K, nu)``: the control a reset that depends on the control reads at the
        ``k``-th event (:class:`hybridoc.events.EventResolver`); default: ``u`` there.

    Returns
    -------
    Evaluation
        ``controls`` holds ``u`` at the grid-interval midpoints (for reports);
        :meth:`~hybridoc.Evaluation.sample` samples the trajectory at any time in
        ``[0, T]`` from the integrator's dense output.
    """
    ocp = as_ocp(problem)
    if (control is None) == (state_feedback is None):
        raise ControlsError("give exactly one of control (u(t)) and state_feedback (pi(t, s))")
    # a scene far from the origin is simulated in its local frame (as hybridoc.evaluate
    # does): a feedback sees the state where the scene is, the results are moved back
    outer = ocp
    ocp, off = in_local_frame(ocp)
    if off is not None:
        if state_feedback is not None:
            feedback, shift = state_feedback, off

            def state_feedback(t: float, s: np.ndarray) -> Any:
                return feedback(t, s + shift)

    u_at = _control_function(ocp, control, state_feedback)
    sim = _Simulation(ocp, u_at, graze_tol, rtol, atol, penetration_tol, max_events)
    if event_controls is not None:
        sim.resolver = EventResolver(ocp, sim.num, sim.graze_tol, event_controls)
    sim.run(breakpoints)
    ev = sim.evaluation()
    if off is None:
        return ev
    off_z = np.concatenate([off, [0.0]])  # the running cost is not moved
    return dataclasses.replace(
        ev,
        ocp=outer,
        states=ev.states + off,
        final_state=ev.final_state + off,
        events=moved_events(ev.events, off),
        dense_pieces=[(t0, t1, _Moved(dense, off_z)) for t0, t1, dense in ev.dense_pieces],
    )


class _Moved:
    """A dense output moved by ``off`` (out of the local frame)."""

    def __init__(self, dense: Any, off: np.ndarray) -> None:
        self.dense, self.off = dense, off

    def __call__(self, t: Any) -> np.ndarray:
        z = np.asarray(self.dense(t), dtype=float)
        return z + (self.off if z.ndim == 1 else self.off[:, None])


_Piece = tuple[float, float, Any, float, float]  # (t0, t1, dense output, lo, hi)


def _control_function(
    ocp: HybridOCP,
    control: Callable[[float], Any] | None,
    state_feedback: Callable[[float, np.ndarray], Any] | None,
) -> Callable[[float, np.ndarray], np.ndarray]:
    """``u(t, s)`` from ``control`` or ``state_feedback``, checked to be ``nu`` finite floats.

    The integrator calls this at each of its stages (about 15 per step); a value that is
    already a float64 array of ``nu`` finite numbers is taken as it is (copied), which costs
    about 1 us against 13 us for the general conversion (``ocp.nu`` alone, a CasADi query,
    took 2 us). Anything else takes the general path, which says what is wrong with it."""
    nu = ocp.nu

    def u_at(t: float, s: np.ndarray) -> np.ndarray:
        if state_feedback is not None:
            val = state_feedback(t, s)
        else:
            assert control is not None
            val = control(t)
        if (
            type(val) is np.ndarray
            and val.dtype == np.float64
            and val.size == nu
            and all(map(math.isfinite, val.ravel().tolist()))
        ):
            return val.reshape(nu).copy()
        arr = as_float_array(val, f"u({t:.6g})", error=ControlsError).ravel()
        if arr.shape != (nu,) or not np.all(np.isfinite(arr)):
            raise ControlsError(f"u({t:.6g}) must be {nu} finite numbers, got {arr}")
        return arr

    # a control of time alone ignores the state: _controls_at then skips the dense output,
    # and calls it directly (checking its values all at once)
    u_at.time_only = state_feedback is None  # type: ignore[attr-defined]
    u_at.control = control  # type: ignore[attr-defined]
    u_at.nu = nu  # type: ignore[attr-defined]
    return u_at


class _Simulation:
    """One simulation under ``u(t, s)``: the current point ``(t, z = [s, running cost])`` and
    the records (trajectory states, events, the integrator's dense pieces)."""

    def __init__(
        self,
        ocp: HybridOCP,
        u_at: Callable[[float, np.ndarray], np.ndarray],
        graze_tol: float,
        rtol: float,
        atol: float,
        penetration_tol: float,
        max_events: int,
    ) -> None:
        self.ocp, self.u_at = ocp, u_at
        # tolerances in the problem's units (hybridoc.scales): atol per state component and
        # for the running cost, graze and penetration in guard units
        sc = ocp.scales
        self.graze_tol, self.rtol = graze_threshold(ocp, graze_tol), rtol
        self.atol = atol * np.concatenate([sc.state_array, [sc.cost]])
        self.penetration_tol = penetration_threshold(ocp, penetration_tol)
        self.max_events = max_events
        self.k = kernels(ocp)
        self.num = self.k.numeric()
        self.nx, self.G = ocp.nx, len(ocp.guards)
        self.resolver = EventResolver(ocp, self.num, self.graze_tol)
        # the integrator's error adds to the rounding of every detector value
        self.integ_factor = 1.0 + rtol / np.finfo(float).eps
        self.z = np.concatenate([ocp.x0, [0.0]])
        self.t = 0.0
        self.times: list[float] = [0.0]
        self.states: list[np.ndarray] = [ocp.x0.copy()]
        self.events: list[Event] = []
        self.pieces: list[_Piece] = []
        self.n_steps = 0

    def run(self, breakpoints: Sequence[float]) -> None:
        """Integrate over ``[0, T]``, restarting at every breakpoint and after every jump."""
        from scipy.integrate import DOP853  # 0.35 s to import: only where it is used

        nx, T, num = self.nx, self.ocp.horizon, self.num
        stops = sorted({float(b) for b in breakpoints if 0 < b < T} | {T})
        a = 0.0
        for b in stops:
            lo, hi = _inside(a, b)

            def u_piece(tt: float, s: np.ndarray, lo: float = lo, hi: float = hi) -> np.ndarray:
                return self.u_at(min(max(tt, lo), hi), s)

            def rhs(tt: float, zz: np.ndarray, u_piece: Any = u_piece) -> np.ndarray:
                s = zz[:nx]
                return np.concatenate(num.fL(s, u_piece(tt, s)))

            while self.t < b:
                solver = DOP853(rhs, self.t, self.z, b, rtol=self.rtol, atol=self.atol)
                if not self._steps(solver, u_piece, lo, hi):
                    self.t = b
            a = b

    def _steps(
        self, solver: Any, u_piece: Callable[[float, np.ndarray], np.ndarray], lo: float, hi: float
    ) -> bool:
        """Step ``solver`` to its end or to the first crossing; whether it stopped at one."""
        ocp, num, nx = self.ocp, self.num, self.nx
        while solver.status == "running":
            msg = solver.step()
            self.n_steps += 1
            if solver.status == "failed":
                raise EvaluationError(f"integration failed at t = {solver.t:.6g}: {msg}")
            if self.n_steps > _MAX_STEPS:
                raise EvaluationError(
                    f"more than {_MAX_STEPS} integrator steps by t = {self.t:.6g}"
                )
            t0, t1 = float(solver.t_old), float(solver.t)
            dense = solver.dense_output()
            hit = (
                _search_step(
                    ocp,
                    num,
                    self.k,
                    dense,
                    u_piece,
                    t0,
                    t1,
                    self.graze_tol,
                    self.integ_factor,
                    self.penetration_tol,
                )  # fmt: skip
                if self.G
                else None
            )
            if hit is None:
                self.pieces.append((t0, t1, dense, lo, hi))
                self.t, self.z = t1, solver.y.copy()
                self.times.append(self.t)
                self.states.append(self.z[:nx].copy())
                s = self.z[:nx]
                _check_penetration(ocp, num, s, u_piece(self.t, s), self.t, self.penetration_tol)
                continue
            tau, j = hit
            self.pieces.append((t0, t0 + tau, dense, lo, hi))
            self._jump(t0 + tau, np.asarray(dense(t0 + tau), dtype=float), u_piece, j)
            return True
        return False

    def _jump(
        self,
        t_ev: float,
        z_ev: np.ndarray,
        u_piece: Callable[[float, np.ndarray], np.ndarray],
        j: int,
    ) -> None:
        """Move to the crossing of guard ``j`` at ``t_ev`` and apply the judge's jump rule."""
        nx = self.nx
        s_ev = z_ev[:nx]
        u_ev = u_piece(t_ev, s_ev)
        self.times.append(t_ev)
        self.states.append(s_ev.copy())
        s_new, evs = self.resolver.resolve(t_ev, s_ev, u_ev, {j})
        self.t, self.z = t_ev, z_ev.copy()
        if evs:
            self.events.extend(evs)
            _check_events(self.events, self.max_events, self.ocp.horizon)
            self.z[:nx] = s_new
            self.times.append(self.t)
            self.states.append(s_new.copy())

    def evaluation(self) -> Evaluation:
        """The :class:`Evaluation` of the finished simulation."""
        ocp, num, nx, z = self.ocp, self.num, self.nx, self.z
        s = z[:nx]
        terminal = float(num.phi_grad(s)[0][0])
        mids = (np.arange(ocp.steps) + 0.5) * ocp.dt
        controls = _controls_at(mids, self.pieces, self.u_at, nx)
        bound = ocp.bound_violation(controls)
        path = 0.0
        if num.path is not None:
            starts = np.array([p[0] for p in self.pieces])
            for tt, ss in zip(self.times, self.states, strict=True):
                uu = _control_at(tt, self.pieces, self.u_at, nx, ss, starts)
                path = max(path, float(np.max(-num.path(ss, uu)[0], initial=0.0)))
        return Evaluation(
            cost=terminal + float(z[nx]),
            terminal_cost=terminal,
            running_cost=float(z[nx]),
            times=np.array(self.times),
            states=np.array(self.states),
            events=self.events,
            controls=controls,
            final_state=s.copy(),
            ocp=ocp,
            bound_violation=bound,
            path_violation=path,
            # the integrator's dense output per step: Evaluation.sample between the states
            dense_pieces=[(t0, t1, dense) for t0, t1, dense, _, _ in self.pieces],
        )


def _search_step(
    ocp: HybridOCP,
    num: Any,
    k: Any,
    dense: Any,
    u_piece: Callable[[float, np.ndarray], np.ndarray],
    t0: float,
    t1: float,
    graze_tol: float,
    integ_factor: float,
    penetration_tol: float,
) -> tuple[float, int] | None:
    """Earliest crossing inside one integrator step ``[t0, t1]`` (times relative to t0)."""
    nx, G = k.nx, k.G
    D = _CHEB.D

    def window(a: float, b: float) -> tuple[np.ndarray, np.ndarray]:
        ts = t0 + _CHEB.nodes(a, b)
        Z = np.asarray(dense(ts), dtype=float)[:nx]  # (nx, D + 1)
        S, Nz = num.det_nodes(Z.T.ravel())
        return S.reshape(D + 1, G).T, integ_factor * Nz.reshape(D + 1, G).T

    def value(j: int, tau: float) -> tuple[float, float, float]:
        s = np.asarray(dense(t0 + tau), dtype=float)[:nx]
        det, rate, nz = num.det_rate(s, u_piece(t0 + tau, s))
        return float(det[j]), float(rate[j]), integ_factor * float(nz[j])

    def appr(j: int, tau: float) -> bool:
        s = np.asarray(dense(t0 + tau), dtype=float)[:nx]
        u = u_piece(t0 + tau, s)
        _, rate, accel, nz = num.contact(s, u)
        return bool(approaching(rate[j : j + 1], accel[j : j + 1], nz[j : j + 1], graze_tol)[0])

    def penetrated(j: int, tau: float) -> None:
        s = np.asarray(dense(t0 + tau), dtype=float)[:nx]
        _check_penetration(ocp, num, s, u_piece(t0 + tau, s), t0 + tau, penetration_tol)

    exact = np.zeros(G, dtype=bool)
    return CrossingSearch(
        _CHEB, exact, window, value, appr, penetrated, time_scale=ocp.scales.time
    ).run(t1 - t0)


def _check_penetration(
    ocp: HybridOCP, num: Any, s: np.ndarray, u: np.ndarray, t: float, tol: float
) -> None:
    psi, _, _, noise = num.contact(s, u)
    lim = np.maximum(tol, 4 * noise)
    bad = np.flatnonzero(psi < -lim)
    if bad.size:
        j = int(bad[np.argmin(psi[bad])])
        raise EvaluationError(
            f"guard {ocp.guards[j].name!r} is violated by {-psi[j]:.3g} at t = {t:.6g} without "
            "an impact: the bodies stay in contact (e.g. restitution 0 with a force pushing "
            "into the contact), which the impulsive model does not represent"
        )


def _check_events(events: list[Event], max_events: int, T: float) -> None:
    n = len(events)
    limit = accumulating([e.time for e in events[-(ZENO_RUN + 2) :]], T)
    if limit is not None:
        raise EvaluationError(
            f"the events accumulate near t = {limit:.9g} (their gaps shrink geometrically): "
            "Zeno behaviour, which the impulsive model does not resolve"
        )
    if n > max_events:
        raise EvaluationError(f"more than {max_events} events by t = {events[-1].time:.6g}")
    if n >= _ZENO_WINDOW and events[-1].time - events[n - _ZENO_WINDOW].time < 1e-9 * T:
        raise EvaluationError(
            f"{_ZENO_WINDOW} events within a vanishing time near t = {events[-1].time:.9g}: "
            "an accumulation of impacts (Zeno behaviour) that the impulsive model does not "
            "resolve"
        )


def _control_at(
    t: float,
    pieces: list[tuple[float, float, Any, float, float]],
    u_at: Any,
    nx: int,
    s: Any,
    starts: np.ndarray | None = None,
) -> np.ndarray:
    """``u(t)`` on the simulated trajectory (``s``: the state there, when known; ``starts``:
    the pieces' start times, when the caller has them)."""
    if not pieces:
        return u_at(t, s if s is not None else np.zeros(nx))
    if starts is None:
        starts = np.array([p[0] for p in pieces])
    i = min(max(int(np.searchsorted(starts, t, side="right")) - 1, 0), len(pieces) - 1)
    _, _, dense, lo, hi = pieces[i]
    if s is None:
        # a control of time alone does not read the state: no dense output to evaluate
        s = np.zeros(nx) if getattr(u_at, "time_only", False) else dense(t)
        s = np.asarray(s, dtype=float)[:nx]
    return u_at(min(max(t, lo), hi), s)


def _controls_at(
    mids: np.ndarray, pieces: list[tuple[float, float, Any, float, float]], u_at: Any, nx: int
) -> np.ndarray:
    starts = np.array([p[0] for p in pieces])
    if pieces and getattr(u_at, "time_only", False):
        fast = _time_controls(mids, pieces, starts, u_at.control, u_at.nu)
        if fast is not None:
            return fast
    return np.array([_control_at(float(tm), pieces, u_at, nx, None, starts) for tm in mids])


def _time_controls(
    mids: np.ndarray,
    pieces: list[tuple[float, float, Any, float, float]],
    starts: np.ndarray,
    control: Callable[[float], Any],
    nu: int,
) -> np.ndarray | None:
    """``u`` of a control of time alone at ``mids``, as :func:`_control_at` gives it (the
    same pieces, the same clamped times, the same values) with the lookups and the checks
    done once for all the times: a dataset draw's report of 480 controls spent most of its
    time in them. ``None`` when a value is not a float64 array of ``nu`` finite numbers;
    the caller's checked path then says what is wrong with it."""
    last = len(pieces) - 1
    idx = np.clip(np.searchsorted(starts, mids, side="right") - 1, 0, last)
    lo = np.array([p[3] for p in pieces])[idx]
    hi = np.array([p[4] for p in pieces])[idx]
    out = np.empty((len(mids), nu))
    for k, t in enumerate(np.minimum(np.maximum(mids, lo), hi).tolist()):
        val = control(t)
        if type(val) is not np.ndarray or val.dtype != np.float64 or val.size != nu:
            return None
        out[k] = val.ravel()
    return out if np.isfinite(out).all() else None
