"""Property tests of the judge on random disc scenes nobody hand-picked.

Random scenes: 1 to 6 discs (masses, radii, initial velocities), 0 to 4 walls around them,
restitution in [0, 1], horizons from 0.1 to 1000, random piecewise-constant forces. For every
case the judge (:func:`hybridoc.evaluate`) either agrees with the independent oracle
(``tests/oracle.py``: conservative advancement, no shared code) on the event sequence, the
event times, the final state and the cost, or raises one of hybridoc's errors with a
message. Cases whose outcome is ill-conditioned (a perturbation of one initial position by
1e-10 changes the oracle's own event sequence, or moves its answer by more than 1e-4:
chaotic billiards, near-grazes) are skipped, since no two correct simulators need agree on
them; otherwise the tolerances are 1e-7 plus ten times what that perturbation moved.
Random mode switches (issue #15): a random two-mode linear system with hysteresis guards
against its exact linear flows (the last test).
Further invariants: no penetration at densely
sampled times, momentum conserved across disc-disc impacts, kinetic energy conserved at
e = 1, and the adjoint gradient equal to central differences where the event sequence does
not change. Metamorphic properties (issue #17): a passive disc up to 1e15 away (at rest or
receding at up to 1e13) or a far wall changes nothing, a translation of the scene changes
nothing and a change of the unit of length scales the answer, each to a tolerance derived
from rounding and the judge's own sensitivity (see the notes above those tests).

``make fuzz`` runs every property 100 times longer with random seeds (``HYBRIDOC_FUZZ=1``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
from conftest import examples
from hypothesis import assume, event, example, given, note, settings
from hypothesis import strategies as st
from scaling import transform

import hybridoc
from hybridoc import Disc, HybridocError, Scene, Wall

oracle = pytest.importorskip("oracle")


# ------------------------------------------------------------------ random scenes


# every hypothesis example is a new structure: compiling each to C would be work for nothing
pytestmark = pytest.mark.usefixtures("virtual_machine")


@st.composite
def scenes(draw: Any, *, max_discs: int = 6, max_walls: int = 4, elastic: bool = False) -> Any:
    """A valid random disc scene and random controls (see the module notes)."""
    n = draw(st.integers(1, max_discs))
    n_walls = draw(st.integers(0, max_walls))
    log_T = draw(st.floats(math.log10(0.1), math.log10(1000.0)))
    horizon = float(10.0**log_T)
    steps = draw(st.integers(1, 24))
    e = 1.0 if elastic else draw(st.one_of(st.sampled_from([0.0, 0.5, 1.0]), st.floats(0, 1)))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    # crowded scenes (a small region, velocities towards its centre) collide more often
    region = float(draw(st.floats(0.5, 1.1)))
    inward = draw(st.booleans())
    # speeds and forces so that a long horizon does not mean tens of thousands of events
    speed = min(2.0, 30.0 / horizon)
    force = min(3.0, 60.0 / horizon**2)
    discs: list[Disc] = []
    tries = 0
    while len(discs) < n and tries < 500:
        tries += 1
        r = float(rng.uniform(0.05, 0.3))
        p = rng.uniform(-region, region, 2)
        if np.hypot(*p) > region or any(
            np.hypot(*(p - np.array(d.position))) < r + d.radius + 1e-3 for d in discs
        ):
            continue
        k = len(discs)
        discs.append(
            Disc(
                name=f"d{k}",
                position=(float(p[0]), float(p[1])),
                radius=r,
                velocity=tuple(
                    float(x)
                    for x in speed * (rng.uniform(-1, 1, 2) - (p / region if inward else 0.0))
                ),
                mass=float(rng.uniform(0.2, 5.0)),
                actuated=k == 0 or bool(rng.random() < 0.3),
                target=(float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1))) if k == 0 else None,
            )
        )
    walls = []
    for k in range(n_walls):
        a = rng.uniform(0, 2 * np.pi)
        nrm = np.array([np.cos(a), np.sin(a)])
        dist = float(rng.uniform(1.5, 3.0))  # discs lie within 1.1 + 0.3 of the origin
        walls.append(Wall(point=tuple(-dist * nrm), normal=tuple(nrm), name=f"w{k}"))
    scene = Scene(horizon=horizon, discs=tuple(discs), walls=tuple(walls), steps=steps,
                  restitution=e, control_weight=0.01)  # fmt: skip
    u = force * rng.uniform(-1, 1, (steps, scene.n_controls))
    return scene, u


def _as_dict(scene: Scene) -> dict[str, Any]:
    return {
        "horizon": scene.horizon,
        "steps": scene.steps,
        "control_weight": scene.control_weight,
        "restitution": scene.restitution,
        "discs": [
            {
                "name": d.name,
                "position": d.position,
                "velocity": d.velocity,
                "radius": d.radius,
                "mass": d.mass,
                "actuated": d.actuated,
                "target": d.target,
            }
            for d in scene.discs
        ],  # fmt: skip
        "walls": [{"name": w.name, "point": w.point, "normal": w.normal} for w in scene.walls],
    }


#: the physical perturbation of the conditioning test (a disc's initial x position): about
#: the accuracy to which the oracle places a contact (its contact band is 1e-10)
DELTA = 1e-10


def _oracle(scene: Scene, u: np.ndarray, x_shift: float = 0.0, **options: float) -> Any:
    data = _as_dict(scene)
    if x_shift:
        d = data["discs"][-1]
        d["position"] = (d["position"][0] + x_shift, d["position"][1])
    try:
        return oracle.simulate(data, u, max_steps=200_000, **options)
    except oracle.StepLimitExceeded:
        return "slow"
    except oracle.OracleError as exc:
        return exc


def _same(a: Any, b: Any, T: float) -> bool:
    """Whether two oracle outcomes have the same events to 1e-6 (the conditioning test)."""
    if isinstance(a, Exception) or isinstance(b, Exception):
        return type(a) is type(b)
    if [n for _, n in a.events] != [n for _, n in b.events]:
        return False
    ta, tb = np.array([t for t, _ in a.events]), np.array([t for t, _ in b.events])
    return bool(np.all(np.abs(ta - tb) <= 1e-6 * max(1.0, T)))


def _spread(a: Any, b: Any) -> tuple[float, float]:
    """How far a perturbation of DELTA moved the oracle's event times and final state: what
    the outcome's sensitivity makes of the two simulators' small errors (contact placement
    to about DELTA, rounding)."""
    if isinstance(a, Exception):
        return 0.0, 0.0
    ta, tb = np.array([t for t, _ in a.events]), np.array([t for t, _ in b.events])
    dt = float(np.max(np.abs(ta - tb), initial=0.0))
    return dt, float(np.max(np.abs(np.array(a.final_state) - np.array(b.final_state))))


CASCADE_GRAZE = 1e-6
"""The oracle's approach threshold for the probe of a cascade's truncation: above the
judge's (``max(graze_tol, sqrt(2 sigma psi''))``, :mod:`hybridoc.events`), so that the
spread it measures bounds what the two simulators' different truncations move."""


