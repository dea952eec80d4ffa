"""The reference solution: HMP shooting with event-sequence discovery and built-in checks.

:func:`solve_reference` returns a :class:`~hybridoc.solution.Solution` whose control is the
exact optimal control ``u(t)`` of the continuous problem for the event sequence it reports,
provided three checks pass:

1. the HMP residual (transversality, guards, costate jumps, Hamiltonian continuity) is below
   ``tol`` after Newton with exact Jacobians;
2. ``u(t)`` re-simulated by :func:`hybridoc.evaluate_callable` produces exactly the modelled
   events, no extra and none missing;
3. the re-simulated cost equals the shooting cost to 1e-9 relative.

Otherwise a :class:`~hybridoc.errors.ConvergenceError` says what failed and what to try.
"""

from __future__ import annotations

import math
import numbers
import sys
import time
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hybridoc.callable_eval import evaluate_callable
from hybridoc.errors import ConvergenceError, EvaluationError, SceneError
from hybridoc.evaluation import Evaluation
from hybridoc.evaluator import evaluate, gradient
from hybridoc.ocp import HybridOCP
from hybridoc.problem import as_ocp
from hybridoc.reference.shooting import (
    NewtonResult,
    ShootingSystem,
    is_disc_scene,
    newton,
    shooting_system,
)

__all__ = ["ReferenceResult", "reference_control", "solve_reference", "verify_reference"]

#: approach speeds ``|d psi/dt|`` below this flag the event as grazing
GRAZE_FLAG = 1e-6
#: relative agreement of the shooting cost and the re-simulated cost
COST_RTOL = 1e-9
_MAX_CANDIDATES = 12
_GUESSES: weakref.WeakKeyDictionary[HybridOCP, dict[Any, Any]] = weakref.WeakKeyDictionary()


