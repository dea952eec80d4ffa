"""Another simulator's trajectory measured against the judge's trajectory of the same controls.

:func:`compare_trajectory` takes states sampled at given times (a MuJoCo rollout's ``qpos``
and ``qvel``, in the order of the problem's state labels), simulates the same
piecewise-constant controls with the event-exact judge (:func:`hybridoc.evaluate`), and
reports the state error at every given time and the events of the given trajectory against
the judge's. :func:`trajectory_figure` draws both.

Sampling the judge
    At a time that appears once, the judge's state after any jump at that instant
    (:meth:`hybridoc.Evaluation.sample`). A time that appears several times in a row is a
    jump recorded twice, as the judge records its own events: the first sample there is
    compared with the state before the jump and the others with the state after it. So the
    judge's own ``(times, states)`` compare with no error.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hybridoc.errors import HybridocError
from hybridoc.ocp import HybridOCP
from hybridoc.problem import ControlsLike, ProblemLike, as_ocp

__all__ = [
    "EventMatch",
    "TrajectoryComparison",
    "TrajectoryError",
    "compare_trajectory",
    "detect_events",
    "trajectory_figure",
]


class TrajectoryError(HybridocError, ValueError):
    """A given trajectory cannot be compared: wrong shapes, NaN, times out of order or
    outside the horizon."""


@dataclass(frozen=True)
class EventMatch:
    """One event of a guard in the judge's trajectory, the given one, or both.

    The ``k``-th event of a guard in one trajectory is paired with the ``k``-th event of the
    same guard in the other; an event without a partner has ``None`` on the other side.

    Attributes
    ----------
    guard
        The guard's name.
    judge_time, given_time
        The event's time in each trajectory (``None``: no such event there).
    """

    guard: str
    judge_time: float | None
    given_time: float | None

    @property
    def shift(self) -> float | None:
        """``given_time - judge_time`` (``None`` unless both are there)."""
        if self.judge_time is None or self.given_time is None:
            return None
        return self.given_time - self.judge_time

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready fields and the shift."""
        return {
            "guard": self.guard,
            "judge_time": self.judge_time,
            "given_time": self.given_time,
            "shift": self.shift,
        }


