"""Where the reference's candidate event sequences come from.

* :func:`guess_candidates`: the events of a simulated control (the initial guess, a
  transcription, a multi-start of the simulator), every sequence with one of them dropped,
  and the sequence with one near-touch (a local minimum of a guard that did not fire) added.
* :func:`enumerate_sequences`: every feasible sequence of up to ``K`` events (``--search``),
  pruned by geometry (disc scenes: a passive disc at rest takes part in no event before
  something has struck it; a passive disc cannot meet the same passive partner twice in a
  row, nor a wall twice in a row, since it moves in a straight line in between) and
  ordered by length, with a lower bound (:func:`lower_bound`) that lets the search skip
  sequences that cannot beat the best extremal found.
* :func:`guess_times`: event-time guesses for any sequence from a simulated trajectory.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np

from hybridoc.evaluation import Evaluation
from hybridoc.ocp import HybridOCP
from hybridoc.problems.disc_ocp import DiscOCP

__all__ = ["enumerate_sequences", "guess_candidates", "guess_times", "lower_bound"]


def _event_list(ev: Evaluation) -> list[tuple[str, float]]:
    return [(e.name, float(e.time)) for e in ev.events]


def _near_touches(ocp: HybridOCP, ev: Evaluation, limit: int = 2) -> list[tuple[str, float]]:
    """Local minima of guards without an event, closest first (at most ``limit``)."""
    if not ocp.guards:
        return []
    # disc scenes: within the largest radius; other problems: a tenth of the guard's range
    thresh = max(d.radius for d in ocp.scene.discs) if isinstance(ocp, DiscOCP) else None
    t, X = ev.times, ev.states
    fired = {(e.name, round(e.time, 3)) for e in ev.events}
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


def guess_candidates(ocp: HybridOCP, ev: Evaluation) -> list[list[tuple[str, float]]]:
    """Candidate sequences (with event-time guesses) around a simulated control."""
    obs = _event_list(ev)
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


def guess_times(ocp: HybridOCP, sequence: Sequence[str], ev: Evaluation | None) -> np.ndarray:
    """Event-time guesses for a sequence: the matching events of a simulated trajectory,
    else where the guard comes closest, else evenly spread."""
    T = ocp.horizon
    K = len(sequence)
    if ev is None:
        return T * np.arange(1, K + 1) / (K + 1)
    obs = _event_list(ev)
    out: list[float] = []
    prev = 0.0
    for name in sequence:
        match = [tt for n, tt in obs if n == name and tt > prev]
        if match:
            tt = match[0]
        else:
            g = ocp.guards[ocp.guard_index(name)]
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


def _disc_layout(ocp: HybridOCP) -> dict[str, Any] | None:
    if not isinstance(ocp, DiscOCP):
        return None
    scene = ocp.scene
    moving = {d.name for d in scene.discs if d.actuated or any(d.velocity)}
    passive = {d.name for d in scene.discs if not d.actuated}
    walls = {w.name for w in scene.walls}
    return {"scene": scene, "moving": moving, "passive": passive, "walls": walls}


def _feasible(seq: Sequence[str], ocp: HybridOCP, layout: dict[str, Any] | None) -> bool:
    """Geometric pruning (module notes); generic problems: everything is feasible."""
    if layout is None:
        return True
    moving = set(layout["moving"])
    passive = layout["passive"]
    bodies = {g.name: g.bodies for g in ocp.guards}
    for k, name in enumerate(seq):
        b = bodies[name]
        if not any(x in moving for x in b):
            return False  # nothing involved is moving yet
        if k > 0 and seq[k - 1] == name and all(x in passive or x in layout["walls"] for x in b):
            return False  # two passive bodies (or one and a wall) cannot meet twice in a row
        moving |= {x for x in b if x not in layout["walls"]}
    return True


def lower_bound(ocp: HybridOCP, sequence: Sequence[str]) -> float:
    """A lower bound of the cost of any control with this event sequence.

    Disc scenes: a passive disc that takes part in no event moves in a straight line, so its
    share of the terminal cost is known exactly; the running cost is non-negative. Other
    problems: 0 (no bound).
    """
    layout = _disc_layout(ocp)
    if layout is None:
        return 0.0
    scene = layout["scene"]
    involved = {x for name in sequence for x in ocp.guards[ocp.guard_index(name)].bodies}
    bound = 0.0
    for d in scene.discs:
        if d.actuated or d.name in involved or d.target is None:
            continue
        p_T = np.asarray(d.position) + ocp.horizon * np.asarray(d.velocity)
        bound += float(np.sum((p_T - np.asarray(d.target)) ** 2))
    return bound


def enumerate_sequences(ocp: HybridOCP, max_events: int) -> Iterator[list[str]]:
    """Every geometrically feasible sequence of up to ``max_events`` events, shortest first."""
    names = [g.name for g in ocp.guards]
    layout = _disc_layout(ocp)
    level: list[list[str]] = [[]]
    yield []
    for _ in range(max_events):
        nxt = []
        for seq in level:
            for name in names:
                cand = seq + [name]
                if _feasible(cand, ocp, layout):
                    nxt.append(cand)
                    yield cand
        level = nxt
