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
    ``d psi/dt < -max(graze_tol, sqrt(2 sigma max(d2 psi/dt2, 0)))`` with
    ``sigma = 4 eps max(1, |s|_inf)`` the rounding level of the guard. The second term is the
    noise floor of the approach speed at a near-tangent root: there a rounding error
    ``sigma`` in ``psi`` moves the computed root by ``sqrt(2 sigma / psi'')`` and gives a
    spurious approach speed of that size. A grazing contact (approach speed below the
    threshold) does not jump; the penetration this allows is of order ``sigma``.

Simultaneous events
    Crossings within ``1e-13 * T`` of the earliest one are simultaneous. They are resolved at
    one time, one reset at a time, always taking the lowest-index guard (the scene's order:
    disc pairs, then disc-wall) that is still in contact and still approaching after the
    previous resets, until none is. The result is deterministic; the gradient at such a point
    is the one-sided derivative for that order.

Speed
    All numerical work goes through CasADi's buffer API (no DM conversions). For SX problems
    (disc scenes) the flow, its cost and the detector samples of all remaining grid intervals
    come from one ``mapaccum`` call; a Chebyshev bound (``|T_k| <= 1``) then proves most
    intervals free of events, and only the first interval that may hold one is handled
    in Python, after which the batch restarts. The adjoint evaluates all segment Jacobians
    in one mapped call.

Not modelled
    Sustained contact (e.g. restitution 0 with a force pushing into the contact) and Zeno
    accumulations of events raise :class:`~hybridoc.errors.EvaluationError` instead of
    returning a wrong number.
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, NamedTuple

import casadi as ca
import numpy as np
from numpy.polynomial import chebyshev as cheb

from hybridoc.errors import ControlsError, EvaluationError
from hybridoc.ocp import HybridOCP, _integrator_flow_samples

__all__ = ["Event", "Evaluation", "Gradient", "evaluate", "gradient", "as_ocp"]

