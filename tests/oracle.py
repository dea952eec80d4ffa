"""An independent, deliberately simple and slow oracle for disc scenes.

It simulates rigid discs in the plane that collide with each other and with straight walls,
under piecewise-constant forces, and returns the events, the final state and the cost. It uses
numpy and the standard library only, shares no code with :mod:`hybridoc`, and uses a different
algorithm from the project's evaluator: *conservative advancement*.

Algorithm
---------
Within one grid interval every disc moves with constant acceleration, so at an offset ``s`` from
the current time ``p(s) = p + v s + a s^2 / 2`` and ``v(s) = v + a s`` exactly. For every guard
(disc pair or disc-wall) with current gap ``d``, rate ``w = d gap / dt`` and a bound ``c >= 0``
on how fast the gap can curve downwards, the gap over the next ``tau`` is at least::

    d + w tau - c tau^2 / 2.

* Wall: the gap is exactly ``d + w tau + (a . n) tau^2 / 2``, so ``c = max(0, -a . n)``.
* Pair: with ``r = p_i - p_j`` and ``f = |r|``, ``f'' = |dv_perp|^2 / f + (r / f) . da`` is at
  least ``-|da|`` wherever ``f > 0``; so ``c = |a_i - a_j|`` (a tighter form of
  ``|dv| tau + |da| tau^2 / 2``: only the normal part of the relative velocity can close a gap).

The first positive root of that lower bound (the *safe time*) is a certified time before which
the gap cannot reach zero. The main loop advances every disc exactly by the smallest of (half
of) the guards' safe times and the end of the grid interval, so no collision can be skipped,
however long the interval or fast the discs.

Once a gap is inside a tiny band (``band_tol``, widened to 16 ulps of the largest coordinate
when the discs travel far, so that rounding never hides a contact), the exact contact time is
located on the closed-form gap: certified full safe steps approach the first root from below;
as soon as a probe at twice the safe step has a non-positive gap, bisection on that bracket
runs to floating-point resolution (which makes a separate Newton/secant polish unnecessary).
The state is then advanced exactly to the contact and the reset is applied.

Event rule
----------
A contact (gap at zero, within the band) fires when it approaches faster than its jump
threshold: pair ``w = (v_i - v_j) . n`` with ``n = (p_i - p_j) / |p_i - p_j|``, wall
``w = v_i . normal``, and the threshold is ``max(graze_tol, sqrt(2 rho |gap''|))`` where ``rho``
is the rounding resolution of gaps (16 ulps of the largest coordinate) and ``|gap''|`` is
bounded by ``|dv_perp|^2 / f + |da|`` (pair) or ``|a . n|`` (wall). The second term is the
approach speed that a gap of this curvature has at a height ``rho``: below it a contact cannot
be told from an exact tangency or from a resting contact. Without it an exactly tangent pass
would jump on a rounding zero of the gap, and a pushed contact with ``e < 1`` would bounce on
rounding noise for ever instead of stopping. It is about ``1e-7`` for unit-size scenes, and
``graze_tol`` alone decides when nothing curves the gap (constant velocity, straight approach).

Resets are frictionless impulses with restitution ``e``. When two or more contacts fire within
``simultaneity_tol`` of each other (the loop always stops at the earliest one, at zero gap),
the resets are applied in both orders for every pair of them (a later reset in a sequence only
if its contact still approaches); if the velocities differ by more than ``velocity_rtol``
(relative), :class:`SimultaneousImpact` is raised, otherwise all are applied in guard order.
Contacts still at zero gap and approaching after the resets fire at the same time (cascades,
e.g. a Newton's cradle). A contact below its threshold does not jump; the oracle then lets the
gap dip (at most ``penetration_tol / 4`` per step) and raises :class:`SustainedContact` when any
gap is below ``-penetration_tol``. ``zeno_events`` events within ``zeno_window`` raise
:class:`ZenoError`; more than ``max_steps`` advancement steps raise :class:`StepLimitExceeded`.
A contact that occurs exactly at the horizon ``T`` is applied (it changes only the final
velocities).

Default thresholds (all can be overridden by keyword)
-----------------------------------------------------
* length scale ``L = max(1, max radius, max |initial position coordinate|)``;
  speed scale ``S = max(1, max initial speed, max over intervals of |a| * T / N)``.
* ``graze_tol = 1e-9 * S``; ``band_tol = 1e-10 * L``; ``penetration_tol = 1e-7 * L``;
  ``simultaneity_tol = 1e-12 * max(1, T)``; ``velocity_rtol = 1e-9`` (against
  ``max(1, max |velocity component|)``); ``zeno_events = 1000`` within
  ``zeno_window = 1e-9 * max(1, T)``; ``max_steps = 1_000_000``.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = [
    "OracleError",
    "OracleResult",
    "SimultaneousImpact",
    "StepLimitExceeded",
    "SustainedContact",
    "ZenoError",
    "simulate",
]

#: Fraction of the certified safe time taken by one advancement step.
STEP_FRACTION = 0.5
#: Certified root-approach iterations before the locator gives up (the main loop then retries).
MAX_MARCH = 100
#: The contact band is never narrower than this many ulps of the largest coordinate.
ROUNDING_ULPS = 16.0
#: Bisection iterations (more than enough to reach floating-point resolution).
MAX_BISECT = 200


class OracleError(ValueError):
    """Base class of the oracle's simulation errors."""


