"""The independent disc oracle (tests/oracle.py) against closed forms derived by hand."""

from __future__ import annotations

import importlib.util
import itertools
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

# Load tests/oracle.py by path, so that this works whatever pytest's import mode or sys.path.
_SPEC = importlib.util.spec_from_file_location(
    "_disc_oracle", Path(__file__).with_name("oracle.py")
)
assert _SPEC is not None and _SPEC.loader is not None
oracle = importlib.util.module_from_spec(_SPEC)
sys.modules[_SPEC.name] = oracle
_SPEC.loader.exec_module(oracle)


def disc(
    name: str, position, velocity=(0.0, 0.0), radius=0.2, mass=1.0, actuated=False, target=None
):
    return {
        "name": name,
        "position": position,
        "velocity": velocity,
        "radius": radius,
        "mass": mass,
        "actuated": actuated,
        "target": target,
    }


def wall(name: str, point, normal) -> dict[str, Any]:
    return {"name": name, "point": point, "normal": normal}


def scene(discs, walls=(), horizon=1.0, steps=1, restitution=1.0, control_weight=0.0):
    return {
        "horizon": horizon,
        "steps": steps,
        "control_weight": control_weight,
        "restitution": restitution,
        "discs": list(discs),
        "walls": list(walls),
    }


def no_controls(sc: dict[str, Any]) -> np.ndarray:
    return np.zeros((sc["steps"], 0))


