"""The judge's rounding levels are per guard and per state component (issue #17).

A passive disc added far away (or receding fast) to ``single-collision`` once raised the
rounding level of every guard, since it was taken from the largest state component: at 1e15
the judge saw 240 phantom ``ball1|ball2`` collisions (cost 1.1525), at 1e14 two, at 1e12 one
placed wrongly (cost 1.18101), and a disc receding at 1e13 gave 1.17375; the right answer is
the scene's own, 1.18159 with one event. The same global scale let two non-commuting
simultaneous jumps pass as commuting when a far body was present. The metamorphic properties
(far bodies, translations, scalings of random scenes) are in ``test_judge_properties.py``.
"""

from __future__ import annotations

import dataclasses

import casadi as ca
import numpy as np
import pytest

import hybridoc
from hybridoc import Disc
from hybridoc.events import commute_defect
from hybridoc.kernels import EPS, flow_scale_fn, kernels, rounding_level
from hybridoc.problems import load_problem

SINGLE_COST = 1.1815869771554746  # README: the judged initial guess of single-collision

FAR = [
    pytest.param((1e12, 0.0), (0.0, 0.0), id="at-1e12"),
    pytest.param((1e14, 0.0), (0.0, 0.0), id="at-1e14"),
    pytest.param((1e15, 0.0), (0.0, 0.0), id="at-1e15"),
    pytest.param((10.0, 0.0), (1e13, 0.0), id="receding-1e13"),
    pytest.param((1e15, 1e15), (1e13, 1e13), id="at-1e15-receding-1e13"),
]


def _with_ball3(position: tuple[float, float], velocity: tuple[float, float]) -> hybridoc.Scene:
    base = load_problem("single-collision")
    ball3 = Disc(name="ball3", position=position, velocity=velocity, radius=0.2)
    return dataclasses.replace(base, discs=(*base.discs, ball3))


@pytest.fixture(scope="module")
def base() -> hybridoc.Evaluation:
    return hybridoc.evaluate("single-collision")


def test_single_collision_without_ball3(base: hybridoc.Evaluation) -> None:
    assert base.cost == pytest.approx(SINGLE_COST, rel=1e-12)
    assert base.sequence == ["ball1|ball2"]


@pytest.mark.parametrize(("position", "velocity"), FAR)
def test_far_passive_disc_changes_nothing(
    base: hybridoc.Evaluation, position: tuple[float, float], velocity: tuple[float, float]
) -> None:
    ev = hybridoc.evaluate(_with_ball3(position, velocity))
    assert ev.sequence == ["ball1|ball2"]
    assert ev.cost == pytest.approx(SINGLE_COST, rel=1e-12)
    assert ev.events[0].time == pytest.approx(base.events[0].time, rel=1e-12)
    n = 2 * 2  # ball1 and ball2 positions, then (after ball3's) their velocities
    np.testing.assert_allclose(ev.final_state[:n], base.final_state[:n], rtol=1e-12)
    np.testing.assert_allclose(ev.final_state[6:10], base.final_state[4:8], rtol=1e-12)


@pytest.mark.parametrize(("position", "velocity"), [FAR[2], FAR[3]])
def test_far_passive_disc_changes_nothing_on_the_callable_path(
    position: tuple[float, float], velocity: tuple[float, float]
) -> None:
    ocp = hybridoc.as_ocp("single-collision")
    grid, U = ocp.time_grid(), ocp.u_guess

    def u(t: float) -> np.ndarray:
        return U[min(max(int(np.searchsorted(grid, t, side="right")) - 1, 0), len(U) - 1)]

    want = hybridoc.evaluate(ocp, u)
    ev = hybridoc.evaluate(_with_ball3(position, velocity), u)
    assert ev.sequence == want.sequence == ["ball1|ball2"]
    assert ev.cost == pytest.approx(want.cost, rel=1e-12)


