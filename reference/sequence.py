"""One event sequence: the HMP extremal from every available start, and its verification.

:func:`solve_sequence` tries, in order, until Newton converges (and keeps the cheapest point
found): the adjoint costate of a given control (its linear-in-time fit per phase for disc
scenes, the judge's adjoint otherwise), the disc scenes' NLP in event times and linear
phase controls, and the direct transcription with the sequence fixed, whose multipliers give
the costates. :func:`verify_reference` re-simulates the extremal's control with the judge.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from hybridoc.errors import ConvergenceError, EvaluationError, HybridocError
from hybridoc.evaluation import Evaluation
from hybridoc.ocp import HybridOCP
from hybridoc.reference.result import ReferenceResult, make_result, reference_control
from hybridoc.reference.shooting import ShootingSystem, newton, shooting_system

__all__ = ["COST_RTOL", "solve_sequence", "verify_reference", "z_from_transcription"]

COST_RTOL = 1e-9
#: Constraint violation above which the search drops a sequence whose NLP failed.
SCREEN_INFEASIBILITY = 1e-3
"""Relative agreement of the shooting cost and the judge's cost of the same control."""


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


def z_from_transcription(S: ShootingSystem, r: Any) -> np.ndarray:
    """Newton start from a direct transcription of the same sequence (its multipliers)."""
    nlp = r._nlp
    _, X, _ = nlp.unpack(r._w)
    cs = r.costates
    # the costates come in one block per phase: its start (the link multiplier), then the
    # M d Radau points, the last of which is the phase's end
    lam_start, lam_end = [], []
    i = 0
    for k in range(nlp.P):
        lam_start.append(cs[i])
        i += nlp.mesh[k] * nlp.d
        lam_end.append(cs[i])
        i += 1
    gam = r.event_times
    pis = [_pi_from_jump(S, k, X[k][:, -1], lam_end[k], lam_start[k + 1]) for k in range(S.K)]
    return S.pack(lam_start[0], gam, pis, lam_start[1:])


def solve_sequence(
    ocp: HybridOCP,
    sequence: Sequence[str],
    gamma0: np.ndarray,
    u_guess: np.ndarray,
    *,
    estimate: bool = False,
    grad: Any = None,
    guess_ev: Evaluation | None = None,
    transcription: bool = True,
    tol: float = 1e-10,
    verbose: bool = False,
    screen: bool = False,
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
    transcription
        Fall back on the direct transcription with the sequence fixed.
    screen
        For the search over many sequences (disc scenes): where IPOPT stops at a point that
        violates the sequence's guard conditions (by more than 1e-3), give the sequence up
        without Newton, and give Newton fewer, shorter tries; most enumerated sequences are
        not realisable, and an extremal's Newton from the NLP takes two or three steps.
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
            found.append(make_result(S, nr, path))
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
    if S.disc:
        # also after a converged estimate: from a poor guess Newton can land on a worse
        # stationary point of the same sequence, while the NLP minimises over it
        coeffs = fit_coeffs(ocp, u_guess, gamma0)
        z0, ok, infeasibility = S.solve_nlp(gamma0, coeffs, max_iter=40 if screen else 100)
        if screen and not ok and infeasibility > SCREEN_INFEASIBILITY:
            reasons.append(
                f"the NLP found no point with these events (violation {infeasibility:.1e})"
            )
        else:
            attempt(z0, "nlp")
    if not found and transcription and guess_ev is not None:
        from hybridoc.solvers.transcription import solve_dt_sequence

        try:
            r = solve_dt_sequence(ocp, list(sequence), guess=guess_ev, guess_controls=u_guess)
        except (ConvergenceError, EvaluationError, ValueError) as exc:
            reasons.append(f"transcription: {exc}")
        else:
            attempt(z_from_transcription(S, r), "transcription")
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


def verify_reference(res: ReferenceResult) -> tuple[bool, Evaluation | None, str]:
    """Re-simulate the extremal's control ``u(t)`` with the judge.

    Returns
    -------
    ok, evaluation, message
        ``ok`` when the re-simulated events are exactly the modelled ones (same guards, same
        order, times within 1e-7 T) and the cost agrees to :data:`COST_RTOL`. Equal events
        with a different cost raise :class:`~hybridoc.errors.ConvergenceError` (an internal
        inconsistency).
    """
    from hybridoc.callable_eval import evaluate_callable

    u, bps = reference_control(res)
    ocp = res.ocp
    try:
        sim = evaluate_callable(ocp, u, breakpoints=bps)
    except HybridocError as exc:
        return False, None, f"re-simulation failed: {exc}"
    times = np.array([e.time for e in sim.events])
    # events at one instant (commuting jumps) are reported in guard order: compare them so
    names = _canonical(ocp, sim.sequence, times)
    if names != _canonical(ocp, res.sequence, res.event_times):
        return False, sim, f"re-simulation gives events {names}, modelled {res.sequence}"
    if times.size and np.max(np.abs(times - res.event_times)) > 1e-7 * ocp.horizon:
        return False, sim, "re-simulated event times differ from the modelled ones"
    rel = abs(sim.cost - res.cost) / max(abs(res.cost), 1e-300)
    if rel > COST_RTOL:
        raise ConvergenceError(
            f"reference for {res.sequence}: shooting cost {res.cost:.12g} but the judge "
            f"gives {sim.cost:.12g} for the same u(t) (relative {rel:.2e} > {COST_RTOL:g})"
        )
    return True, sim, ""