_UNKNOWN_DEGREE = 16
_MAX_EVENTS_PER_INTERVAL = 200
_EPS = float(np.finfo(float).eps)
_SX_CHUNK = 64  # grid intervals per batched call of SX functions


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

    def __post_init__(self) -> None:
        # plain floats, so reprs and JSON read the same whatever produced them
        object.__setattr__(self, "time", float(self.time))
        object.__setattr__(self, "approach_speed", float(self.approach_speed))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready ``{"time", "kind", "bodies"}``."""
        return {"time": float(self.time), "kind": self.kind, "bodies": list(self.bodies)}


class _Segment(NamedTuple):
    """A piece of the trajectory under one constant control (cheap to build in bulk)."""

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
        flow = _compiled(self.ocp).numeric().flow
        for k, tk in enumerate(t):
            i = max(int(np.searchsorted(starts, tk, side="right")) - 1, 0)
            seg = self.segments[i]
            tau = min(max(tk - seg.t0, 0.0), seg.h) if i < len(self.segments) - 1 else tk - seg.t0
            out[k] = flow(seg.s0, self.controls[seg.interval], tau)[0]
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


class _Num:
    """Numerical evaluation of a CasADi Function through its buffer API.

    Calling a Function with numpy arrays converts every argument and result to and from DM,
    which costs about a hundred times the arithmetic of a small disc-scene function. Here
    the inputs and outputs are numpy buffers bound once; a call copies the arguments in,
    evaluates, and returns flat copies of the (dense) outputs in CasADi's column-major order.
    """

    def __init__(self, fn: ca.Function) -> None:
        for i in range(fn.n_in()):
            if not fn.sparsity_in(i).is_dense():
                raise ValueError(f"{fn.name()}: input {i} is not dense")
        for i in range(fn.n_out()):
            if not fn.sparsity_out(i).is_dense():
                raise ValueError(f"{fn.name()}: output {i} is not dense")
        self.name = fn.name()
        self._args = [np.zeros(fn.nnz_in(i)) for i in range(fn.n_in())]
        self._res = [np.zeros(fn.nnz_out(i)) for i in range(fn.n_out())]
        self._buf, self._eval = fn.buffer()
        for i, a in enumerate(self._args):
            self._buf.set_arg(i, memoryview(a))
        for i, r in enumerate(self._res):
            self._buf.set_res(i, memoryview(r))

    def __call__(self, *args: Any) -> list[np.ndarray]:
        for a, x in zip(self._args, args, strict=True):
            a[...] = x
        self._eval()
        if self._buf.ret() != 0:
            raise EvaluationError(f"numerical evaluation of {self.name!r} failed")
        return [r.copy() for r in self._res]


def _dense_fn(name: str, args: list[Any], outs: list[Any]) -> ca.Function:
    return ca.Function(name, args, [ca.densify(o) for o in outs])


class _Compiled:
    """CasADi functions an evaluator needs, built once per OCP."""

    def __init__(self, ocp: HybridOCP) -> None:
        nx, nu, G = ocp.nx, ocp.nu, len(ocp.guards)
        self.is_sx = _is_sx(ocp)
        sym = ca.SX if self.is_sx else ca.MX
        s, u, h = sym.sym("s", nx), sym.sym("u", nu), sym.sym("h")
        degrees = [g.degree for g in ocp.guards]
        if G and all(d is not None for d in degrees):
            D = max(max(int(d) for d in degrees if d is not None), 1)
        else:
            D = _UNKNOWN_DEGREE
        self.nx, self.nu, self.G, self.D = nx, nu, G, D
        # Chebyshev-Lobatto nodes on [-1, 1], ascending, and the interpolation matrix
        self.x_nodes = -np.cos(np.pi * np.arange(D + 1) / D)
        self.interp = np.linalg.inv(cheb.chebvander(self.x_nodes, D))
        fm = ocp.flow_map
        assert fm is not None
        s_end, cost = fm(s, u, h)
        dets = [g.detector if g.detector is not None else g.psi for g in ocp.guards]

        def det_of(x: Any) -> Any:
            return ca.vertcat(*[d(x) for d in dets]) if G else sym(0, 1)

        if ocp._cache.get("integrator_flow"):
            # the built-in CVODES flow map: all nodes from one integration with a time grid
            fracs = (self.x_nodes[1:] + 1) / 2
            fracs[-1] = 1.0
            sampler = _integrator_flow_samples(ocp.f, ocp.L, fracs)
            xs, qs = sampler(s, u, h)
            node_states = [s] + [xs[:, k] for k in range(D)]
            s_end, cost = xs[:, D - 1], qs[:, D - 1]
        else:
            # the end nodes are s itself and s_end: no extra flow evaluation (exact)
            node_states = [s]
            node_states += [fm(s, u, h * (xk + 1) / 2)[0] for xk in self.x_nodes[1:-1]]
            node_states.append(s_end)
        cols = [det_of(sk) for sk in node_states]
        samples = ca.horzcat(*cols) if G else sym(0, D + 1)
        psi_end = ca.vertcat(*[g.psi(s_end) for g in ocp.guards]) if G else sym(0, 1)
        self.interval = _dense_fn("interval", [s, u, h], [s_end, cost, samples, psi_end])
        # SX functions are cheap: many grid intervals per call (what lies past an event is
        # computed again from the new state); an MX flow map (an integrator) is too costly to
        # evaluate past an event, so one interval per call
        self.chunk = min(ocp.steps, _SX_CHUNK) if self.is_sx else 1
        self.batch = (
            self.interval.mapaccum("interval_acc", self.chunk) if self.chunk > 1 else self.interval
        )
        # the flow map alone, for dense sampling
        self.flow = _dense_fn("flow", [s, u, h], [s_end, cost])
        # detector, its time derivative at s(h)
        det_v = det_of(s_end)
        det_r = ca.jacobian(det_v, h) if G else sym(0, 1)
        self.point = _dense_fn("point", [s, u, h], [s_end, det_v, det_r])
        sp = sym.sym("sp", nx)
        fs = ocp.f(sp, u)
        psi = ca.vertcat(*[g.psi(sp) for g in ocp.guards]) if G else sym(0, 1)
        rate = ca.jtimes(psi, sp, fs) if G else sym(0, 1)
        accel = ca.jtimes(rate, sp, fs) if G else sym(0, 1)
        self.contact = _dense_fn("contact", [sp, u], [psi, rate, accel])
        self.guards_psi = _dense_fn("guards_psi", [sp], [psi])
        self.resets = [
            _dense_fn(f"reset{j}", [sp], [g.reset(sp)]) for j, g in enumerate(ocp.guards)
        ]
        # adjoint pieces
        # one Jacobian of (s_end, cost) w.r.t. (s, u): for an integrator flow map a single
        # forward-sensitivity solve instead of four
        jac = ca.jacobian(ca.vertcat(s_end, cost), ca.vertcat(s, u))
        seg_jac = _dense_fn(
            "seg_jac",
            [s, u, h],
            [jac[:nx, :nx], jac[:nx, nx:], jac[nx, :nx].T, jac[nx, nx:].T],
        )
        self.seg_jac = seg_jac.map(self.chunk) if self.chunk > 1 else seg_jac
        self.event_jac = [
            _dense_fn(
                f"event_jac{j}",
                [sp, u],
                [ca.gradient(g.psi(sp), sp), ca.jacobian(g.reset(sp), sp), g.reset(sp)],
            )
            for j, g in enumerate(ocp.guards)
        ]
        self.fL = _dense_fn("fL", [sp, u], [fs, ocp.L(sp, u)])
        sf = sym.sym("sf", nx)
        self.phi_grad = _dense_fn("phi_grad", [sf], [ocp.phi(sf), ca.gradient(ocp.phi(sf), sf)])
        self._local = threading.local()

    def numeric(self) -> _Numeric:
        """This thread's buffer-bound evaluators (buffers are not shared between threads)."""
        num = getattr(self._local, "num", None)
        if num is None:
            num = _Numeric(self)
            self._local.num = num
        return num

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        del state["_local"]
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._local = threading.local()