def _has_cascade(events: list[tuple[float, str]], tol: float) -> bool:
    return any(isinstance(k, frozenset) for _, k in _instants(events, tol))


def _spread_instants(a: list[tuple[float, Any]], b: list[tuple[float, Any]]) -> float:
    return float(max((abs(ta - tb) for (ta, _), (tb, _) in zip(a, b, strict=True)), default=0.0))


def _instants(events: list[tuple[float, str]], tol: float) -> list[tuple[float, Any]]:
    """Events grouped by instant: ``(time, guards in order)``, or ``(time, set of guards)``
    for a cascade (a guard firing again at the same instant: a disc wedged in a corner at
    restitution < 1). A cascade is an infinite geometric series of jumps that a simulator
    stops where the approach speed falls below its rounding-level threshold, so the number of
    its terms is not part of the answer: the guards that take part are, and so is the state
    after it (compared by the caller)."""
    out: list[tuple[float, Any]] = []
    group: list[str] = []
    t0 = 0.0
    for t, name in [*events, (math.inf, "")]:
        if group and abs(t - t0) > tol:
            key = frozenset(group) if len(set(group)) < len(group) else tuple(group)
            out.append((t0, key))
            group = []
        if not group:
            t0 = t
        group.append(name)
    return out


# ------------------------------------------------------------------ the properties
def _agrees_with_the_oracle(case: Any) -> None:
    """The judge and the oracle agree on one random scene (or the judge raises its own error,
    or the case is ill-conditioned and skipped): the body of the two tests below."""
    scene, u = case
    T = scene.horizon
    ref = _oracle(scene, u)
    assume(ref != "slow")
    # ill-conditioned outcomes (chaotic billiards, near-grazes): no two simulators need agree
    shifted = _oracle(scene, u, x_shift=DELTA)
    assume(shifted != "slow" and _same(ref, shifted, T))
    spread_t, spread_x = _spread(ref, shifted)
    if not isinstance(ref, Exception) and _has_cascade(ref.events, 1e-8 * max(1.0, T)):
        # a cascade (an instant with a repeated guard) is an infinite series of jumps that
        # each simulator truncates where the approach speed falls below its own threshold:
        # the oracle truncated more coarsely measures what that choice moves
        coarse = _oracle(scene, u, graze_tol=CASCADE_GRAZE)
        assume(not isinstance(coarse, Exception | str))
        tol = 1e-8 * max(1.0, T)
        same = _instants(coarse.events, tol), _instants(ref.events, tol)
        assume([k for _, k in same[0]] == [k for _, k in same[1]])
        event("cascade")
        spread_t = max(spread_t, _spread_instants(*same))
        spread_x = max(spread_x, float(np.abs(coarse.final_state - ref.final_state).max()))
    assume(spread_x < 1e-4 * max(1.0, T))  # sensitivity 1e6: beyond what a test can compare
    if not isinstance(ref, Exception):
        assume(len(ref.events) <= 400)
        # a gap that came within 1e-7 of zero without an event: a graze, decided differently
        # by rounding-level thresholds
        events = {n for _, n in ref.events}
        assume(all(g > 1e-7 or name in events for name, g in ref.min_gaps.items()))
    try:
        ev = hybridoc.evaluate(scene, u)
    except HybridocError as exc:
        event(f"judge raised {type(exc).__name__}; oracle {type(ref).__name__}")
        note(f"judge raised {type(exc).__name__}: {exc}; oracle: {ref!r}")
        # an error is allowed, but only one of the judge's own, with a message
        assert isinstance(exc, hybridoc.EvaluationError) and str(exc)
        return
    assert not isinstance(ref, Exception), (
        f"the judge returned a number where the oracle raised {ref!r}"
    )
    names = [e.name for e in ev.events]
    k = len(names)
    event("agree: no event" if k == 0 else "agree: 1-9 events" if k < 10 else "agree: 10+ events")
    note(f"judge events {list(zip(names, [e.time for e in ev.events], strict=True))[:8]}")
    note(f"oracle events {ref.events[:8]}")
    tol_t = 1e-8 * max(1.0, T) + 10 * spread_t
    mine = _instants([(e.time, e.name) for e in ev.events], tol_t)
    theirs = _instants(ref.events, tol_t)
    assert [k for _, k in mine] == [k for _, k in theirs]
    np.testing.assert_allclose([t for t, _ in mine], [t for t, _ in theirs], rtol=0, atol=tol_t)
    scale = max(1.0, float(np.abs(ref.final_state).max()))
    tol_x = 1e-7 * scale + 10 * spread_x
    np.testing.assert_allclose(ev.final_state, ref.final_state, rtol=0, atol=tol_x)
    slope = 2 * math.sqrt(max(ref.cost, 0.0)) + 1.0  # d cost / d state, roughly, at this cost
    assert ev.cost == pytest.approx(ref.cost, rel=1e-6, abs=1e-9 + slope * 10 * spread_x)


