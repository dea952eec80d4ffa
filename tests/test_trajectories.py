"""Another simulator's trajectory against the judge's (hybridoc.workflows.trajectories): the
judge's own trajectory compares with no error and the same events; a moved body shifts the
event by its closed-form amount; a penetrating (penalty) simulator's contact is one event at
its closed-form entry time; bad input is one clear error."""

from __future__ import annotations

import math

import numpy as np
import pytest

import hybridoc
from hybridoc import Disc, Scene
from hybridoc.problems.library.bouncing_ball import bouncing_ball
from hybridoc.workflows.trajectories import (
    TrajectoryError,
    compare_trajectory,
    detect_events,
    trajectory_figure,
)

N = 40
PUSH = 2.0  # constant force on the striker: x(t) = t^2, contact when x = gap


def head_on(target_x: float = 1.0, velocity: float = 0.0) -> Scene:
    return Scene(
        horizon=1.0,
        steps=N,
        discs=(
            Disc(name="a", position=(0.0, 0.0), radius=0.2, velocity=(velocity, 0.0),
                 actuated=True),
            Disc(name="b", position=(target_x, 0.0), radius=0.2, target=(2.0, 0.0)),
        ),
    )  # fmt: skip


def push(steps: int = N) -> np.ndarray:
    return np.tile([PUSH, 0.0], (steps, 1))


@pytest.mark.parametrize("problem", ["scene", "ball"])
def test_judge_trajectory_has_no_error(problem):
    ocp = head_on().to_ocp() if problem == "scene" else bouncing_ball(bounces=2, steps=N)
    u = push() if problem == "scene" else ocp.u_guess
    ev = hybridoc.evaluate(ocp, u)
    assert ev.events
    # the judge records each event twice (before and after the jump, at one time)
    assert np.sum(np.diff(ev.times) == 0) == len(ev.events)
    c = compare_trajectory(ocp, ev.times, ev.states, u)
    # the same flow from the same segment starts: equal to rounding (the ball's flow is an
    # integrator's, its recorded states one step of it)
    assert np.abs(c.error).max() <= 1e-14 * np.abs(ev.states).max()
    assert c.sequence_matches and len(c.matches) == len(ev.events)
    for m, e in zip(c.matches, ev.events, strict=True):
        assert m.judge_time == e.time
        assert abs(m.shift) <= 1e-14
    assert c.cost == ev.cost


def test_moved_target_shifts_the_event():
    delta = 0.05
    ocp = head_on().to_ocp()
    moved = head_on(1.0 + delta).to_ocp()
    t_judge, t_moved = math.sqrt(0.6), math.sqrt(0.6 + delta)  # gap 1 - 0.4, x = t^2
    ev = hybridoc.evaluate(moved, push())
    assert ev.events[0].time == pytest.approx(t_moved, rel=1e-13)
    c = compare_trajectory(ocp, ev.times, ev.states, push())
    assert c.judge_events[0]["time"] == pytest.approx(t_judge, rel=1e-13)
    (m,) = c.matches
    assert m.shift == pytest.approx(t_moved - t_judge, rel=1e-12)
    # sampled on a plain grid (no sample at the event): the shift to O(h^2)
    times = np.linspace(0.0, 1.0, 401)
    c = compare_trajectory(ocp, times, ev.sample(times), push())
    (m,) = c.matches
    assert abs(m.shift - (t_moved - t_judge)) < 1e-5
    # the error: b's initial offset delta before either event
    early = times < t_judge
    assert np.allclose(c.error[early], [0, 0, delta, 0, 0, 0, 0, 0], rtol=0, atol=1e-14)


def penalty_rollout(ocp, stiffness=1e5, dt=1e-3):
    """A soft-contact simulator (semi-implicit Euler, a spring on the penetration)."""
    x = np.array(ocp.x0, dtype=float)
    ts, xs = [0.0], [x.copy()]
    for i in range(round(ocp.horizon / dt)):
        pa, pb, va, vb = x[0:2], x[2:4], x[4:6], x[6:8]
        d = pb - pa
        dist = np.linalg.norm(d)
        force = stiffness * max(0.4 - dist, 0.0) * d / dist
        va, vb = va - force * dt, vb + force * dt
        x = np.concatenate([pa + va * dt, pb + vb * dt, va, vb])
        ts.append((i + 1) * dt)
        xs.append(x.copy())
    return np.array(ts), np.array(xs)


def test_penetrating_contact_is_one_event_at_its_entry():
    ocp = head_on(velocity=1.0).to_ocp()  # coasting at speed 1 into a gap of 0.6
    times, states = penalty_rollout(ocp)
    gap = np.linalg.norm(states[:, 2:4] - states[:, 0:2], axis=1) - 0.4
    assert np.sum(gap < 0) > 3  # the contact lasts several steps
    events = detect_events(ocp, times, states, np.zeros((N, 2)))
    assert len(events) == 1 and events[0]["guard"] == "a|b"
    assert events[0]["time"] == pytest.approx(0.6, abs=1e-12)
    c = compare_trajectory(ocp, times, states, np.zeros((N, 2)))
    assert c.judge_events[0]["time"] == pytest.approx(0.6, abs=1e-14)
    assert abs(c.matches[0].shift) < 1e-12
    # before contact the semi-implicit steps of a free body are exact to rounding
    assert np.abs(c.error[times < 0.599]).max() < 1e-12
    # during the soft contact, velocities differ by O(1) from the instantaneous exchange
    assert np.abs(c.error[:, 4]).max() > 0.5


def test_no_event_found_without_contact():
    ocp = head_on(velocity=-1.0).to_ocp()  # moving away
    ev = hybridoc.evaluate(ocp, np.zeros((N, 2)))
    c = compare_trajectory(ocp, ev.times, ev.states, np.zeros((N, 2)))
    assert c.judge_events == [] and c.given_events == [] and c.matches == []


def test_bad_input():
    ocp = head_on().to_ocp()
    ev = hybridoc.evaluate(ocp, push())
    t, x = ev.times, ev.states
    cases = [
        ((t[:5], x), r"states: expected shape \(5, 8\)"),
        ((t, x[:, :7]), r"expected shape \(\d+, 8\) .*a\.x, a\.y"),
        ((t[:1], x[:1]), "at least 2 times"),
        ((t[::-1], x), "times: must not decrease"),
        ((t + 0.5, x), r"must lie in \[0, T\]"),
        ((np.where(np.arange(t.size) == 3, np.nan, t), x), "times: non-finite value at row 3"),
        ((t, np.where(np.arange(t.size)[:, None] == 2, np.inf, x)), "states: non-finite .* row 2"),
    ]
    for (tt, xx), match in cases:
        with pytest.raises(TrajectoryError, match=match):
            compare_trajectory(ocp, tt, xx, push())


def test_figure_and_report():
    # drawn to PNG by the command-line test; here the figure is built and read back
    ocp = head_on(velocity=1.0).to_ocp()
    times, states = penalty_rollout(ocp, dt=5e-3)
    c = compare_trajectory(ocp, times, states, np.zeros((N, 2)))
    fig = trajectory_figure(c, label="penalty")
    top, bottom = fig.axes[:2]
    assert top.get_yscale() == "log" and bottom.get_ylabel() == "guard psi"
    marked = [ln.get_xdata()[0] for ln in bottom.get_lines() if ln.get_linestyle() == "--"]
    assert marked == pytest.approx([c.given_events[0]["time"]])
    d = c.to_dict()
    assert d["samples"] == times.size and len(d["error_norm"]) == times.size
    assert d["events"][0]["guard"] == "a|b" and d["sequence_matches"]