class SimultaneousImpact(OracleError):
    """Two contacts at one time whose resets do not commute (the outcome depends on order)."""

    def __init__(self, message: str, guards: tuple[str, str], time: float) -> None:
        super().__init__(message)
        self.guards = guards
        self.time = time


class SustainedContact(OracleError):
    """A gap went below ``-penetration_tol`` without an event (resting or pushed contact)."""

    def __init__(self, message: str, guard: str, time: float, gap: float) -> None:
        super().__init__(message)
        self.guard = guard
        self.time = time
        self.gap = gap


class ZenoError(OracleError):
    """Too many events accumulated in a vanishing time."""


class StepLimitExceeded(OracleError):
    """The conservative advancement needed more than ``max_steps`` steps."""


@dataclass
class OracleResult:
    """What :func:`simulate` returns.

    ``final_state`` is ``[x_1, y_1, ..., x_n, y_n, vx_1, vy_1, ..., vx_n, vy_n]`` at ``T``;
    ``min_gaps`` maps each guard name to the smallest gap seen at the oracle's step points
    (every advancement step and every event, so a sampled upper bound of the true minimum).
    """

    events: list[tuple[float, str]]
    final_state: np.ndarray
    cost: float
    terminal_cost: float
    running_cost: float
    min_gaps: dict[str, float] = field(default_factory=dict)
    n_steps: int = 0
    tolerances: dict[str, float] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Scene data
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Guard:
    kind: str  # "pair" or "wall"
    i: int  # disc index
    j: int  # second disc index (pair) or wall index (wall)
    name: str


@dataclass
class _Scene:
    horizon: float
    steps: int
    eps: float
    e: float
    names: list[str]
    radius: np.ndarray  # (n,)
    mass: np.ndarray  # (n,)
    actuated: list[int]  # disc indices, in disc order
    targets: list[tuple[int, np.ndarray]]
    pos0: np.ndarray  # (n, 2)
    vel0: np.ndarray  # (n, 2)
    wall_names: list[str]
    wall_point: np.ndarray  # (m, 2)
    wall_normal: np.ndarray  # (m, 2), unit