#: a cascade at t = 0.4 (d0 strikes d1, which rests against the wall, at e = 0.5): one in
#: 150 random scenes is one, so CI's 50 are given this one as well
CASCADE = (
    Scene(
        horizon=1.0,
        steps=4,
        restitution=0.5,
        control_weight=0.01,
        discs=(
            Disc(
                name="d0",
                position=(1.0, 0.0),
                radius=0.2,
                velocity=(-1.0, 0.0),
                actuated=True,
                target=(0.5, 0.5),
            ),
            Disc(name="d1", position=(0.2, 0.0), radius=0.2, mass=2.0),
        ),  # fmt: skip
        walls=(Wall(point=(0.0, 0.0), normal=(1.0, 0.0), name="w0"),),
    ),
    np.zeros((4, 2)),
)


# About 0.35 s per scene (the oracle, pure Python, twice, and the judge's kernels of a new
# structure): CI checks 50 scenes (no events, 1-9 and 10+ events, the judge's errors) and
# the cascade above; the slow tier 150 others.
@settings(max_examples=examples(50))
@given(case=scenes())
@example(case=CASCADE)
def test_judge_agrees_with_the_oracle(case: Any) -> None:
    _agrees_with_the_oracle(case)


@pytest.mark.slow
@settings(max_examples=examples(150))
@given(case=scenes())
def test_judge_agrees_with_the_oracle_on_more_scenes(case: Any) -> None:
    _agrees_with_the_oracle(case)


# The properties below check a handful of random cases in CI (each is 0.1-1 s: a new
# structure's kernels, probes); each has a ``*_more_cases`` twin in the slow tier (``make
# test-all``) that runs the same body (``.hypothesis.inner_test``) on the number of cases CI
# ran before (issue #18).
@settings(max_examples=examples(20))
@given(case=scenes(max_discs=4))
def test_no_penetration_at_dense_times(case: Any) -> None:
    scene, u = case
    try:
        ev = hybridoc.evaluate(scene, u)
    except HybridocError:
        return
    ocp = scene.to_ocp()
    t = np.linspace(0.0, scene.horizon, 40 * scene.steps + 1)
    X = ev.sample(t)
    for g in ocp.guards:
        psi = np.asarray(g.psi.map(t.size)(X.T)).ravel()
        scale = max(1.0, float(np.abs(X).max()))
        assert psi.min() >= -1e-8 * scale, f"{g.name} penetrates by {-psi.min():.3g}"


@pytest.mark.slow
@settings(max_examples=examples(60))
@given(case=scenes(max_discs=4))
def test_no_penetration_at_dense_times_more_cases(case: Any) -> None:
    test_no_penetration_at_dense_times.hypothesis.inner_test(case)  # type: ignore[attr-defined]


def _momentum(scene: Scene, s: np.ndarray) -> np.ndarray:
    n = scene.n_discs
    m = np.array([d.mass for d in scene.discs])
    return (m[:, None] * s[2 * n :].reshape(n, 2)).sum(0)


def _kinetic(scene: Scene, s: np.ndarray) -> float:
    n = scene.n_discs
    m = np.array([d.mass for d in scene.discs])
    return float(0.5 * (m * (s[2 * n :].reshape(n, 2) ** 2).sum(1)).sum())