@dataclass
class TrajectoryComparison:
    """Result of :func:`compare_trajectory`.

    Attributes
    ----------
    problem
        The problem's name.
    cost
        The judge's cost of the controls.
    times
        The ``M`` given times.
    states, judge_states
        ``(M, nx)``: the given states and the judge's at the same times.
    state_labels
        The names of the state components.
    judge_events
        The judge's events (JSON-ready dicts).
    given_events
        The events found in the given trajectory (:func:`detect_events`).
    matches
        The two lists of events paired guard by guard, in time order.
    evaluation
        The judge's :class:`~hybridoc.Evaluation` of the controls.
    substeps
        ``K`` when the controls hold ``K`` values per interval of the problem's grid.
    """

    problem: str
    cost: float
    times: np.ndarray = field(repr=False)
    states: np.ndarray = field(repr=False)
    judge_states: np.ndarray = field(repr=False)
    state_labels: list[str]
    judge_events: list[dict[str, Any]]
    given_events: list[dict[str, Any]]
    matches: list[EventMatch]
    evaluation: Any = field(repr=False, default=None)
    substeps: int = 1

    @property
    def error(self) -> np.ndarray:
        """``(M, nx)``: given state minus the judge's."""
        return self.states - self.judge_states

    @property
    def error_norm(self) -> np.ndarray:
        """``(M,)``: the 2-norm of the state error at each given time."""
        return np.linalg.norm(self.error, axis=1)

    @property
    def max_error(self) -> dict[str, float]:
        """The largest ``|error|`` of each state component."""
        err = np.abs(self.error).max(axis=0)
        return {name: float(e) for name, e in zip(self.state_labels, err, strict=True)}

    @property
    def sequence_matches(self) -> bool:
        """Whether both trajectories have the same guards firing in the same order."""
        return [e["guard"] for e in self.judge_events] == [e["guard"] for e in self.given_events]

    @property
    def max_event_shift(self) -> float | None:
        """The largest ``|shift|`` of the paired events (``None`` when none pair)."""
        shifts = [abs(m.shift) for m in self.matches if m.shift is not None]
        return max(shifts) if shifts else None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: summaries, the events, and the error norm at every given time."""
        norm = self.error_norm
        k = int(np.argmax(norm))
        err = np.abs(self.error)
        return {
            "problem": self.problem,
            "cost": self.cost,
            "substeps": self.substeps,
            "samples": int(self.times.size),
            "max_error_norm": float(norm[k]),
            "max_error_time": float(self.times[k]),
            "final_error_norm": float(norm[-1]),
            "final_time": float(self.times[-1]),
            "components": [
                {
                    "state": name,
                    "max_error": float(err[:, j].max()),
                    "max_error_time": float(self.times[int(np.argmax(err[:, j]))]),
                    "final_error": float(err[-1, j]),
                }
                for j, name in enumerate(self.state_labels)
            ],
            "judge_events": list(self.judge_events),
            "given_events": list(self.given_events),
            "events": [m.to_dict() for m in self.matches],
            "sequence_matches": self.sequence_matches,
            "max_event_shift": self.max_event_shift,
            "times": self.times.tolist(),
            "error_norm": norm.tolist(),
        }


def _checked(ocp: HybridOCP, times: Any, states: Any) -> tuple[np.ndarray, np.ndarray]:
    from hybridoc.ocp import as_float_array

    t = as_float_array(times, "times", error=TrajectoryError)
    x = as_float_array(states, "states", error=TrajectoryError)
    if t.ndim == 2 and t.shape[1] == 1:
        t = t[:, 0]
    if t.ndim != 1 or t.size < 2:
        raise TrajectoryError(
            f"times: expected a 1-D array of at least 2 times, got shape {t.shape}"
        )
    labels = ", ".join(ocp.state_labels or [])
    if x.ndim != 2 or x.shape != (t.size, ocp.nx):
        raise TrajectoryError(
            f"states: expected shape ({t.size}, {ocp.nx}) (one row per time, one column per "
            f"state component: {labels}), got {x.shape}"
        )
    for what, arr in (("times", t), ("states", x)):
        if not np.all(np.isfinite(arr)):
            k = int(np.argwhere(~np.isfinite(arr.reshape(arr.shape[0], -1)))[0][0])
            raise TrajectoryError(f"{what}: non-finite value at row {k}")
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        k = int(back[0])
        raise TrajectoryError(
            f"times: must not decrease; row {k + 1} ({t[k + 1]!r}) comes before row {k} ({t[k]!r})"
        )
    # a simulator adds its step N*K times: allow its rounding at the ends, not more
    slack = 1e-9 * ocp.horizon
    if t[0] < -slack or t[-1] > ocp.horizon + slack:
        raise TrajectoryError(
            f"times: must lie in [0, T] = [0, {ocp.horizon!r}]; they run from {t[0]!r} to {t[-1]!r}"
        )
    return np.clip(t, 0.0, ocp.horizon), x


def _judge_at(ev: Any, times: np.ndarray) -> np.ndarray:
    """The judge's states at ``times`` (module notes: a repeated time is a jump)."""
    from hybridoc.kernels import kernels

    segs = ev.segments
    starts = np.array([seg.t0 for seg in segs])
    flow = kernels(ev.ocp).numeric().flow
    before = np.zeros(times.size, dtype=bool)
    before[:-1] = (times[1:] == times[:-1]) & np.concatenate([[True], times[1:-1] != times[:-2]])
    out = np.empty((times.size, ev.ocp.nx))
    last = len(segs) - 1
    for k, tk in enumerate(times):
        i = int(np.searchsorted(starts, tk, side="left" if before[k] else "right")) - 1
        i = max(i, 0)
        seg = segs[i]
        tau = min(max(tk - seg.t0, 0.0), seg.h) if i < last else tk - seg.t0
        out[k] = flow(seg.s0, ev.controls[seg.interval], tau)[0]
    return out