class _Numeric:
    """Lazily bound :class:`_Num` evaluators of one :class:`_Compiled` (one thread)."""

    def __init__(self, c: _Compiled) -> None:
        self.c = c
        self._resets: dict[int, _Num] = {}
        self._event_jac: dict[int, _Num] = {}

    @cached_property
    def interval(self) -> _Num:
        return _Num(self.c.interval)

    @cached_property
    def batch(self) -> _Num:
        return _Num(self.c.batch)

    @cached_property
    def flow(self) -> _Num:
        return _Num(self.c.flow)

    @cached_property
    def point(self) -> _Num:
        return _Num(self.c.point)

    @cached_property
    def contact(self) -> _Num:
        return _Num(self.c.contact)

    @cached_property
    def guards_psi(self) -> _Num:
        return _Num(self.c.guards_psi)

    @cached_property
    def seg_jac(self) -> _Num:
        return _Num(self.c.seg_jac)

    @cached_property
    def fL(self) -> _Num:
        return _Num(self.c.fL)

    @cached_property
    def phi_grad(self) -> _Num:
        return _Num(self.c.phi_grad)

    def reset(self, j: int) -> _Num:
        if j not in self._resets:
            self._resets[j] = _Num(self.c.resets[j])
        return self._resets[j]

    def event_jac(self, j: int) -> _Num:
        if j not in self._event_jac:
            self._event_jac[j] = _Num(self.c.event_jac[j])
        return self._event_jac[j]


def _is_sx(ocp: HybridOCP) -> bool:
    fns = [ocp.f, ocp.L, ocp.phi, ocp.flow_map]
    for g in ocp.guards:
        fns += [g.psi, g.reset, g.detector]
    return all(fn.is_a("SXFunction") for fn in fns if fn is not None)


def _compiled(ocp: HybridOCP) -> _Compiled:
    c = ocp._cache.get("evaluator")
    if c is None:
        c = _Compiled(ocp)
        ocp._cache["evaluator"] = c
    return c


def _approaching(
    rate: np.ndarray, accel: np.ndarray, s: np.ndarray, graze_tol: float
) -> np.ndarray:
    """Which guards approach fast enough to jump (see the module notes on grazing)."""
    sigma = 4.0 * _EPS * max(1.0, float(np.max(np.abs(s), initial=0.0)))
    floor = np.sqrt(2.0 * sigma * np.maximum(accel, 0.0))
    return rate < -np.maximum(graze_tol, floor)


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
        guess. A callable ``u(t)`` is accepted too: it goes to :func:`evaluate_callable`
        with the grid times as breakpoints (``u`` may jump there).
    graze_tol
        Approach speeds ``|d psi/dt|`` below this (or below the rounding floor described in
        the module notes) are grazing: no jump.
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

        return evaluate_callable(
            ocp,
            controls,
            breakpoints=ocp.time_grid(),
            graze_tol=graze_tol,
            penetration_tol=penetration_tol,
        )
    u_all = ocp.check_controls(ocp.u_guess if controls is None else controls)
    return _Forward(ocp, u_all, graze_tol, penetration_tol).run()