@settings(max_examples=examples(20))
@given(case=scenes(elastic=True))
def test_impacts_conserve_momentum_and_elastic_energy(case: Any) -> None:
    scene, u = case
    try:
        ev = hybridoc.evaluate(scene, u)
    except HybridocError:
        return
    for e in ev.events:
        before, after = e.state_before, e.state_after
        scale = max(1.0, float(np.abs(before).max()))
        if e.kind == "disc-disc":
            np.testing.assert_allclose(
                _momentum(scene, after), _momentum(scene, before), rtol=0, atol=1e-12 * scale
            )
        assert _kinetic(scene, after) == pytest.approx(
            _kinetic(scene, before), rel=1e-12, abs=1e-12
        )
        np.testing.assert_array_equal(after[: 2 * scene.n_discs], before[: 2 * scene.n_discs])


@pytest.mark.slow
@settings(max_examples=examples(60))
@given(case=scenes(elastic=True))
def test_impacts_conserve_momentum_and_elastic_energy_more_cases(case: Any) -> None:
    test_impacts_conserve_momentum_and_elastic_energy.hypothesis.inner_test(case)  # type: ignore[attr-defined]


@settings(max_examples=examples(15))
@given(
    case=scenes(max_discs=3, max_walls=2),
    picks=st.lists(st.integers(0, 10**6), min_size=3, max_size=3),
)
def test_adjoint_gradient_equals_central_differences(case: Any, picks: list[int]) -> None:
    scene, u = case
    assume(scene.horizon <= 20.0)
    try:
        g = hybridoc.gradient(scene, u)
    except HybridocError:
        return
    seq = g.evaluation.sequence
    h = 1e-6
    for p in picks:
        n, k = divmod(p % u.size, u.shape[1])
        up, um = u.copy(), u.copy()
        up[n, k] += h
        um[n, k] -= h
        try:
            ep, em = hybridoc.evaluate(scene, up), hybridoc.evaluate(scene, um)
        except HybridocError:
            continue
        if ep.sequence != seq or em.sequence != seq:
            continue  # the event sequence changes: the cost is not differentiable there
        fd = (ep.cost - em.cost) / (2 * h)
        assert g.d_controls[n, k] == pytest.approx(fd, rel=1e-4, abs=1e-6 * max(1.0, abs(g.cost)))


@pytest.mark.slow
@settings(max_examples=examples(40))
@given(
    case=scenes(max_discs=3, max_walls=2),
    picks=st.lists(st.integers(0, 10**6), min_size=3, max_size=3),
)
def test_adjoint_gradient_equals_central_differences_more_cases(
    case: Any, picks: list[int]
) -> None:
    test_adjoint_gradient_equals_central_differences.hypothesis.inner_test(case, picks)  # type: ignore[attr-defined]


# ------------------------------------------------------------------ metamorphic properties
# What does not change the physics must not change the judge's answer: a body or a wall far
# away, where the scene sits, the unit of length. The judge's rounding levels are per guard
# and per state component (:mod:`hybridoc.kernels`, issue #17), so these hold to rounding.
#
# Tolerances. A variant computes the same trajectory with other roundings: positions rounded
# at another length scale ``L`` (a translation by ``c``: ``|c|``), event times located by
# another path. Both are disturbances of the state: ``4 eps L`` per rounding of the
# positions (initially and at every flow step and event), and at each event a time
# uncertain by ``dt = 8 eps (L / |w| + max(1, T))`` (a gap's rounding over the approach
# speed ``w``, or Newton's stopping rule), which moves the bodies by up to ``2 V dt`` (``V``
# the largest speed: the velocity jump times the shift). Those are allowed directly; how
# much the disturbance ``d`` they sum to moves everything after it is measured as in the
# oracle comparison: the judge's own spread when every disc moves by DELTA (in two sets of
# directions), times ``d / DELTA`` (linear sensitivity). Cases whose event sequence changes
# under that perturbation, or under one of ``1000`` ulps of ``L`` (a contact that is
# near-simultaneous or grazing at that rounding level), are ill-conditioned there and
# skipped; so are cascades (:func:`_cascade`) where the variant changes ``L``.

EPS = float(np.finfo(float).eps)


def _judge(problem: Any, u: np.ndarray, **options: float) -> Any:
    try:
        return hybridoc.evaluate(problem, u, **options)
    except HybridocError as exc:
        return exc


def _moved(ocp: Any, u: np.ndarray, size: float, turn: float = 0.0) -> Any:
    """The judge with every disc moved by ``size``, each in another direction (golden-angle
    steps, turned by ``turn``), so that every pair's relative position changes; the same
    structure (no new kernels)."""
    n = ocp.meta["n_discs"]
    angles = 1.0 + turn + 2.4 * np.arange(n)
    x0 = ocp.x0.copy()
    x0[: 2 * n] += size * np.c_[np.cos(angles), np.sin(angles)].ravel()
    return _judge(ocp.replace(x0=x0), u)