def split(state: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions (n, 2) and velocities (n, 2) of a final state."""
    return state[: 2 * n].reshape(n, 2), state[2 * n :].reshape(n, 2)


# 1. Head-on collision in 1-D --------------------------------------------------------------


@pytest.mark.parametrize(
    ("m_a", "m_b", "e"), [(1.0, 1.0, 1.0), (1.0, 1.0, 0.5), (1.0, 3.0, 1.0), (2.0, 0.5, 0.3)]
)
def test_head_on_collision(m_a: float, m_b: float, e: float) -> None:
    # a at x=0 moving right at u=1 towards b at rest at x=1; radii 0.1: gap 0.8, hit at t=0.8.
    u = 1.0
    sc = scene(
        [disc("a", (0.0, 0.0), (u, 0.0), 0.1, m_a), disc("b", (1.0, 0.0), (0.0, 0.0), 0.1, m_b)],
        horizon=2.0,
        steps=4,
        restitution=e,
    )
    res = oracle.simulate(sc, no_controls(sc))
    assert len(res.events) == 1
    (t_ev, name) = res.events[0]
    assert name == "a|b"
    assert t_ev == pytest.approx(0.8, abs=1e-13)
    # 1-D impulse with restitution: v_a' = (m_a - e m_b) u / M, v_b' = (1 + e) m_a u / M.
    total = m_a + m_b
    va, vb = (m_a - e * m_b) * u / total, (1.0 + e) * m_a * u / total
    pos, vel = split(res.final_state, 2)
    np.testing.assert_allclose(vel, [[va, 0.0], [vb, 0.0]], rtol=0, atol=1e-13)
    np.testing.assert_allclose(
        pos, [[0.8 + va * 1.2, 0.0], [1.0 + vb * 1.2, 0.0]], rtol=0, atol=1e-12
    )
    assert m_a * vel[0, 0] + m_b * vel[1, 0] == pytest.approx(m_a * u, abs=1e-13)
    if m_a == m_b and e == 1.0:
        assert vel[0, 0] == pytest.approx(0.0, abs=1e-15)
        assert vel[1, 0] == pytest.approx(u, abs=1e-15)
    if m_a == m_b and e == 0.5:
        np.testing.assert_allclose(vel[:, 0], [0.25, 0.75], rtol=0, atol=1e-15)
    assert res.min_gaps["a|b"] == pytest.approx(0.0, abs=1e-12)
    assert res.min_gaps["a|b"] > -1e-12


# 2. Constant force from rest towards a wall -------------------------------------------------


@pytest.mark.parametrize("e", [1.0, 0.5])
def test_constant_force_into_wall(e: float) -> None:
    # Gap D = 0.5 to the floor y = 0, mass 2, force 4 downwards: t* = sqrt(2 D m / F).
    D, m, F, r = 0.5, 2.0, 4.0, 0.25
    eps, horizon, steps = 0.1, 1.0, 5
    t_star = math.sqrt(2.0 * D * m / F)
    acc = F / m
    sc = scene(
        [disc("d", (0.3, r + D), (0.0, 0.0), r, m, actuated=True, target=(0.0, 0.0))],
        [wall("floor", (0.0, 0.0), (0.0, 1.0))],
        horizon=horizon,
        steps=steps,
        restitution=e,
        control_weight=eps,
    )
    controls = np.tile([0.0, -F], (steps, 1))
    res = oracle.simulate(sc, controls)
    assert [n for _, n in res.events] == ["d|floor"]
    assert res.events[0][0] == pytest.approx(t_star, abs=1e-13)
    # Impact speed acc t*, reversed and scaled by e; then decelerating for tau = T - t*.
    v_up = e * acc * t_star
    tau = horizon - t_star
    y_final = r + v_up * tau - 0.5 * acc * tau**2
    pos, vel = split(res.final_state, 1)
    np.testing.assert_allclose(pos, [[0.3, y_final]], rtol=0, atol=1e-12)
    np.testing.assert_allclose(vel, [[0.0, v_up - acc * tau]], rtol=0, atol=1e-12)
    terminal = 0.3**2 + y_final**2
    running = eps * steps * F**2 * horizon / steps
    assert res.terminal_cost == pytest.approx(terminal, rel=1e-12)
    assert res.running_cost == pytest.approx(running, rel=1e-14)
    assert res.cost == pytest.approx(terminal + running, rel=1e-12)


# 3. Periodic series driven by a constant force -------------------------------------------


def periodic_scene(horizon: float, steps: int) -> tuple[dict[str, Any], np.ndarray]:
    sc = scene(
        [disc("a", (-1.0, -2.0), actuated=True), disc("b", (-1.0, -1.0))],
        horizon=horizon,
        steps=steps,
    )
    return sc, np.tile([0.0, 3.0], (steps, 1))


@pytest.mark.parametrize(
    ("horizon", "steps"),
    # 791 collisions in a long horizon (about 5 s): the scale is in the slow tier, the
    # behaviour (40 collisions) in CI
    [(50.0, 25), pytest.param(1000.0, 120, marks=pytest.mark.slow)],
)
def test_periodic_series(horizon: float, steps: int) -> None:
    # a accelerates at 3 towards b: gap 0.6 = 1.5 t^2, so t1 = sqrt(0.4). Each elastic exchange
    # leaves a at the speed b had and b faster by w = 3 t1; the centre distance then follows
    # 0.4 + w t - 1.5 t^2, so the next touch is w / 1.5 = 2 sqrt(0.4) later, every time.
    t1 = math.sqrt(0.4)
    period = 2.0 * t1
    assert period == pytest.approx(1.2649110640673518, rel=1e-15)
    sc, controls = periodic_scene(horizon, steps)
    res = oracle.simulate(sc, controls)
    times = np.array([t for t, _ in res.events])
    assert {n for _, n in res.events} == {"a|b"}
    expected = math.floor((horizon - t1) / period) + 1  # 40 for T = 50, 791 for T = 1000
    assert len(times) == expected
    assert times[0] == pytest.approx(t1, abs=1e-13)
    # By T = 1000 the discs are near y = 7.5e5 and move at 1500, where one ulp of a coordinate
    # is 1.2e-10: each collision time is then only determined to ~1e-10 and those errors
    # random-walk through the neutral dynamics (about 2e-7 after 791 collisions).
    spacing_tol, time_tol = (1e-11, 1e-10) if horizon < 100 else (1e-8, 1e-6)
    np.testing.assert_allclose(np.diff(times), period, rtol=0, atol=spacing_tol)
    np.testing.assert_allclose(times, t1 + period * np.arange(expected), rtol=0, atol=time_tol)
    pos, vel = split(res.final_state, 2)
    assert pos[0, 1] < pos[1, 1]  # a never ends above b
    # By T = 1000 the discs are near y = 7.5e5, where one ulp is about 1.2e-10.
    assert res.min_gaps["a|b"] > -16 * np.spacing(np.max(np.abs(pos)))
    # Momentum: the force 3 acted for T on the pair (initial momentum 0).
    assert vel[:, 1].sum() == pytest.approx(3.0 * horizon, rel=1e-12)


# 4. Right-angled corner -----------------------------------------------------------------------


@pytest.mark.parametrize("e", [1.0, 0.5])
def test_corner_hits_both_walls_at_once(e: float) -> None:
    sc = scene(
        [disc("d", (1.2, 1.2), (-1.0, -1.0), 0.2)],
        [wall("wx", (0.0, 0.0), (1.0, 0.0)), wall("wy", (0.0, 0.0), (0.0, 1.0))],
        horizon=2.0,
        steps=2,
        restitution=e,
    )
    res = oracle.simulate(sc, no_controls(sc))
    assert res.events == [(1.0, "d|wx"), (1.0, "d|wy")]
    pos, vel = split(res.final_state, 1)
    np.testing.assert_allclose(vel, [[e, e]], rtol=0, atol=1e-14)
    np.testing.assert_allclose(pos, [[0.2 + e, 0.2 + e]], rtol=0, atol=1e-13)


# 5. Striker hitting two symmetric discs -------------------------------------------------------


def striker_scene(y_low: float) -> dict[str, Any]:
    return scene(
        [
            disc("s", (-1.0, 0.0), (4.0, 0.0)),
            disc("u", (0.0, 0.25)),
            disc("l", (0.0, y_low)),
        ],
        horizon=1.0,
        steps=4,
    )


def test_striker_symmetric_is_simultaneous_and_order_dependent() -> None:
    # Touch when x^2 + 0.25^2 = 0.4^2, x = -sqrt(0.0975): both at t_c = (1 - sqrt(0.0975)) / 4
    # (mirror images, the same instant). The contact normals are not orthogonal, so applying
    # one impulse first changes the other's approach speed: the outcome depends on the order.
    t_c = (1.0 - math.sqrt(0.0975)) / 4.0
    sc = striker_scene(-0.25)
    with pytest.raises(oracle.SimultaneousImpact) as info:
        oracle.simulate(sc, np.zeros((4, 0)))
    assert isinstance(info.value, ValueError)
    assert set(info.value.guards) == {"s|u", "s|l"}
    assert info.value.time == pytest.approx(t_c, abs=1e-12)
    assert "s|u" in str(info.value) and "s|l" in str(info.value)
    # Before the contact nothing happens.
    early = dict(sc, horizon=0.9 * t_c)
    assert oracle.simulate(early, np.zeros((4, 0))).events == []


def test_striker_asymmetric_is_sequential() -> None:
    # Lower disc at y = -0.26: its contact would need x = -sqrt(0.0924) > -sqrt(0.0975), later.
    t_u = (1.0 - math.sqrt(0.0975)) / 4.0
    res = oracle.simulate(striker_scene(-0.26), np.zeros((4, 0)))
    assert res.events[0][1] == "s|u"
    assert res.events[0][0] == pytest.approx(t_u, abs=1e-13)
    _, vel = split(res.final_state, 3)
    assert vel.sum(axis=0) == pytest.approx([4.0, 0.0], abs=1e-12)  # momentum


# 6. Restitution 0 with a force pushing into a wall ----------------------------------------


def test_sustained_contact() -> None:
    sc = scene(
        [disc("d", (0.0, 0.5), radius=0.2, actuated=True)],
        [wall("floor", (0.0, 0.0), (0.0, 1.0))],
        horizon=3.0,
        steps=3,
        restitution=0.0,
    )
    with pytest.raises(oracle.SustainedContact) as info:
        oracle.simulate(sc, np.tile([0.0, -1.0], (3, 1)))
    assert info.value.guard == "d|floor"
    assert info.value.time >= math.sqrt(0.6)  # after the impact at t = sqrt(2 * 0.3 / 1)
    assert isinstance(info.value, ValueError)
    # Without a force, a disc falling at constant speed stops on the floor: no error.
    falling = scene(
        [disc("d", (0.0, 0.5), (0.0, -1.0), radius=0.2, actuated=True)],
        [wall("floor", (0.0, 0.0), (0.0, 1.0))],
        horizon=3.0,
        steps=3,
        restitution=0.0,
    )
    res = oracle.simulate(falling, np.zeros((3, 2)))
    assert res.events == [(pytest.approx(0.3, abs=1e-13), "d|floor")]
    pos, vel = split(res.final_state, 1)
    np.testing.assert_allclose(vel, 0.0, rtol=0, atol=1e-14)
    np.testing.assert_allclose(pos, [[0.0, 0.2]], rtol=0, atol=1e-13)


# 7. Pass-through traps: long grid intervals, high speeds ---------------------------------


def test_fast_discs_long_interval_still_collide() -> None:
    # Intervals of length 100; the discs close at 200 and overlap for only 0.002 s.
    sc = scene(
        [
            disc("a", (-50.0, 0.0), (100.0, 0.0), 0.1),
            disc("b", (50.0, 0.0), (-100.0, 0.0), 0.1),
        ],
        horizon=1000.0,
        steps=10,
    )
    res = oracle.simulate(sc, no_controls(sc))
    assert [n for _, n in res.events] == ["a|b"]
    assert res.events[0][0] == pytest.approx(99.8 / 200.0, abs=1e-12)
    pos, vel = split(res.final_state, 2)
    np.testing.assert_allclose(vel, [[-100.0, 0.0], [100.0, 0.0]], rtol=0, atol=1e-12)
    x_end = 0.1 + 100.0 * (1000.0 - 0.499)
    np.testing.assert_allclose(pos, [[-x_end, 0.0], [x_end, 0.0]], rtol=1e-13)


def test_fast_disc_between_two_walls_single_interval() -> None:
    # Width 1, radius 0.1, speed 100, one grid interval: bounces at 0.004 + 0.008 k.
    sc = scene(
        [disc("d", (0.5, 0.5), (100.0, 0.0), 0.1)],
        [wall("left", (0.0, 0.0), (1.0, 0.0)), wall("right", (1.0, 0.0), (-1.0, 0.0))],
        horizon=1.0,
        steps=1,
    )
    res = oracle.simulate(sc, no_controls(sc))
    times = np.array([t for t, _ in res.events])
    assert len(times) == 125
    np.testing.assert_allclose(times, 0.004 + 0.008 * np.arange(125), rtol=0, atol=1e-12)
    assert [n for _, n in res.events] == ["d|right", "d|left"] * 62 + ["d|right"]
    pos, vel = split(res.final_state, 1)
    np.testing.assert_allclose(pos, [[0.5, 0.5]], rtol=0, atol=1e-10)
    np.testing.assert_allclose(vel, [[-100.0, 0.0]], rtol=0, atol=1e-12)


# Further closed forms and checks ------------------------------------------------------------


def test_newtons_cradle_cascade() -> None:
    # b and c touch exactly (centres 0.4 apart); a hits b at t = 0.6: the momentum passes on.
    sc = scene(
        [disc("a", (-1.0, 0.0), (1.0, 0.0)), disc("b", (0.0, 0.0)), disc("c", (0.4, 0.0))],
        horizon=1.0,
        steps=2,
    )
    res = oracle.simulate(sc, no_controls(sc))
    assert [n for _, n in res.events] == ["a|b", "b|c"]
    assert res.events[0][0] == pytest.approx(0.6, abs=1e-13)
    assert res.events[1][0] == res.events[0][0]
    pos, vel = split(res.final_state, 3)
    np.testing.assert_allclose(vel[:, 0], [0.0, 0.0, 1.0], rtol=0, atol=1e-13)
    np.testing.assert_allclose(pos[:, 0], [-0.4, 0.0, 0.8], rtol=0, atol=1e-12)


def test_independent_simultaneous_pairs_are_applied() -> None:
    sc = scene(
        [
            disc("a", (-1.0, 0.0), (1.0, 0.0)),
            disc("b", (1.0, 0.0), (-1.0, 0.0)),
            disc("c", (-1.0, 5.0), (1.0, 0.0)),
            disc("d", (1.0, 5.0), (-1.0, 0.0)),
        ],
        horizon=1.0,
        steps=1,
    )
    res = oracle.simulate(sc, no_controls(sc))
    assert [n for _, n in res.events] == ["a|b", "c|d"]
    assert all(t == pytest.approx(0.8, abs=1e-13) for t, _ in res.events)
    _, vel = split(res.final_state, 4)
    np.testing.assert_allclose(vel[:, 0], [-1.0, 1.0, -1.0, 1.0], rtol=0, atol=1e-13)


def test_near_graze_reported_in_min_gaps() -> None:
    # a passes b with the centre distance at least 0.401: closest gap 1e-3 at t = 2, no event.
    sc = scene([disc("a", (-2.0, 0.0), (1.0, 0.0)), disc("b", (0.0, 0.401))], horizon=4.0, steps=2)
    res = oracle.simulate(sc, no_controls(sc))
    assert res.events == []
    assert 1e-3 - 1e-12 <= res.min_gaps["a|b"] <= 1.05e-3


def test_elastic_box_conserves_energy() -> None:
    rng = np.random.default_rng(7)
    names = "pqrs"
    discs = [
        disc(n, (x, y), tuple(rng.uniform(-2.0, 2.0, 2)), 0.3, float(rng.uniform(0.5, 2.0)))
        for n, (x, y) in zip(names, [(1.0, 1.0), (3.0, 1.0), (1.0, 3.0), (3.0, 3.0)], strict=True)
    ]
    walls = [
        wall("W", (0.0, 0.0), (1.0, 0.0)),
        wall("E", (4.0, 0.0), (-1.0, 0.0)),
        wall("S", (0.0, 0.0), (0.0, 1.0)),
        wall("N", (0.0, 4.0), (0.0, -1.0)),
    ]
    sc = scene(discs, walls, horizon=6.0, steps=3)
    res = oracle.simulate(sc, no_controls(sc))
    masses = np.array([d["mass"] for d in discs])
    v0 = np.array([d["velocity"] for d in discs])
    _, v1 = split(res.final_state, 4)
    ke = lambda v: 0.5 * float(np.sum(masses * np.sum(v**2, axis=1)))  # noqa: E731
    assert len(res.events) > 5
    assert ke(v1) == pytest.approx(ke(v0), rel=1e-12)
    assert min(res.min_gaps.values()) > -1e-12
    names_seen = {n for _, n in res.events}
    pair_names = {f"{a}|{b}" for a, b in itertools.combinations(names, 2)}
    wall_names = {f"{a}|{w}" for a in names for w in "WESN"}
    assert names_seen <= pair_names | wall_names


def test_bad_controls_shape() -> None:
    sc, _ = periodic_scene(1.0, 4)
    with pytest.raises(ValueError, match="shape"):
        oracle.simulate(sc, np.zeros((3, 2)))


def test_force_switching_between_intervals() -> None:
    # Force +1 on [0, 1), -1 on [1, 2): at t = 1, x = 0.5, v = 1; then x = 0.5 + tau - tau^2 / 2
    # meets the wall (gap 0.4) at tau = 1 - sqrt(0.2) with speed sqrt(0.2); after the elastic
    # bounce the same deceleration acts for the remaining sqrt(0.2).
    sc = scene(
        [disc("d", (0.0, 0.0), radius=0.1, actuated=True)],
        [wall("R", (1.0, 0.0), (-1.0, 0.0))],
        horizon=2.0,
        steps=2,
    )
    res = oracle.simulate(sc, np.array([[1.0, 0.0], [-1.0, 0.0]]))
    q = math.sqrt(0.2)
    assert res.events == [(pytest.approx(2.0 - q, abs=1e-13), "d|R")]
    pos, vel = split(res.final_state, 1)
    np.testing.assert_allclose(pos, [[0.9 - 1.5 * q * q, 0.0]], rtol=0, atol=1e-13)
    np.testing.assert_allclose(vel, [[-2.0 * q, 0.0]], rtol=0, atol=1e-13)


def test_bouncing_ball_is_periodic() -> None:
    # Drop height 1 under acceleration 1, e = 1: hits at sqrt(2) + 2 sqrt(2) k.
    sc = scene(
        [disc("d", (0.0, 1.2), actuated=True)],
        [wall("F", (0.0, 0.0), (0.0, 1.0))],
        horizon=100.0,
        steps=10,
    )
    res = oracle.simulate(sc, np.tile([0.0, -1.0], (10, 1)))
    times = np.array([t for t, _ in res.events])
    count = math.floor((100.0 - math.sqrt(2.0)) / (2.0 * math.sqrt(2.0))) + 1
    assert len(times) == count
    np.testing.assert_allclose(
        times, math.sqrt(2.0) * (1.0 + 2.0 * np.arange(count)), rtol=0, atol=1e-11
    )


@pytest.mark.parametrize(("inside", "events"), [(0.0, 0), (1e-9, 1), (1e-6, 1)])
def test_tangent_pass(inside: float, events: int) -> None:
    # a moves along y = 0 past b at height 0.4 - inside (radii 0.2). Exactly tangent: a graze,
    # no jump. Slightly inside: a real, glancing contact at 2 - sqrt(0.16 - (0.4 - inside)^2).
    height = 0.4 - inside
    sc = scene([disc("a", (-2.0, 0.0), (1.0, 0.0)), disc("b", (0.0, height))], horizon=4.0, steps=2)
    res = oracle.simulate(sc, no_controls(sc))
    assert len(res.events) == events
    if events:
        t_c = 2.0 - math.sqrt(0.16 - height**2)
        assert res.events[0] == (pytest.approx(t_c, abs=1e-9), "a|b")
    else:
        _, vel = split(res.final_state, 2)
        np.testing.assert_allclose(vel, [[1.0, 0.0], [0.0, 0.0]], rtol=0, atol=0.0)


def test_wedged_disc_is_zeno() -> None:
    # A disc that fits exactly between two walls and moves: infinitely many events at t = 0.
    sc = scene(
        [disc("d", (0.5, 0.0), (1.0, 0.0), 0.5)],
        [wall("L", (0.0, 0.0), (1.0, 0.0)), wall("R", (1.0, 0.0), (-1.0, 0.0))],
    )
    with pytest.raises(oracle.ZenoError):
        oracle.simulate(sc, no_controls(sc))
