"""Initial guesses: the guess's controls and events, the candidate sequences they propose, and
the NLP's starting point read from the guess's simulated trajectory.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from hybridoc.errors import HybridocError, SimultaneousEventError
from hybridoc.evaluation import Evaluation
from hybridoc.evaluator import evaluate
from hybridoc.ocp import HybridOCP
from hybridoc.solvers.transcription.nlp import PhaseNLP

__all__ = [
    "admissible_candidates",
    "candidate_sequences",
    "evaluate_guess",
    "initial_controls",
    "initial_point",
]


_GUESS_PERTURBATIONS = 3  # perturbed retries of a guess with simultaneous events


def _match_events(ev: Evaluation, guards: Sequence[int], T: float) -> list[tuple[float, Any]]:
    """Event times (and the matched Event or None) for each guard of the sequence."""
    matched: list[tuple[float, Any]] = []
    start = 0
    for g in guards:
        hit = None
        for i in range(start, len(ev.events)):
            if ev.events[i].guard == g:
                hit = i
                break
        if hit is None:
            matched.append((np.nan, None))
        else:
            matched.append((ev.events[hit].time, ev.events[hit]))
            start = hit + 1
    # unmatched events: spread evenly between their matched neighbours
    times = np.array([m[0] for m in matched] + [T])
    prev_t = 0.0
    i = 0
    while i < len(matched):
        if np.isnan(times[i]):
            j = i
            while np.isnan(times[j]):
                j += 1
            nxt = times[j]
            for q in range(i, j):
                times[q] = prev_t + (nxt - prev_t) * (q - i + 1) / (j - i + 1)
                matched[q] = (times[q], None)
            i = j
        else:
            prev_t = times[i]
            i += 1
    # keep the phases ordered and non-degenerate
    out = []
    floor = 0.0
    K = len(matched)
    for q, (t, e) in enumerate(matched):
        t = min(max(t, floor + 1e-3 * T), T - 1e-3 * T * (K - q))
        out.append((t, e))
        floor = t
    return out


def initial_point(
    nlp: PhaseNLP, ev: Evaluation, controls: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    ocp = nlp.ocp
    T = ocp.horizon
    matched = _match_events(ev, nlp.guards, T)
    bounds = np.array([0.0] + [m[0] for m in matched] + [T])
    h = np.diff(bounds)
    times = nlp.node_times(h)
    N = ocp.steps
    X, U = [], []
    for k in range(nlp.P):
        Xk = ev.sample(times[k]).T
        if k > 0 and matched[k - 1][1] is not None:
            Xk[:, 0] = matched[k - 1][1].state_after
        if k < nlp.P - 1 and matched[k][1] is not None:
            Xk[:, -1] = matched[k][1].state_before
        X.append(Xk)
        idx = np.clip((times[k][1:] / T * N).astype(int), 0, N - 1)
        U.append(nlp.clip_controls(np.asarray(controls, dtype=float)[idx].T))
    V = None
    if nlp.reset_events:
        # each reset's control: the guess's control in the cell of its event
        cells = [int(np.clip(bounds[k + 1] / T * N, 0, N - 1)) for k in nlp.reset_events]
        V = nlp.clip_controls(np.asarray(controls, dtype=float)[cells].T)
    return nlp.pack(h, X, U, V), h


def _sequence_of_events(ocp: HybridOCP, events: Sequence[Any]) -> list[str]:
    """Guard names of events given as :class:`Event` objects or ``{"bodies": ...}`` dicts."""
    out = []
    for e in events:
        if hasattr(e, "guard"):
            out.append(ocp.guards[e.guard].name)
            continue
        bodies = tuple(e["bodies"])
        hits = [g.name for g in ocp.guards if tuple(g.bodies) == bodies]
        if not hits:
            hits = [g.name for g in ocp.guards if g.name == "|".join(bodies)]
        if not hits:
            raise HybridocError(f"event with bodies {list(bodies)} matches no guard")
        out.append(hits[0])
    return out


def initial_controls(ocp: HybridOCP, initial: Any) -> tuple[np.ndarray, list[str] | None]:
    """Controls (N, nu) and, when ``initial`` is a solution, its event sequence."""
    if initial is None:
        return np.asarray(ocp.u_guess, dtype=float), None
    controls = getattr(initial, "controls", None)
    if controls is not None and hasattr(initial, "events"):  # a Solution or an Evaluation
        u = ocp.check_controls(controls, what="initial controls")
        info = getattr(initial, "info", {}) or {}
        seq = info.get("sequence")
        if seq is None:
            seq = _sequence_of_events(ocp, initial.events)
        return u, list(seq)
    return ocp.check_controls(initial, what="initial controls"), None


def candidate_sequences(observed: list[str]) -> list[list[str]]:
    """The observed sequence and every sequence with one of its events dropped."""
    out = [list(observed)]
    for i in range(len(observed)):
        cand = observed[:i] + observed[i + 1 :]
        if cand not in out:
            out.append(cand)
    return out


def admissible_candidates(
    ocp: HybridOCP, cands: list[list[str]]
) -> tuple[list[list[str]], list[dict[str, Any]]]:
    """The candidates worth an NLP, and a record of those that are not: the observed
    sequence (the first) always, the others only where the modes admit them
    (:meth:`~hybridoc.HybridOCP.sequence_admissible`). On a problem with modes, dropping one
    event mostly leaves a sequence that fires a transition outside its source mode (the
    hopper's ``[touchdown, touchdown, liftoff]``): its NLP has no feasible point, and IPOPT
    took 30 to 40 iterations to say so (three of the hopper's five NLPs)."""
    if ocp.modes is None:
        return cands, []
    keep, skipped = cands[:1], []
    for cand in cands[1:]:
        if ocp.sequence_admissible(cand):
            keep.append(cand)
        else:
            skipped.append(
                {"sequence": cand, "nlp_cost": None,
                 "status": "not solved: the modes do not admit this sequence"}
            )  # fmt: skip
    return keep, skipped


def evaluate_guess(ocp: HybridOCP, u0: np.ndarray) -> tuple[Evaluation, np.ndarray, float]:
    """The judge's evaluation of the guess, its controls and the perturbation used.

    A guess whose events fire at the same instant without an order (a symmetric scene, a
    :class:`~hybridoc.errors.SimultaneousEventError`) is retried with the controls perturbed
    by ``1e-6 max(1, |u|) k z`` (``z`` one fixed-seed normal sample, ``k = 1, 2, 3``), so
    that the contacts happen one after the other and propose an event sequence.
    """
    try:
        return evaluate(ocp, u0), u0, 0.0
    except SimultaneousEventError as exc:
        first = exc
    z = np.random.default_rng(20240601).standard_normal(u0.shape)
    # in the controls' units: 1e-6 sigma_u max(1, |u / sigma_u|)
    su = ocp.scales.control_array
    scale = 1e-6 * max(1.0, float(np.abs(u0 / su).max(initial=0.0)))
    for k in range(1, _GUESS_PERTURBATIONS + 1):
        u = np.clip(u0 + scale * k * z * su, ocp.u_min, ocp.u_max)
        try:
            return evaluate(ocp, u), u, scale * k * float(np.max(su))  # in u's units
        except SimultaneousEventError:
            continue
    raise SimultaneousEventError(
        f"{first} (also with the initial guess perturbed by up to "
        f"{scale * _GUESS_PERTURBATIONS * float(np.max(su)):.1e}); give another initial guess "
        "or a sequence",
        guards=first.guards,
        time=first.time,
    ) from None