def test_far_passive_disc_leaves_the_gradient_alone(base: hybridoc.Evaluation) -> None:
    want = hybridoc.gradient("single-collision")
    got = hybridoc.gradient(_with_ball3((1e15, 0.0), (0.0, 0.0)))
    np.testing.assert_allclose(got.d_controls, want.d_controls, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("x", [1e9, 1e12, 1e15])
def test_far_disc_does_not_hide_a_simultaneous_impact(x: float) -> None:
    # the striker touches a and b at once and the two jumps do not commute: an error with or
    # without a passive disc far away (a far disc's 1e15 once made the commute test's scale
    # 1e15 and the jumps "commuted")
    sc = hybridoc.load_scene("tests/scenes/symmetric-striker.toml")
    far = Disc(name="far", position=(x, 0.0), radius=0.2)
    with pytest.raises(hybridoc.SimultaneousEventError):
        hybridoc.evaluate(dataclasses.replace(sc, discs=(*sc.discs, far)))


# ------------------------------------------------------------------ the rounding levels
def test_rounding_level_ignores_components_a_guard_does_not_depend_on() -> None:
    ocp = _with_ball3((1e15, 0.0), (1e13, 0.0)).to_ocp()
    num = kernels(ocp).numeric()
    far = np.array(ocp.x0)
    far[4], far[10] = 1e15, 1e13  # ball3.x, ball3.vx
    near = far.copy()
    near[4], near[10] = 5.0, 0.0
    j = [g.name for g in ocp.guards].index("ball1|ball2")
    for fn in (lambda x: num.contact(x, ocp.u_guess[0])[3], lambda x: num.det(x)[1]):
        assert fn(far)[j] == fn(near)[j]
        assert fn(far)[j] < 1e-13
    # and along the flow (the interval kernel's samples)
    h = ocp.horizon / ocp.steps
    nz_far = num.interval(far, ocp.u_guess[0], h)[3]
    nz_near = num.interval(near, ocp.u_guess[0], h)[3]
    k = kernels(ocp)
    np.testing.assert_array_equal(
        nz_far.reshape(k.D + 1, k.G)[:, j], nz_near.reshape(k.D + 1, k.G)[:, j]
    )


def test_rounding_level_second_order_term_side_by_side_far_away() -> None:
    # two discs side by side at y = 1e15: the pair detector |dp|^2 - R^2 depends on dy only
    # to second order (dy = 0), but each y is uncertain by 8 eps 1e15 ~ 1.8, so the detector
    # is uncertain by (1.8 + 1.8)^2 ~ 13: the first order alone would say 2e-15
    x = ca.SX.sym("x", 4)  # x1, y1, x2, y2
    det = (x[0] - x[2]) ** 2 + (x[1] - x[3]) ** 2 - 0.4**2
    f = ca.Function("f", [x], [rounding_level(det, x, ca.fmax(1, ca.fabs(x)))])
    s = np.array([0.0, 1e15, 0.5, 1e15])
    delta = 8 * EPS * 1e15
    assert float(f(s)) >= (2 * delta) ** 2
    # in unit scenes the level is the first-order one, a few ulps
    assert float(f(np.array([0.0, 0.0, 0.5, 0.0]))) < 1e-14


def test_flow_scale_is_the_sum_of_the_terms_of_the_disc_flow() -> None:
    # a disc passing the origin fast: x(tau) = 0 while its terms are 1e13; the rounding scale
    # of x is |x0| + |vx| tau + |ax| tau^2 / 2, not max(1, |x(tau)|)
    d = Disc(name="d", position=(-1e13, 0.0), velocity=(1e13, 0.0), radius=0.1,
             actuated=True, mass=2.0, target=(0.0, 0.0))  # fmt: skip
    ocp = hybridoc.Scene(horizon=1.0, steps=1, discs=(d,)).to_ocp()
    fn = flow_scale_fn(ocp.flow_map, ca.SX, ocp.nx, ocp.nu)
    state, scale = (np.asarray(v, dtype=float).ravel() for v in fn(ocp.x0, [4.0, 0.0], 1.0))
    # x(1) = -1e13 + 1e13 + (4 / 2) / 2 = 1 (exactly, here)
    assert state[0] == 1.0
    # |x0| + |vx| tau + |ax| tau^2 / 2, and |vx + ax tau| tau for the rounding of tau itself
    assert scale[0] == pytest.approx(1e13 + 1e13 + 1.0 + (1e13 + 2.0), rel=1e-15)
    assert scale[1] == 1.0  # y: all terms zero, the floor


def test_commute_defect_counts_only_the_components_the_jumps_touch() -> None:
    s = np.array([1e15, 0.0, 1.0, -1.0])  # a far coordinate, then two velocities
    ab = np.array([1e15, 0.0, 0.5, -0.5])
    ba = np.array([1e15, 0.0, 0.5 + 1e-6, -0.5])
    assert commute_defect(ab, ba, s) == pytest.approx(1e-6)
    assert commute_defect(ab, ab.copy(), s) == 0.0
    assert commute_defect(s, s.copy(), s) == 0.0
