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

from hybridoc.errors import ConvergenceError, EvaluationError, HybridocError
from hybridoc.evaluation import Evaluation
from hybridoc.ocp import HybridOCP
from hybridoc.reference.result import ReferenceResult, make_result, reference_control
from hybridoc.reference.shooting import (
    DEFAULT_RTOL,
    NewtonResult,
    ShootingSystem,
    newton,
    refine,
    shooting_system,
)
from hybridoc.reference.sources import PhaseCostates, SequenceStarter

__all__ = [
    "COST_RTOL",
    "JUDGE_RETRIES",
    "SCREEN_NLP_ITER",
    "check_rtol",
    "judged_reference",
    "solve_sequence",
    "verify_reference",
    "z_from_costates",
]

COST_RTOL = DEFAULT_RTOL
"""The default relative agreement of the shooting cost and the judge's cost of the same
control (``rtol``)."""
#: Constraint violation above which the search drops a sequence whose NLP failed.
SCREEN_INFEASIBILITY = 1e-3
#: IPOPT iterations of a disc scene's NLP when the search screens many sequences.
SCREEN_NLP_ITER = 40
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
    S: ShootingSystem, k: int, s_minus: np.ndarray, lm: np.ndarray, lp: np.ndarray
) -> float:
    _, gpsi, _, Dg = (np.asarray(x) for x in S.guard_fns[k](s_minus))
    gpsi = gpsi.ravel()
    r = lm - Dg.T @ lp
    return float(gpsi @ r / max(float(gpsi @ gpsi), 1e-300))


def z_from_gradient(S: ShootingSystem, grad: Any, gamma: np.ndarray) -> np.ndarray:
    """Newton start from the judge's adjoint costate of a control with these events."""
    ct, cs = np.asarray(grad.costate_times), np.asarray(grad.costates)
    lps, pis = [], []
    for k, g in enumerate(gamma):
        i_after = int(np.searchsorted(ct, g, side="right")) - 1
        i_after = min(max(i_after, 0), ct.size - 1)
        lp = cs[i_after]
        lm = cs[max(i_after - 1, 0)]
        s_m = grad.evaluation.sample([g])[0]
        pis.append(_pi_from_jump(S, k, s_m, lm, lp))
        lps.append(lp)
    return S.pack(np.asarray(grad.d_initial_state), gamma, pis, lps)


def z_from_costates(S: ShootingSystem, w: PhaseCostates) -> np.ndarray:
    """Newton start from costates per phase (a transcription's multipliers): the costate
    jumps follow from the costates on both sides of each event."""
    pis = [
        _pi_from_jump(S, k, np.asarray(w.state_end[k]), w.costate_end[k], w.costate_start[k + 1])
        for k in range(S.K)
    ]
    return S.pack(w.costate_start[0], np.asarray(w.event_times), pis, list(w.costate_start[1:]))


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
    reasons: list[str] = []
    found: list[ReferenceResult] = []

    def attempt(z0: np.ndarray, path: str) -> None:
        if screen:
            nr = newton(S, z0, tol=tol, verbose=verbose, max_iter=20, min_step=1e-3)
        else:
            nr = newton(S, z0, tol=tol, verbose=verbose)
        if nr.converged:
            ref = refine(S, nr, rtol=rtol, tol=tol, verbose=verbose)
            if ref.ok:
                found.append(make_result(ref.system, ref.newton, path, ref.error))
            else:
                reasons.append(f"from the {path}: {ref.reason}")
        elif nr.residual <= tol:
            times = ", ".join(f"{float(g):.6g}" for g in S.unpack(nr.z)[1])
            reasons.append(
                f"Newton from the {path} found a root with event times [{times}], not in "
                f"order inside (0, T = {S.T:g})"
            )
        else:
            reasons.append(f"Newton from the {path}: residual {nr.residual:.2e}")

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
        return best, ""
    return None, "; ".join(reasons) or "no start for Newton"


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
        sim = evaluate_callable(ocp, u, breakpoints=bps)
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
    rel = abs(sim.cost - res.cost) / max(abs(res.cost), 1e-300)
    return rel <= rtol, sim, "", rel, True


def _disagreement(res: ReferenceResult, sim: Evaluation, rel: float, rtol: float) -> str:
    steps = "" if res.levels is None else (
        f" with {max(res.levels)} DOP853 steps on its longest-resolved phase (estimated "
        f"integration error {res.integration_error:.1e})"
    )  # fmt: skip
    return (
        f"reference for {res.sequence}: shooting cost {res.cost:.12g} but the judge gives "
        f"{sim.cost:.12g} for the same u(t) (relative {rel:.2e} > rtol = {rtol:g}){steps}"
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