def _own_spread(
    ocp: Any, u: np.ndarray, ev: Any, length: float = 1.0
) -> tuple[float, float, float] | None:
    """``(times, final state, cost)`` moved by the DELTA perturbations of :func:`_moved` (the
    larger of two sets of directions, a quarter turn apart: one alone may move every pair
    along its contact's tangent); ``None`` (ill-conditioned) when one of them, or one of
    +-1000 ulps of ``length``, changes the event sequence."""
    rho = 1000 * EPS * length
    probes = [(size, 0.0) for size in (rho, -rho) if rho > DELTA]
    spread = np.zeros(3)
    for size, turn in [(DELTA, 0.0), (DELTA, 0.5 * math.pi), *probes]:
        other = _moved(ocp, u, size, turn)
        if isinstance(other, Exception) or other.sequence != ev.sequence:
            return None
        if size != DELTA:
            continue
        ta = np.array([e.time for e in ev.events])
        tb = np.array([e.time for e in other.events])
        moved = [
            float(np.max(np.abs(ta - tb), initial=0.0)),
            float(np.max(np.abs(ev.final_state - other.final_state))),
            abs(ev.cost - other.cost),
        ]
        spread = np.maximum(spread, moved)
    return float(spread[0]), float(spread[1]), float(spread[2])


def _extent(ev: Any) -> tuple[float, float]:
    """The largest position coordinate and the largest speed along the trajectory (at least 1)."""
    n = ev.ocp.meta["n_discs"]
    X = ev.states
    return max(1.0, float(np.abs(X[:, : 2 * n]).max())), max(
        1.0, float(np.abs(X[:, 2 * n :]).max())
    )


def _disturbance(ev: Any, T: float, length: float, rounds: int) -> tuple[float, float]:
    """``(d, dt)`` of the notes above: the state disturbance ``d`` of ``rounds`` roundings of
    the positions at the scale ``length`` and of every event's time located to
    ``8 eps (length / |w| + max(1, T))``, and ``dt`` the sum of those times."""
    speed = _extent(ev)[1]
    w = np.array([abs(e.approach_speed) for e in ev.events])
    dt = float((8 * EPS * (length / np.maximum(w, 1e-300) + max(1.0, T))).sum())
    return 4 * EPS * length * rounds + 2 * speed * dt, dt


def _cascade(ev: Any, T: float) -> bool:
    """Whether the evaluation holds a cascade (a guard repeated at one instant: a disc wedged
    between others at restitution < 1). The judge truncates it where the approach speed falls
    below the rounding floor ``sqrt(2 sigma psi'')`` (:mod:`hybridoc.events`), whose
    ``sigma`` has an absolute floor (``max(1, |s_i|)``: a length of 1): neither a
    translation nor a change of units leaves it alone, so the number of terms (and with it
    whether the Zeno check sees the series) may change. Such cases are skipped there."""
    if _has_cascade([(e.time, e.name) for e in ev.events], 1e-8 * max(1.0, T)):
        event("cascade: truncated at an absolute threshold, skipped")
        return True
    return False


def _baseline(ocp: Any, u: np.ndarray, T: float) -> Any:
    """The judge's answer on the scene before a translation or a change of units, or
    ``None`` when there is nothing to compare: the judge raised (noted), or a cascade."""
    want = _judge(ocp, u)
    if isinstance(want, Exception):
        event(f"judge raised {type(want).__name__}")
        return None
    return None if _cascade(want, T) else want


def _conditioned_spread(
    ocp: Any, u: np.ndarray, want: Any, T: float, length: float = 1.0
) -> tuple[float, float, float]:
    """:func:`_own_spread`, with the case skipped (``assume``) when it is ill-conditioned."""
    spread = _own_spread(ocp, u, want, length)
    assume(spread is not None and spread[1] < 1e-4 * max(1.0, T))
    assert spread is not None
    return spread


def _assert_same_answer(
    got: Any,
    want: Any,
    T: float,
    spread: tuple[float, float, float],
    amplify: float,
    *,
    keep: Any = slice(None),
    offset: Any = 0.0,
    length: float = 1.0,
    cost_scale: float = 1.0,
    floor: float = 0.0,
    direct_t: float = 0.0,
) -> None:
    """``got`` equals ``want``: the events grouped by instant, the final state (``got``'s
    components ``keep``, less ``offset``, over ``length``) and the cost (``got``'s over
    ``cost_scale``); tolerances 1e-12 relative plus ``amplify`` times the spread (in
    ``want``'s units), plus what is allowed directly: ``direct_t`` in the times, and
    ``floor`` (a rounding of ``got``'s lengths) and ``2 V direct_t`` in the state
    (``2 sqrt(cost)`` times that in the cost)."""
    spread_t, spread_x, spread_c = spread
    floor += 2 * _extent(want)[1] * direct_t
    tol_t = 1e-12 * max(1.0, T) + amplify * spread_t + direct_t
    mine = _instants([(e.time, e.name) for e in got.events], tol_t)
    theirs = _instants([(e.time, e.name) for e in want.events], tol_t)
    assert [k for _, k in mine] == [k for _, k in theirs]
    np.testing.assert_allclose([t for t, _ in mine], [t for t, _ in theirs], rtol=0, atol=tol_t)
    x_want = want.final_state
    x_got = (np.asarray(got.final_state)[keep] - offset) / length
    tol_x = 1e-12 * max(1.0, float(np.abs(x_want).max())) + amplify * spread_x + floor
    np.testing.assert_allclose(x_got, x_want, rtol=0, atol=tol_x)
    tol_c = 1e-12 * max(1.0, abs(want.cost)) + amplify * spread_c
    tol_c += 2 * math.sqrt(max(want.cost, 0.0)) * floor + floor**2
    assert got.cost / cost_scale == pytest.approx(want.cost, rel=0, abs=tol_c)