class _Forward:
    """One forward simulation (the state of :func:`evaluate`)."""

    def __init__(
        self, ocp: HybridOCP, u_all: np.ndarray, graze_tol: float, penetration_tol: float
    ) -> None:
        self.ocp = ocp
        self.c = _compiled(ocp)
        self.num = self.c.numeric()
        self.u_all = u_all
        self.graze_tol = graze_tol
        self.penetration_tol = penetration_tol
        self.tol_time = 1e-13 * ocp.horizon
        self.grid = ocp.time_grid()
        self.hs = np.diff(self.grid)
        # blocks of recorded times (1-D) and states (2-D), concatenated at the end
        self.times: list[np.ndarray] = [np.zeros(1)]
        self.states: list[np.ndarray] = [ocp.x0[None, :].copy()]
        self.events: list[Event] = []
        self.segments: list[_Segment] = []
        self.running = 0.0

    def run(self) -> Evaluation:
        ocp, c = self.ocp, self.c
        nx, nu, G, D, L = c.nx, c.nu, c.G, c.D, c.chunk
        N = ocp.steps
        grid, hs = self.grid, self.hs
        s = ocp.x0.copy()
        n = 0
        while n < N:
            m = min(L, N - n)
            uu = np.zeros((L, nu))
            uu[:m] = self.u_all[n : n + m]
            hh = np.zeros(L)
            hh[:m] = hs[n : n + m]
            s_end, cost, samples, psi_end = self.num.batch(s, uu.ravel(), hh)
            s_end = s_end.reshape(L, nx)
            samples = samples.reshape(L, D + 1, G)
            k = m  # intervals n .. n+k-1 are free of events
            if G:
                coeffs = samples[:m].transpose(0, 2, 1) @ c.interp.T  # (m, G, D+1)
                # |T_k| <= 1 on [-1, 1]: a positive lower bound proves the detector positive
                lower = coeffs[..., 0] - np.abs(coeffs[..., 1:]).sum(axis=2)
                flag = (lower <= 0).any(axis=1)
                flag |= (psi_end.reshape(L, G)[:m] < -self.penetration_tol).any(axis=1)
                hits = np.flatnonzero(flag)
                if hits.size:
                    k = int(hits[0])
            if k > 0:
                starts = [s, *s_end[: k - 1]]
                self.segments.extend(
                    map(
                        _Segment,
                        grid[n : n + k].tolist(),
                        starts,
                        range(n, n + k),
                        hs[n : n + k].tolist(),
                        [None] * k,
                    )
                )
                # cumsum adds left to right: the same rounding as adding one by one
                self.running = float(np.cumsum(np.r_[self.running, cost[:k]])[-1])
                self.times.append(grid[n + 1 : n + k + 1])
                self.states.append(s_end[:k])
                s = s_end[k - 1]
            n += k
            if k < m:
                first = (s_end[k], float(cost[k]), samples[k].T)
                s = self._interval(n, s, first)
                n += 1
        terminal = float(self.num.phi_grad(s)[0][0])
        t_arr, s_arr = _dedupe(np.concatenate(self.times), np.concatenate(self.states))
        ev = Evaluation(
            cost=terminal + self.running,
            terminal_cost=terminal,
            running_cost=self.running,
            times=t_arr,
            states=s_arr,
            events=self.events,
            controls=self.u_all,
            final_state=s.copy(),
            ocp=ocp,
            segments=self.segments,
        )
        if not np.isfinite(ev.cost):
            raise EvaluationError(
                "the cost is not finite: the controls drive the state to overflow"
            )
        return ev

    def _interval(
        self, n: int, s: np.ndarray, first: tuple[np.ndarray, float, np.ndarray]
    ) -> np.ndarray:
        """Grid interval ``n`` from state ``s``, event by event; returns the end state."""
        ocp, num = self.ocp, self.num
        G, D = self.c.G, self.c.D
        u = self.u_all[n]
        t = self.grid[n]
        t_end = self.grid[n + 1]
        n_events = 0
        pre: tuple[np.ndarray, float, np.ndarray] | None = first
        while True:
            h = t_end - t
            if pre is not None:
                s_end, cost, samples = pre
                pre = None
            else:
                s_end, cost_a, samples, _ = num.interval(s, u, h)
                cost = float(cost_a[0])
                samples = samples.reshape(D + 1, G).T
            hit = self._first_crossing(s, u, h, samples)
            if hit is None:
                self.segments.append(_Segment(t, s, n, h, None))
                self.running += cost
                s = s_end
                break
            tau, first_j, simultaneous = hit
            s_ev, cost_ev, _, _ = num.interval(s, u, tau)
            self.segments.append(_Segment(t, s, n, tau, None))  # event index set below
            self.running += float(cost_ev[0])
            s = s_ev
            t = t + tau
            self._record(t, s)
            pending = set(simultaneous) | {first_j}
            fired_any = False
            while True:
                psi, rate, accel = num.contact(s, u)
                appr = _approaching(rate, accel, s, self.graze_tol)
                cand = [j for j in range(G) if appr[j] and (j in pending or abs(psi[j]) <= 1e-12)]
                if not cand:
                    break
                j = min(cand)
                pending.discard(j)
                s_new = num.reset(j)(s)[0]
                g = ocp.guards[j]
                self.events.append(Event(t, g.kind, g.bodies, j, float(rate[j]), s, s_new))
                if fired_any:
                    self.segments.append(_Segment(t, s, n, 0.0, j))
                else:
                    last = self.segments[-1]
                    self.segments[-1] = _Segment(last.t0, last.s0, last.interval, last.h, j)
                fired_any = True
                s = s_new
                n_events += 1
                if n_events > _MAX_EVENTS_PER_INTERVAL:
                    raise EvaluationError(
                        f"more than {_MAX_EVENTS_PER_INTERVAL} events in grid interval {n} "
                        f"near t = {t:.6g}: an accumulation of impacts (Zeno behaviour) that "
                        "the impulsive model does not resolve"
                    )
            if not fired_any:
                # _first_crossing applied the same test at the same point up to rounding of
                # the flow: a borderline graze; go on without a jump
                n_events += 1
                continue
            self._record(t, s)
        if G:
            psi = num.contact(s, u)[0]
            worst = int(np.argmin(psi))
            if psi[worst] < -self.penetration_tol:
                g = ocp.guards[worst]
                raise EvaluationError(
                    f"guard {g.name!r} is violated by {-psi[worst]:.3g} at t = {t_end:.6g}: "
                    "the bodies stay in contact (e.g. restitution 0 with a force pushing into "
                    "the contact), which the impulsive model does not represent"
                )
        self._record(t_end, s)
        return s

    def _record(self, t: float, s: np.ndarray) -> None:
        self.times.append(np.array([t]))
        self.states.append(s[None, :])

    def _first_crossing(
        self, s: np.ndarray, u: np.ndarray, h: float, samples: np.ndarray
    ) -> tuple[float, int, list[int]] | None:
        """Earliest downward crossing in [0, h]: (tau, guard, guards crossing within tol)."""
        if h <= 0:
            return None
        c, num = self.c, self.num
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
                tau = self._polish(s, u, h, int(j), tau0)
                if tau is None:
                    continue
                s_tau = num.point(s, u, tau)[0]
                _, rate, accel = num.contact(s_tau, u)
                # the same test the event loop applies
                if _approaching(rate[j : j + 1], accel[j : j + 1], s_tau, self.graze_tol)[0]:
                    found.append((tau, int(j)))
                    break
        if not found:
            return None
        found.sort()
        tau, first = found[0]
        simultaneous = [j for (tj, j) in found if tj <= tau + self.tol_time]
        return tau, first, simultaneous

    def _polish(self, s: np.ndarray, u: np.ndarray, h: float, j: int, tau: float) -> float | None:
        """Newton on the detector from an interpolated root, kept inside [0, h]."""
        point = self.num.point
        for _ in range(30):
            _, det, rate = point(s, u, tau)
            d, r = float(det[j]), float(rate[j])
            if d == 0.0:
                return tau
            if r == 0.0:
                break
            new = min(max(tau - d / r, 0.0), h)
            if abs(new - tau) <= 4e-16 * max(h, 1.0):
                return new
            tau = new
        d = float(point(s, u, tau)[1][j])
        return tau if abs(d) < 1e-10 else None


