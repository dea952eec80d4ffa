"""A scene's solver hints (``[hints.<method>]``): parsed, validated, kept, written back, and
passed to the problem's capabilities; the paper scenes carry the paper's gd settings."""

from __future__ import annotations

import dataclasses
import tomllib

import pytest

from hybridoc.errors import SceneError
from hybridoc.problem import as_ocp
from hybridoc.problems import Scene, builtin_names, load_problem, load_scene
from hybridoc.problems.paper import PAPER_SETTINGS


def base(**extra: object) -> dict:
    data = {
        "horizon": 1.0,
        "steps": 8,
        "discs": [
            {"name": "a", "position": [0.0, 0.0], "radius": 0.1, "actuated": True},
            {"name": "b", "position": [1.0, 0.0], "radius": 0.1, "target": [2.0, 0.0]},
        ],
    }
    data.update(extra)
    return data


def test_paper_settings_are_the_paper_scenes_hints() -> None:
    for name, (lr, iters) in PAPER_SETTINGS.items():
        hints = as_ocp(load_problem(name)).capabilities.hints_for("gd")
        assert dict(hints) == {"lr": lr, "iters": iters}
        assert type(hints["lr"]) is float and type(hints["iters"]) is int
    # no other builtin scene names gd settings
    others = [n for n in builtin_names() if n not in PAPER_SETTINGS]
    assert others and all(not load_scene(n).hints for n in others)


def test_hints_parse_round_trip_and_survive_data_changes() -> None:
    hints = {"gd": {"lr": 0.5, "iters": 7, "optimizer": "adam", "toi": True}, "dt": {}}
    sc = Scene.from_dict(base(hints=hints))
    assert sc.hints == hints
    text = sc.to_toml()
    assert "[hints.gd]" in text
    back = Scene.from_dict(tomllib.loads(text))
    assert back == sc and back.to_toml() == text and back.hints == hints
    assert Scene.from_dict(base()) != sc  # hints are part of the scene
    assert sc.with_steps(5).hints == hints
    assert sc.with_initial_state(sc.initial_state() + 0.01).hints == hints
    assert dataclasses.replace(sc, horizon=2.0).hints == hints
    ocp = sc.to_ocp()
    assert dict(ocp.capabilities.hints_for("gd")) == hints["gd"]
    assert dict(ocp.capabilities.hints_for("reference")) == {}
    assert dict(ocp.replace(steps=4).capabilities.hints_for("gd")) == hints["gd"]
    hash(sc)  # still hashable


def test_no_hints_write_nothing() -> None:
    sc = Scene.from_dict(base())
    assert sc.hints == {} and "hints" not in sc.to_toml()
    assert dict(sc.to_ocp().capabilities.hints) == {}


@pytest.mark.parametrize(
    ("hints", "message"),
    [
        (3, "hints must be a table"),
        ({"gd": 1.0}, "hints.gd must be a table"),
        ({"1gd": {}}, "method name '1gd' is not allowed"),
        ({"gd": {"a b": 1}}, "option name 'a b' is not allowed"),
        ({"gd": {"lr": [1, 2]}}, "hints.gd.lr must be a number, a string or a boolean"),
        ({"gd": {"lr": float("inf")}}, "hints.gd.lr must be finite"),
        ({"gd": {"lr": None}}, "hints.gd.lr must be a number"),
    ],
)
def test_bad_hints_are_one_scene_error(hints: object, message: str) -> None:
    with pytest.raises(SceneError, match=message) as info:
        Scene.from_dict(base(hints=hints))
    assert "\n" not in str(info.value)


def test_bad_hints_in_a_file_name_the_file(tmp_path) -> None:
    path = tmp_path / "s.toml"
    path.write_text(Scene.from_dict(base()).to_toml() + "\n[hints.gd]\nlr = [1]\n")
    with pytest.raises(SceneError, match=r"s\.toml.*hints\.gd\.lr"):
        Scene.from_toml(path)
