"""The event-exact evaluator: the judge of any control.

:func:`evaluate` simulates the continuous hybrid system of a problem under a control that is
piecewise constant on the N-grid (or a feedback policy sampled at the grid times, or a
continuous-time control) and returns the trajectory, every event and the cost.
:func:`gradient` returns the exact gradient of that continuous cost with respect to the
initial state and to every control value, by the adjoint with the hybrid minimum
principle's jump relation (the saltation-matrix adjoint).

How events are located
    See :mod:`hybridoc.rootfind`: on each grid interval (the control is constant there) each
    guard's detector is sampled along the exact flow at Chebyshev-Lobatto nodes; a bound on
    the interpolant proves most intervals free of events, intervals where the bound is not
    conclusive are halved until the interpolant is resolved to the rounding level of the
    samples, and a crossing is bracketed and located on the true detector. For the
    polynomial flows and guards of disc scenes (degree 4 for disc-disc, 2 for disc-wall) the
    interpolant *is* the detector; other guards use degree 16 with an error estimate.

What jumps, and simultaneous events
    See :mod:`hybridoc.events`: the grazing rule, and the rule for several guards at one
    instant (commuting jumps in guard order, non-commuting ones an error).

Speed
    All numerical work goes through CasADi's buffer API. For SX problems (disc scenes) the
    flow, its cost and the detector samples of 64 grid intervals come from one ``mapaccum``
    call; only intervals that may hold an event are handled one by one.

Many bodies: the broad phase
    A scene of more than :data:`hybridoc.broadphase.THRESHOLD` guards whose guards are the
    contacts of its :attr:`~hybridoc.capabilities.Capabilities.geometry` (round bodies and
    walls, under a closed-form flow) is judged through :mod:`hybridoc.broadphase`: the flow
    of 64 grid intervals in one call, then on each interval only the guards whose bodies'
    swept boxes meet are sampled, located and resolved, through per-guard kernels whose
    values are the all-pairs kernels' rows bit for bit. The other guards stay apart by
    more than the broad phase's margin and cannot fire. The crossing search examines
    fewer guards (it halves a window for all of them when one needs it), so an event time
    can be polished from another bracket: the same events as the all-pairs judge, times
    and costs bit for bit or apart by an ulp that later collisions amplify (within 5e-14
    relative on random crowded scenes; ``docs/trust.rst``, "Resources").

Not modelled
    Sustained contact (e.g. restitution 0 with a force pushing into the contact) and Zeno
    accumulations of events raise :class:`~hybridoc.errors.EvaluationError` instead of
    returning a wrong number.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import numpy as np

from hybridoc import tolerances
from hybridoc.callable_eval import evaluate_callable
from hybridoc.errors import ControlsError, EvaluationError
from hybridoc.evaluation import Evaluation, Gradient, Segment
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
from hybridoc.kernels import Kernels, Numeric, kernels
from hybridoc.ocp import HybridOCP, as_float_array
from hybridoc.problem import ControlsLike, ProblemLike, as_ocp
from hybridoc.rootfind import CrossingSearch

__all__ = ["evaluate", "gradient", "at_horizon", "Policy"]

Policy = Callable[[float, np.ndarray], Any]
"""A feedback policy ``u = pi(t, s)``: any callable, e.g. a ``torch.nn.Module``."""

ZENO_WINDOW = 100
"""Events that, packed into less than ``1e-9 T``, mean an accumulation (Zeno behaviour)."""
MAX_EVENTS = 10**6
"""Default cap on the number of events of one evaluation."""


def evaluate(
    problem: ProblemLike,
    controls: ControlsLike | None = None,
    *,
    policy: Policy | None = None,
    hold: str = "zoh",
    graze_tol: float = 1e-10,
    penetration_tol: float = tolerances.value("penetration"),
    max_events: int = MAX_EVENTS,
) -> Evaluation:
    """Simulate the continuous hybrid system and return its cost and events.

    Parameters
    ----------
    problem
        A :class:`~hybridoc.HybridOCP`, a :class:`~hybridoc.problems.Scene`, a built-in name,
        a ``.toml`` path or ``file.py:function`` (see :func:`hybridoc.problem.as_ocp`).
    controls
        ``(N, nu)`` values, constant on each grid interval; default: the problem's initial
        guess. A :class:`~hybridoc.Solution` is judged by its own control
        (:meth:`~hybridoc.Solution.control_function`: its ``controls`` when piecewise
        constant, else its continuous ``u(t)`` through :func:`hybridoc.evaluate_callable`
        with its breakpoints), so its ``cost`` comes back bit for bit; for a problem with a
        free final time, at the final time it found, ``info["horizon"]`` (see
        :func:`at_horizon`). A path to a saved Solution (``.npz`` or ``.json``) is loaded
        and judged so; a ``.npy`` or ``.csv`` path is read as controls
        (:func:`hybridoc.io.read_controls`). A callable ``u(t)`` goes to
        :func:`hybridoc.evaluate_callable` with the grid times as breakpoints (``u`` may
        jump there).
    policy
        A feedback policy ``u = pi(t, s)`` instead of ``controls``. With ``hold="zoh"`` it is
        sampled at the grid times from the exact state and held over the interval, as a
        digital controller runs; with ``hold="continuous"`` it is evaluated continuously
        (through :func:`hybridoc.evaluate_callable`). Torch modules are called with float64
        tensors and without gradient tracking.
    hold
        ``"zoh"`` (default) or ``"continuous"``; only with ``policy``.
    graze_tol
        Approach speeds ``|d psi/dt|`` below this (or below the rounding floor described in
        :mod:`hybridoc.events`) are grazing: no jump. In the problem's units
        (:attr:`HybridOCP.scales <hybridoc.ocp.HybridOCP.scales>`): guard units
        (``scales.length``, a disc scene's length unit) per unit time (``scales.time``), so
        that the same scene in other units grazes alike (:func:`hybridoc.events.graze_threshold`).
    penetration_tol
        A guard more negative than this (or than its rounding level) at the end of a grid
        interval means the impulsive model cannot represent the motion (sustained contact):
        an error, not a number. In guard units (``scales.length``).
    max_events
        More events than this raise :class:`~hybridoc.errors.EvaluationError`.

    Returns
    -------
    Evaluation
    """
    if isinstance(controls, str | os.PathLike):
        from hybridoc.io import read_controls

        controls = read_controls(controls, problem)
    ocp = at_horizon(as_ocp(problem), controls)
    if policy is not None:
        if controls is not None:
            raise ControlsError("give either controls or a policy, not both")
        if hold not in ("zoh", "continuous"):
            raise ControlsError(f"hold must be 'zoh' or 'continuous', got {hold!r}")
        pol = PolicyCaller(policy, ocp)
        if hold == "continuous":
            return evaluate_callable(
                ocp, state_feedback=pol, graze_tol=graze_tol, penetration_tol=penetration_tol
            )
        return Forward(ocp, None, pol, graze_tol, penetration_tol, max_events).run()
    control_function = getattr(controls, "control_function", None)
    if control_function is not None and controls.control_kind != "piecewise-constant":
        # a Solution whose control is continuous: judged as it is, with its breakpoints
        u = control_function(ocp)
        return evaluate_callable(
            ocp,
            u,
            breakpoints=u.breakpoints,
            graze_tol=graze_tol,
            penetration_tol=penetration_tol,
            event_controls=getattr(u, "event_controls", None),
        )
    controls = getattr(controls, "controls", controls)  # a Solution
    if callable(controls):
        return evaluate_callable(
            ocp,
            controls,
            breakpoints=ocp.time_grid(),
            graze_tol=graze_tol,
            penetration_tol=penetration_tol,
        )
    u_all = ocp.check_controls(ocp.u_guess if controls is None else controls)
    return Forward(ocp, u_all, None, graze_tol, penetration_tol, max_events).run()


def at_horizon(ocp: HybridOCP, controls: Any) -> HybridOCP:
    """The problem at the final time a solution found, for a free final time.

    For a problem with :attr:`~hybridoc.HybridOCP.horizon_bounds` and ``controls`` a
    :class:`~hybridoc.Solution` whose ``info`` holds ``"horizon"``, the problem with that
    ``T`` (its grid stretched to ``T / N`` cells; the compiled functions are reused);
    otherwise ``ocp`` itself: given controls alone are judged at ``ocp.horizon``, and a
    fixed final time is never changed.

    Raises
    ------
    hybridoc.errors.ControlsError
        If the solution's ``horizon`` is not a number within the problem's bounds.
    """
    info = getattr(controls, "info", None)
    if not ocp.free_horizon or not isinstance(info, dict) or info.get("horizon") is None:
        return ocp
    assert ocp.horizon_bounds is not None
    lo, hi = ocp.horizon_bounds
    try:
        T = float(info["horizon"])
    except (TypeError, ValueError):
        raise ControlsError(
            f"the solution's final time info['horizon'] is not a number: {info['horizon']!r}"
        ) from None
    if not lo <= T <= hi:
        raise ControlsError(
            f"the solution's final time {T!r} lies outside the problem's horizon_bounds "
            f"({lo}, {hi})"
        )
    return ocp if T == ocp.horizon else ocp.replace(horizon=T)


class PolicyCaller:
    """Calls a user policy and checks what it returns (one clear error per failure)."""

    def __init__(self, policy: Policy, ocp: HybridOCP) -> None:
        if not callable(policy):
            raise ControlsError(f"policy must be callable (t, state) -> u, got {policy!r}")
        self.policy = policy
        self.ocp = ocp
        self.torch = _is_torch_module(policy)

    def __call__(self, t: float, s: np.ndarray) -> np.ndarray:
        try:
            if self.torch:
                import torch

                with torch.no_grad():
                    out = self.policy(
                        torch.tensor(float(t), dtype=torch.float64),
                        torch.as_tensor(np.array(s, dtype=float), dtype=torch.float64),
                    )
            else:
                out = self.policy(float(t), np.array(s, dtype=float))
        except Exception as exc:  # the user's code: report it as a user error
            raise ControlsError(
                f"the policy raised {type(exc).__name__} at t = {t:.6g}: {exc}"
            ) from exc
        u = as_float_array(out, f"policy output at t = {t:.6g}", error=ControlsError).ravel()
        if u.shape != (self.ocp.nu,):
            raise ControlsError(
                f"the policy returned {u.size} value(s) at t = {t:.6g}; expected {self.ocp.nu} "
                f"(one per control: {', '.join(self.ocp.control_labels or [])})"
            )
        if not np.all(np.isfinite(u)):
            raise ControlsError(f"the policy returned a non-finite control {u} at t = {t:.6g}")
        return u


def _is_torch_module(obj: Any) -> bool:
    mod = type(obj).__module__
    if not (mod.startswith("torch") or hasattr(obj, "parameters")):
        return False
    try:
        import torch
    except ImportError:  # pragma: no cover
        return False
    return isinstance(obj, torch.nn.Module | torch.jit.ScriptModule | torch.jit.ScriptFunction)


class Forward:
    """One forward simulation (the state of :func:`evaluate`)."""

    def __init__(
        self,
        ocp: HybridOCP,
        u_all: np.ndarray | None,
        policy: PolicyCaller | None,
        graze_tol: float,
        penetration_tol: float,
        max_events: int,
    ) -> None:
        # a scene far from the origin is simulated in its local frame (positions less the
        # scales' offset, exact to take off): its numbers then round at its own length scale
        # instead of at the rounding of its coordinates; the results are moved back
        self.outer = ocp
        ocp, self.offset = in_local_frame(ocp)
        self.ocp = ocp
        self.k: Kernels = kernels(ocp)
        self.num: Numeric = self.k.numeric()
        self.policy = policy
        self.u_all = np.zeros((ocp.steps, ocp.nu)) if u_all is None else u_all
        # the tolerances are in the problem's units (module notes of hybridoc.scales)
        self.graze_tol = graze_threshold(ocp, graze_tol)
        self.penetration_tol = penetration_threshold(ocp, penetration_tol)
        self.max_events = int(max_events)
        # many guards of round bodies: the broad phase picks the guards to sample
        self.table = self.k.broad
        contacts = None if self.table is None else self._contacts
        self.resolver = EventResolver(ocp, self.num, self.graze_tol, contacts=contacts)
        self.grid = ocp.time_grid()
        self.hs = np.diff(self.grid)
        # blocks of recorded times (1-D) and states (2-D), concatenated at the end
        self.times: list[np.ndarray] = [np.zeros(1)]
        self.states: list[np.ndarray] = [ocp.x0[None, :].copy()]
        self.events: list[Event] = []
        self.segments: list[Segment] = []
        self.running = 0.0
        self.zeno_T = 1e-9 * max(ocp.horizon, 1e-300)
        self._t_origin = 0.0

    def run(self) -> Evaluation:
        ocp, k = self.ocp, self.k
        nx, nu, G, D, L = k.nx, k.nu, k.G, k.D, k.chunk
        N = ocp.steps
        grid, hs = self.grid, self.hs
        s = ocp.x0.copy()
        n = 0
        batched = self.policy is None and L > 1
        while n < N:
            if not batched:
                if self.policy is not None:
                    s_out = s if self.offset is None else s + self.offset
                    self.u_all[n] = self.policy(grid[n], s_out)
                s = self._interval(n, s, None)
                n += 1
                continue
            m = min(L, N - n)
            uu = np.zeros((L, nu))
            uu[:m] = self.u_all[n : n + m]
            hh = np.zeros(L)
            hh[:m] = hs[n : n + m]
            if self.table is not None:
                s, n = self._broad_batch(n, s, m, uu, hh)
                continue
            s_end, cost, samples, noise, psi_end = self.num.batch(s, uu.ravel(), hh)
            s_end = s_end.reshape(L, nx)
            samples = samples.reshape(L, D + 1, G).transpose(0, 2, 1)
            noise = noise.reshape(L, D + 1, G).transpose(0, 2, 1)
            kk = m  # intervals n .. n+kk-1 are free of events
            if G:
                free = self._free(samples[:m], noise[:m], psi_end.reshape(L, G)[:m], k.exact)
                hits = np.flatnonzero(~free)
                if hits.size:
                    kk = int(hits[0])
            s = self._accept(n, kk, s, s_end, cost)
            n += kk
            if kk < m:
                first = (s_end[kk], float(cost[kk]), samples[kk], noise[kk], None)
                s = self._interval(n, s, first)
                n += 1
        return self._finish(s)

    def _accept(
        self, n: int, kk: int, s: np.ndarray, s_end: np.ndarray, cost: np.ndarray
    ) -> np.ndarray:
        """Records grid intervals ``n .. n + kk - 1``, free of events, from ``s`` (their end
        states ``s_end`` and costs ``cost``); returns the state at their end."""
        if kk <= 0:
            return s
        grid, hs = self.grid, self.hs
        starts = [s, *s_end[: kk - 1]]
        self.segments.extend(
            map(
                Segment,
                grid[n : n + kk].tolist(),
                starts,
                range(n, n + kk),
                hs[n : n + kk].tolist(),
                [None] * kk,
            )
        )
        # cumsum adds left to right: the same rounding as adding one by one
        self.running = float(np.cumsum(np.r_[self.running, cost[:kk]])[-1])
        self.times.append(grid[n + 1 : n + kk + 1])
        self.states.append(s_end[:kk])
        return s_end[kk - 1]

    def _broad_batch(
        self, n: int, s: np.ndarray, m: int, uu: np.ndarray, hh: np.ndarray
    ) -> tuple[np.ndarray, int]:
        """:meth:`run`'s batch of ``m`` grid intervals from ``n`` with the broad phase: the
        flow of the batch in one call, then per interval the detectors of its candidate
        guards only, up to the first interval that may hold an event (then handled by
        :meth:`_interval`). Returns the state and the next interval."""
        k = self.k
        s_end, cost = self.num.flow_batch(s, uu.ravel(), hh)
        s_end = s_end.reshape(k.chunk, k.nx)
        kk, first = m, None
        start = s
        for i in range(m):
            S, Nz, psi_end, cand = self._broad_samples(start, uu[i], float(hh[i]))
            if cand.size:
                if not self._free(S, Nz, psi_end, k.exact[cand]):
                    kk, first = i, (s_end[i], float(cost[i]), S, Nz, cand)
                    break
            start = s_end[i]
        s = self._accept(n, kk, s, s_end, cost)
        n += kk
        if first is not None:
            s = self._interval(n, s, first)
            n += 1
        return s, n

    def _broad_samples(
        self, s: np.ndarray, u: np.ndarray, h: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The broad phase's candidates over ``[0, h]`` from ``s`` and their detector
        samples, rounding levels (``(c, D + 1)`` each) and values at the end ``(c,)``."""
        assert self.table is not None
        cand = self.table.candidates(s, u, h)
        D = self.k.D
        S, Nz, psi_end = (
            np.empty((cand.size, D + 1)),
            np.empty((cand.size, D + 1)),
            np.empty(cand.size),
        )
        for r, j in enumerate(cand):
            S[r], Nz[r], psi = self.num.guard(int(j)).interval(s, u, h)
            psi_end[r] = psi[0]
        return S, Nz, psi_end, cand

    def _free(self, S: np.ndarray, Nz: np.ndarray, psi_end: np.ndarray, exact: np.ndarray) -> Any:
        """Whether no guard (the last axis) crosses over an interval: the Chebyshev test on
        its samples ``S`` (rounding levels ``Nz``), and no value at the end below the
        penetration tolerance (or four rounding levels)."""
        tol = np.maximum(self.penetration_tol, 4 * Nz[..., -1])
        return (self.k.cheb.free(S, Nz, exact) & (psi_end >= -tol)).all(axis=-1)

    def _contacts(
        self, s: np.ndarray, u: np.ndarray, extra: Any = ()
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every guard's ``(psi, rate, accel, rounding level)`` at ``s`` as the ``contact``
        kernel gives them; with the broad phase, those of the candidates at ``s`` and of
        ``extra``, and for the others (apart by more than the broad phase's margin) ``psi =
        inf``, the rest 0 (not due, not penetrated)."""
        if self.table is None:
            return self.num.contact(s, u)
        G = self.k.G
        psi, rate, accel, noise = np.full(G, np.inf), np.zeros(G), np.zeros(G), np.zeros(G)
        cand = np.union1d(self.table.candidates(s, u, 0.0), np.asarray(list(extra), dtype=int))
        for j in cand:
            out = self.num.guard(int(j)).contact(s, u)
            psi[j], rate[j], accel[j], noise[j] = (float(o[0]) for o in out)
        return psi, rate, accel, noise

    def _finish(self, s: np.ndarray) -> Evaluation:
        terminal = float(self.num.phi_grad(s)[0][0])
        t_arr, s_arr = _dedupe(np.concatenate(self.times), np.concatenate(self.states))
        cost = terminal + self.running
        if not np.isfinite(cost):
            raise EvaluationError(
                "the cost is not finite: the controls drive the state to overflow"
            )
        path_violation = _path_violation(
            self.num, self.ocp, self.segments, self.u_all, t_arr, s_arr
        )
        ocp = self.outer
        off = self.offset
        if off is not None:  # back from the local frame
            s = s + off
            s_arr = s_arr + off
            self.segments = [seg._replace(s0=seg.s0 + off) for seg in self.segments]
            self.events = moved_events(self.events, off)
        return Evaluation(
            cost=cost,
            terminal_cost=terminal,
            running_cost=self.running,
            times=t_arr,
            states=s_arr,
            events=self.events,
            controls=self.u_all,
            final_state=s.copy(),
            ocp=ocp,
            segments=self.segments,
            bound_violation=ocp.bound_violation(self.u_all),
            path_violation=path_violation,
        )

    def _search(self, s: np.ndarray, u: np.ndarray) -> CrossingSearch:
        num, k = self.num, self.k
        G, D = k.G, k.D

        def window(a: float, b: float) -> tuple[np.ndarray, np.ndarray]:
            S, Nz = num.window(s, u, a, b)
            return S.reshape(D + 1, G).T, Nz.reshape(D + 1, G).T

        def value(j: int, tau: float) -> tuple[float, float, float]:
            _, det, rate, nz = num.point(s, u, tau)
            return float(det[j]), float(rate[j]), float(nz[j])

        def appr(j: int, tau: float) -> bool:
            s_tau = num.point(s, u, tau)[0]
            _, rate, accel, nz = num.contact(s_tau, u)
            return bool(
                approaching(rate[j : j + 1], accel[j : j + 1], nz[j : j + 1], self.graze_tol)[0]
            )

        def penetrated(j: int, tau: float) -> None:
            s_tau = num.point(s, u, tau)[0]
            self._check_penetration(s_tau, u, float(self._t_origin + tau))

        return CrossingSearch(
            k.cheb, k.exact, window, value, appr, penetrated, time_scale=self.ocp.scales.time
        )

    def _broad_search(self, s: np.ndarray, u: np.ndarray, cand: np.ndarray) -> CrossingSearch:
        """:meth:`_search` over the broad phase's candidates ``cand`` only (its guard ``r``
        is ``cand[r]``), through their own kernels."""
        num = self.num
        guards = [num.guard(int(j)) for j in cand]
        D = self.k.D

        def window(a: float, b: float) -> tuple[np.ndarray, np.ndarray]:
            S, Nz = np.empty((len(guards), D + 1)), np.empty((len(guards), D + 1))
            for r, g in enumerate(guards):
                S[r], Nz[r] = g.window(s, u, a, b)
            return S, Nz

        def value(r: int, tau: float) -> tuple[float, float, float]:
            det, rate, nz = guards[r].point(s, u, tau)
            return float(det[0]), float(rate[0]), float(nz[0])

        def appr(r: int, tau: float) -> bool:
            s_tau = num.flow(s, u, tau)[0]
            _, rate, accel, nz = guards[r].contact(s_tau, u)
            return bool(approaching(rate, accel, nz, self.graze_tol)[0])

        def penetrated(r: int, tau: float) -> None:
            s_tau = num.flow(s, u, tau)[0]
            self._check_penetration(s_tau, u, float(self._t_origin + tau))

        return CrossingSearch(
            self.k.cheb,
            self.k.exact[cand],
            window,
            value,
            appr,
            penetrated,
            time_scale=self.ocp.scales.time,
        )

    def _check_penetration(self, s: np.ndarray, u: np.ndarray, t: float) -> None:
        """Sustained contact: a guard violated beyond tolerance without an impact."""
        psi, _, _, noise_psi = self._contacts(s, u)
        tol = np.maximum(self.penetration_tol, 4 * noise_psi)
        bad = np.flatnonzero(psi < -tol)
        if bad.size:
            worst = int(bad[np.argmin(psi[bad])])
            g = self.ocp.guards[worst]
            raise EvaluationError(
                f"guard {g.name!r} is violated by {-psi[worst]:.3g} at t = {t:.6g} without an "
                "impact: the bodies stay in contact (e.g. restitution 0 with a force pushing "
                "into the contact), which the impulsive model does not represent"
            )

    def _interval(
        self,
        n: int,
        s: np.ndarray,
        first: tuple[np.ndarray, float, np.ndarray, np.ndarray] | None,
    ) -> np.ndarray:
        """Grid interval ``n`` from state ``s``, event by event; returns the end state."""
        num, k = self.num, self.k
        G, D = k.G, k.D
        u = self.u_all[n]
        t = self.grid[n]
        t_end = self.grid[n + 1]
        pre = first
        while True:
            h = t_end - t
            cand: np.ndarray | None
            if pre is not None:
                s_end, cost, samples, noise, cand = pre
                pre = None
            elif self.table is not None:
                s_end, cost_a = num.flow(s, u, h)
                cost = float(cost_a[0])
                samples, noise, _, cand = self._broad_samples(s, u, h)
            else:
                s_end, cost_a, samples, noise, _ = num.interval(s, u, h)
                cost = float(cost_a[0])
                samples = samples.reshape(D + 1, G).T
                noise = noise.reshape(D + 1, G).T
                cand = None
            self._t_origin = t
            if cand is not None:
                hit = self._broad_search(s, u, cand).run(h, (samples, noise)) if cand.size else None
                if hit is not None:
                    hit = (hit[0], int(cand[hit[1]]))
            else:
                hit = self._search(s, u).run(h, (samples, noise)) if G else None
            if hit is None:
                self.segments.append(Segment(t, s, n, h, None))
                self.running += cost
                s = s_end
                break
            tau, j = hit
            s_ev, cost_ev = num.flow(s, u, tau)
            self.segments.append(Segment(t, s, n, tau, None))  # event index set below
            self.running += float(cost_ev[0])
            t = t + tau
            self._record(t, s_ev)
            s_new, evs = self.resolver.resolve(t, s_ev, u, {j})
            if not evs:
                # the search and the jump rule disagree only for a borderline graze: no jump
                s = s_ev
                if tau == 0.0:
                    raise EvaluationError(
                        f"guard {self.ocp.guards[j].name!r} stalls at t = {t:.9g}: a borderline "
                        "graze the jump rule cannot decide"
                    )
                continue
            last = self.segments[-1]
            self.segments[-1] = Segment(last.t0, last.s0, last.interval, last.h, evs[0].guard)
            for ev in evs[1:]:
                self.segments.append(Segment(t, ev.state_before, n, 0.0, ev.guard))
            self.events.extend(evs)
            self._check_count(t)
            s = s_new
            self._record(t, s)
        if G:
            self._check_penetration(s, u, t_end)
        self._record(t_end, s)
        return s

    def _check_count(self, t: float) -> None:
        n = len(self.events)
        if n > self.max_events:
            raise EvaluationError(
                f"more than {self.max_events} events by t = {t:.6g}; raise max_events to "
                "simulate longer collision series"
            )
        limit = accumulating([e.time for e in self.events[-(ZENO_RUN + 2) :]], self.ocp.horizon)
        if limit is not None:
            raise EvaluationError(
                f"the events accumulate near t = {limit:.9g} (their gaps shrink "
                f"geometrically over the last {ZENO_RUN}): Zeno behaviour, e.g. a body "
                "coming to rest on a contact through infinitely many impacts, which the "
                "impulsive model does not resolve"
            )
        if n >= ZENO_WINDOW:
            span = t - self.events[n - ZENO_WINDOW].time
            if span < self.zeno_T:
                raise EvaluationError(
                    f"{ZENO_WINDOW} events within {span:.3g} s near t = {t:.9g}: an "
                    "accumulation of impacts (Zeno behaviour) that the impulsive model does "
                    "not resolve"
                )

    def _record(self, t: float, s: np.ndarray) -> None:
        self.times.append(np.array([t]))
        self.states.append(s[None, :])


def _path_violation(
    num: Numeric,
    ocp: HybridOCP,
    segments: list[Segment],
    u_all: np.ndarray,
    times: np.ndarray,
    states: np.ndarray,
) -> float:
    """Largest violation of the path constraints at the recorded states (grid and events)."""
    if num.path is None or not len(times):
        return 0.0
    idx = np.clip(np.searchsorted(ocp.time_grid(), times, side="right") - 1, 0, ocp.steps - 1)
    worst = 0.0
    for s, i in zip(states, idx, strict=True):
        c = num.path(s, u_all[i])[0]
        worst = max(worst, float(np.max(-c, initial=0.0)))
    return worst


def _dedupe(times: np.ndarray, states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop exact repeats (same time and same state) that the loop records."""
    same = (times[1:] == times[:-1]) & np.all(states[1:] == states[:-1], axis=1)
    keep = np.concatenate([[True], ~same])
    return times[keep], states[keep]


def gradient(
    problem: ProblemLike, controls: ControlsLike | None = None, **kwargs: float | int | str
) -> Gradient:
    """Exact gradient of the continuous cost (adjoint with the HMP jump relation).

    Between events the costate follows ``d lambda/dt = -dH/ds`` (done exactly by the
    transposed Jacobians of the flow map); at an event
    ``lambda(gamma-) = Dg^T lambda(gamma+) + pi grad psi`` with ``pi`` chosen so that the
    Hamiltonian ``H = L + lambda^T f`` is continuous. Then ``dJ/ds(0) = lambda(0)`` and
    ``dJ/du_n`` is the integral of ``dH/du`` over grid interval ``n``.

    The final time: with ``t = T sigma`` the problem is autonomous in ``sigma`` with the
    parameter ``T`` (``ds/dsigma = T f``, cost rate ``T L``), so ``dJ/dT`` is the integral
    over ``sigma`` of ``H``; under a constant control ``H`` is constant along the flow and,
    by the choice of ``pi``, across events, hence ``dJ/dT = (1/N) sum_n H_n``, ``H_n`` the
    Hamiltonian of cell ``n`` (:attr:`Gradient.d_horizon`). The terminal constraints'
    gradients come from the same recursion started at ``grad h_i(s(T))`` without running
    cost (:attr:`Gradient.terminal_d_controls`).

    Parameters
    ----------
    problem
        Anything :func:`hybridoc.evaluate` accepts.
    controls
        ``(N, nu)`` piecewise-constant values (or a Solution); default: the initial guess.
    **kwargs
        Passed to :func:`evaluate`.
    """
    ocp = at_horizon(as_ocp(problem), controls)
    controls = getattr(controls, "controls", controls)
    if callable(controls) or "policy" in kwargs:
        raise ControlsError("gradient needs piecewise-constant controls on the N-grid")
    ev = evaluate(ocp, controls, **kwargs)
    return adjoint(ev)


def adjoint(ev: Evaluation, feedback: np.ndarray | None = None) -> Gradient:
    """The adjoint pass of :func:`gradient` on an existing evaluation.

    Parameters
    ----------
    ev
        An evaluation of piecewise-constant controls, or of a feedback policy with
        zero-order hold (``evaluate(problem, policy=pi, hold="zoh")``).
    feedback
        ``None`` (default): the open-loop gradient, the controls held fixed. An
        ``(N, nu, nx)`` array: the Jacobians ``d pi / d s`` of a zero-order-hold feedback
        ``u_n = pi(t_n, s(t_n))`` at the evaluated grid states, for the *closed-loop*
        gradient by the discrete adjoint of ``s_{n+1} = F_n(s_n, u_n)``: at each grid time
        the costate gains ``(d pi / d s)^T dJ/du_n``.

    Returns
    -------
    Gradient
        With ``feedback``, ``d_controls[n]`` is the total derivative of the closed-loop cost
        with respect to a perturbation of ``u_n`` alone (the policy's reaction to it in later
        intervals included), so that a policy parameter ``theta`` has
        ``dJ/dtheta = sum_n (d pi / d theta (t_n, s_n))^T d_controls[n]``, and
        ``d_initial_state`` is ``dJ/ds(0)`` of the closed loop.
    """
    ocp = ev.ocp
    k = kernels(ocp)
    num = k.numeric()
    nx, nu = k.nx, k.nu
    u_all = ev.controls
    segs = ev.segments
    M = len(segs)
    idx = np.array([seg.interval for seg in segs], dtype=int)
    FsT_a, FuT_a, Cs_a, Cu_a = _segment_jacobians(k, num, segs, u_all[idx])
    lam = num.phi_grad(ev.final_state)[1]
    lam_end = np.empty((M, nx))  # lambda at each segment's end, after any jump there
    lam_start = np.empty((M, nx))
    lam_jump: dict[int, np.ndarray] = {}  # lambda(gamma-) at the event ending segment i
    if feedback is not None:
        feedback = np.asarray(feedback, dtype=float)
        if feedback.shape != (ocp.steps, nu, nx):
            raise ControlsError(
                f"feedback Jacobians must have shape (N, nu, nx) = ({ocp.steps}, {nu}, {nx}), "
                f"got {feedback.shape}"
            )
        # the first segment of each grid interval starts at the grid time t_n
        first = np.r_[True, idx[1:] != idx[:-1]]
        d_closed = np.zeros_like(u_all)
    # a reset that reads the control of its cell: lambda(gamma+)^T dg/du joins that cell
    reset_u = np.zeros((M, nu)) if any(k.reset_uses_u) else None
    for i in range(M - 1, -1, -1):
        seg = segs[i]
        if seg.event is not None:
            if reset_u is not None and k.reset_uses_u[seg.event]:
                reset_u[i] = _reset_du(num, seg, u_all[seg.interval]).T @ lam
            lam = _costate_jump(num, seg, u_all[seg.interval], lam)
            lam_jump[i] = lam
        lam_end[i] = lam
        if feedback is not None:
            d_closed[idx[i]] += Cu_a[i] + FuT_a[i] @ lam
            if reset_u is not None:
                d_closed[idx[i]] += reset_u[i]
        lam = Cs_a[i] + FsT_a[i] @ lam
        if feedback is not None and first[i]:
            # u_n = pi(t_n, s_n): s_n also acts through the control of its interval
            lam = lam + feedback[idx[i]].T @ d_closed[idx[i]]
        lam_start[i] = lam
    t_rec, lam_rec = _costate_record(
        segs, lam_start, lam_jump, num.phi_grad(ev.final_state)[1], ocp.horizon
    )
    if feedback is not None:
        d_u = d_closed
    else:
        contrib = Cu_a + np.einsum("kij,kj->ki", FuT_a, lam_end)
        if reset_u is not None:
            contrib = contrib + reset_u
        d_u = np.zeros_like(u_all)
        # later segments first, as the recursion visits them
        np.add.at(d_u, idx[::-1], contrib[::-1])
    out = Gradient(
        cost=ev.cost,
        d_initial_state=lam,
        d_controls=d_u,
        costate_times=t_rec,
        costates=lam_rec,
        evaluation=ev,
    )
    if feedback is None:
        f_seg, L_seg = _segment_fL(num, segs, u_all)
        h_seg = np.array([seg.h for seg in segs])
        H = L_seg + np.einsum("ki,ki->k", lam_start, f_seg)
        out.d_horizon = float(h_seg @ H) / ocp.horizon
        if num.terminal is not None:
            tc, tx, tT = _terminal_adjoint(num, ev, idx, FsT_a, FuT_a, f_seg, h_seg)
            out.terminal_d_controls, out.terminal_d_initial_state = tc, tx
            out.terminal_d_horizon = tT
    return out


def _segment_fL(
    num: Numeric, segs: list[Segment], u_all: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``f`` and ``L`` at every segment's start state, ``(M, nx)`` and ``(M,)``."""
    k = num.k
    M, C = len(segs), k.chunk
    n_chunks = -(-M // C)
    S0 = np.zeros((n_chunks * C, k.nx))
    S0[:M] = [seg.s0 for seg in segs]
    U = np.zeros((n_chunks * C, k.nu))
    U[:M] = u_all[[seg.interval for seg in segs]]
    F, Lv = [], []
    for c in range(n_chunks):
        sl = slice(c * C, (c + 1) * C)
        f_c, L_c = num.fL_batch(S0[sl].ravel(), U[sl].ravel())
        F.append(f_c.reshape(C, k.nx))  # column-major: one column (row here) per state
        Lv.append(L_c)
    return np.concatenate(F)[:M], np.concatenate(Lv)[:M]


def _terminal_adjoint(
    num: Numeric,
    ev: Evaluation,
    idx: np.ndarray,
    FsT_a: np.ndarray,
    FuT_a: np.ndarray,
    f_seg: np.ndarray,
    h_seg: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Derivatives of the terminal constraints ``h(s(T))`` (equalities first) with respect
    to the controls, the initial state and ``T``: the costate recursion of :func:`adjoint`
    with one column per constraint, started at ``grad h_i`` and without running cost."""
    assert num.terminal is not None
    ocp = ev.ocp
    nx, N, nu = num.k.nx, ocp.steps, num.k.nu
    vals, jac = num.terminal(ev.final_state)
    m = vals.size
    lam = jac.reshape((m, nx), order="F").T.copy()  # (nx, m): one costate per constraint
    d_u = np.zeros((m, N, nu))
    d_T = np.zeros(m)
    segs = ev.segments
    for i in range(len(segs) - 1, -1, -1):
        seg = segs[i]
        u = ev.controls[seg.interval]
        if seg.event is not None:
            if num.k.reset_uses_u[seg.event]:
                d_u[:, idx[i], :] += (_reset_du(num, seg, u).T @ lam).T
            lam = _costate_jump_block(num, seg, u, lam)
        d_u[:, idx[i], :] += (FuT_a[i] @ lam).T
        lam = FsT_a[i] @ lam
        d_T += h_seg[i] * (lam.T @ f_seg[i])
    return d_u, lam.T.copy(), d_T / ocp.horizon


def _costate_jump_block(num: Numeric, seg: Segment, u: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """:func:`_costate_jump` for several costates ``(nx, m)`` of costs without running
    cost (the terminal constraints'): ``pi`` per column from the continuity of
    ``lambda^T f``."""
    assert seg.event is not None
    nx = lam.shape[0]
    b = num.flow(seg.s0, u, seg.h)[0]
    grad_psi, Dg, gb = num.event_jac(seg.event)(b, u)
    Dg = Dg.reshape(nx, nx).T
    f_minus = num.fL(b, u)[0]
    f_plus = num.fL(gb, u)[0]
    pi = (lam.T @ f_plus - lam.T @ (Dg @ f_minus)) / (grad_psi @ f_minus)
    return Dg.T @ lam + np.outer(grad_psi, pi)


def _segment_jacobians(
    k: Kernels, num: Numeric, segs: list[Segment], U_seg: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every segment's transposed flow-map Jacobians ``(Fs^T, Fu^T)`` and cost gradients."""
    nx, nu = k.nx, k.nu
    M = len(segs)
    # chunk by chunk (padding with h = 0)
    L = k.chunk
    n_chunks = -(-M // L)
    S0 = np.zeros((n_chunks * L, nx))
    S0[:M] = np.array([seg.s0 for seg in segs])
    U = np.zeros((n_chunks * L, nu))
    U[:M] = U_seg
    H = np.zeros(n_chunks * L)
    H[:M] = [seg.h for seg in segs]
    FsT, FuT, Cs, Cu = [], [], [], []
    for c in range(n_chunks):
        sl = slice(c * L, (c + 1) * L)
        a, b, cs, cu = num.seg_jac(S0[sl].ravel(), U[sl].ravel(), H[sl])
        # column-major blocks: row k of the reshape is the transposed Jacobian of segment k
        FsT.append(a.reshape(L, nx, nx))
        FuT.append(b.reshape(L, nu, nx))
        Cs.append(cs.reshape(L, nx))
        Cu.append(cu.reshape(L, nu))
    FsT_a, FuT_a = np.concatenate(FsT)[:M], np.concatenate(FuT)[:M]
    Cs_a, Cu_a = np.concatenate(Cs)[:M], np.concatenate(Cu)[:M]
    return FsT_a, FuT_a, Cs_a, Cu_a


def _costate_record(
    segs: list[Segment],
    lam_start: np.ndarray,
    lam_jump: dict[int, np.ndarray],
    lam_T: np.ndarray,
    horizon: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The costate's times and values in time order, both sides of every jump."""
    M, nx = lam_start.shape
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
    lam_rec[-1] = lam_T
    t_rec[-1] = horizon
    return t_rec, lam_rec


def _reset_du(num: Numeric, seg: Segment, u: np.ndarray) -> np.ndarray:
    """``dg/du`` ``(nx, nu)`` of the reset at the event ending ``seg``, at ``s(gamma-)``."""
    assert seg.event is not None
    b = num.flow(seg.s0, u, seg.h)[0]
    return num.reset_du(seg.event)(b, u)[0].reshape((num.k.nx, num.k.nu), order="F")


def _costate_jump(num: Numeric, seg: Segment, u: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """``lambda(gamma-)`` from ``lambda(gamma+)`` at the event ending ``seg``."""
    assert seg.event is not None
    nx = lam.size
    b = num.flow(seg.s0, u, seg.h)[0]  # s(gamma-)
    grad_psi, Dg, gb = num.event_jac(seg.event)(b, u)
    Dg = Dg.reshape(nx, nx).T  # column-major
    f_minus, L_minus = num.fL(b, u)
    f_plus, L_plus = num.fL(gb, u)
    H_plus = float(L_plus[0]) + lam @ f_plus
    # Hamiltonian continuity fixes the multiplier pi of grad psi
    pi = (H_plus - float(L_minus[0]) - lam @ (Dg @ f_minus)) / (grad_psi @ f_minus)
    return Dg.T @ lam + pi * grad_psi
