"""One event sequence: the HMP extremal from every available start, and its verification.

:func:`solve_sequence` tries, in order, until Newton converges (and keeps the cheapest point
found): the adjoint costate of a given control (its linear-in-time fit per phase for disc
scenes, the judge's adjoint otherwise), the disc scenes' NLP in event times and linear
phase controls, and the warm starts of the :class:`~hybridoc.reference.sources.SequenceStarter`
sources (the direct transcription with the sequence fixed, whose multipliers give the
costates). :func:`verify_reference` re-simulates the extremal's control with the judge.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

from hybridoc import tolerances
from hybridoc.errors import ConvergenceError, EvaluationError, HybridocError
from hybridoc.evaluation import Evaluation
from hybridoc.ocp import HybridOCP
from hybridoc.reference.result import ReferenceResult, make_result, reference_control
from hybridoc.reference.shooting import (
    DEFAULT_RTOL,
    NewtonResult,
    ShootingSystem,
    free_mode,
    newton,
    refine,
    saturate,
    shooting_system,
)
from hybridoc.reference.sources import PhaseCostates, SequenceStarter
from hybridoc.reference.units import cost_shown as _J

__all__ = [
    "BOUND_SIGN_TOL",
    "COST_FLOOR",
    "COST_RTOL",
    "JUDGE_RETRIES",
    "SCREEN_NLP_ITER",
    "check_rtol",
    "TERMINAL_TOL",
    "judged_reference",
    "judged_violation",
    "solve_sequence",
    "verify_reference",
    "z_from_costates",
    "z_zero_costate",
]

COST_RTOL = DEFAULT_RTOL
"""The default relative agreement of the shooting cost and the judge's cost of the same
control (``rtol``)."""
COST_FLOOR = 1e-14
"""Costs below this are zero to rounding: the judge's re-simulation must agree with the
shooting cost to ``rtol`` relative, or to ``rtol * COST_FLOOR`` absolutely below it."""
#: Constraint violation above which the search drops a sequence whose NLP failed.
SCREEN_INFEASIBILITY = 1e-3
#: IPOPT iterations of a disc scene's NLP when the search screens many sequences.
SCREEN_NLP_ITER = 40
BOUND_SIGN_TOL = tolerances.value("bound_sign")
"""A final time at a bound is a minimum in ``T`` when ``H(T)`` has the right sign, to this
much relative (its residual is rounding there)."""
TERMINAL_TOL = tolerances.TERMINAL
"""The largest violation of the terminal constraints the judge's re-simulation of an
extremal may show: the table's ``"terminal"`` tolerance (:mod:`hybridoc.tolerances`), shared
by the methods (issue #15)."""
JUDGE_RETRIES = 2
"""When the judge's cost differs from the shooting's by more than ``rtol`` although the
events agree, the extremal is refined this many times more, each to a target 100 times
tighter (:func:`judged_reference`), before the disagreement is an error."""
RTOL_RANGE = (1e-11, 1e-6)
"""The ``rtol`` the reference accepts: the judge integrates to 1e-12 (its own cost is off by
a few 1e-12 relative: it could not confirm less than 1e-11), and beyond 1e-6 the
re-simulated event times (checked to 1e-7 T) stop agreeing."""


def check_rtol(rtol: object) -> float:
    """``rtol`` as a float in :data:`RTOL_RANGE`.

    Raises
    ------
    ValueError
        With a one-line reason.
    """
    lo, hi = RTOL_RANGE
    try:
        value = float(rtol)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"rtol must be a number from {lo:g} to {hi:g}, got {rtol!r}") from None
    if isinstance(rtol, bool) or not (math.isfinite(value) and lo <= value <= hi):
        raise ValueError(
            f"rtol must be a number from {lo:g} to {hi:g} (the judge integrates to 1e-12; "
            f"beyond {hi:g} the re-simulated event times stop agreeing), got {rtol!r}"
        )
    return value


