"""The event-exact evaluator against closed forms and conservation laws."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.polynomial import polynomial as P

import hybridoc
from hybridoc import ControlsError, Disc, EvaluationError, Scene, Wall, load_scene


def masses(scene: Scene) -> np.ndarray:
    return np.array([d.mass for d in scene.discs])


def velocities(scene: Scene, s: np.ndarray) -> np.ndarray:
    return s[2 * scene.n_discs :].reshape(scene.n_discs, 2)


def positions(scene: Scene, s: np.ndarray) -> np.ndarray:
    return s[: 2 * scene.n_discs].reshape(scene.n_discs, 2)


def kinetic(scene: Scene, s: np.ndarray) -> float:
    v = velocities(scene, s)
    return float(0.5 * np.sum(masses(scene) * np.sum(v**2, axis=1)))


def momentum(scene: Scene, s: np.ndarray) -> np.ndarray:
    return masses(scene) @ velocities(scene, s)


def perturbed(scene: Scene, scale: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    u = scene.initial_controls()
    return u + scale * rng.standard_normal(u.shape)


def free_disc_scene(**kw) -> Scene:
    """One actuated disc far from everything (no guards can fire)."""
    args = dict(
        horizon=1.5,
        steps=30,
        control_weight=0.02,
        discs=(
            Disc(
                "a",
                (0.3, -0.2),
                0.1,
                velocity=(0.5, 1.0),
                mass=2.0,
                actuated=True,
                initial_control=(1.2, -0.7),
                target=(1.0, 1.0),
            ),
        ),
    )
    args.update(kw)
    return Scene(**args)


# ----------------------------------------------------------------- event times: closed forms
def test_single_collision_initial_guess_closed_form():
    sc = load_scene("single-collision")
    ev = hybridoc.evaluate(sc)
    # y1 = -2 + 1.5 t^2 closes the gap 0.6 to ball2 at 1.5 t^2 = 0.6
    t_star = math.sqrt(0.4)
    assert len(ev.events) == 1
    e = ev.events[0]
    assert (e.kind, e.bodies, e.guard) == ("disc-disc", ("ball1", "ball2"), 0)
    assert e.time == pytest.approx(t_star, abs=2e-15)
    assert e.approach_speed == pytest.approx(-3 * t_star, rel=1e-14)
    # head-on, equal masses, e = 1: the velocities are exchanged
    np.testing.assert_allclose(e.state_after[4:], [0, 0, 0, 3 * t_star], atol=1e-14)
    y2_T = -1 + 3 * t_star * (1 - t_star)
    assert ev.terminal_cost == pytest.approx(1 + y2_T**2, rel=1e-14)
    assert ev.running_cost == pytest.approx(0.01 * 9 * 1.0, rel=1e-14)
    assert ev.cost == ev.terminal_cost + ev.running_cost
    assert ev.event_dicts() == [
        {"time": e.time, "kind": "disc-disc", "bodies": ["ball1", "ball2"], "guard": "ball1|ball2"}
    ]


def test_disc_wall_event_time_and_state():
    sc = load_scene("damped-walls")
    ev = hybridoc.evaluate(sc)
    # x = 2 t^2 (force 4, mass 1) reaches x = 1 - r = 0.8 at t = sqrt(0.4)
    t1 = math.sqrt(0.4)
    assert [(e.kind, e.bodies) for e in ev.events] == [("disc-wall", ("puck", "right"))]
    assert ev.events[0].time == pytest.approx(t1, abs=2e-15)
    vx_after = -0.7 * 4 * t1
    tau = 1 - t1
    x_T = 0.8 + vx_after * tau + 2 * tau**2
    y_T = 0.5 * 1.0**2
    np.testing.assert_allclose(ev.final_state, [x_T, y_T, vx_after + 4 * tau, 1.0], atol=1e-14)


def _quartic_contact_time(p0, v0, a0, R):
    """Earliest t > 0 with |p0 + v0 t + a0 t^2 / 2| = R, solved independently with numpy."""
    comps = [np.array([p0[k], v0[k], 0.5 * a0[k]]) for k in range(2)]
    quartic = P.polyadd(P.polymul(comps[0], comps[0]), P.polymul(comps[1], comps[1]))
    quartic = P.polysub(quartic, [R**2])
    roots = P.polyroots(quartic)
    real = np.sort(roots[(np.abs(roots.imag) < 1e-9) & (roots.real > 0)].real)
    t = real[0]
    d1 = P.polyder(quartic)
    for _ in range(3):  # polish on the polynomial
        t -= P.polyval(t, quartic) / P.polyval(t, d1)
    return t


def oblique_scene(restitution: float) -> Scene:
    return Scene(
        horizon=1.0,
        steps=50,
        restitution=restitution,
        discs=(
            Disc(
                "a",
                (0.0, 0.0),
                0.15,
                velocity=(1.0, 0.5),
                mass=1.3,
                actuated=True,
                initial_control=(0.6, -0.4),
            ),
            Disc("b", (1.0, 0.45), 0.25, velocity=(-0.3, 0.05), mass=0.7, target=(0.0, 0.0)),
        ),
    )


@pytest.mark.parametrize("e", [1.0, 0.5])
def test_oblique_disc_disc_against_quartic(e):
    sc = oblique_scene(e)
    ev = hybridoc.evaluate(sc)
    a_rel = np.array([0.6, -0.4]) / 1.3
    t_c = _quartic_contact_time(np.array([-1.0, -0.45]), np.array([1.3, 0.45]), a_rel, 0.4)
    assert 0 < t_c < 1
    assert len(ev.events) == 1
    event = ev.events[0]
    assert event.time == pytest.approx(t_c, abs=1e-14)
    # the impulse along the line of centres, computed here from scratch
    p = positions(sc, event.state_before)
    v = velocities(sc, event.state_before)
    n = (p[0] - p[1]) / np.linalg.norm(p[0] - p[1])
    w = (v[0] - v[1]) @ n
    assert w < 0 and event.approach_speed == pytest.approx(w, rel=1e-13)
    m1, m2 = 1.3, 0.7
    J = -(1 + e) * w / (1 / m1 + 1 / m2)
    v_after = velocities(sc, event.state_after)
    np.testing.assert_allclose(v_after[0], v[0] + J / m1 * n, atol=1e-14)
    np.testing.assert_allclose(v_after[1], v[1] - J / m2 * n, atol=1e-14)
    # relative normal velocity reversed and scaled by e, momentum kept
    assert (v_after[0] - v_after[1]) @ n == pytest.approx(-e * w, rel=1e-13)
    np.testing.assert_allclose(
        momentum(sc, event.state_after), momentum(sc, event.state_before), atol=1e-14
    )
    # the normal kinetic energy of the relative motion loses exactly the factor (1 - e^2)
    mu = m1 * m2 / (m1 + m2)
    loss = kinetic(sc, event.state_before) - kinetic(sc, event.state_after)
    assert loss == pytest.approx((1 - e**2) * 0.5 * mu * w**2, rel=1e-12, abs=1e-14)


# ----------------------------------------------------------------- conservation across events
@pytest.mark.parametrize(
    ("name", "seed"),
    [
        ("three-disc-chain", None),
        ("three-disc-chain", 3),
        ("multiple-collision", None),
        ("multiple-collision", 5),
        ("head-on", None),
        ("single-collision", 7),
    ],
)
def test_momentum_and_energy_conserved_at_elastic_impacts(name, seed):
    sc = load_scene(name)
    u = sc.initial_controls() if seed is None else perturbed(sc, 0.5, seed)
    ev = hybridoc.evaluate(sc, u)
    assert ev.events
    assert sc.restitution == 1.0
    for e in ev.events:
        before, after = e.state_before, e.state_after
        np.testing.assert_array_equal(positions(sc, before), positions(sc, after))
        assert kinetic(sc, after) == pytest.approx(kinetic(sc, before), rel=1e-14)
        if e.kind == "disc-disc":
            np.testing.assert_allclose(momentum(sc, after), momentum(sc, before), atol=1e-14)
        else:
            wall = next(w for w in sc.walls if w.name == e.bodies[1])
            n = np.array(wall.normal)
            # the wall takes normal momentum only
            t = np.array([-n[1], n[0]])
            assert momentum(sc, after) @ t == pytest.approx(momentum(sc, before) @ t, abs=1e-14)


def test_three_disc_chain_has_unequal_masses_and_chain_of_impacts():
    sc = load_scene("three-disc-chain")
    assert len(set(masses(sc))) > 1
    ev = hybridoc.evaluate(sc)
    assert [e.bodies for e in ev.events] == [("striker", "middle"), ("middle", "end")]


def test_damped_walls_lose_exactly_1_minus_e2_of_normal_energy():
    sc = load_scene("damped-walls")
    e = sc.restitution
    u = np.zeros((sc.steps, 2))
    u[: sc.steps // 2] = [12.0, 1.0]
    u[sc.steps // 2 :] = [-12.0, -1.0]
    ev = hybridoc.evaluate(sc, u)
    assert [x.bodies[1] for x in ev.events] == ["right", "left"]
    for x in ev.events:
        n = np.array(next(w.normal for w in sc.walls if w.name == x.bodies[1]))
        vb, va = x.state_before[2:], x.state_after[2:]
        assert va @ n == pytest.approx(-e * (vb @ n), rel=1e-14)
        assert (va @ n) ** 2 == pytest.approx(e**2 * (vb @ n) ** 2, rel=1e-14)
        t = np.array([-n[1], n[0]])
        assert va @ t == vb @ t
        lost = kinetic(sc, x.state_before) - kinetic(sc, x.state_after)
        assert lost == pytest.approx((1 - e**2) * 0.5 * (vb @ n) ** 2, rel=1e-13)


# ----------------------------------------------------------------- cost parts
def test_cost_parts_constant_force_closed_form():
    sc = free_disc_scene()
    ev = hybridoc.evaluate(sc)
    assert ev.events == []
    T, m, eps = 1.5, 2.0, 0.02
    u = np.array([1.2, -0.7])
    p_T = np.array([0.3, -0.2]) + np.array([0.5, 1.0]) * T + 0.5 * u / m * T**2
    assert ev.terminal_cost == pytest.approx(np.sum((p_T - 1.0) ** 2), rel=1e-14)
    assert ev.running_cost == pytest.approx(eps * (u @ u) * T, rel=1e-14)
    np.testing.assert_allclose(ev.final_state[:2], p_T, rtol=1e-15, atol=1e-15)


def test_cost_parts_piecewise_constant_closed_form():
    sc = free_disc_scene()
    rng = np.random.default_rng(11)
    u = rng.standard_normal((sc.steps, 2))
    ev = hybridoc.evaluate(sc, u)
    T, m, eps, N = 1.5, 2.0, 0.02, sc.steps
    dt = T / N
    t_next = dt * np.arange(1, N + 1)
    # each interval's force acts for dt, then its velocity gain coasts to T
    dp = ((dt * (T - t_next) + 0.5 * dt**2)[:, None] * u / m).sum(axis=0)
    p_T = np.array([0.3, -0.2]) + np.array([0.5, 1.0]) * T + dp
    v_T = np.array([0.5, 1.0]) + u.sum(axis=0) * dt / m
    np.testing.assert_allclose(ev.final_state, np.r_[p_T, v_T], rtol=1e-13, atol=1e-13)
    assert ev.terminal_cost == pytest.approx(np.sum((p_T - 1.0) ** 2), rel=1e-13)
    assert ev.running_cost == pytest.approx(eps * dt * np.sum(u**2), rel=1e-13)
    # dense output between the grid points is the exact parabola
    ts = np.array([0.0, 0.3 * dt, 7.5 * dt, T])
    k = np.minimum((ts / dt).astype(int), N - 1)
    for t, kk, s in zip(ts, k, ev.sample(ts), strict=True):
        tn = dt * np.arange(kk)
        p = np.array([0.3, -0.2]) + np.array([0.5, 1.0]) * t
        p += ((dt * (t - tn - dt) + 0.5 * dt**2)[:, None] * u[:kk] / m).sum(axis=0)
        p += 0.5 * u[kk] / m * (t - kk * dt) ** 2
        np.testing.assert_allclose(s[:2], p, atol=1e-14)


def test_trajectory_records_grid_and_both_sides_of_events():
    sc = load_scene("multiple-collision")
    ev = hybridoc.evaluate(sc)
    assert np.all(np.diff(ev.times) >= 0)
    assert set(sc.time_grid()) <= set(ev.times)
    for e in ev.events:
        k = np.flatnonzero(ev.times == e.time)
        assert len(k) == 2
        np.testing.assert_array_equal(ev.states[k[0]], e.state_before)
        np.testing.assert_array_equal(ev.states[k[1]], e.state_after)
    np.testing.assert_array_equal(ev.states[-1], ev.final_state)
    np.testing.assert_allclose(
        ev.sample(sc.time_grid()[::40]),
        ev.states[np.searchsorted(ev.times, sc.time_grid()[::40], side="right") - 1],
        atol=1e-15,
    )


# ----------------------------------------------------------------- grazing
def grazing_scene(offset: float) -> Scene:
    """Disc a moves along y = 0 past disc b at (0, 0.4 - offset): touching if offset = 0."""
    return Scene(
        horizon=2.0,
        steps=7,
        discs=(
            Disc("a", (-1.0, 0.0), 0.2, velocity=(1.0, 0.0), actuated=True),
            Disc("b", (0.0, 0.4 - offset), 0.2, target=(0.0, 0.0)),
        ),
    )


def test_grazing_contact_does_not_jump():
    sc = grazing_scene(0.0)
    for ev in (
        hybridoc.evaluate(sc),
        hybridoc.evaluate_callable(sc.to_ocp(), lambda t: np.zeros(2)),
    ):
        assert ev.events == []
        np.testing.assert_allclose(ev.final_state, [1, 0, 0, 0.4, 1, 0, 0, 0], atol=1e-15)


def test_sliding_along_a_wall_does_not_jump():
    sc = Scene(
        horizon=1.0,
        steps=10,
        discs=(Disc("a", (0.0, -0.8), 0.2, velocity=(1.0, 0.0), actuated=True, target=(0, 0)),),
        walls=(Wall((0.0, -1.0), (0.0, 1.0)),),
    )
    ev = hybridoc.evaluate(sc)
    assert ev.events == []
    np.testing.assert_array_equal(ev.final_state, [1.0, -0.8, 1.0, 0.0])


def test_shallow_contact_still_jumps_with_the_right_approach_speed():
    delta = 1e-4
    sc = grazing_scene(delta)
    ev = hybridoc.evaluate(sc)
    assert len(ev.events) == 1
    # contact when x^2 + (0.4 - delta)^2 = 0.4^2; rate d|dp|/dt = x * vx / 0.4 there
    x = -math.sqrt(0.16 - (0.4 - delta) ** 2)
    assert ev.events[0].time == pytest.approx(1 + x, abs=1e-12)
    assert ev.events[0].approach_speed == pytest.approx(x / 0.4, rel=1e-8)


# ----------------------------------------------------------------- simultaneous events
def corner_scene(walls_reversed: bool) -> Scene:
    walls = [Wall((1.0, 0.0), (-1.0, 0.0), name="right"), Wall((0.0, 1.0), (0.0, -1.0), name="top")]
    if walls_reversed:
        walls.reverse()
    return Scene(
        horizon=1.2,
        steps=12,
        discs=(Disc("d", (0.0, 0.0), 0.2, velocity=(1.0, 1.0), actuated=True, target=(0, 0)),),
        walls=tuple(walls),
    )


@pytest.mark.parametrize("walls_reversed", [False, True])
def test_disc_into_a_corner_resolved_in_guard_order(walls_reversed):
    sc = corner_scene(walls_reversed)
    ev1 = hybridoc.evaluate(sc)
    ev2 = hybridoc.evaluate(sc)
    order = [w.name for w in sc.walls]
    assert [e.bodies[1] for e in ev1.events] == order
    assert [e.guard for e in ev1.events] == [0, 1]
    assert ev1.events[0].time == ev1.events[1].time == pytest.approx(0.8, abs=1e-15)
    # both normal components reversed
    np.testing.assert_array_equal(ev1.events[-1].state_after[2:], [-1.0, -1.0])
    np.testing.assert_array_equal(ev1.final_state, ev2.final_state)
    assert ev1.event_dicts() == ev2.event_dicts()


def test_two_discs_hit_a_third_symmetrically():
    sc = Scene(
        horizon=1.0,
        steps=10,
        discs=(
            Disc("a", (-1.0, 0.0), 0.2, velocity=(1.0, 0.0)),
            Disc("b", (1.0, 0.0), 0.2, velocity=(-1.0, 0.0)),
            Disc("c", (0.0, 0.0), 0.2, actuated=True, target=(0.0, 0.0)),
        ),
    )
    # a and b reach c at the same instant; their jumps do not commute (the outcome of the
    # impulsive model would depend on an order the physics does not give): a clear error
    with pytest.raises(hybridoc.SimultaneousEventError, match="same instant") as info:
        hybridoc.evaluate(sc)
    assert set(info.value.guards) == {"a|c", "b|c"}
    assert info.value.time == pytest.approx(0.6, abs=1e-15)
    # one after the other (b a little later), both hits are resolved: c takes and gives back
    late = Scene(
        horizon=1.0,
        steps=10,
        discs=(sc.discs[0], Disc("b", (1.05, 0.0), 0.2, velocity=(-1.0, 0.0)), sc.discs[2]),
    )
    ev = hybridoc.evaluate(late)
    assert [e.name for e in ev.events][:2] == ["a|c", "b|c"]
    for e in ev.events:
        np.testing.assert_allclose(momentum(late, e.state_after), 0.0, atol=1e-15)
        assert kinetic(late, e.state_after) == pytest.approx(1.0, rel=1e-14)


# ----------------------------------------------------------------- several events per interval
def test_many_wall_bounces_inside_one_grid_interval():
    sc = Scene(
        horizon=0.49,
        steps=2,
        discs=(Disc("d", (0.0, 0.0), 0.1, velocity=(10.0, 0.0), actuated=True, target=(0, 0)),),
        walls=(Wall((-0.3, 0.0), (1.0, 0.0), name="L"), Wall((0.3, 0.0), (-1.0, 0.0), name="R")),
    )
    ev = hybridoc.evaluate(sc)
    expected = 0.02 + 0.04 * np.arange(12)  # first hit at x = 0.2, then every 0.4 / 10
    np.testing.assert_allclose([e.time for e in ev.events], expected, atol=1e-14)
    assert [e.bodies[1] for e in ev.events] == ["R", "L"] * 6
    assert sum(e.time < 0.245 for e in ev.events) == 6
    assert {s.interval for s in ev.segments if s.event is not None} == {0, 1}
    # the last event is at 0.46 (wall L), after which the disc moves at +10 from x = -0.2
    np.testing.assert_allclose(ev.final_state, [-0.2 + 10 * 0.03, 0.0, 10.0, 0.0], atol=1e-13)


def test_chain_of_impacts_inside_one_grid_interval():
    sc = Scene(
        horizon=1.0,
        steps=2,
        discs=(
            Disc("a", (0.0, 0.0), 0.2, velocity=(1.0, 0.0), actuated=True),
            Disc("b", (0.5, 0.0), 0.2),
            Disc("c", (1.0, 0.0), 0.2, target=(2.0, 0.0)),
        ),
    )
    ev = hybridoc.evaluate(sc)
    assert [e.bodies for e in ev.events] == [("a", "b"), ("b", "c")]
    np.testing.assert_allclose([e.time for e in ev.events], [0.1, 0.2], atol=1e-15)
    np.testing.assert_allclose(
        ev.final_state, [0.1, 0, 0.6, 0, 1.8, 0, 0, 0, 0, 0, 1, 0], atol=1e-14
    )


# ----------------------------------------------------------------- what is not modelled
def pushed_into_wall(e: float) -> Scene:
    """Force 1 into a wall: e = 0 sticks at t = sqrt(0.6); e = 0.5 bounces ever more
    often (Zeno) until t = 3 sqrt(0.6) and then sticks."""
    return Scene(
        horizon=3.0,
        steps=60,
        restitution=e,
        discs=(
            Disc("a", (0.0, 0.0), 0.2, actuated=True, initial_control=(1.0, 0.0), target=(0, 0)),
        ),
        walls=(Wall((0.5, 0.0), (-1.0, 0.0)),),
    )


@pytest.mark.parametrize("e", [0.0, 0.5])
def test_sustained_contact_raises(e):
    sc = pushed_into_wall(e)
    with pytest.raises(EvaluationError, match="contact|Zeno"):
        hybridoc.evaluate(sc)


@pytest.mark.parametrize("e", [0.0, 0.5])
def test_sustained_contact_raises_on_the_callable_path(e):
    sc = pushed_into_wall(e)
    with pytest.raises(EvaluationError, match="stay in contact|Zeno"):
        hybridoc.evaluate_callable(sc.to_ocp(), lambda t: np.array([1.0, 0.0]))
    with pytest.raises(EvaluationError):
        hybridoc.gradient(sc)


# ----------------------------------------------------------------- callable path
@pytest.mark.parametrize("name", ["single-collision", "multiple-collision", "three-disc-chain"])
def test_callable_path_agrees_with_piecewise_constant(name):
    sc = load_scene(name)
    ocp = sc.to_ocp()
    u = perturbed(sc, 0.3, 0)
    grid = sc.time_grid()

    def u_fn(t: float) -> np.ndarray:
        return u[min(max(int(np.searchsorted(grid, t, side="right")) - 1, 0), sc.steps - 1)]

    ev_pc = hybridoc.evaluate(sc, u)
    ev_fn = hybridoc.evaluate_callable(ocp, u_fn, breakpoints=grid)
    assert ev_fn.cost == pytest.approx(ev_pc.cost, rel=1e-10)
    assert ev_fn.terminal_cost == pytest.approx(ev_pc.terminal_cost, rel=1e-10)
    assert ev_fn.running_cost == pytest.approx(ev_pc.running_cost, rel=1e-10)
    assert [e.bodies for e in ev_fn.events] == [e.bodies for e in ev_pc.events]
    np.testing.assert_allclose(
        [e.time for e in ev_fn.events], [e.time for e in ev_pc.events], atol=1e-10
    )
    np.testing.assert_allclose(ev_fn.final_state, ev_pc.final_state, atol=1e-9)
    np.testing.assert_array_equal(ev_fn.controls, u)
    # evaluate() hands callables to the same path, with the grid as breakpoints
    ev = hybridoc.evaluate(sc, u_fn)
    assert ev.cost == pytest.approx(ev_fn.cost, rel=1e-15)


# ----------------------------------------------------------------- controls validation
@pytest.mark.parametrize(
    ("controls", "words"),
    [
        (np.zeros((479, 2)), "expected shape (480, 2)"),
        (np.zeros((480, 3)), "expected shape (480, 2)"),
        (np.zeros(960), "expected shape"),
        (np.zeros((480, 2, 1)), "expected shape"),
        ("abc", "not a numeric array"),
        ([[1, 2], [3]], "not a numeric array"),
    ],
)
def test_controls_shape_errors(controls, words):
    with pytest.raises(ControlsError) as info:
        hybridoc.evaluate(load_scene("single-collision"), controls)
    assert words in str(info.value)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_controls_non_finite(bad):
    u = load_scene("single-collision").initial_controls()
    u[17, 1] = bad
    with pytest.raises(ControlsError, match="non-finite value at row 17, column 1"):
        hybridoc.evaluate(load_scene("single-collision"), u)
    with pytest.raises(ControlsError):
        hybridoc.gradient(load_scene("single-collision"), u)


def test_callable_control_errors():
    ocp = load_scene("single-collision").to_ocp()
    with pytest.raises(ControlsError, match="must be 2 finite numbers"):
        hybridoc.evaluate_callable(ocp, lambda t: np.zeros(3))
    with pytest.raises(ControlsError, match="must be 2 finite numbers"):
        hybridoc.evaluate_callable(ocp, lambda t: np.array([np.nan, 0.0]))
    with pytest.raises(ControlsError, match="piecewise-constant"):
        hybridoc.gradient(ocp, lambda t: np.zeros(2))


def test_controls_are_not_modified_and_are_float64():
    sc = load_scene("head-on")
    u = sc.initial_controls().astype(np.float32)
    ev = hybridoc.evaluate(sc, u)
    assert ev.controls.dtype == np.float64
    assert ev.controls is not u


def test_overflow_raises():
    sc = free_disc_scene()
    with pytest.raises(EvaluationError, match="not finite"):
        hybridoc.evaluate(sc, np.full((sc.steps, 2), 1e300))