@dataclass
class ReferenceResult:
    """The HMP solution for one event sequence.

    Attributes
    ----------
    ocp
        The problem.
    sequence
        Guard names in event order.
    event_times
        ``gamma_k``, shape ``(K,)``.
    multipliers
        Jump multipliers ``pi_k``.
    phase_starts, phase_states, phase_costates
        Start time, ``s`` and ``lambda`` (after the jump) of each of the ``K + 1`` phases.
    states_minus, costates_minus
        ``s(gamma_k-)`` and ``lambda(gamma_k-)``, shape ``(K, nx)``.
    approach_speeds
        ``d psi_k / dt`` just before each event (negative for a real impact).
    final_state, final_costate
        ``s(T)``, ``lambda(T)``.
    cost, terminal_cost, running_cost
        Shooting cost and its parts.
    residual
        Max-norm of the HMP residual at the solution.
    newton_iterations, residual_history
        Newton's iteration count and residual per iteration (quadratic convergence).
    grazing
        True if some event has approach speed below ``GRAZE_FLAG`` in magnitude.
    path
        How Newton was started: ``"costate-estimate"``, ``"nlp"`` or ``"feasibility"``.
    """

    ocp: HybridOCP
    sequence: list[str]
    event_times: np.ndarray
    multipliers: np.ndarray
    phase_starts: np.ndarray
    phase_states: np.ndarray
    phase_costates: np.ndarray
    states_minus: np.ndarray
    costates_minus: np.ndarray
    approach_speeds: np.ndarray
    final_state: np.ndarray
    final_costate: np.ndarray
    cost: float
    terminal_cost: float
    running_cost: float
    residual: float
    newton_iterations: int
    residual_history: list[float]
    grazing: bool
    path: str
    system: ShootingSystem = field(repr=False)
    z: np.ndarray = field(repr=False)

    # ------------------------------------------------------------------ dense evaluation
    def _phase_of(self, t: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.phase_starts, t, side="right") - 1, 0, None)

    def control_coefficients(self) -> np.ndarray | None:
        """Disc scenes: ``(K + 1, 2, nu)`` with ``u = c0 + c1 (t - t_k)`` on phase ``k``."""
        S = self.system
        if not S.disc:
            return None
        out = np.empty((self.phase_starts.size, 2, S.nu))
        for k, lam in enumerate(self.phase_costates):
            c0, c1 = S.control_coeffs(lam)
            out[k, 0] = np.asarray(c0).ravel()
            out[k, 1] = np.asarray(c1).ravel()
        return out

    def dense(
        self, times: Sequence[float] | np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(s, lambda, u)`` at ``times`` (after any jump at exactly that time)."""
        t = np.atleast_1d(np.asarray(times, dtype=float))
        S = self.system
        k = self._phase_of(t)
        tau = t - self.phase_starts[k]
        nx, n2 = S.nx, S.nx // 2
        if S.disc:
            C = self.control_coefficients()
            assert C is not None
            c0, c1 = C[k, 0], C[k, 1]
            u = c0 + c1 * tau[:, None]
            a0, a1 = c0 @ S.A.T, c1 @ S.A.T
            s0, l0 = self.phase_states[k], self.phase_costates[k]
            tt = tau[:, None]
            p = s0[:, :n2] + s0[:, n2:] * tt + a0 * tt**2 / 2 + a1 * tt**3 / 6
            v = s0[:, n2:] + a0 * tt + a1 * tt**2 / 2
            lam = np.hstack([l0[:, :n2], l0[:, n2:] - l0[:, :n2] * tt])
            return np.hstack([p, v]), lam, u
        s_out = np.empty((t.size, nx))
        l_out = np.empty((t.size, nx))
        u_out = np.empty((t.size, S.nu))
        for i in range(t.size):
            s_out[i], l_out[i] = S.flow(self.phase_states[k[i]], self.phase_costates[k[i]], tau[i])
            u_out[i] = np.asarray(S.u_star(s_out[i], l_out[i])).ravel()
        return s_out, l_out, u_out

    def control(self, t: float) -> np.ndarray:
        """The optimal control ``u(t)`` (right-continuous at events)."""
        return self.dense([t])[2][0]

    def control_function(self) -> Callable[[float], np.ndarray]:
        """A fast scalar callable ``u(t)`` for :func:`hybridoc.evaluate_callable`."""
        C = self.control_coefficients()
        if C is None:
            return self.control
        starts = self.phase_starts

        def u(t: float) -> np.ndarray:
            k = max(int(np.searchsorted(starts, t, side="right")) - 1, 0)
            return C[k, 0] + C[k, 1] * (t - starts[k])

        return u

    def cell_averages(self) -> np.ndarray:
        """``(N, nu)``: the mean of ``u(t)`` over each grid interval.

        Gauss-Legendre (6 points) on each piece between grid points and events: exact for
        the linear controls of disc scenes.
        """
        grid = self.ocp.time_grid()
        x, w = np.polynomial.legendre.leggauss(6)
        cuts = np.union1d(grid, self.event_times)
        a, b = cuts[:-1], cuts[1:]
        mid = 0.5 * (a + b)
        # evaluate each piece strictly inside so the phase is unambiguous
        tq = (mid[:, None] + 0.5 * (b - a)[:, None] * x[None, :]).ravel()
        u = self.dense(tq)[2].reshape(a.size, x.size, -1)
        integ = 0.5 * (b - a)[:, None] * np.einsum("q,pqn->pn", w, u)
        cell = np.clip(np.searchsorted(grid, mid, side="right") - 1, 0, grid.size - 2)
        out = np.zeros((grid.size - 1, u.shape[2]))
        np.add.at(out, cell, integ)
        return out / np.diff(grid)[:, None]

    def trajectory(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Times (grid and events, events twice: before and after), states, costates."""
        grid = self.ocp.time_grid()
        t = np.union1d(grid, self.event_times)
        s, lam, _ = self.dense(t)
        times, S, L = list(t), list(s), list(lam)
        for k in range(len(self.sequence) - 1, -1, -1):
            i = int(np.searchsorted(t, self.event_times[k]))
            times.insert(i, float(self.event_times[k]))
            S.insert(i, self.states_minus[k])
            L.insert(i, self.costates_minus[k])
        # at T: the end of the last phase
        S[-1], L[-1] = self.final_state, self.final_costate
        return np.array(times), np.array(S), np.array(L)

    def event_dicts(self) -> list[dict[str, Any]]:
        """``[{"time", "kind", "bodies"}]`` as the evaluator writes them."""
        out = []
        for name, t in zip(self.sequence, self.event_times, strict=True):
            g = self.ocp.guards[[gg.name for gg in self.ocp.guards].index(name)]
            out.append({"time": float(t), "kind": g.kind, "bodies": list(g.bodies)})
        return out

    def hmp_residuals(self) -> dict[str, float]:
        """Max-norm of each group of HMP conditions, recomputed from the stored numbers."""
        R = np.asarray(self.system.F(self.z)[0]).ravel()
        nx = self.system.nx
        out = {"transversality": float(np.max(np.abs(R[:nx])))}
        K = len(self.sequence)
        blk = R[nx:].reshape(K, nx + 2) if K else np.zeros((0, nx + 2))
        out["guard"] = float(np.max(np.abs(blk[:, 0]), initial=0.0))
        out["costate_jump"] = float(np.max(np.abs(blk[:, 1:-1]), initial=0.0))
        out["hamiltonian"] = float(np.max(np.abs(blk[:, -1]), initial=0.0))
        return out

    def to_solution(
        self, *, timings: dict[str, Any] | None = None, info: dict[str, Any] | None = None
    ) -> Any:
        """The :class:`~hybridoc.solution.Solution` (method ``"reference"``)."""
        from hybridoc.solution import Solution

        times, states, costates = self.trajectory()
        arrays = {
            "event_times": np.asarray(self.event_times, dtype=float),
            "multipliers": np.asarray(self.multipliers, dtype=float),
            "phase_starts": self.phase_starts,
            "phase_states": self.phase_states,
            "phase_costates": self.phase_costates,
            "residual_history": np.asarray(self.residual_history),
        }
        C = self.control_coefficients()
        if C is not None:
            arrays["control_coefficients"] = C
        base_info = {
            "residual": float(self.residual),
            "sequence": list(self.sequence),
            "newton_iterations": int(self.newton_iterations),
            "grazing": bool(self.grazing),
            "event_times": [float(t) for t in self.event_times],
            "approach_speeds": [float(a) for a in self.approach_speeds],
            "start": self.path,
        }
        base_info.update(info or {})
        sol = Solution(
            method="reference",
            scene=self.ocp.name,
            controls=self.cell_averages(),
            time_grid=self.ocp.time_grid(),
            cost=self.cost,
            terminal_cost=self.terminal_cost,
            running_cost=self.running_cost,
            events=self.event_dicts(),
            state_times=times,
            states=states,
            costate_times=times,
            costates=costates,
            settings={},
            timings=dict(timings or {}),
            info=base_info,
            arrays=arrays,
        )
        sol.reference = self  # type: ignore[attr-defined]  # u(t) for generic problems
        return sol


def reference_control(obj: Any) -> tuple[Callable[[float], np.ndarray], list[float]]:
    """The continuous optimal control of a reference solution and its breakpoints.

    Parameters
    ----------
    obj
        A :class:`ReferenceResult`, or a :class:`~hybridoc.solution.Solution` of method
        ``"reference"`` (also one loaded from disk: disc scenes store the linear control
        coefficients of every phase).

    Returns
    -------
    u, breakpoints
        ``u(t) -> (nu,)`` and the event times, ready for
        ``hybridoc.evaluate_callable(ocp, u, breakpoints=breakpoints)``.
    """
    if isinstance(obj, ReferenceResult):
        return obj.control_function(), [float(t) for t in obj.event_times]
    ref = getattr(obj, "reference", None)
    if isinstance(ref, ReferenceResult):
        return reference_control(ref)
    arrays = getattr(obj, "arrays", {})
    if "control_coefficients" not in arrays or "phase_starts" not in arrays:
        raise ValueError(
            "this solution carries no reference control (need arrays 'phase_starts' and "
            "'control_coefficients' from hybridoc.reference)"
        )
    C = np.asarray(arrays["control_coefficients"], dtype=float)
    starts = np.asarray(arrays["phase_starts"], dtype=float)

    def u(t: float) -> np.ndarray:
        k = max(int(np.searchsorted(starts, t, side="right")) - 1, 0)
        return C[k, 0] + C[k, 1] * (t - starts[k])

    return u, [float(t) for t in starts[1:]]


# ---------------------------------------------------------------------- one sequence
def _result(S: ShootingSystem, nr: NewtonResult, path: str) -> ReferenceResult:
    out = [np.asarray(x) for x in S.traj(nr.z)]
    starts, s0, l0, _, phiT, run, sm, lm, rates, sT, lT = out
    _, gam, pis, _ = S.unpack(nr.z)
    rates = rates.ravel()
    return ReferenceResult(
        ocp=S.ocp,
        sequence=list(S.sequence),
        event_times=np.array([float(g) for g in gam]),
        multipliers=np.array([float(p) for p in pis]),
        phase_starts=starts.ravel(),
        phase_states=s0.T.copy(),
        phase_costates=l0.T.copy(),
        states_minus=sm.T.copy(),
        costates_minus=lm.T.copy(),
        approach_speeds=rates,
        final_state=sT.ravel(),
        final_costate=lT.ravel(),
        cost=float(phiT.item()) + float(run.item()),
        terminal_cost=float(phiT.item()),
        running_cost=float(run.item()),
        residual=nr.residual,
        newton_iterations=nr.iterations,
        residual_history=list(nr.history),
        grazing=bool(np.any(np.abs(rates) < GRAZE_FLAG)),
        path=path,
        system=S,
        z=nr.z,
    )


def _fit_coeffs(ocp: HybridOCP, u: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """Least-squares ``c0 + c1 (t - t_k)`` per phase to a piecewise-constant guess."""
    mids = (np.arange(ocp.steps) + 0.5) * ocp.dt
    edges = np.concatenate([[0.0], gamma, [ocp.horizon]])
    out = np.zeros((edges.size - 1, 2 * ocp.nu))
    for k in range(edges.size - 1):
        m = (mids >= edges[k]) & (mids < edges[k + 1])
        if m.sum() >= 2:
            X = np.column_stack([np.ones(m.sum()), mids[m] - edges[k]])
            c = np.linalg.lstsq(X, u[m], rcond=None)[0]
            out[k] = np.concatenate([c[0], c[1]])
        elif m.sum() == 1:
            out[k, : ocp.nu] = u[m][0]
        else:
            i = min(int(edges[k] / ocp.dt), ocp.steps - 1)
            out[k, : ocp.nu] = u[i]
    return out


def _z_from_gradient(S: ShootingSystem, grad: Any, gamma: np.ndarray) -> np.ndarray:
    """Newton start from an adjoint costate (the evaluator's, for the initial control)."""
    ct, cs = np.asarray(grad.costate_times), np.asarray(grad.costates)
    lps, pis = [], []
    for k, g in enumerate(gamma):
        i_after = int(np.searchsorted(ct, g, side="right")) - 1
        i_after = min(max(i_after, 0), ct.size - 1)
        lp = cs[i_after]
        lm = cs[max(i_after - 1, 0)]
        s_m = grad.evaluation.sample([g])[0]
        _, gpsi, _, Dg = (np.asarray(x) for x in S.guard_fns[k](s_m))
        gpsi = gpsi.ravel()
        r = lm - Dg.T @ lp
        pis.append(float(gpsi @ r / max(gpsi @ gpsi, 1e-300)))
        lps.append(lp)
    return S.pack(np.asarray(grad.d_initial_state), gamma, pis, lps)


def solve_sequence(
    ocp: HybridOCP,
    sequence: Sequence[str],
    gamma0: np.ndarray,
    u_guess: np.ndarray,
    *,
    estimate: bool = False,
    grad: Any = None,
    tol: float = 1e-10,
    verbose: bool = False,
) -> tuple[ReferenceResult | None, str]:
    """Solve the HMP system of one sequence; ``(result, "")`` or ``(None, reason)``.

    With ``estimate`` (a given initial control), Newton starts from the adjoint costate of
    the guess: for disc scenes of its linear-in-time fit per phase, otherwise the
    evaluator's adjoint ``grad``. Disc scenes also solve the NLP in event times and phase
    controls with IPOPT and polish it by Newton, and the cheaper converged point is kept;
    other problems fall back to an IPOPT feasibility solve when the estimate fails.
    """
    S = shooting_system(ocp, list(sequence))
    gamma0 = np.asarray(gamma0, dtype=float)
    reasons = []
    found: list[ReferenceResult] = []
    if estimate and (S.disc or grad is not None):
        if S.disc:  # adjoint of the guess fitted by linear phase laws: exact jump rule
            z0 = S.z_from_controls(gamma0, _fit_coeffs(ocp, u_guess, gamma0))
        else:
            z0 = _z_from_gradient(S, grad, gamma0)
        nr = newton(S, z0, tol=tol, verbose=verbose)
        if nr.converged:
            found.append(_result(S, nr, "costate-estimate"))
        else:
            reasons.append(f"Newton from the costate estimate: residual {nr.residual:.2e}")
    if S.disc:
        # Also after a converged estimate: from a poor guess Newton can land on a worse
        # stationary point of the same sequence, while the NLP minimises over it.
        z0, ok = S.solve_nlp(gamma0, _fit_coeffs(ocp, u_guess, gamma0))
        nr = newton(S, z0, tol=tol, verbose=verbose)
        if nr.converged:
            found.append(_result(S, nr, "nlp"))
        else:
            reasons.append(
                f"IPOPT ({'converged' if ok else 'failed'}) then Newton: residual {nr.residual:.2e}"
            )
    elif grad is not None and not found:
        z0, ok = S.solve_feasibility(_z_from_gradient(S, grad, gamma0))
        nr = newton(S, z0, tol=tol, verbose=verbose)
        if nr.converged:
            found.append(_result(S, nr, "feasibility"))
        else:
            reasons.append(f"IPOPT feasibility then Newton: residual {nr.residual:.2e}")
    if found:  # the first (the estimate's) unless another is cheaper beyond rounding
        best = found[0]
        for r in found[1:]:
            if r.cost < best.cost - 1e-12 * abs(best.cost):
                best = r
        return best, ""
    return None, "; ".join(reasons)


# ---------------------------------------------------------------------- verification
def verify_reference(res: ReferenceResult) -> tuple[bool, Evaluation, str]:
    """Re-simulate ``u(t)`` with the event-exact evaluator.

    Returns
    -------
    ok, evaluation, message
        ``ok`` when the re-simulated events are exactly the modelled ones (same guards, same
        order, times within 1e-7) and the cost agrees to ``COST_RTOL``. Equal events with a
        different cost raise :class:`ConvergenceError` (an internal inconsistency).
    """
    u, bps = reference_control(res)
    ocp = res.ocp
    sim = evaluate_callable(ocp, u, breakpoints=bps)
    names = [ocp.guards[e.guard].name for e in sim.events]
    times = np.array([e.time for e in sim.events])
    if names != res.sequence:
        return False, sim, f"re-simulation gives events {names}, modelled {res.sequence}"
    if times.size and np.max(np.abs(times - res.event_times)) > 1e-7:
        return False, sim, "re-simulated event times differ from the modelled ones"
    rel = abs(sim.cost - res.cost) / max(abs(res.cost), 1e-300)
    if rel > COST_RTOL:
        raise ConvergenceError(
            f"reference for {res.sequence}: shooting cost {res.cost:.12g} but the evaluator "
            f"gives {sim.cost:.12g} for the same u(t) (relative {rel:.2e} > {COST_RTOL:g})"
        )
    return True, sim, ""


# ---------------------------------------------------------------------- discovery
def _event_list(ocp: HybridOCP, ev: Evaluation) -> list[tuple[str, float]]:
    return [(ocp.guards[e.guard].name, float(e.time)) for e in ev.events]


def _near_touches(ocp: HybridOCP, ev: Evaluation, limit: int = 2) -> list[tuple[str, float]]:
    """Local minima of guards without an event, closest first (at most ``limit``)."""
    if not ocp.guards:
        return []
    radii = ocp.meta.get("radii")
    thresh = float(np.max(radii)) if radii is not None else None
    t, X = ev.times, ev.states
    fired = {(ocp.guards[e.guard].name, round(e.time, 3)) for e in ev.events}
    found = []
    for g in ocp.guards:
        psi = np.asarray(g.psi.map(X.shape[0])(X.T)).ravel()
        th = thresh if thresh is not None else 0.1 * (np.ptp(psi) or 1.0)
        for i in range(1, psi.size - 1):
            if psi[i] <= psi[i - 1] and psi[i] <= psi[i + 1] and 0 < psi[i] < th:
                if not any(name == g.name and abs(tt - t[i]) < 0.05 for name, tt in fired):
                    found.append((psi[i], g.name, float(t[i])))
    found.sort()
    return [(name, tt) for _, name, tt in found[:limit]]


def _candidates(ocp: HybridOCP, ev: Evaluation) -> list[list[tuple[str, float]]]:
    obs = _event_list(ocp, ev)
    cands = [obs]
    for i in range(len(obs)):
        cands.append(obs[:i] + obs[i + 1 :])
    for name, tt in _near_touches(ocp, ev):
        cands.append(sorted(obs + [(name, tt)], key=lambda x: x[1]))
    cands.append([])
    out, seen = [], set()
    for c in cands:
        key = tuple(n for n, _ in c)
        if key not in seen:
            seen.add(key)
            out.append(c)
    return out


def _guess_times(ocp: HybridOCP, sequence: Sequence[str], ev: Evaluation) -> np.ndarray:
    """Event-time guesses for an explicit sequence from the guess trajectory."""
    obs = _event_list(ocp, ev)
    names = [g.name for g in ocp.guards]
    T = ocp.horizon
    out: list[float] = []
    prev = 0.0
    for name in sequence:
        match = [tt for n, tt in obs if n == name and tt > prev]
        if match:
            tt = match[0]
        else:
            g = ocp.guards[names.index(name)]
            m = (ev.times > prev) & (ev.times < T)
            if m.any():
                psi = np.asarray(g.psi.map(int(m.sum()))(ev.states[m].T)).ravel()
                tt = float(ev.times[m][int(np.argmin(psi))])
            else:
                tt = 0.5 * (prev + T)
        tt = min(max(tt, prev + 1e-3 * T), T * (1 - 1e-3))
        out.append(tt)
        prev = tt
    return np.array(out)


def _guess_evaluation(ocp: HybridOCP, u0: np.ndarray, *, want_costate: bool) -> tuple[Any, Any]:
    """Evaluation (and adjoint) of the initial guess, cached per problem and guess."""
    cache = _GUESSES.setdefault(ocp, {})
    key = (u0.tobytes(), want_costate)
    hit = cache.get(key)
    if hit is not None:
        return hit
    try:
        if want_costate:
            grad = gradient(ocp, u0)
            out = (grad.evaluation, grad)
        else:
            out = (evaluate(ocp, u0), None)
    except EvaluationError as exc:
        raise ConvergenceError(f"cannot simulate the initial guess: {exc}") from None
    if len(cache) > 8:
        cache.clear()
    cache[key] = out
    return out


def _initial_controls(ocp: HybridOCP, initial: Any) -> tuple[np.ndarray, bool]:
    if initial is None:
        return np.asarray(ocp.u_guess, dtype=float), False
    controls = getattr(initial, "controls", initial)
    return ocp.check_controls(controls, what="initial"), True


def solve_reference(
    problem: Any,
    *,
    sequence: Sequence[str] | str | None = None,
    initial: Any = None,
    verbose: bool = False,
    tol: float = 1e-10,
    verify: bool = True,
) -> Any:
    """The optimal control by shooting on the hybrid minimum principle.

    Parameters
    ----------
    problem
        A :class:`~hybridoc.problems.Scene`, a built-in scene name or a
        :class:`~hybridoc.HybridOCP`.
    sequence
        Guard names in event order (e.g. ``["ball1|ball2", "ball2|wall"]`` or the string
        ``"ball1|ball2,ball2|wall"``; ``[]`` for no event), or ``None`` to discover it.
    initial
        ``None`` (the problem's initial guess) or a Solution / ``(N, nu)`` controls from
        another solver: its events and adjoint costate start Newton.
    verbose
        Print Newton's iterations (residual norms) and the candidates to stderr.
    tol
        Max-norm of the HMP residual required.
    verify
        Re-simulate the winning control with :func:`hybridoc.evaluate_callable` (events and
        cost must agree). Only an explicit ``sequence`` may skip it (for timing): discovery
        always verifies, since it chooses among candidates by the re-simulation.

    Returns
    -------
    hybridoc.solution.Solution
        Method ``"reference"``; ``info`` holds ``residual``, ``sequence``,
        ``newton_iterations``, ``grazing``, ``event_times``; ``arrays`` the phase data;
        :func:`reference_control` rebuilds ``u(t)``.

    Raises
    ------
    SceneError
        ``sequence`` names an event that is not a guard of the problem, or ``tol`` is not a
        positive number.
    ConvergenceError
        No candidate sequence satisfies the conditions and re-simulates to its own events.
    """
    t_start = time.perf_counter()
    if isinstance(problem, str):
        from hybridoc.problems import load_scene

        problem = load_scene(problem)
    ocp = as_ocp(problem)
    seq = None if sequence is None else ocp.check_sequence(sequence)
    if not (isinstance(tol, numbers.Real) and math.isfinite(tol) and tol > 0):
        raise SceneError(f"tol must be a positive finite number, got {tol!r}")
    u0, given = _initial_controls(ocp, initial)
    ev, grad = _guess_evaluation(ocp, u0, want_costate=not is_disc_scene(ocp))
    if seq is not None:
        queue = [list(zip(seq, _guess_times(ocp, seq, ev), strict=True))]
    else:
        queue = _candidates(ocp, ev)
    tried: dict[tuple[str, ...], str] = {}
    solved: list[ReferenceResult] = []
    verified: dict[tuple[str, ...], tuple[bool, str, Evaluation | None]] = {}
    t_verify = 0.0
    best: ReferenceResult | None = None
    for _round in range(3):
        while queue and len(tried) < _MAX_CANDIDATES:
            cand = queue.pop(0)
            key = tuple(n for n, _ in cand)
            if key in tried:
                continue
            gamma0 = np.array([tt for _, tt in cand])
            res, why = solve_sequence(
                ocp,
                key,
                gamma0,
                u0,
                estimate=given or grad is not None,
                grad=grad,
                tol=tol,
                verbose=verbose,
            )
            tried[key] = why if res is None else f"cost {res.cost:.12g}"
            if verbose:
                print(f"reference: candidate {list(key)}: {tried[key]}", file=sys.stderr)
            if res is not None:
                solved.append(res)
        if not verify and sequence is not None:
            best = min(solved, key=lambda r: r.cost) if solved else None
            break
        best, dt_v = _best_verified(solved, verified, verbose)
        t_verify += dt_v
        if best is not None or sequence is not None:
            break
        # a re-simulation with other events proposes its own sequence
        for r in solved:
            ok, _, sim = verified[tuple(r.sequence)]
            if sim is not None and not ok:
                cand = _event_list(ocp, sim)
                if tuple(n for n, _ in cand) not in tried:
                    queue.append(cand)
        if not queue:
            break
    if best is None:
        lines = [f"{list(k)}: {v}" for k, v in tried.items()]
        lines += [
            f"{list(k)}: re-simulation failed: {msg}"
            for k, (ok, msg, _) in verified.items()
            if not ok
        ]
        raise ConvergenceError(
            "no event sequence satisfies the HMP conditions and re-simulates to its own events"
            + (" (" + "; ".join(lines) + ")" if lines else "")
            + ". hint: start from another initial guess (e.g. a solver's solution) or give "
            "an explicit --sequence"
        )
    sol = best.to_solution(
        timings={"verify_time_s": t_verify},
        info={
            "verified": bool(verify or sequence is None),
            "candidates": [{"sequence": list(k), "result": v} for k, v in tried.items()],
        },
    )
    sol.settings = {"tol": tol, "sequence": seq}
    sol.timings = {"solve_time_s": time.perf_counter() - t_start, **sol.timings}
    return sol


def _best_verified(
    solved: list[ReferenceResult],
    verified: dict[tuple[str, ...], tuple[bool, str, Evaluation | None]],
    verbose: bool,
) -> tuple[ReferenceResult | None, float]:
    """Lowest-cost solved candidate whose re-simulation reproduces its events."""
    t0 = time.perf_counter()
    for res in sorted(solved, key=lambda r: r.cost):
        key = tuple(res.sequence)
        if key not in verified:
            try:
                ok, sim, msg = verify_reference(res)
            except EvaluationError as exc:
                ok, sim, msg = False, None, str(exc)
            verified[key] = (ok, msg, sim)
            if verbose:
                print(f"reference: verify {list(key)}: {'ok' if ok else msg}", file=sys.stderr)
        if verified[key][0]:
            return res, time.perf_counter() - t0
    return None, time.perf_counter() - t0