@st.composite
def far_things(draw: Any) -> dict[str, Any]:
    """A passive disc or a wall between 1e3 and 1e15 away in a random direction; the disc at
    rest or receding at up to 1e13 (the scenes' discs stay within a few hundred units)."""
    return {
        "kind": draw(st.sampled_from(["disc", "disc", "wall"])),
        "angle": draw(st.floats(0.0, 2 * math.pi)),
        "distance": 10.0 ** draw(st.floats(3.0, 15.0)),
        "speed": draw(st.one_of(st.just(0.0), st.floats(-2.0, 13.0).map(lambda e: 10.0**e))),
        "radius": draw(st.floats(0.05, 0.3)),
        "mass": draw(st.floats(0.2, 5.0)),
    }


@settings(max_examples=examples(10))
@given(case=scenes(max_discs=4, max_walls=3), far=far_things())
def test_a_far_body_or_wall_changes_nothing(case: Any, far: dict[str, Any]) -> None:
    scene, u = case
    T = scene.horizon
    d = np.array([math.cos(far["angle"]), math.sin(far["angle"])])
    if far["kind"] == "disc":
        # the walls the far disc is in front of (and recedes from); the others are dropped
        walls = tuple(w for w in scene.walls if float(np.dot(w.normal, d)) > 0.1)
        base = dataclasses.replace(scene, walls=walls)
        body = Disc(
            name="far",
            position=tuple(far["distance"] * d),
            velocity=tuple(far["speed"] * d),
            radius=far["radius"],
            mass=far["mass"],
        )
        variant = dataclasses.replace(base, discs=(*base.discs, body))
        n = base.n_discs
        # the base discs' positions and velocities inside the variant's state
        keep = np.r_[0 : 2 * n, 2 * n + 2 : 4 * n + 2]
    else:
        base = scene
        wall = Wall(point=tuple(-far["distance"] * d), normal=tuple(d), name="far")
        variant = dataclasses.replace(scene, walls=(*scene.walls, wall))
        keep = np.arange(4 * scene.n_discs)
    ocp = base.to_ocp()
    want = _judge(ocp, u)
    got = _judge(variant, u)
    if isinstance(want, Exception) or isinstance(got, Exception):
        event(
            f"judge raised: base {type(want).__name__}, with far {far['kind']} {type(got).__name__}"
        )
        # the far body is no part of what went wrong (the guards between the others have the
        # same rounding levels, cascades included): the same outcome
        assert type(got) is type(want), f"base: {want!r}; with the far {far['kind']}: {got!r}"
        return
    spread = _conditioned_spread(ocp, u, want, T)
    same = got.cost == want.cost and np.array_equal(got.final_state[keep], want.final_state)
    event(f"far {far['kind']}: " + ("identical" if same else "equal to rounding"))
    # the same roundings at the same scale; only event times may be located by another path
    d, dt = _disturbance(want, T, _extent(want)[0], 0)
    _assert_same_answer(got, want, T, spread, d / DELTA, keep=keep, direct_t=dt)


@pytest.mark.slow
@settings(max_examples=examples(30))
@given(case=scenes(max_discs=4, max_walls=3), far=far_things())
def test_a_far_body_or_wall_changes_nothing_more_cases(case: Any, far: dict[str, Any]) -> None:
    test_a_far_body_or_wall_changes_nothing.hypothesis.inner_test(case, far)  # type: ignore[attr-defined]


@settings(max_examples=examples(10))
@given(
    case=scenes(max_discs=4, max_walls=3),
    log_offset=st.floats(-3.0, 6.0),
    angle=st.floats(0.0, 2 * math.pi),
)
def test_translating_the_scene_changes_nothing(case: Any, log_offset: float, angle: float) -> None:
    scene, u = case
    T = scene.horizon
    c = 10.0**log_offset * np.array([math.cos(angle), math.sin(angle)])
    ocp = scene.to_ocp()
    want = _baseline(ocp, u, T)
    if want is None:
        return
    # the translated scene rounds every position at the scale |c| + the scene's extent
    length = float(np.abs(c).max()) + _extent(want)[0]
    spread = _conditioned_spread(ocp, u, want, T, length)
    got = _judge(transform(scene, shift=(float(c[0]), float(c[1]))), u)
    assert not isinstance(got, Exception), f"translated by {c}: {got!r}; untranslated: fine"
    event(f"translated by 1e{math.floor(log_offset)}")
    # positions, targets and walls rounded once, then at every flow step and event
    rounds = 3 + scene.steps + 2 * len(want.events)
    d, dt = _disturbance(want, T, length, rounds)
    offset = np.r_[np.tile(c, scene.n_discs), np.zeros(2 * scene.n_discs)]
    # got's final positions, less c, are what they are to a rounding at the scale |c|
    floor = 4 * EPS * length
    _assert_same_answer(got, want, T, spread, d / DELTA, offset=offset, floor=floor, direct_t=dt)