def _vec2(value: Any, what: str) -> np.ndarray:
    arr = np.asarray(value, dtype=float).reshape(-1)
    if arr.shape != (2,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be two finite numbers, got {value!r}")
    return arr


def _parse_scene(scene: dict[str, Any]) -> _Scene:
    horizon = float(scene["horizon"])
    steps = scene["steps"]
    if not (math.isfinite(horizon) and horizon > 0):
        raise ValueError(f"horizon must be finite and > 0, got {horizon!r}")
    if isinstance(steps, bool) or int(steps) != steps or int(steps) < 1:
        raise ValueError(f"steps must be a positive integer, got {steps!r}")
    e = float(scene["restitution"])
    if not 0.0 <= e <= 1.0:
        raise ValueError(f"restitution must be in [0, 1], got {e!r}")
    eps = float(scene.get("control_weight", 0.0))
    discs = list(scene["discs"])
    if not discs:
        raise ValueError("a scene needs at least one disc")
    names, radius, mass, actuated, targets, pos, vel = [], [], [], [], [], [], []
    for idx, disc in enumerate(discs):
        names.append(str(disc["name"]))
        r = float(disc["radius"])
        m = float(disc.get("mass", 1.0))
        if not (math.isfinite(r) and r > 0 and math.isfinite(m) and m > 0):
            raise ValueError(f"disc {names[-1]!r}: radius and mass must be finite and > 0")
        radius.append(r)
        mass.append(m)
        pos.append(_vec2(disc["position"], f"disc {names[-1]!r} position"))
        vel.append(_vec2(disc.get("velocity", (0.0, 0.0)), f"disc {names[-1]!r} velocity"))
        if disc.get("actuated", False):
            actuated.append(idx)
        if disc.get("target") is not None:
            targets.append((idx, _vec2(disc["target"], f"disc {names[-1]!r} target")))
    wall_names, wall_point, wall_normal = [], [], []
    for wall in scene.get("walls", []) or []:
        wall_names.append(str(wall["name"]))
        point = _vec2(wall["point"], f"wall {wall_names[-1]!r} point")
        normal = _vec2(wall["normal"], f"wall {wall_names[-1]!r} normal")
        norm = math.hypot(normal[0], normal[1])
        if abs(norm - 1.0) > 1e-6:
            raise ValueError(f"wall {wall_names[-1]!r}: normal must be a unit vector")
        wall_point.append(point)
        wall_normal.append(normal / norm)
    return _Scene(
        horizon=horizon,
        steps=int(steps),
        eps=eps,
        e=e,
        names=names,
        radius=np.array(radius),
        mass=np.array(mass),
        actuated=actuated,
        targets=targets,
        pos0=np.array(pos),
        vel0=np.array(vel),
        wall_names=wall_names,
        wall_point=np.array(wall_point).reshape(-1, 2),
        wall_normal=np.array(wall_normal).reshape(-1, 2),
    )


def _guards(sc: _Scene) -> list[_Guard]:
    """Guard order: disc pairs (i < j) first, then disc-wall, disc-major."""
    n = len(sc.names)
    out = [
        _Guard("pair", i, j, f"{sc.names[i]}|{sc.names[j]}")
        for i in range(n)
        for j in range(i + 1, n)
    ]
    out += [
        _Guard("wall", i, w, f"{sc.names[i]}|{sc.wall_names[w]}")
        for i in range(n)
        for w in range(len(sc.wall_names))
    ]
    return out


def _accelerations(sc: _Scene, controls: Any) -> tuple[np.ndarray, np.ndarray]:
    """Controls as (N, 2 * n_actuated) and per-interval accelerations (N, n, 2)."""
    n_act = len(sc.actuated)
    u = np.asarray(controls if controls is not None else np.zeros((sc.steps, 0)), dtype=float)
    if u.size == 0 and n_act == 0:
        u = np.zeros((sc.steps, 0))
    if u.shape != (sc.steps, 2 * n_act):
        raise ValueError(f"controls must have shape {(sc.steps, 2 * n_act)}, got {u.shape}")
    if not np.all(np.isfinite(u)):
        raise ValueError("controls must be finite")
    acc = np.zeros((sc.steps, len(sc.names), 2))
    for m, disc in enumerate(sc.actuated):
        acc[:, disc, :] = u[:, 2 * m : 2 * m + 2] / sc.mass[disc]
    return u, acc


# --------------------------------------------------------------------------------------------
# Closed-form flow, gaps, safe times, resets
# --------------------------------------------------------------------------------------------


def _flow(
    pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Exact constant-acceleration motion over an offset ``s``."""
    return pos + s * vel + (0.5 * s * s) * acc, vel + s * acc


def _safe_time(d: float, w: float, c: float) -> float:
    """First ``tau > 0`` with ``d + w tau - c tau^2 / 2 = 0`` (``inf`` if none), for ``d >= 0``.

    Returns 0 when ``d <= 0`` and the gap is not opening (``w <= 0``).
    """
    if d <= 0.0:
        if w <= 0.0:
            return 0.0
        d = 0.0
    if c <= 0.0:
        return d / -w if w < 0.0 else math.inf
    root = math.sqrt(w * w + 2.0 * c * d)
    if w >= 0.0:
        return (w + root) / c
    return 2.0 * d / (root - w)  # the same root, written without cancellation


class _Sim:
    """One run of the oracle (state and bookkeeping)."""

    def __init__(self, sc: _Scene, acc: np.ndarray, tol: dict[str, float], max_steps: int):
        self.sc = sc
        self.acc = acc
        self.tol = tol
        self.max_steps = max_steps
        self.guards = _guards(sc)
        self.events: list[tuple[float, str]] = []
        self.recent: deque[float] = deque(maxlen=int(tol["zeno_events"]))
        self.min_gaps = {g.name: math.inf for g in self.guards}
        self.n_steps = 0
        self.graze: dict[_Guard, float] = {}  # per-guard jump threshold at the current time

    # ---- measurements -------------------------------------------------------------------

    def measure(
        self, g: _Guard, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray
    ) -> tuple[float, float, float]:
        """Gap ``d``, rate ``w`` and downward-curvature bound ``c`` of guard ``g``."""
        sc = self.sc
        if g.kind == "pair":
            rx = float(pos[g.i, 0] - pos[g.j, 0])
            ry = float(pos[g.i, 1] - pos[g.j, 1])
            f = math.hypot(rx, ry)
            if f == 0.0:
                raise SustainedContact(
                    f"{g.name}: disc centres coincide", g.name, math.nan, -math.inf
                )
            dvx = float(vel[g.i, 0] - vel[g.j, 0])
            dvy = float(vel[g.i, 1] - vel[g.j, 1])
            d = f - float(sc.radius[g.i] + sc.radius[g.j])
            w = (rx * dvx + ry * dvy) / f
            c = math.hypot(float(acc[g.i, 0] - acc[g.j, 0]), float(acc[g.i, 1] - acc[g.j, 1]))
            return d, w, c
        nx, ny = (float(x) for x in sc.wall_normal[g.j])
        px, py = (float(x) for x in sc.wall_point[g.j])
        d = (float(pos[g.i, 0]) - px) * nx + (float(pos[g.i, 1]) - py) * ny - float(sc.radius[g.i])
        w = float(vel[g.i, 0]) * nx + float(vel[g.i, 1]) * ny
        c = max(0.0, -(float(acc[g.i, 0]) * nx + float(acc[g.i, 1]) * ny))
        return d, w, c

    def curvature(self, g: _Guard, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray) -> float:
        """A bound on ``|gap''|`` now: pair ``|dv_perp|^2 / f + |da|``, wall ``|a . n|``."""
        if g.kind == "pair":
            rx, ry = (float(x) for x in pos[g.i] - pos[g.j])
            dvx, dvy = (float(x) for x in vel[g.i] - vel[g.j])
            f = math.hypot(rx, ry)
            perp = (rx * dvy - ry * dvx) / f
            dax, day = (float(x) for x in acc[g.i] - acc[g.j])
            return perp * perp / f + math.hypot(dax, day)
        nx, ny = (float(x) for x in self.sc.wall_normal[g.j])
        return abs(float(acc[g.i, 0]) * nx + float(acc[g.i, 1]) * ny)

    def measure_at(
        self, g: _Guard, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, s: float
    ) -> tuple[float, float, float]:
        """``measure`` after flowing the whole state by ``s`` (bit-identical to advancing)."""
        p, v = _flow(pos, vel, acc, s)
        return self.measure(g, p, v, acc)

    # ---- root location --------------------------------------------------------------------

    def locate(
        self, g: _Guard, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, s_max: float
    ) -> tuple[str, float]:
        """First zero of the closed-form gap of ``g`` on ``(0, s_max]``; the gap at 0 is > 0.

        Returns ``("root", s)`` with the gap at ``s`` <= 0 (to floating-point resolution the
        first crossing), ``("none", nan)`` when the gap is certified positive on ``[0, s_max]``,
        or ``("unresolved", nan)`` when the certified approach stalled (near-tangential).
        """
        s = 0.0
        for _ in range(MAX_MARCH):
            d, w, c = self.measure_at(g, pos, vel, acc, s)
            if d <= 0.0:
                return "root", s
            tau = _safe_time(d, w, c)
            if s + tau > s_max:
                return "none", math.nan
            lo = s + tau  # the gap is certified positive on [0, lo)
            if w < 0.0:
                probe = min(s + 2.0 * tau, s_max)
                if probe > lo and self.measure_at(g, pos, vel, acc, probe)[0] <= 0.0:
                    if self.measure_at(g, pos, vel, acc, lo)[0] <= 0.0:
                        return "root", lo
                    return "root", self.bisect(g, pos, vel, acc, lo, probe)
            if lo <= s:
                break
            s = lo
        return "unresolved", math.nan

    def bisect(
        self, g: _Guard, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray, lo: float, hi: float
    ) -> float:
        """Bisection with gap(lo) > 0 >= gap(hi), down to floating-point resolution."""
        for _ in range(MAX_BISECT):
            mid = 0.5 * (lo + hi)
            if not lo < mid < hi:
                break
            if self.measure_at(g, pos, vel, acc, mid)[0] > 0.0:
                lo = mid
            else:
                hi = mid
        return hi

    # ---- resets ---------------------------------------------------------------------------

    def approach(self, g: _Guard, pos: np.ndarray, vel: np.ndarray) -> float:
        return self.measure(g, pos, vel, np.zeros_like(pos))[1]

    def reset(self, g: _Guard, pos: np.ndarray, vel: np.ndarray) -> np.ndarray:
        """Velocities after the frictionless impulse of contact ``g`` (positions unchanged)."""
        sc = self.sc
        out = vel.copy()
        if g.kind == "pair":
            r = pos[g.i] - pos[g.j]
            n = r / math.hypot(float(r[0]), float(r[1]))
            w = float(np.dot(vel[g.i] - vel[g.j], n))
            impulse = -(1.0 + sc.e) * w / (1.0 / sc.mass[g.i] + 1.0 / sc.mass[g.j])
            out[g.i] = vel[g.i] + (impulse / sc.mass[g.i]) * n
            out[g.j] = vel[g.j] - (impulse / sc.mass[g.j]) * n
        else:
            n = sc.wall_normal[g.j]
            w = float(np.dot(vel[g.i], n))
            out[g.i] = vel[g.i] - (1.0 + sc.e) * w * n
        return out

    def sequence(self, order: list[_Guard], pos: np.ndarray, vel: np.ndarray) -> np.ndarray:
        """Apply resets in ``order``, each only if its contact still approaches."""
        for g in order:
            if self.approach(g, pos, vel) < -self.graze[g]:
                vel = self.reset(g, pos, vel)
        return vel

    def fire(self, firing: list[_Guard], t: float, pos: np.ndarray, vel: np.ndarray) -> np.ndarray:
        """Resolve the contacts firing at time ``t``; returns the new velocities."""
        rtol = self.tol["velocity_rtol"]
        if len(firing) > 1:
            scale = max(1.0, float(np.max(np.abs(vel))))
            for a, b in itertools.combinations(firing, 2):
                v_ab = self.sequence([a, b], pos, vel)
                v_ba = self.sequence([b, a], pos, vel)
                if float(np.max(np.abs(v_ab - v_ba))) > rtol * scale:
                    raise SimultaneousImpact(
                        f"simultaneous impacts {a.name!r} and {b.name!r} at t={t!r}: "
                        "the outcome depends on the order of the resets",
                        (a.name, b.name),
                        t,
                    )
        for g in firing:  # guard order
            if self.approach(g, pos, vel) < -self.graze[g]:
                vel = self.reset(g, pos, vel)
                self.events.append((t, g.name))
                self.recent.append(t)
                if (
                    len(self.recent) == self.recent.maxlen
                    and self.recent[-1] - self.recent[0] <= self.tol["zeno_window"]
                ):
                    raise ZenoError(
                        f"{len(self.recent)} events within {self.recent[-1] - self.recent[0]!r} "
                        f"up to t={t!r} (last: {g.name!r})"
                    )
        return vel

    # ---- main loop ----------------------------------------------------------------------------

    def run(self) -> tuple[np.ndarray, np.ndarray]:
        sc, tol = self.sc, self.tol
        budget = tol["penetration_tol"] / 4.0
        wall_extent = float(np.max(np.abs(sc.wall_point))) if len(sc.wall_names) else 0.0
        pos, vel = sc.pos0.copy(), sc.vel0.copy()
        n_int, horizon = sc.steps, sc.horizon
        k, s = 0, 0.0  # grid interval and offset into it
        zero_acc = np.zeros_like(pos)
        while True:
            acc = self.acc[k] if k < n_int else zero_acc
            t_k = horizon * k / n_int
            t = t_k + s
            s_rem = horizon * (k + 1) / n_int - t_k - s if k < n_int else 0.0
            meas = [self.measure(g, pos, vel, acc) for g in self.guards]
            # Gaps are differences of coordinates: never ask for a band below their rounding.
            extent = max(wall_extent, float(np.max(np.abs(pos))))
            resolution = ROUNDING_ULPS * float(np.spacing(extent))
            band = max(tol["band_tol"], resolution)
            # Approach speed needed to jump, per guard: graze_tol, or sqrt(2 rho |gap''|), the
            # approach speed that a gap with this curvature has at a height of the rounding
            # resolution rho. A slower contact cannot be told from a tangency or a resting
            # contact: without this floor an exactly tangent pass would jump on a rounding
            # zero, and a pushed contact with e < 1 would micro-bounce on rounding noise for
            # ever instead of stopping.
            self.graze = {
                g: max(
                    tol["graze_tol"],
                    math.sqrt(2.0 * resolution * self.curvature(g, pos, vel, acc)),
                )
                for g in self.guards
            }
            for g, (d, _, _) in zip(self.guards, meas, strict=True):
                if d < self.min_gaps[g.name]:
                    self.min_gaps[g.name] = d
                if d < -tol["penetration_tol"]:
                    raise SustainedContact(
                        f"{g.name}: gap {d!r} at t={t!r} is below -{tol['penetration_tol']!r} "
                        "(penetration without an event: sustained or resting contact)",
                        g.name,
                        t,
                        d,
                    )

            # Contacts at zero gap and approaching; if there are any, also those reaching zero
            # within simultaneity_tol (the main loop always stops at the earliest contact, so a
            # contact alone never fires before its gap is zero).
            touching = [
                -band <= d <= 0.0 and w < -self.graze[g]
                for g, (d, w, _) in zip(self.guards, meas, strict=True)
            ]
            firing = []
            for g, (d, w, c), now in zip(self.guards, meas, touching, strict=True):
                graze = self.graze[g]
                if now:
                    firing.append(g)
                elif (
                    any(touching)
                    and 0.0 < d <= band
                    and w < -graze
                    and _safe_time(d, w, c) <= tol["simultaneity_tol"]
                ):
                    status, root = self.locate(
                        g, pos, vel, acc, min(tol["simultaneity_tol"], s_rem)
                    )
                    if status == "root" and self.measure_at(g, pos, vel, acc, root)[1] < -graze:
                        firing.append(g)
            if firing:
                vel = self.fire(firing, t, pos, vel)
                continue
            if k >= n_int:
                return pos, vel

            self.n_steps += 1
            if self.n_steps > self.max_steps:
                raise StepLimitExceeded(
                    f"more than {self.max_steps} advancement steps (reached t={t!r}); "
                    "a near-grazing or Zeno-like configuration?"
                )
            delta = s_rem
            for g, (d, w, c) in zip(self.guards, meas, strict=True):
                graze = self.graze[g]
                if d > band:  # ordinary guard: half of the certified safe time
                    lim = STEP_FRACTION * _safe_time(d, w, c)
                elif w > graze:  # separating contact: until it could come back
                    lim = STEP_FRACTION * _safe_time(max(d, 0.0), w, c)
                else:  # in the band, approaching or grazing, or penetrating
                    # A grazing/penetrating guard may dip by at most `budget` in this step.
                    dip = _safe_time(max(d, 0.0) + budget, w, c)
                    lim = dip
                    if d > 0.0:
                        cap = min(s_rem, dip) if w >= -graze else s_rem
                        status, root = self.locate(g, pos, vel, acc, cap)
                        if status == "root":
                            w_root = self.measure_at(g, pos, vel, acc, root)[1]
                            lim = root if w_root < -graze else dip
                        elif status == "none":
                            lim = cap
                        else:
                            lim = STEP_FRACTION * _safe_time(d, w, c)
                delta = min(delta, lim)
            if delta >= s_rem:
                pos, vel = _flow(pos, vel, acc, s_rem)
                k, s = k + 1, 0.0
            else:
                pos, vel = _flow(pos, vel, acc, delta)
                s += delta


def _tolerances(sc: _Scene, acc: np.ndarray, overrides: dict[str, float | None]) -> dict:
    length = max(1.0, float(np.max(sc.radius)), float(np.max(np.abs(sc.pos0))))
    h = sc.horizon / sc.steps
    speed = max(
        1.0,
        float(np.max(np.hypot(sc.vel0[:, 0], sc.vel0[:, 1]))),
        float(np.max(np.hypot(acc[..., 0], acc[..., 1]))) * h,
    )
    tol = {
        "length_scale": length,
        "speed_scale": speed,
        "graze_tol": 1e-9 * speed,
        "band_tol": 1e-10 * length,
        "penetration_tol": 1e-7 * length,
        "simultaneity_tol": 1e-12 * max(1.0, sc.horizon),
        "velocity_rtol": 1e-9,
        "zeno_events": 1000.0,
        "zeno_window": 1e-9 * max(1.0, sc.horizon),
    }
    for key, value in overrides.items():
        if value is not None:
            tol[key] = float(value)
    if tol["zeno_events"] < 2:
        raise ValueError("zeno_events must be at least 2")
    return tol


def simulate(
    scene: dict[str, Any],
    controls: Any,
    *,
    graze_tol: float | None = None,
    band_tol: float | None = None,
    penetration_tol: float | None = None,
    simultaneity_tol: float | None = None,
    velocity_rtol: float | None = None,
    zeno_events: int | None = None,
    zeno_window: float | None = None,
    max_steps: int = 1_000_000,
) -> OracleResult:
    """Simulate ``scene`` under piecewise-constant ``controls``; see the module notes.

    Parameters
    ----------
    scene
        Plain data: ``horizon``, ``steps``, ``restitution``, ``discs`` (``name``, ``position``,
        ``radius``, and optionally ``velocity`` (0), ``mass`` (1), ``actuated`` (False),
        ``target`` (None)), optionally ``control_weight`` (0) and ``walls`` (``name``,
        ``point``, unit ``normal`` into free space). Unknown keys are ignored.
    controls
        ``(steps, 2 * n_actuated)`` forces ``[ux, uy]`` per actuated disc, in disc order,
        constant on each grid interval.
    graze_tol, band_tol, penetration_tol, simultaneity_tol, velocity_rtol, zeno_events, \
zeno_window, max_steps
        Thresholds; ``None`` selects the defaults listed in the module notes.

    Raises
    ------
    SimultaneousImpact, SustainedContact, ZenoError, StepLimitExceeded
        All subclasses of :class:`OracleError` (a ``ValueError``).
    ValueError
        Malformed scene or controls, or discs/walls overlapping at the start.
    """
    sc = _parse_scene(scene)
    u, acc = _accelerations(sc, controls)
    tol = _tolerances(
        sc,
        acc,
        {
            "graze_tol": graze_tol,
            "band_tol": band_tol,
            "penetration_tol": penetration_tol,
            "simultaneity_tol": simultaneity_tol,
            "velocity_rtol": velocity_rtol,
            "zeno_events": zeno_events,
            "zeno_window": zeno_window,
        },
    )
    sim = _Sim(sc, acc, tol, max_steps)
    for g in sim.guards:
        d = sim.measure(g, sc.pos0, sc.vel0, acc[0])[0]
        if d < -tol["penetration_tol"]:
            raise ValueError(f"{g.name}: overlapping at t=0 (gap {d!r})")
    pos, vel = sim.run()

    terminal = sum(float(np.sum((pos[i] - target) ** 2)) for i, target in sc.targets)
    running = sc.eps * float(np.sum(u**2)) * sc.horizon / sc.steps
    return OracleResult(
        events=sim.events,
        final_state=np.concatenate([pos.reshape(-1), vel.reshape(-1)]),
        cost=terminal + running,
        terminal_cost=terminal,
        running_cost=running,
        min_gaps=sim.min_gaps,
        n_steps=sim.n_steps,
        tolerances=tol,
    )