def fit_coeffs(ocp: HybridOCP, u: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """Least-squares ``c0 + c1 (t - t_k)`` per phase to a piecewise-constant control."""
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


def _pi_from_jump(
    S: ShootingSystem,
    k: int,
    s_minus: np.ndarray,
    lm: np.ndarray,
    lp: np.ndarray,
    v: np.ndarray | None = None,
) -> float:
    _, gpsi, _, Dg = (np.asarray(x) for x in S.core.guard_at(k, s_minus, v))
    gpsi = gpsi.ravel()
    r = lm - Dg.T @ lp
    return float(gpsi @ r / max(float(gpsi @ gpsi), 1e-300))


def _terminal_estimate(
    S: ShootingSystem, s_end: np.ndarray, lam_end: np.ndarray
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Terminal multipliers ``(nu, mu)`` that best explain a final costate: the least
    squares solution of ``lambda(T) = grad phi - Dh_eq^T nu - Dh_in^T mu``, ``mu`` clipped
    at 0; ``(None, None)`` without terminal constraints."""
    core = S.core
    if core.terminal is None:
        return None, None
    s_end = np.asarray(s_end, dtype=float).ravel()
    _, gphi = (np.asarray(x, dtype=float) for x in core.phi(s_end))
    _, D_eq, _, D_in = (np.asarray(x, dtype=float) for x in core.terminal(s_end))
    D = np.vstack([D_eq.reshape(core.m_eq, S.nx), D_in.reshape(core.m_in, S.nx)])
    rhs = gphi.ravel() - np.asarray(lam_end, dtype=float).ravel()
    m = np.linalg.lstsq(D.T, rhs, rcond=None)[0] if D.size else np.zeros(0)
    if not np.all(np.isfinite(m)):
        return None, None
    return m[: core.m_eq], np.maximum(m[core.m_eq :], 0.0)


def z_zero_costate(S: ShootingSystem, gamma: np.ndarray) -> np.ndarray:
    """Newton start with every costate and multiplier 0 (``u = argmin H`` at ``lambda = 0``)
    and the guessed event times: the reference's own start on a problem with terminal
    constraints or a free final time, where no other start may exist (the sources that do
    not honour them are skipped, and the guess's adjoint ignores the constraints)."""
    zeros = np.zeros(S.nx)
    return S.pack(zeros, gamma, np.zeros(S.K), [zeros] * S.K, T=S.T)


def z_from_gradient(S: ShootingSystem, grad: Any, gamma: np.ndarray) -> np.ndarray:
    """Newton start from the judge's adjoint costate of a control with these events."""
    ct, cs = np.asarray(grad.costate_times), np.asarray(grad.costates)
    lps, pis, vs = [], [], []
    for k, g in enumerate(gamma):
        i_after = int(np.searchsorted(ct, g, side="right")) - 1
        i_after = min(max(i_after, 0), ct.size - 1)
        lp = cs[i_after]
        lm = cs[max(i_after - 1, 0)]
        s_m = grad.evaluation.sample([g])[0]
        # a reset that reads the control: its own control minimises lambda+^T g there
        vs.append(S.core.start_event_control(k, s_m, lp))
        pis.append(_pi_from_jump(S, k, s_m, lm, lp, vs[-1]))
        lps.append(lp)
    # the adjoint ends at grad phi: no terminal multipliers
    return S.pack(np.asarray(grad.d_initial_state), gamma, pis, lps, T=S.T, v=vs)


def z_from_costates(S: ShootingSystem, w: PhaseCostates) -> np.ndarray:
    """Newton start from costates per phase (a transcription's multipliers): the costate
    jumps follow from the costates on both sides of each event."""
    vs = [
        S.core.start_event_control(k, np.asarray(w.state_end[k]), w.costate_start[k + 1])
        for k in range(S.K)
    ]
    pis = [
        _pi_from_jump(
            S, k, np.asarray(w.state_end[k]), w.costate_end[k], w.costate_start[k + 1], vs[k]
        )
        for k in range(S.K)
    ]
    nu, mu = _terminal_estimate(S, np.asarray(w.state_end[-1]), np.asarray(w.costate_end[-1]))
    T = S.T if getattr(w, "horizon", None) is None else float(w.horizon)  # type: ignore[arg-type]
    return S.pack(
        w.costate_start[0], np.asarray(w.event_times), pis, list(w.costate_start[1:]), nu, mu,
        T=T, v=vs,
    )  # fmt: skip


def solve_sequence(
    ocp: HybridOCP,
    sequence: Sequence[str],
    gamma0: np.ndarray,
    u_guess: np.ndarray,
    *,
    estimate: bool = False,
    grad: Any = None,
    guess_ev: Evaluation | None = None,
    starters: Sequence[SequenceStarter] = (),
    tol: float = 1e-10,
    verbose: bool = False,
    screen: bool = False,
    warm_start: PhaseCostates | None = None,
    rtol: float = COST_RTOL,
) -> tuple[ReferenceResult | None, str]:
    """Solve the HMP system of one sequence; ``(result, "")`` or ``(None, reasons)``.

    Parameters
    ----------
    ocp, sequence
        The problem and the guard names in event order.
    gamma0, u_guess
        Event-time guesses and a control to start from.
    estimate
        Start Newton from the adjoint costate of ``u_guess`` (its events should be the
        sequence's).
    grad
        The judge's adjoint of ``u_guess`` (generic problems' costate estimate).
    guess_ev
        A simulated trajectory to initialise the transcription's phases.
    starters
        Fall back on their warm starts, in order, until Newton converges (the direct
        transcription with the sequence fixed); they need ``guess_ev``.
    screen
        For the search over many sequences (disc scenes): where IPOPT stops at a point that
        violates the sequence's guard conditions (by more than 1e-3), give the sequence up
        without Newton, and give Newton fewer, shorter tries; most enumerated sequences are
        not realisable, and an extremal's Newton from the NLP takes two or three steps.
    warm_start
        Costates per phase (a source's proposal) to start Newton from, after the estimate.
    rtol
        The relative accuracy of the cost: a converged point is refined
        (:func:`~hybridoc.reference.shooting.refine`) until the integration's error
        estimate is within it; a sequence that cannot reach it fails with the reason.
    """
    S = shooting_system(ocp, list(sequence))
    gamma0 = np.asarray(gamma0, dtype=float)
    tries = _Attempts(ocp, sequence, S, tol=tol, verbose=verbose, screen=screen, rtol=rtol)
    reasons, found, attempt = tries.reasons, tries.found, tries.attempt

    if estimate and (S.disc or grad is not None):
        z0 = (
            S.z_from_controls(gamma0, fit_coeffs(ocp, u_guess, gamma0))
            if S.disc
            else z_from_gradient(S, grad, gamma0)
        )
        attempt(z0, "costate-estimate")
    if warm_start is not None and len(warm_start.event_times) == S.K:
        attempt(z_from_costates(S, warm_start), "warm start")
    if S.disc:
        # also after a converged estimate: from a poor guess Newton can land on a worse
        # stationary point of the same sequence, while the NLP minimises over it
        coeffs = fit_coeffs(ocp, u_guess, gamma0)
        z0, ok, infeasibility = S.solve_nlp(
            gamma0, coeffs, max_iter=SCREEN_NLP_ITER if screen else 100
        )
        if screen and not ok and infeasibility > SCREEN_INFEASIBILITY:
            reasons.append(
                f"the NLP found no point with these events (violation {infeasibility:.1e})"
            )
        else:
            attempt(z0, "nlp")
    if not found and (ocp.has_terminal_constraints or ocp.free_horizon):
        attempt(z_zero_costate(S, gamma0), "zero costate")
    for starter in starters if guess_ev is not None else ():
        if found:
            break
        try:
            proposal = starter.start(ocp, list(sequence), guess_ev, u_guess)
        except (ConvergenceError, EvaluationError, ValueError) as exc:
            reasons.append(f"{starter.name}: {exc}")
            continue
        if proposal is not None and proposal.warm_start is not None:
            attempt(z_from_costates(S, proposal.warm_start), starter.name)
    if found:
        best = min(found, key=lambda r: r.cost)
        # every converged start's extremal: the search counts those that agree
        best.start_costs = tuple(float(r.cost) for r in found)
        return best, ""
    return None, "; ".join(reasons) or "no start for Newton"


class _Attempts:
    """The Newton runs of one sequence's :func:`solve_sequence`, one per start: the
    extremals found (:attr:`found`) and why the other starts failed (:attr:`reasons`)."""

    def __init__(
        self,
        ocp: HybridOCP,
        sequence: Sequence[str],
        S: ShootingSystem,
        *,
        tol: float,
        verbose: bool,
        screen: bool,
        rtol: float,
    ) -> None:
        self.ocp, self.sequence, self.S = ocp, sequence, S
        self.tol, self.verbose, self.screen, self.rtol = tol, verbose, screen, rtol
        self.reasons: list[str] = []
        self.found: list[ReferenceResult] = []

    def solve(self, system: ShootingSystem, z0: np.ndarray) -> NewtonResult:
        if self.screen:
            return newton(
                system, z0, tol=self.tol, verbose=self.verbose, max_iter=20, min_step=1e-3
            )
        return newton(system, z0, tol=self.tol, verbose=self.verbose)

    def run(self, system: ShootingSystem, z0: np.ndarray) -> tuple[ShootingSystem, NewtonResult]:
        ocp = self.ocp
        nr = self.solve(system, z0)
        if not (ocp.has_bounds or ocp.path is not None):
            return system, nr
        # control bounds: the saturated arcs (shooting.saturate), from the extremal of the
        # clipped control (a disc scene: of its closed-form phases), else from the
        # unconstrained one (from a poor start the clip's flat branches stall Newton)
        tries = [(system, nr)]
        if not system.disc:
            tries.append((system.with_arcs(((free_mode(ocp.nu),),) * (system.K + 1)), None))
        last = (system, nr)
        for base, first in tries:
            nr_b = first if first is not None else self.solve(base, z0)
            if not nr_b.converged:
                last = (base, nr_b) if first is not None else last
                continue
            sat, nr_sat, why = saturate(base, nr_b, tol=self.tol, verbose=self.verbose)
            if not why:
                return sat, nr_sat
            self.reasons.append(f"saturation: {why}")
            last = (sat, NewtonResult(nr_sat.z, nr_sat.residual, nr_sat.iterations, False))
        return last

    def keep(self, system: ShootingSystem, nr: NewtonResult, path: str) -> None:
        ref = refine(system, nr, rtol=self.rtol, tol=self.tol, verbose=self.verbose)
        if ref.ok:
            self.found.append(make_result(ref.system, ref.newton, path, ref.error))
        else:
            self.reasons.append(f"from the {path}: {ref.reason}")

    def failed(self, system: ShootingSystem, nr: NewtonResult, path: str) -> None:
        if nr.residual <= self.tol:
            times = ", ".join(f"{float(g):.6g}" for g in system.unpack(nr.z)[1])
            self.reasons.append(
                f"Newton from the {path} found a root with event times [{times}], not in "
                f"order inside (0, T = {system.horizon_of(nr.z):g})"
            )
        else:
            self.reasons.append(f"Newton from the {path}: residual {nr.residual:.2e}")

    def attempt(self, z0: np.ndarray, path: str, again: bool = True) -> None:
        S = self.S
        Sr, nr = self.run(S, z0)
        if not S.core.free:
            if nr.converged:
                self.keep(Sr, nr, path)
                # the first-order conditions of a reset's control hold at any stationary
                # point of the cost in it: Newton again from other extremes of lambda+^T g
                for z1 in _reset_controls_moved(Sr, nr.z) if again else []:
                    self.attempt(Sr.core.strip_switches(z1), f"{path}, reset controls moved", False)
            else:
                self.failed(Sr, nr, path)
            return
        lo, hi = self.ocp.horizon_bounds  # type: ignore[misc]
        T = Sr.horizon_of(nr.z)
        if nr.converged and lo <= T <= hi:
            self.keep(Sr, nr, path)
            return
        if nr.converged:
            self.reasons.append(
                f"from the {path}: H(T) = 0 at T = {T:.6g}, outside [{lo:g}, {hi:g}]: "
                "solved at the bounds"
            )
        else:
            self.failed(Sr, nr, path)
        self._at_bounds(z0[:-1], path, T if nr.converged else S.T)

    def _at_bounds(self, z0: np.ndarray, path: str, near: float) -> None:
        """A final time at a bound: solved there with ``T`` fixed, kept where ``H(T)``
        has the sign of a minimum (``>= 0`` at ``T_min``, ``<= 0`` at ``T_max``)."""
        ocp = self.ocp
        lo, hi = ocp.horizon_bounds  # type: ignore[misc]
        for bound in sorted({lo, hi}, key=lambda b: abs(b - near)):
            Sb = shooting_system(ocp.replace(horizon=bound), list(self.sequence), free=False)
            where = f"{path} at T = {bound:g}"
            Sb, nr = self.run(Sb, z0)
            if not nr.converged:
                self.failed(Sb, nr, where)
                continue
            H_T = float(Sb.traj(nr.z)[12].item())
            slack = BOUND_SIGN_TOL * max(1.0, abs(H_T))
            if (bound == lo and H_T >= -slack) or (bound == hi and H_T <= slack):
                self.keep(Sb, nr, where)
            else:
                self.reasons.append(
                    f"from the {where}: H(T) = {H_T:.3g} has the sign of a larger cost "
                    "there (not a minimum in T)"
                )


def _reset_controls_moved(S: ShootingSystem, z: np.ndarray) -> list[np.ndarray]:
    """Other starts for an extremal with reset controls ``v_k``: ``z`` with every ``v_k``
    moved to the sampled minimum of ``lambda(gamma+)^T g(s(gamma-), v)`` over its bounds
    (the HMP's pointwise minimum at this costate), and ``z`` with every ``v_k`` moved to
    its maximum (the minimum for a costate of the other sign: a reset that is not monotone
    in ``v`` admits an extremal whose costate has the wrong sign for the optimum), each
    where it moves some ``v_k``; empty without such resets."""
    core = S.core
    if not getattr(core, "n_v", 0):
        return []
    sm = np.asarray(S.traj(z)[6], dtype=float)
    lps = S.unpack(z)[3]
    vs = core.unpack_event_controls(np.asarray(z, dtype=float))
    out = []
    for sign in (1.0, -1.0):
        moved, changed = list(vs), False
        for k, v in enumerate(vs):
            if v is None:
                continue
            lam = sign * np.asarray(lps[k], dtype=float)
            w = core.start_event_control(k, sm[:, k], lam, hint=v)
            if w is not None and not np.array_equal(w, np.clip(v, *core.v_bounds)):
                moved[k], changed = w, True
        if changed:
            out.append(core.with_event_controls(z, moved))
    return out


def _canonical(ocp: HybridOCP, names: list[str], times: np.ndarray) -> list[str]:
    """Guard names in time order, those at one instant (to rounding) in guard order."""
    order = sorted(
        range(len(names)),
        key=lambda k: (
            round(float(times[k]) / max(ocp.horizon, 1e-300), 11),
            ocp.guard_index(names[k]),
        ),
    )
    return [names[k] for k in order]


def _compare(
    res: ReferenceResult, rtol: float
) -> tuple[bool, Evaluation | None, str, float | None, bool]:
    """The judge's re-simulation of ``u(t)`` against the extremal: ``(ok, evaluation,
    message, relative cost difference, same guards)``; the difference is ``None`` where the
    events differ (then the costs are not comparable); ``same guards``: the same events in
    the same order, their times perhaps not (an integration error can move them)."""
    from hybridoc.callable_eval import evaluate_callable

    u, bps = reference_control(res)
    ocp = res.ocp
    try:
        sim = evaluate_callable(ocp, u, breakpoints=bps, event_controls=res.event_controls)
    except HybridocError as exc:
        return False, None, f"re-simulation failed: {exc}", None, False
    times = np.array([e.time for e in sim.events])
    # events at one instant (commuting jumps) are reported in guard order: compare them so
    names = _canonical(ocp, sim.sequence, times)
    if names != _canonical(ocp, res.sequence, res.event_times):
        msg = f"re-simulation gives events {names}, modelled {res.sequence}"
        return False, sim, msg, None, False
    if times.size and np.max(np.abs(times - res.event_times)) > 1e-7 * ocp.horizon:
        return False, sim, "re-simulated event times differ from the modelled ones", None, True
    # a cost that is zero to rounding (a ball left to bounce to its target: 5e-31 shot, 1e-28
    # judged) has no relative accuracy: below COST_FLOOR the costs are compared absolutely
    rel = abs(sim.cost - res.cost) / max(abs(res.cost), COST_FLOOR)
    viol = judged_violation(ocp, sim)
    if viol > TERMINAL_TOL:
        # the integration moved s(T): refined like a cost disagreement (judged_reference)
        msg = (
            f"the judge's re-simulation violates the terminal constraints by {viol:.2e} "
            f"(> {TERMINAL_TOL:g})"
        )
        return False, sim, msg, rel, True
    return rel <= rtol, sim, "", rel, True


def judged_violation(ocp: HybridOCP, sim: Evaluation) -> float:
    """The terminal constraints' violation at the judge's final state (0 without them)."""
    if not ocp.has_terminal_constraints:
        return 0.0
    judged = getattr(sim, "terminal_violation", None)
    if judged is not None:
        return float(judged)
    return float(ocp.terminal_violation(sim.final_state))


def _disagreement(res: ReferenceResult, sim: Evaluation, rel: float, rtol: float) -> str:
    steps = "" if res.levels is None else (
        f" with {max(res.levels)} DOP853 steps on its longest-resolved phase (estimated "
        f"integration error {res.integration_error:.1e})"
    )  # fmt: skip
    viol = judged_violation(res.ocp, sim)
    if rel <= rtol and viol > TERMINAL_TOL:
        return (
            f"reference for {res.sequence}: the judge's re-simulation of u(t) violates the "
            f"terminal constraints by {viol:.2e} (> {TERMINAL_TOL:g}){steps}"
        )
    return (
        f"reference for {res.sequence}: shooting cost {_J(res.cost):.12g} but the judge gives "
        f"{_J(sim.cost):.12g} for the same u(t) (relative {rel:.2e} > rtol = {rtol:g}){steps}"
    )


def verify_reference(
    res: ReferenceResult, rtol: float = COST_RTOL
) -> tuple[bool, Evaluation | None, str]:
    """Re-simulate the extremal's control ``u(t)`` with the judge.

    Parameters
    ----------
    res
        The extremal.
    rtol
        The relative agreement of the costs required.

    Returns
    -------
    ok, evaluation, message
        ``ok`` when the re-simulated events are exactly the modelled ones (same guards, same
        order, times within 1e-7 T) and the cost agrees to ``rtol``. Equal events with a
        different cost raise :class:`~hybridoc.errors.ConvergenceError` that names
        ``rtol`` (:func:`judged_reference` refines the integration first).
    """
    ok, sim, msg, rel, _ = _compare(res, rtol)
    if rel is not None and not ok:
        assert sim is not None
        raise ConvergenceError(_disagreement(res, sim, rel, rtol))
    return ok, sim, msg


def judged_reference(
    res: ReferenceResult, *, rtol: float = COST_RTOL, tol: float = 1e-10, verbose: bool = False
) -> tuple[ReferenceResult, bool, Evaluation | None, str]:
    """:func:`verify_reference`, refining the integration where only the costs disagree.

    A generic problem's extremal whose re-simulated events are its own but whose cost (or
    event times) differ from the judge's by more than ``rtol`` (``1e-7 T``) is refined again
    (:func:`~hybridoc.reference.shooting.refine`) to a target 100 times tighter, at most
    :data:`JUDGE_RETRIES` times; a disagreement that remains raises
    :class:`~hybridoc.errors.ConvergenceError` naming ``rtol``.

    Returns
    -------
    result, ok, evaluation, message
        The (possibly refined) extremal and :func:`verify_reference`'s outcome for it.
    """
    target = rtol
    for attempt in range(JUDGE_RETRIES + 1):
        ok, sim, msg, rel, same = _compare(res, rtol)
        if sim is not None:
            res.judged_terminal_violation = judged_violation(res.ocp, sim)
        if ok:
            res.judged = sim  # the judge's cost of the Solution (ReferenceResult.to_solution)
        if ok or not same or res.system.disc:
            if rel is not None and not ok:  # a disc scene's costs disagree: a real error
                assert sim is not None
                raise ConvergenceError(_disagreement(res, sim, rel, rtol))
            return res, ok, sim, msg
        assert sim is not None
        if attempt == JUDGE_RETRIES:
            if rel is None:
                return res, ok, sim, msg  # the event times still differ: not verified
            break
        target *= 1e-2
        if verbose:
            what = "event times differ" if rel is None else f"cost differs by {rel:.1e} relative"
            print(
                f"  judge {res.sequence}: {what} (rtol {rtol:g}): refining the integration "
                f"to {target:.0e}",
                file=sys.stderr,
            )
        nr = NewtonResult(res.z, res.residual, res.newton_iterations, True, res.residual_history)
        ref = refine(res.system, nr, rtol=target, tol=tol, verbose=verbose)
        if not ref.ok:
            if rel is None:
                return res, ok, sim, f"{msg}; {ref.reason}"
            raise ConvergenceError(_disagreement(res, sim, rel, rtol) + f"; {ref.reason}")
        res = make_result(ref.system, ref.newton, res.path, ref.error)
    assert sim is not None and rel is not None
    raise ConvergenceError(_disagreement(res, sim, rel, rtol))
