"""The supported range of units and sizes, and one clear refusal outside it (issue #32).

The closed form: single-collision's initial guess with both radii ``r``. The striker
(mass 1, force ``(0, 3)``, from ``(-1, -2)``) meets the target disc (from ``(-1, -1)``)
head-on when ``-2 + 1.5 t^2 = -1 - 2 r``, at ``t_c = sqrt((1 - 2 r) / 1.5)`` with speed
``3 t_c``; the equal masses exchange velocities (e = 1), the target disc ends at
``y = -1 + 3 t_c (1 - t_c)`` (the striker, now at rest and pushed at ``1.5 (t - t_c)^2``,
stays behind it), so ``J = 1 + y^2 + 0.01 * 9``. At ``r = 0.2`` this is the 1.18159 of the
paper's initial guess; as ``r -> 0`` it tends to 1.39306. Radii of ``1e-300`` square to zero
and the judge missed the contact (2.09: the target disc never moves).
"""

from __future__ import annotations

import dataclasses
import math
import tomllib

import numpy as np
import pytest
from cli_here import run_here
from hypothesis import given, settings
from hypothesis import strategies as st
from scaling import CORNERS, transform
from scene_generator import generate

import hybridoc
from hybridoc.errors import SceneError
from hybridoc.problems import Scene, load_scene
from hybridoc.problems.scene import MAGNITUDE_RANGE, MAX_OFFSET_RATIO, MIN_RADIUS_RATIO


def _closed_form(r: float) -> float:
    tc = math.sqrt((1 - 2 * r) / 1.5)
    y = -1 + 3 * tc * (1 - tc)
    return 1 + y * y + 0.09


def _radii(scene: Scene, r: float) -> Scene:
    return dataclasses.replace(
        scene, discs=tuple(dataclasses.replace(d, radius=r) for d in scene.discs)
    )


@pytest.mark.parametrize("r", [0.2, 1e-3, 1e-6, MIN_RADIUS_RATIO])
def test_small_radii_inside_the_range_meet_the_closed_form(r: float) -> None:
    ev = hybridoc.evaluate(_radii(load_scene("single-collision"), r))
    assert len(ev.events) == 1
    assert ev.cost == pytest.approx(_closed_form(r), rel=1e-12)


def test_radii_1e_minus_300_are_refused_naming_the_radius() -> None:
    """The issue's example: both radii 1e-300 (the judge said 2.09, the closed form is
    1.39306): one SceneError naming the field and the range."""
    with pytest.raises(SceneError, match=r"disc 'ball1': radius.*supported range") as exc:
        _radii(load_scene("single-collision"), 1e-300)
    assert "\n" not in str(exc.value)


def test_radii_1e_minus_300_are_refused_by_the_cli(tmp_path) -> None:
    path = tmp_path / "tiny.toml"
    text = load_scene("single-collision").to_toml().replace("radius = 0.2", "radius = 1e-300")
    assert "1e-300" in text
    path.write_text(text)
    out = run_here("evaluate", str(path))
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "radius" in lines[0] and "supported range" in lines[0]


@pytest.mark.parametrize(
    "change, fragment",
    [
        (lambda s: _radii(s, 1e-12), "MIN_RADIUS_RATIO"),
        (lambda s: transform(s, shift=(2e12, 0.0)), "MAX_OFFSET_RATIO"),
        (lambda s: transform(s, length=1e61), "too large"),
        (lambda s: transform(s, time=1e40), "force unit"),
        (lambda s: transform(s, mass=1e-70), "too small"),
    ],
    ids=["radius-ratio", "far-offset", "huge-lengths", "tiny-forces", "tiny-masses"],
)
def test_outside_the_range_one_clear_refusal(change, fragment: str) -> None:
    with pytest.raises(SceneError, match=fragment) as exc:
        change(load_scene("single-collision"))
    assert "\n" not in str(exc.value)


def test_just_inside_the_limits_is_accepted() -> None:
    scene = load_scene("single-collision")
    _radii(scene, 0.2 * (1 + 1e-9) * MIN_RADIUS_RATIO / 0.2)
    transform(scene, shift=(0.5 * MAX_OFFSET_RATIO, 0.0))
    lo, hi = MAGNITUDE_RANGE
    ev = hybridoc.evaluate(transform(scene, length=1e-50))
    assert len(ev.events) == 1
    assert lo < 1e-50 < hi


def test_overlap_is_refused_in_any_units() -> None:
    """The overlap slack was ``1e-12 (1 + |x|)``: in units of 1e-12 it accepted discs
    overlapping by half their radius."""
    for L in (1.0, 1e-12):
        small = transform(load_scene("single-collision"), length=L)
        ball1, ball2 = small.discs
        inside = dataclasses.replace(ball2, position=(-1.0 * L, -1.7 * L))  # overlap 0.1 L
        with pytest.raises(SceneError, match="overlap"):
            dataclasses.replace(small, discs=(ball1, inside))


def _scenes() -> list[Scene]:
    names = ["single-collision", "head-on", "multiple-collision", "damped-walls"]
    out = [load_scene(n) for n in names]
    out += [Scene.from_dict(tomllib.loads(generate(i).to_toml())) for i in (0, 1, 4)]
    return out


@settings(max_examples=25, deadline=None)
@given(
    k=st.integers(0, 6),
    log_l=st.floats(-6, 6),
    log_t=st.floats(-6, 6),
    log_m=st.floats(-6, 6),
    shift=st.tuples(st.floats(-1e6, 1e6), st.floats(-1e6, 1e6)),
)
def test_scenes_inside_the_range_are_accepted_and_round_trip(k, log_l, log_t, log_m, shift) -> None:
    scene = transform(
        _scenes()[k], length=10.0**log_l, time=10.0**log_t, mass=10.0**log_m, shift=shift
    )
    again = Scene.from_dict(tomllib.loads(scene.to_toml()))
    assert again == scene
    assert again.to_ocp().scales == scene.to_ocp().scales


@pytest.mark.parametrize("kw", CORNERS, ids=[str(c) for c in CORNERS])
def test_corners_round_trip_through_a_file(kw: dict, tmp_path) -> None:
    scene = transform(load_scene("multiple-collision"), **kw)
    path = tmp_path / "moved.toml"
    path.write_text(scene.to_toml())
    again = Scene.from_toml(path)
    assert again.discs == scene.discs and again.walls == scene.walls
    assert again.horizon == scene.horizon and again.control_weight == scene.control_weight
    np.testing.assert_array_equal(again.initial_state(), scene.initial_state())