def _dedupe(times: np.ndarray, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop exact repeats (same time and same state) that the loop records."""
    same = (times[1:] == times[:-1]) & np.all(states[1:] == states[:-1], axis=1)
    keep = np.concatenate([[True], ~same])
    return times[keep], states[keep]


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
    num = c.numeric()
    nx, nu = c.nx, c.nu
    u_all = ev.controls
    segs = ev.segments
    M = len(segs)
    idx = np.array([seg.interval for seg in segs], dtype=int)
    # all segment Jacobians, chunk by chunk (padding with h = 0)
    L = c.chunk
    n_chunks = -(-M // L)
    S0 = np.zeros((n_chunks * L, nx))
    S0[:M] = np.array([seg.s0 for seg in segs])
    U = np.zeros((n_chunks * L, nu))
    U[:M] = u_all[idx]
    H = np.zeros(n_chunks * L)
    H[:M] = [seg.h for seg in segs]
    FsT, FuT, Cs, Cu = [], [], [], []
    for k in range(n_chunks):
        sl = slice(k * L, (k + 1) * L)
        a, b, cs, cu = num.seg_jac(S0[sl].ravel(), U[sl].ravel(), H[sl])
        # column-major blocks: row k of the reshape is the transposed Jacobian of segment k
        FsT.append(a.reshape(L, nx, nx))
        FuT.append(b.reshape(L, nu, nx))
        Cs.append(cs.reshape(L, nx))
        Cu.append(cu.reshape(L, nu))
    FsT_a, FuT_a = np.concatenate(FsT)[:M], np.concatenate(FuT)[:M]
    Cs_a, Cu_a = np.concatenate(Cs)[:M], np.concatenate(Cu)[:M]
    lam = num.phi_grad(ev.final_state)[1]
    lam_end = np.empty((M, nx))  # lambda at each segment's end, after any jump there
    lam_start = np.empty((M, nx))
    lam_jump: dict[int, np.ndarray] = {}  # lambda(gamma-) at the event ending segment i
    for i in range(M - 1, -1, -1):
        seg = segs[i]
        if seg.event is not None:
            lam = _costate_jump(num, seg, u_all[seg.interval], lam)
            lam_jump[i] = lam
        lam_end[i] = lam
        lam = Cs_a[i] + FsT_a[i] @ lam
        lam_start[i] = lam
    # in time order: each segment's start, lambda(gamma-) after a segment ending in an
    # event (lambda(gamma+) is the next segment's start), and lambda(T)
    has_jump = np.array([seg.event is not None for seg in segs], dtype=bool)
    pos = np.arange(M) + np.concatenate([[0], np.cumsum(has_jump)[:-1]])
    n_rec = M + int(has_jump.sum()) + 1
    lam_rec = np.empty((n_rec, nx))
    t_rec = np.empty(n_rec)
    lam_rec[pos] = lam_start
    t_rec[pos] = [seg.t0 for seg in segs]
    for i, lj in lam_jump.items():
        lam_rec[pos[i] + 1] = lj
        t_rec[pos[i] + 1] = segs[i].t0 + segs[i].h
    lam_rec[-1] = num.phi_grad(ev.final_state)[1]
    t_rec[-1] = ocp.horizon
    contrib = Cu_a + np.einsum("kij,kj->ki", FuT_a, lam_end)
    d_u = np.zeros_like(u_all)
    # later segments first, as the recursion visits them
    np.add.at(d_u, idx[::-1], contrib[::-1])
    return Gradient(
        cost=ev.cost,
        d_initial_state=lam,
        d_controls=d_u,
        costate_times=t_rec,
        costates=lam_rec,
        evaluation=ev,
    )


def _costate_jump(num: _Numeric, seg: _Segment, u: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """``lambda(gamma-)`` from ``lambda(gamma+)`` at the event ending ``seg``."""
    assert seg.event is not None
    nx = lam.size
    b = num.interval(seg.s0, u, seg.h)[0]  # s(gamma-)
    grad_psi, Dg, gb = num.event_jac(seg.event)(b, u)
    Dg = Dg.reshape(nx, nx).T  # column-major
    f_minus, L_minus = num.fL(b, u)
    f_plus, L_plus = num.fL(gb, u)
    H_plus = float(L_plus[0]) + lam @ f_plus
    # Hamiltonian continuity fixes the multiplier pi of grad psi
    pi = (H_plus - float(L_minus[0]) - lam @ (Dg @ f_minus)) / (grad_psi @ f_minus)
    return Dg.T @ lam + pi * grad_psi