def detect_events(
    problem: ProblemLike, times: Any, states: Any, controls: ControlsLike | None = None
) -> list[dict[str, Any]]:
    """The events in a sampled trajectory: where a guard is reached and its approach reverses.

    The rule, for each guard ``psi`` and each pair of consecutive samples ``i, i+1`` (``h``
    apart): with ``r = d psi/dt = grad psi . f(s, u)`` evaluated on the given states (the
    approach speed, which for a distance guard is the relative normal velocity),

    * the approach reverses: ``r_i < 0 <= r_{i+1}``, and
    * the guard is reached: ``psi`` is at or below zero at either sample (to its rounding
      level), or the straight line from either sample at its own rate reaches zero within
      the step (``psi_i + r_i h <= 0`` or ``psi_{i+1} - r_{i+1} h <= 0``).

    The first covers a simulator that penetrates (soft contact, MuJoCo): one event per
    contact, however many steps it lasts. The second covers an impulsive simulator, whose
    guard stays positive while the velocity jumps between two samples, and the judge's own
    trajectory, which holds each event twice (before and after the jump, at the same time).
    A smooth turn-around near a guard (an approach stopped by the control within a step of
    contact) meets the rule only if it comes within about ``|r| h`` of contact.

    The event time: if the guard went below zero, where the linear interpolation of ``psi``
    between the last sample above zero and the first at or below crosses zero (the start of
    the contact, the time of the equivalent impulse); else where the straight line from
    sample ``i`` at rate ``r_i`` reaches zero, kept within ``[t_i, t_{i+1}]``.

    Parameters
    ----------
    problem
        Any problem; its guards and flow give ``psi`` and ``r``.
    times, states
        ``(M,)`` nondecreasing times in ``[0, T]`` and ``(M, nx)`` states.
    controls
        The ``(N, nu)`` controls of the run (default: the initial guess); they enter ``r``
        only for guards whose rate depends on the control.

    Returns
    -------
    list of dict
        ``{"time", "guard", "kind", "bodies", "sample"}`` in time order; ``sample`` is ``i``.
    """
    from hybridoc.kernels import kernels

    ocp = as_ocp(problem)
    t, x = _checked(ocp, times, states)
    u = ocp.check_controls(
        ocp.u_guess if controls is None else getattr(controls, "controls", controls)
    )
    if not ocp.guards:
        return []
    contact = kernels(ocp).numeric().contact
    cell = np.minimum((t / ocp.dt).astype(int), ocp.steps - 1)
    psi = np.empty((t.size, len(ocp.guards)))
    rate = np.empty_like(psi)
    noise = np.empty_like(psi)
    for k in range(t.size):
        p, r, _, nz = contact(x[k], u[cell[k]])
        psi[k], rate[k], noise[k] = p, r, nz
    found = []
    for j, guard in enumerate(ocp.guards):
        level = noise[:, j]
        inside = psi[:, j] <= level
        last_entry = None
        for i in range(t.size - 1):
            p0, p1, r0, r1 = psi[i, j], psi[i + 1, j], rate[i, j], rate[i + 1, j]
            if not (r0 < 0.0 <= r1):
                continue
            h = t[i + 1] - t[i]
            reached = inside[i] or inside[i + 1]
            if not (reached or p0 + r0 * h <= level[i] or p1 - r1 * h <= level[i + 1]):
                continue
            if inside[i]:
                m = i
                while m >= 0 and inside[m]:
                    m -= 1
                if m == last_entry:  # the same contact, reversing again while it lasts
                    continue
                last_entry = m
                if m < 0:
                    when = t[0]
                else:
                    a, b = psi[m, j], psi[m + 1, j]
                    when = t[m] + (t[m + 1] - t[m]) * (a / (a - b) if a > b else 1.0)
            else:
                last_entry = None
                when = t[i] + min(max(p0 / -r0, 0.0), h)
            found.append(
                {
                    "time": float(when),
                    "guard": guard.name,
                    "kind": guard.kind,
                    "bodies": list(guard.bodies),
                    "sample": i,
                }
            )
    found.sort(key=lambda e: (e["time"], e["sample"]))
    return found


def _pair(judge: list[dict[str, Any]], given: list[dict[str, Any]]) -> list[EventMatch]:
    names = list(dict.fromkeys([e["guard"] for e in judge] + [e["guard"] for e in given]))
    out = []
    for name in names:
        a = [e["time"] for e in judge if e["guard"] == name]
        b = [e["time"] for e in given if e["guard"] == name]
        for k in range(max(len(a), len(b))):
            out.append(EventMatch(name, a[k] if k < len(a) else None, b[k] if k < len(b) else None))
    first = [min(x for x in (m.judge_time, m.given_time) if x is not None) for m in out]
    return [m for _, m in sorted(zip(first, out, strict=True), key=lambda p: p[0])]