@pytest.mark.slow
@settings(max_examples=examples(30))
@given(
    case=scenes(max_discs=4, max_walls=3),
    log_offset=st.floats(-3.0, 6.0),
    angle=st.floats(0.0, 2 * math.pi),
)
def test_translating_the_scene_changes_nothing_more_cases(
    case: Any, log_offset: float, angle: float
) -> None:
    test_translating_the_scene_changes_nothing.hypothesis.inner_test(case, log_offset, angle)  # type: ignore[attr-defined]


@settings(max_examples=examples(10))
@given(
    case=scenes(max_discs=4, max_walls=3),
    log_factor=st.floats(-3.0, 3.0),
    power_of_two=st.booleans(),
)
def test_scaling_lengths_scales_the_answer(
    case: Any, log_factor: float, power_of_two: bool
) -> None:
    scene, u = case
    T = scene.horizon
    # lengths times lam, times unchanged: positions, radii, targets, walls and velocities
    # scale by lam, and so do the forces (u = m a, masses unchanged). The cost
    # (problems/physics.py, problems/compile.py) is sum_i |p_i(T) - target_i|^2 + w int |u|^2
    # dt with the control weight w unchanged: both terms scale by lam^2. A power of two makes
    # every input exact, so that only the judge's absolute thresholds can tell the two
    # apart: graze_tol (a speed) and penetration_tol (a length) are scaled with the lengths,
    # and the rounding floor max(1, |s_i|) is a length of 1, which in the scene's units is
    # 1 / lam: the rounding scale there is max(extent, 1 / lam).
    lam = 2.0 ** round(log_factor / math.log10(2)) if power_of_two else 10.0**log_factor

    def sc(p: Any) -> tuple[float, float]:
        return (float(lam * p[0]), float(lam * p[1]))

    discs = tuple(
        dataclasses.replace(
            d,
            position=sc(d.position),
            velocity=sc(d.velocity),
            radius=lam * d.radius,
            target=None if d.target is None else sc(d.target),
        )
        for d in scene.discs
    )
    walls = tuple(dataclasses.replace(w, point=sc(w.point)) for w in scene.walls)
    scaled = dataclasses.replace(scene, discs=discs, walls=walls)
    ocp = scene.to_ocp()
    want = _baseline(ocp, u, T)
    if want is None:
        return
    length = max(_extent(want)[0], 1.0 / lam)
    spread = _conditioned_spread(ocp, u, want, T, length)
    got = _judge(scaled, lam * u, graze_tol=1e-10 * lam, penetration_tol=1e-9 * lam)
    assert not isinstance(got, Exception), f"lengths times {lam}: {got!r}; unscaled: fine"
    event("power of two" if power_of_two else "any factor")
    # an inexact factor rounds every input once
    d, dt = _disturbance(want, T, length, 0 if power_of_two else 3)
    _assert_same_answer(got, want, T, spread, d / DELTA, length=lam, cost_scale=lam**2, direct_t=dt)


@pytest.mark.slow
@settings(max_examples=examples(30))
@given(
    case=scenes(max_discs=4, max_walls=3),
    log_factor=st.floats(-3.0, 3.0),
    power_of_two=st.booleans(),
)
def test_scaling_lengths_scales_the_answer_more_cases(
    case: Any, log_factor: float, power_of_two: bool
) -> None:
    test_scaling_lengths_scales_the_answer.hypothesis.inner_test(case, log_factor, power_of_two)  # type: ignore[attr-defined]


# ------------------------------------------------------------------ random mode switches
# A random two-mode linear system, s' = A_q s + b u + c_q, with a thermostat's hysteresis:
# "down" (mode a -> b) when s_0 falls through theta, "up" (b -> a) when it rises through
# theta + gap; the resets scale s_1 by r_q; the running cost rho_q u^2 depends on the mode.
# The independent simulation: the exact linear flow (matrix exponential of the augmented
# system), the guard sampled densely along it on each cell and its crossing bracketed by
# brentq. Near-grazing crossings (a dip of the guard within 1e-6 of zero, or an approach
# slower than 1e-3) are ill-conditioned and skipped.
@st.composite
def mode_systems(draw: Any) -> dict[str, Any]:
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    sysd: dict[str, Any] = {"A": [], "c": [], "r": [], "rho": []}
    for _ in range(2):
        w = rng.uniform(1.0, 4.0)
        sysd["A"].append(np.array([[rng.uniform(-0.5, 0.5), w], [-w, rng.uniform(-0.5, 0.5)]]))
        sysd["c"].append(rng.uniform(-1, 1, 2))
        sysd["r"].append(float(rng.uniform(0.5, 1.0)))
        sysd["rho"].append(float(rng.uniform(0.1, 2.0)))
    theta = float(rng.uniform(-0.5, 0.0))
    gap = float(rng.uniform(0.05, 0.5))
    sysd.update(
        theta=theta,
        gap=gap,
        x0=np.array([theta + gap + rng.uniform(0.0, 0.5), rng.uniform(-1, 1)]),
        T=float(rng.uniform(0.5, 3.0)),
        steps=int(rng.integers(1, 10)),
    )
    sysd["u"] = rng.uniform(-2, 2, (sysd["steps"], 1))
    return sysd


