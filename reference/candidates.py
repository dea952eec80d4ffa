"""Where the reference's candidate event sequences come from.

* :func:`guess_candidates`: the events of a simulated control (the initial guess, a
  transcription, a multi-start of the simulator), every sequence with one of them dropped,
  and the sequence with one near-touch (a local minimum of a guard that did not fire) added;
  on a problem with modes only those whose every guard fires in its source mode.
* :func:`enumerate_sequences`: every feasible sequence of up to ``K`` events (``--search``):
  on a problem with modes the mode sequences (each guard fires in its source mode),
  pruned by geometry (disc scenes: a passive disc at rest takes part in no event before
  something has struck it; a passive disc cannot meet the same passive partner twice in a
  row, nor a wall twice in a row, since it moves in a straight line in between) and
  ordered by length, with a lower bound (:func:`lower_bound`) that lets the search skip
  sequences that cannot beat the best extremal found.
* :func:`guess_times`: event-time guesses for any sequence from a simulated trajectory.
* :func:`default_depth`: how long the sequences are that the default reference enumerates.

The reachability bound (:func:`reach_bound`, disc scenes)
    An actuated disc of mass ``m`` under forces ``u`` leaves its ballistic path by
    ``dp(t) = int_0^t (t - s) u(s) / m ds``; by Cauchy-Schwarz ``|dp(t)|^2 <= t^3 / (3 m^2)
    int_0^t |u|^2 ds``, so moving it by ``d`` by the time ``t`` costs at least
    ``eps 3 m^2 d^2 / t^3`` of running cost. An event whose two bodies took part in no
    earlier event of the sequence (a *fresh* event: the sequence's first, and any later one
    between untouched bodies) happens at some ``t`` in ``(0, T]`` where the bodies, on their
    ballistic paths, are ``g(t)`` apart (centre distance less radii, or distance to the
    wall less the radius); the control must close ``d(t) = max(0, g(t))``. Two actuated
    discs share it (``|dp_a - dp_b| >= d`` costs at least ``eps 3 d^2 / t^3 / (1/m_a^2 +
    1/m_b^2)``); a passive disc or a wall contributes no deviation. So the event costs at
    least ``eps 3 M min_t d(t)^2 / t^3``, with the minimum taken safely over a grid of
    intervals (``d``'s exact minimum on each, divided by the interval's end cubed). Fresh
    events involve disjoint discs, so their bounds add; so does the terminal cost of a
    passive disc that takes part in no event (it moves in a straight line), which is the
    terminal part of the cost. A fresh event between two bodies that cannot move
    themselves (passive discs, walls) and never touch on their ballistic paths cannot
    happen at all: the sequence is infeasible.
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Iterator, Sequence
from typing import Any, NamedTuple

import numpy as np

from hybridoc.evaluation import Evaluation
from hybridoc.ocp import HybridOCP

__all__ = [
    "DEPTH_SEQUENCES",
    "MAX_DEFAULT_DEPTH",
    "default_depth",
    "enumerate_sequences",
    "guess_candidates",
    "guess_times",
    "lower_bound",
    "reach_bound",
]

MAX_DEFAULT_DEPTH = 3
"""The longest sequences the default reference enumerates (:func:`default_depth`)."""
DEPTH_SEQUENCES = 16
"""At most this many feasible sequences of one to ``K`` events for the default to enumerate
up to ``K`` events (:func:`default_depth`)."""
_GRID = 2000  # intervals of (0, T] over which the reachability bound is minimised


def _event_list(ev: Evaluation) -> list[tuple[str, float]]:
    return [(e.name, float(e.time)) for e in ev.events]


def _near_touches(ocp: HybridOCP, ev: Evaluation, limit: int = 2) -> list[tuple[str, float]]:
    """Local minima of guards without an event, closest first (at most ``limit``)."""
    if not ocp.guards:
        return []
    # round bodies (disc scenes): within the largest radius; other problems: a tenth of the
    # guard's range
    geometry = ocp.capabilities.geometry
    thresh = max(b.radius for b in geometry.bodies) if geometry is not None else None
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
        if key not in seen and ocp.sequence_admissible(list(key)):
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
            m = (ev.times > prev) & (ev.times < T)
            if m.any():
                psi = _psi_along(ocp, ev, ocp.guard_index(name))[m]
                tt = float(ev.times[m][int(np.argmin(psi))])
            else:
                tt = 0.5 * (prev + T)
        tt = min(max(tt, prev + 1e-3 * T), T * (1 - 1e-3))
        out.append(tt)
        prev = tt
    return np.array(out)


# per trajectory (by id, with a weak reference that tells a reused id), per guard: psi at
# each of its states (a search guesses the times of a hundred sequences from one trajectory)
_PSI: dict[int, tuple[Any, dict[Any, Any]]] = {}


def _psi_along(ocp: HybridOCP, ev: Evaluation, j: int) -> np.ndarray:
    """Guard ``j``'s ``psi`` at every state of ``ev``, computed once per (trajectory, guard):
    column by column, the values a map over any subset of the states gives."""
    entry = _PSI.get(id(ev))
    if entry is None or entry[0]() is not ev:
        for key in [k for k, (ref, _) in _PSI.items() if ref() is None]:
            _PSI.pop(key, None)
        entry = _PSI[id(ev)] = (weakref.ref(ev), {})
    psi_fn = ocp.guards[j].psi
    key = (j, id(psi_fn))
    hit = entry[1].get(key)
    if hit is None:
        values = np.asarray(psi_fn.map(ev.states.shape[0])(ev.states.T), dtype=float).ravel()
        hit = entry[1][key] = (psi_fn, values)  # psi_fn kept alive: its id stays its own
    return hit[1]


class _Disc(NamedTuple):
    """A round body of the problem's geometry at its initial state."""

    name: str
    position: np.ndarray
    velocity: np.ndarray
    radius: float
    mass: float
    actuated: bool
    target: tuple[float, float] | None