def compare_trajectory(
    problem: ProblemLike,
    times: Any,
    states: Any,
    controls: ControlsLike | None = None,
    *,
    substeps: int = 1,
) -> TrajectoryComparison:
    """Compare a sampled trajectory from another simulator with the judge's.

    Parameters
    ----------
    problem
        Any problem.
    times
        ``(M,)`` nondecreasing times in ``[0, T]`` (a repeated time is a jump recorded
        twice: module notes).
    states
        ``(M, nx)`` states at those times, in the order of the problem's state labels.
    controls
        The controls the trajectory was run with (a Solution is accepted); default: the
        problem's initial guess.
    substeps
        ``K``: the controls hold ``K`` values per grid interval (a simulator's log at ``K``
        substeps) and are judged on the ``K`` times finer grid
        (:func:`hybridoc.io.substep_problem`).

    Returns
    -------
    TrajectoryComparison

    Raises
    ------
    TrajectoryError
        Shapes that do not fit the problem, NaN or infinity, decreasing times, or times
        outside ``[0, T]``.
    """
    from hybridoc.evaluator import evaluate
    from hybridoc.io import substep_problem

    ocp = substep_problem(as_ocp(problem), substeps)
    t, x = _checked(ocp, times, states)
    ev = evaluate(ocp, controls)
    judge = _judge_at(ev, t)
    given_events = detect_events(ocp, t, x, ev.controls)
    judge_events = ev.event_dicts()
    return TrajectoryComparison(
        problem=ocp.name,
        cost=float(ev.cost),
        times=t,
        states=x,
        judge_states=judge,
        state_labels=list(ocp.state_labels or [f"s{k}" for k in range(ocp.nx)]),
        judge_events=judge_events,
        given_events=given_events,
        matches=_pair(judge_events, given_events),
        evaluation=ev,
        substeps=int(substeps),
    )


def trajectory_figure(comparison: TrajectoryComparison, *, label: str = "given") -> Any:
    """The state error against time, and the guards that fire, with both trajectories'
    event times marked.

    Top: ``|error|`` of each state component (the components with the largest errors when
    there are more than eight) and its norm, on a log scale (an error of exactly zero is
    drawn at the floor of ``1e-16`` times the states' scale). Bottom: each guard that fires
    in either trajectory, the judge's ``psi(t)`` (line, sampled densely) against the given
    states' (dots). Judge's events: grey solid lines; the given trajectory's: red dashed.

    Parameters
    ----------
    comparison
        A :func:`compare_trajectory` result.
    label
        The legend name of the given trajectory.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure

    from hybridoc.kernels import kernels

    c = comparison
    ev = c.evaluation
    ocp = ev.ocp
    guards = list(dict.fromkeys(e["guard"] for e in c.judge_events + c.given_events))
    panels = 2 if guards else 1
    fig = Figure(figsize=(7.5, 3.2 * panels + 0.5), layout="constrained")
    axes = fig.subplots(panels, 1, sharex=True, squeeze=False)[:, 0]
    err = np.abs(c.error)
    floor = 1e-16 * max(1.0, float(np.abs(c.states).max()))
    order = np.argsort(-err.max(axis=0))
    shown = order if err.shape[1] <= 8 else order[:6]
    ax = axes[0]
    # the norm underneath: where one component carries the error, its line lies on top
    ax.semilogy(c.times, np.maximum(c.error_norm, floor), color="0.75", lw=3.5, label="norm")
    for j in sorted(shown):
        ax.semilogy(c.times, np.maximum(err[:, j], floor), lw=1.0, label=c.state_labels[j])
    ax.set_ylabel(f"|{label} - judge|")
    ax.legend(fontsize=7, ncol=3, loc="best")
    if panels == 2:
        ax = axes[1]
        dense = np.union1d(np.linspace(0.0, ocp.horizon, 2001), [e["time"] for e in c.judge_events])
        sj = ev.sample(dense)
        contact = kernels(ocp).numeric().contact
        names = [g.name for g in ocp.guards]
        cell = np.minimum((c.times / ocp.dt).astype(int), ocp.steps - 1)
        dcell = np.minimum((dense / ocp.dt).astype(int), ocp.steps - 1)
        for n, name in enumerate(guards):
            j = names.index(name)
            pj = [float(contact(s, ev.controls[k])[0][j]) for s, k in zip(sj, dcell, strict=True)]
            pg = [
                float(contact(s, ev.controls[k])[0][j]) for s, k in zip(c.states, cell, strict=True)
            ]
            ax.plot(dense, pj, color=f"C{n}", lw=1.2, label=f"{name} (judge)")
            ax.plot(c.times, pg, ".", color=f"C{n}", ms=2.5, label=f"{name} ({label})")
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_ylabel("guard psi")
        ax.legend(fontsize=7, loc="best")
    axes[-1].set_xlabel("time")
    for ax in axes:
        for k, e in enumerate(c.judge_events):
            ax.axvline(e["time"], color="0.45", lw=0.9, label="judge's events" if k == 0 else None)
        for e in c.given_events:
            ax.axvline(e["time"], color="C3", ls="--", lw=0.9)
        ax.grid(True, lw=0.4, alpha=0.5)
    shift = c.max_event_shift
    text = "" if shift is None else f", largest event shift {shift:.3g}"
    fig.suptitle(
        f"{c.problem}: {label} trajectory against the judge's\n(max |error| "
        f"{float(c.error_norm.max()):.3g}{text}; events: judge grey, {label} red dashed)",
        fontsize=9,
    )
    return fig
