"""What happens at an event: the jump rule shared by every simulation path of the judge.

Which crossings jump
    A guard fires when it reaches zero with approach speed
    ``d psi/dt < -max(graze_tol, sqrt(2 sigma_j max(d2 psi/dt2, 0)))`` with ``sigma_j`` the
    rounding level of guard ``j``: a quarter of the bound of
    :func:`hybridoc.kernels.rounding_level`, ``2 eps (|psi_j| + sum_i |d psi_j / d s_i|
    max(1, |s_i|))`` to first order. It comes from the components guard ``j`` depends on
    only, so a far or fast body does not raise the threshold of the guards between others;
    for a gap whose bodies hold the largest coordinates it is about the ``4 eps
    max(1, |s|_inf)`` of a unit-gradient guard. The second term is the noise floor of the
    approach speed at a near-tangent root: there a rounding error ``sigma_j`` in ``psi``
    moves the computed root by ``sqrt(2 sigma_j / psi'')`` and gives a spurious approach
    speed of that size. A grazing contact (approach speed below the threshold) does not
    jump; the penetration this allows is of order ``sigma_j``.

Several guards at one instant
    At an event time every guard that is at zero (within its rounding level) and approaching
    is due. If two due guards have resets that do not commute (``g_a(g_b(s)) != g_b(g_a(s))``
    beyond rounding, judged on the components the resets change and against their scale,
    e.g. a striker touching two discs at once), the outcome of the impulsive model depends on
    an order that the physics does not give: the judge raises
    :class:`~hybridoc.errors.SimultaneousEventError` instead of choosing one. Commuting resets
    (a disc in a right-angled corner, two separate pairs) are applied one after the other in
    guard order, which gives the same state in any order. After each jump the due set is
    computed again, so jumps that a jump causes at the same instant (a Newton's cradle) follow.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hybridoc import tolerances
from hybridoc.errors import EvaluationError, HybridocError, SimultaneousEventError

__all__ = [
    "Event",
    "EventResolver",
    "MAX_EVENTS_AT_ONE_TIME",
    "MAX_REPEATS_AT_ONE_TIME",
    "accumulating",
    "approaching",
    "commute_defect",
    "graze_threshold",
    "in_local_frame",
    "moved_events",
    "penetration_threshold",
]

EPS = float(np.finfo(float).eps)
MAX_EVENTS_AT_ONE_TIME = 200
"""More jumps than this at one instant are an error."""
MAX_REPEATS_AT_ONE_TIME = 8
"""One guard firing more often than this at one instant (a cascade that only converges in the
limit, e.g. a disc squeezed between two bodies with restitution < 1) is an error, not a count
that depends on the grazing threshold."""
_COMMUTE_RTOL = tolerances.value("commute")


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
    name
        The guard's name (for a problem with modes: the transition's).
    mode_before, mode_after
        For a problem with modes (:meth:`hybridoc.HybridOCP.from_modes`): the mode before and
        after the jump; ``None`` without modes.
    """

    time: float
    kind: str
    bodies: tuple[str, ...]
    guard: int
    approach_speed: float
    state_before: np.ndarray = field(repr=False)
    state_after: np.ndarray = field(repr=False)
    name: str = ""
    mode_before: str | None = None
    mode_after: str | None = None

    def __post_init__(self) -> None:
        # plain floats, so reprs and JSON read the same whatever produced them
        object.__setattr__(self, "time", float(self.time))
        object.__setattr__(self, "approach_speed", float(self.approach_speed))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready ``{"time", "kind", "bodies", "guard"}``, with ``"mode_before"`` and
        ``"mode_after"`` for a problem with modes (absent without, so that the records of
        problems without modes stay as they were)."""
        out: dict[str, Any] = {
            "time": float(self.time),
            "kind": self.kind,
            "bodies": list(self.bodies),
            "guard": self.name,
        }
        if self.mode_before is not None or self.mode_after is not None:
            out["mode_before"] = self.mode_before
            out["mode_after"] = self.mode_after
        return out


def approaching(
    rate: np.ndarray, accel: np.ndarray, noise: np.ndarray, graze_tol: float
) -> np.ndarray:
    """Which guards approach fast enough to jump (see the module notes on grazing).

    Parameters
    ----------
    rate, accel
        ``d psi/dt`` and ``d2 psi/dt2`` per guard.
    noise
        Per guard, the bound on the rounding of ``psi`` from the ``contact`` kernel
        (:func:`hybridoc.kernels.rounding_level`); ``sigma_j`` is a quarter of it.
    graze_tol
        The grazing threshold.
    """
    sigma = 0.25 * np.asarray(noise, dtype=float)
    floor = np.sqrt(2.0 * sigma * np.maximum(accel, 0.0))
    return rate < -np.maximum(graze_tol, floor)


def graze_threshold(ocp: Any, graze_tol: float) -> float:
    """The grazing threshold on ``d psi/dt`` of a tolerance given in the problem's units.

    ``graze_tol`` counts guard units (:attr:`Scales.length <hybridoc.scales.Scales.length>`,
    the unit of a disc scene's gaps) per unit time (:attr:`Scales.time
    <hybridoc.scales.Scales.time>`): the same physical scene in other units grazes at the
    same contacts. ``graze_tol`` itself for a problem that states no units.
    """
    sc = ocp.scales
    return float(graze_tol) * (sc.length / sc.time)


def penetration_threshold(ocp: Any, penetration_tol: float) -> float:
    """The depth below which a guard counts as penetrated, of a tolerance given in guard
    units (:attr:`Scales.length <hybridoc.scales.Scales.length>`), as
    :func:`graze_threshold` scales its own."""
    return penetration_tol * ocp.scales.length


def in_local_frame(ocp: Any) -> tuple[Any, np.ndarray | None]:
    """``(problem, offset)``: the problem in its local frame and the offset to add back to
    its states, where it has one (a disc scene far from the origin:
    ``DiscOCP.local_frame``), else ``(ocp, None)``. The judges simulate there, so that the
    numbers round at the scene's own length scale rather than at its coordinates'."""
    frame_of = getattr(ocp, "local_frame", None)
    frame = frame_of() if frame_of is not None else None
    return (ocp, None) if frame is None else frame


def moved_events(events: list[Event], offset: np.ndarray) -> list[Event]:
    """``events`` with their states moved by ``offset`` (back from a local frame)."""
    return [
        dataclasses.replace(
            e, state_before=e.state_before + offset, state_after=e.state_after + offset
        )
        for e in events
    ]


def commute_defect(
    ab: np.ndarray, ba: np.ndarray, s: np.ndarray, *jumps: np.ndarray, floor: Any = 1.0
) -> float:
    """How far two jumps fail to commute, relative to rounding: ``max |ab_i - ba_i|`` over
    the components either jump changes, divided by their scale ``max(floor_i, |s_i|, |ab_i|,
    |ba_i|, |jump_i|)``.

    Only the components the jumps touch enter: a body they leave alone (copied, bit for bit,
    in both orders) does not lend them its scale, so a far body at 1e15 cannot hide two
    non-commuting jumps of others below a tolerance ``1e-9 * 1e15``.

    Parameters
    ----------
    ab, ba
        ``g_a(g_b(s))`` and ``g_b(g_a(s))``.
    s
        The state before.
    *jumps
        ``g_a(s)`` and ``g_b(s)``.
    floor
        Per component (or one number), its unit (:attr:`HybridOCP.scales
        <hybridoc.ocp.HybridOCP.scales>`): the scale of a component near zero. An absolute
        floor of 1 hid any non-commuting pair of jumps in a scene measured in micrometres.
    """
    touched = (ab != s) | (ba != s)
    for g in jumps:
        touched |= g != s
    if not touched.any():
        return 0.0
    mags = [np.abs(x[touched]) for x in (s, ab, ba, *jumps)]
    low = np.broadcast_to(np.asarray(floor, dtype=float), s.shape)[touched]
    scale = np.maximum(low, np.max(mags, axis=0))
    return float(np.max(np.abs(ab[touched] - ba[touched]) / scale))


ZENO_RUN = 12
"""Consecutive shrinking gaps between events that signal an accumulation (Zeno behaviour)."""


def accumulating(times: list[float], horizon: float) -> float | None:
    """The accumulation time when the last :data:`ZENO_RUN` gaps between events shrink
    geometrically (each at most 0.9 times the previous, or zero) towards a point before the
    horizon; ``None`` otherwise. A bouncing ball with restitution below 1 comes to rest this
    way after infinitely many bounces, which the impulsive model does not resolve."""
    if len(times) < ZENO_RUN + 2:
        return None
    gaps = np.diff(np.asarray(times[-(ZENO_RUN + 2) :], dtype=float))
    if gaps[0] <= 0:
        return None
    ratios = gaps[1:] / np.maximum(gaps[:-1], 1e-300)
    if not np.all((gaps[1:] == 0) | (ratios <= 0.9)):
        return None
    r = float(np.max(ratios[gaps[1:] > 0], initial=0.0))
    limit = times[-1] + gaps[-1] * r / (1 - r) if r < 1 else math.inf
    return limit if limit <= horizon * (1 + 1e-9) else None


class EventResolver:
    """Applies the jumps due at one instant (see the module notes).

    Parameters
    ----------
    ocp
        The problem (guard names, kinds, bodies).
    num
        The problem's buffer-bound kernels (:meth:`hybridoc.kernels.Kernels.numeric`).
    graze_tol
        The grazing threshold, in the guards' units per unit time (the caller converts a
        tolerance given in the problem's units, :func:`graze_threshold`).
    event_controls
        Optional ``(K, nu)`` controls of the resets, event by event in the order this
        resolver applies them: a reset that depends on the control reads row ``k`` at the
        ``k``-th event instead of the control in force (a continuous-time solution's own
        choice at its switches, :attr:`hybridoc.Solution.event_controls`). Events past the
        last row read the control in force.
    contacts
        Optional ``contacts(s, u, pending) -> (psi, rate, accel, noise)``, every guard's
        values as the ``contact`` kernel gives them, in place of that kernel: the broad
        phase's (:meth:`hybridoc.evaluator.Forward._contacts`), which evaluates the guards
        near contact and those in ``pending`` only and gives the others ``psi = inf`` and
        a zero rate (never due).
    """

    def __init__(
        self,
        ocp: Any,
        num: Any,
        graze_tol: float,
        event_controls: np.ndarray | None = None,
        contacts: Callable[..., tuple[np.ndarray, ...]] | None = None,
    ) -> None:
        self.ocp = ocp
        self.num = num
        self.contacts = contacts
        self.graze_tol = graze_tol
        self.G = len(ocp.guards)
        self.floor = ocp.scales.state_array
        self.event_controls = (
            None if event_controls is None else np.asarray(event_controls, dtype=float)
        )
        self.count = 0  # events applied so far (the row of event_controls of the next)

    def reset_control(self, u: np.ndarray) -> np.ndarray:
        """The control the next reset reads: ``u`` (in force) or its event control."""
        ec = self.event_controls
        if ec is not None and self.count < len(ec):
            return ec[self.count]
        return u

    def due(self, s: np.ndarray, u: np.ndarray, pending: set[int]) -> tuple[list[int], np.ndarray]:
        """Guards due at ``s``: approaching, and pending or at zero; and their rates."""
        if self.contacts is None:
            psi, rate, accel, noise = self.num.contact(s, u)
        else:
            psi, rate, accel, noise = self.contacts(s, u, pending)
        appr = approaching(rate, accel, noise, self.graze_tol)
        tol = 4.0 * noise + 1e-300
        due = [j for j in np.flatnonzero(appr).tolist() if j in pending or abs(psi[j]) <= tol[j]]
        return due, rate

    def resolve(
        self, t: float, s: np.ndarray, u: np.ndarray, pending: set[int]
    ) -> tuple[np.ndarray, list[Event]]:
        """All jumps at time ``t`` from state ``s``; returns the new state and the events."""
        events: list[Event] = []
        pending = set(pending)
        while True:
            due, rate = self.due(s, u, pending)
            if not due:
                return s, events
            u_reset = self.reset_control(u)
            if len(due) > 1:
                self._check_commute(t, s, due, u_reset)
            j = due[0]
            pending.discard(j)
            s_new = self.num.reset(j)(s, u_reset)[0]
            self.count += 1
            g = self.ocp.guards[j]
            before, after = self._modes(g.name, t, s, s_new)
            events.append(
                Event(t, g.kind, g.bodies, j, float(rate[j]), s, s_new, g.name, before, after)
            )
            s = s_new
            if sum(e.guard == j for e in events) > MAX_REPEATS_AT_ONE_TIME:
                names = sorted({e.name for e in events})
                raise EvaluationError(
                    f"guard {g.name!r} fires more than {MAX_REPEATS_AT_ONE_TIME} times at one "
                    f"instant t = {t:.9g} ({', '.join(names)}): a cascade of impacts that only "
                    "converges in the limit (e.g. a body squeezed between two others with "
                    "restitution < 1), which the impulsive model does not resolve in finitely "
                    "many events"
                )
            if len(events) > MAX_EVENTS_AT_ONE_TIME:
                names = sorted({e.name for e in events})
                raise EvaluationError(
                    f"more than {MAX_EVENTS_AT_ONE_TIME} jumps at one instant t = {t:.9g} "
                    f"({', '.join(names)}): a cascade of impacts that only converges in the "
                    "limit (e.g. a body squeezed between two others with restitution < 1), "
                    "which the impulsive model does not resolve in finitely many events"
                )

    def _modes(
        self, name: str, t: float, s: np.ndarray, s_new: np.ndarray
    ) -> tuple[str | None, str | None]:
        """The modes before and after a jump (``None`` without modes)."""
        if self.ocp.modes is None:
            return None, None
        try:
            return self.ocp.mode_of(s), self.ocp.mode_of(s_new)
        except HybridocError as exc:
            raise EvaluationError(
                f"the reset of guard {name!r} at t = {t:.9g} leaves no valid mode: {exc}"
            ) from None

    def _check_commute(self, t: float, s: np.ndarray, due: list[int], u: np.ndarray) -> None:
        for ia, a in enumerate(due):
            for b in due[ia + 1 :]:
                ga, gb = self.num.reset(a), self.num.reset(b)
                sa, sb = ga(s, u)[0], gb(s, u)[0]
                ab, ba = ga(sb, u)[0], gb(sa, u)[0]
                if commute_defect(ab, ba, s, sa, sb, floor=self.floor) > _COMMUTE_RTOL:
                    na, nb = self.ocp.guards[a].name, self.ocp.guards[b].name
                    raise SimultaneousEventError(
                        f"guards {na!r} and {nb!r} fire at the same instant t = {t:.12g} and "
                        "their jumps do not commute: the impulsive model's outcome depends on "
                        "an order the physics does not give. Perturb the scene or the control "
                        "slightly so that the contacts happen one after the other",
                        guards=(na, nb),
                        time=t,
                    )