def _disc_layout(ocp: HybridOCP) -> dict[str, Any] | None:
    """What the geometric screens and bounds read of a problem of round bodies and planes
    with the closed-form flow ``f = (v, A u)``, ``L = eps |u|^2`` (its
    :class:`~hybridoc.capabilities.Geometry` and
    :class:`~hybridoc.capabilities.LinearControlFlow`, a disc scene's); ``None`` for any
    other problem."""
    caps = ocp.capabilities
    geometry, flow = caps.geometry, caps.flow
    if geometry is None or flow is None:
        return None
    x0 = np.asarray(ocp.x0, dtype=float)
    discs = [
        _Disc(
            b.name,
            geometry.position(x0, i),
            geometry.velocity(x0, i),
            b.radius,
            b.mass,
            b.actuated,
            b.target,
        )
        for i, b in enumerate(geometry.bodies)
    ]
    moving = {d.name for d in discs if d.actuated or bool(np.any(d.velocity))}
    passive = {d.name for d in discs if not d.actuated}
    walls = {w.name for w in geometry.planes}
    return {
        "moving": moving,
        "passive": passive,
        "walls": walls,
        "discs": {d.name: d for d in discs},
        "wall_of": {w.name: w for w in geometry.planes},
        "eps": float(flow.eps),
        "T": float(ocp.horizon),
        "bodies": {g.name: tuple(g.bodies) for g in ocp.guards},
        "memo": {},
    }


def _feasible(seq: Sequence[str], ocp: HybridOCP, layout: dict[str, Any] | None) -> bool:
    """Geometric pruning (module notes); problems with modes: each guard fires in its source
    mode (:meth:`~hybridoc.HybridOCP.sequence_feasible`); other generic problems: everything
    is feasible."""
    if layout is None:
        return ocp.sequence_feasible(list(seq))
    moving = set(layout["moving"])
    passive = layout["passive"]
    walls = layout["walls"]
    bodies = layout["bodies"]
    involved: set[str] = set()
    for k, name in enumerate(seq):
        b = bodies[name]
        if not any(x in moving for x in b):
            return False  # nothing involved is moving yet
        if k > 0 and seq[k - 1] == name and all(x in passive or x in walls for x in b):
            return False  # two passive bodies (or one and a wall) cannot meet twice in a row
        if not involved.intersection(b) and all(x in passive or x in walls for x in b):
            if math.isinf(_fresh_bound(name, layout)):
                return False  # untouched passive bodies that never meet on their own
        moving |= {x for x in b if x not in walls}
        involved |= set(b)
    return True


def _gap_minima(name: str, layout: dict[str, Any]) -> np.ndarray:
    """The smallest ballistic gap of the guard's two bodies on each interval of the grid
    ``T i / n`` (exact on each: the relative motion is a straight line)."""
    scene_discs, wall_of = layout["discs"], layout["wall_of"]
    a, b = layout["bodies"][name]
    da = scene_discs[a]
    t = np.linspace(0.0, layout["T"], _GRID + 1)
    ta, tb = t[:-1], t[1:]
    if b in wall_of:
        w = wall_of[b]
        n = np.asarray(w.normal, dtype=float)
        g0 = float(n @ (np.asarray(da.position) - np.asarray(w.point))) - da.radius
        gv = float(n @ np.asarray(da.velocity))
        return np.minimum(g0 + gv * ta, g0 + gv * tb)
    db = scene_discs[b]
    r0 = np.asarray(da.position, dtype=float) - np.asarray(db.position, dtype=float)
    v = np.asarray(da.velocity, dtype=float) - np.asarray(db.velocity, dtype=float)
    vv = float(v @ v)
    s = np.clip(-float(r0 @ v) / vv, ta, tb) if vv > 0 else ta
    closest = r0[None, :] + s[:, None] * v[None, :]
    return np.sqrt(np.sum(closest**2, axis=1)) - (da.radius + db.radius)