def _mode_ocp(d: dict[str, Any]) -> hybridoc.HybridOCP:
    import casadi as ca

    s, u = ca.SX.sym("s", 2), ca.SX.sym("u")
    modes = {
        name: (ca.mtimes(ca.DM(d["A"][q]), s) + ca.vertcat(0, u) + ca.DM(d["c"][q]),
               d["rho"][q] * u**2)
        for q, name in enumerate(("a", "b"))
    }  # fmt: skip
    th, gap = d["theta"], d["gap"]
    down = hybridoc.Guard.from_expressions(
        "down", s, s[0] - th, ca.vertcat(s[0], d["r"][0] * s[1]), source="a", target="b"
    )
    up = hybridoc.Guard.from_expressions(
        "up", s, th + gap - s[0], ca.vertcat(s[0], d["r"][1] * s[1]), source="b", target="a"
    )
    return hybridoc.HybridOCP.from_modes(
        s, u, modes=modes, transitions=[down, up], initial_mode="a",
        phi=s[0] ** 2 + s[1] ** 2, x0=d["x0"], horizon=d["T"], steps=d["steps"],
    )  # fmt: skip


def _mode_oracle(d: dict[str, Any]) -> tuple[list[tuple[float, str, str]], np.ndarray, float]:
    """Events ``(time, guard, mode after)``, the final state and the cost (module notes)."""
    from scipy.linalg import expm
    from scipy.optimize import brentq

    def flow(q: int, s: np.ndarray, u: float, tau: Any) -> np.ndarray:
        """The exact flow at one time or (batched) at an array of times."""
        M = np.zeros((3, 3))
        M[:2, :2] = d["A"][q]
        M[:2, 2] = d["c"][q] + np.array([0.0, u])
        E = expm(np.multiply.outer(np.atleast_1d(tau), M))
        out = (E @ np.r_[s, 1.0])[:, :2]
        return out if np.ndim(tau) else out[0]

    def psi(q: int, s: np.ndarray) -> Any:
        x = s[..., 0]
        return x - d["theta"] if q == 0 else d["theta"] + d["gap"] - x

    s, q, cost, events = np.array(d["x0"], dtype=float), 0, 0.0, []
    h = d["T"] / d["steps"]
    for n in range(d["steps"]):
        u = float(d["u"][n, 0])
        t, left = n * h, h
        while True:
            taus = np.linspace(0.0, left, 401)
            vals = psi(q, flow(q, s, u, taus))
            cross = np.flatnonzero((vals[:-1] > 0) & (vals[1:] <= 0))
            if cross.size == 0:
                assume(np.min(vals[1:]) > 1e-6)  # no near-graze
                cost += d["rho"][q] * u * u * left
                s = flow(q, s, u, left)
                break
            i = int(cross[0])
            assume(np.min(vals[1 : i + 1], initial=1.0) > 1e-6)
            tau = brentq(
                lambda x, q=q, s=s, u=u: psi(q, flow(q, s, u, x)), taus[i], taus[i + 1],
                xtol=1e-15,
            )  # fmt: skip
            s_ev = flow(q, s, u, tau)
            rate = (psi(q, flow(q, s, u, tau + 1e-7)) - psi(q, flow(q, s, u, tau - 1e-7))) / 2e-7
            assume(rate < -1e-3)
            cost += d["rho"][q] * u * u * tau
            s = np.array([s_ev[0], d["r"][q] * s_ev[1]])
            name = "down" if q == 0 else "up"
            q = 1 - q
            t, left = t + tau, left - tau
            events.append((t, name, "ab"[q]))
            assume(len(events) <= 30)
    return events, s, cost + float(s @ s)


@settings(max_examples=examples(3), deadline=None)  # about 1 s each (CVODES kernels)
@given(d=mode_systems())
def test_judge_agrees_with_an_exact_simulation_of_random_mode_switches(d: dict[str, Any]) -> None:
    events, s_T, cost = _mode_oracle(d)
    event(f"{len(events)} switches")
    ev = hybridoc.evaluate(_mode_ocp(d), d["u"])
    note(f"oracle {events}; judge {[(e.time, e.name, e.mode_after) for e in ev.events]}")
    assert [(e.name, e.mode_after) for e in ev.events] == [(n, m) for _, n, m in events]
    assert all(e.mode_before != e.mode_after for e in ev.events)
    np.testing.assert_allclose([e.time for e in ev.events], [t for t, _, _ in events], atol=1e-8)
    np.testing.assert_allclose(ev.final_state[:2], s_T, rtol=1e-7, atol=1e-7)
    assert ev.final_state[2] == (0.0 if not events or events[-1][2] == "a" else 1.0)
    assert ev.cost == pytest.approx(cost, rel=1e-7, abs=1e-9)