def _fresh_bound(name: str, layout: dict[str, Any]) -> float:
    """The least running cost of a fresh event of guard ``name`` (module notes); ``inf``
    when its bodies cannot move themselves and never touch within the horizon."""
    memo = layout["memo"]
    if name in memo:
        return memo[name]
    discs = layout["discs"]
    inv = sum(1.0 / discs[x].mass ** 2 for x in layout["bodies"][name] if x in discs and
              discs[x].actuated)  # fmt: skip
    gaps = _gap_minima(name, layout)
    d = np.maximum(gaps, 0.0)
    if inv == 0.0:
        # nothing can leave its path: the event happens only where the gap closes itself
        value = 0.0 if float(np.min(gaps)) <= 1e-12 else math.inf
    else:
        tb = np.linspace(0.0, layout["T"], _GRID + 1)[1:]
        value = float(np.min(3.0 * layout["eps"] / inv * d**2 / tb**3))
    memo[name] = value
    return value


def reach_bound(ocp: HybridOCP, sequence: Sequence[str]) -> float:
    """A lower bound of the running cost of any control with this event sequence: the sum
    of the reachability bounds of its fresh events (module notes); ``inf`` when a fresh
    event cannot happen. Generic problems: 0."""
    layout = _disc_layout(ocp)
    if layout is None:
        return 0.0
    return _reach(sequence, layout)


def _reach(sequence: Sequence[str], layout: dict[str, Any]) -> float:
    involved: set[str] = set()
    total = 0.0
    for name in sequence:
        b = layout["bodies"][name]
        if not involved.intersection(b):
            total += _fresh_bound(name, layout)
        involved |= set(b)
    return total


def _terminal(sequence: Sequence[str], layout: dict[str, Any]) -> float:
    """The terminal cost of the passive discs with a target that take part in no event."""
    involved = {x for name in sequence for x in layout["bodies"][name]}
    T = layout["T"]
    bound = 0.0
    for d in layout["discs"].values():
        if d.actuated or d.name in involved or d.target is None:
            continue
        p_T = np.asarray(d.position) + T * np.asarray(d.velocity)
        bound += float(np.sum((p_T - np.asarray(d.target)) ** 2))
    return bound


def lower_bound(ocp: HybridOCP, sequence: Sequence[str]) -> float:
    """A lower bound of the cost of any control with this event sequence.

    Disc scenes: a passive disc that takes part in no event moves in a straight line, so its
    share of the terminal cost is known exactly; to it adds the reachability bound of the
    running cost (:func:`reach_bound`, module notes). ``inf``: no control has this sequence.
    Other problems: 0 (no bound).
    """
    layout = _disc_layout(ocp)
    if layout is None:
        return 0.0
    return _terminal(sequence, layout) + _reach(sequence, layout)


def default_depth(ocp: HybridOCP) -> int:
    """The length up to which the default reference enumerates every feasible sequence.

    Disc scenes: the largest ``K`` of at most :data:`MAX_DEFAULT_DEPTH` whose feasible
    sequences of one to ``K`` events (the geometric screens of :func:`enumerate_sequences`,
    which see the bodies, the walls and, through the ballistic paths, the horizon) number
    at most :data:`DEPTH_SEQUENCES`, and at least 1: small scenes (one or two discs, a
    wall) reach 2 or 3 events, larger ones fewer. Generic problems: 1 (they have neither
    screen nor bound, and each of their sequences is started from a transcription, about
    a second: longer sequences come from the sources, or from ``search``).
    """
    if _disc_layout(ocp) is None:
        return 1
    count, depth = 0, 1
    per_length = [0] * (MAX_DEFAULT_DEPTH + 1)
    for seq in enumerate_sequences(ocp, MAX_DEFAULT_DEPTH):
        per_length[len(seq)] += 1
    for k in range(1, MAX_DEFAULT_DEPTH + 1):
        count += per_length[k]
        if count > DEPTH_SEQUENCES:
            break
        depth = k
    return depth


def enumerate_sequences(ocp: HybridOCP, max_events: int) -> Iterator[list[str]]:
    """Every geometrically feasible sequence of up to ``max_events`` events, shortest first."""
    names = [g.name for g in ocp.guards]
    layout = _disc_layout(ocp)
    level: list[list[str]] = [[]]
    if ocp.ends_in_final_mode([]):
        yield []
    for _ in range(max_events):
        nxt = []
        for seq in level:
            for name in names:
                cand = seq + [name]
                if _feasible(cand, ocp, layout):
                    nxt.append(cand)  # a prefix may still reach the final mode
                    if ocp.ends_in_final_mode(cand):
                        yield cand
        level = nxt
