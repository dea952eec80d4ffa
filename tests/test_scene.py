"""Scene format: every validation error, defaults, built-ins, round trips, Python objects."""

from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import hybridoc
from hybridoc import Disc, Scene, SceneError, Wall, load_scene


def base() -> dict[str, Any]:
    """A valid scene: one striker with a force, one target disc, one wall."""
    return {
        "name": "t",
        "horizon": 1.0,
        "steps": 10,
        "discs": [
            {
                "name": "a",
                "position": [0.0, 0.0],
                "radius": 0.2,
                "actuated": True,
                "initial_control": [1.0, 0.0],
            },
            {"name": "b", "position": [1.0, 0.0], "radius": 0.2, "target": [2.0, 0.0]},
        ],
        "walls": [{"name": "floor", "point": [0.0, -1.0], "normal": [0.0, 1.0]}],
    }


def edit(path: tuple[Any, ...], value: Any) -> dict[str, Any]:
    """``base()`` with the item at ``path`` set to ``value`` (or deleted if value is DELETE)."""
    data = base()
    node: Any = data
    for key in path[:-1]:
        node = node[key]
    if value is DELETE:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return data


DELETE = object()
NAN, INF = float("nan"), float("inf")

# (case id, path to edit, new value, words the message must contain)
CASES = [
    ("unknown top key", ("gravity",), 9.81, ["unknown top-level key", "gravity"]),
    ("unknown disc key", ("discs", 0, "colour"), "red", ["discs[0]", "unknown key", "colour"]),
    ("unknown wall key", ("walls", 0, "friction"), 0.1, ["walls[0]", "unknown key", "friction"]),
    ("missing horizon", ("horizon",), DELETE, ["missing", "horizon"]),
    ("missing discs", ("discs",), DELETE, ["missing", "discs"]),
    ("missing disc name", ("discs", 0, "name"), DELETE, ["discs[0]", "missing", "name"]),
    ("missing disc position", ("discs", 1, "position"), DELETE, ["discs[1]", "'b'", "position"]),
    ("missing disc radius", ("discs", 0, "radius"), DELETE, ["missing", "radius"]),
    ("missing wall point", ("walls", 0, "point"), DELETE, ["walls[0]", "missing", "point"]),
    ("missing wall normal", ("walls", 0, "normal"), DELETE, ["walls[0]", "missing", "normal"]),
    ("horizon string", ("horizon",), "1.0", ["horizon", "number"]),
    ("steps float", ("steps",), 4.5, ["steps", "integer"]),
    ("steps bool", ("steps",), True, ["steps", "integer"]),
    ("steps zero", ("steps",), 0, ["steps", "positive"]),
    ("position 3 components", ("discs", 0, "position"), [0.0, 0.0, 0.0], ["position", "2"]),
    ("position scalar", ("discs", 0, "position"), 1.0, ["position", "list of 2"]),
    ("position string", ("discs", 0, "position"), "00", ["position", "list of 2"]),
    ("velocity entry string", ("discs", 0, "velocity"), [0.0, "x"], ["velocity", "number"]),
    ("actuated string", ("discs", 0, "actuated"), "yes", ["actuated", "true or false"]),
    ("disc name number", ("discs", 0, "name"), 7, ["name", "string"]),
    ("wall name number", ("walls", 0, "name"), 7, ["wall name", "string"]),
    ("discs not a list", ("discs",), {"name": "a"}, ["discs", "array of tables"]),
    ("walls not a list", ("walls",), {"point": [0, 0]}, ["walls", "array of tables"]),
    ("description number", ("description",), 3, ["description", "string"]),
    ("control 3 components", ("discs", 0, "initial_control"), [1, 2, 3], ["initial_control"]),
    ("control rows != steps", ("discs", 0, "initial_control"), [[1, 0]] * 3, ["3 rows", "10"]),
    ("NaN position", ("discs", 0, "position"), [NAN, 0.0], ["position", "finite"]),
    ("inf velocity", ("discs", 0, "velocity"), [0.0, INF], ["velocity", "finite"]),
    ("NaN horizon", ("horizon",), NAN, ["horizon", "finite"]),
    ("inf target", ("discs", 1, "target"), [INF, 0.0], ["target", "finite"]),
    ("NaN control", ("discs", 0, "initial_control"), [NAN, 0.0], ["initial_control", "finite"]),
    ("NaN wall normal", ("walls", 0, "normal"), [0.0, NAN], ["normal", "finite"]),
    ("NaN restitution", ("restitution",), NAN, ["restitution", "finite"]),
    ("zero radius", ("discs", 0, "radius"), 0.0, ["'a'", "radius", "positive"]),
    ("negative radius", ("discs", 1, "radius"), -0.1, ["'b'", "radius", "positive"]),
    ("zero mass", ("discs", 0, "mass"), 0, ["mass", "positive"]),
    ("negative mass", ("discs", 1, "mass"), -2.0, ["mass", "positive"]),
    ("zero horizon", ("horizon",), 0.0, ["horizon", "positive"]),
    ("zero control weight", ("control_weight",), 0.0, ["control_weight", "positive"]),
    ("restitution above 1", ("restitution",), 1.5, ["restitution", "[0, 1]"]),
    ("restitution below 0", ("restitution",), -0.1, ["restitution", "[0, 1]"]),
    ("restitution bool", ("restitution",), True, ["restitution", "number"]),
    ("discs overlap", ("discs", 1, "position"), [0.3, 0.0], ["'a'", "'b'", "overlap", "t = 0"]),
    ("disc overlaps wall", ("discs", 0, "position"), [0.0, -0.9], ["'a'", "'floor'", "overlap"]),
    ("disc behind wall", ("discs", 1, "position"), [1.0, -3.0], ["'b'", "'floor'", "overlap"]),
    ("no actuated disc", ("discs", 0, "actuated"), False, ["no actuated disc"]),
    ("no target", ("discs", 1, "target"), DELETE, ["nothing in the terminal cost"]),
    ("zero wall normal", ("walls", 0, "normal"), [0.0, 0.0], ["normal", "zero length"]),
    ("duplicate disc names", ("discs", 1, "name"), "a", ["unique", "a"]),
    ("wall named like a disc", ("walls", 0, "name"), "b", ["wall names", "unique"]),
    ("no discs", ("discs",), [], ["no discs"]),
    # names become CasADi function names, which take ASCII only (was a CasADi traceback)
    (
        "non-ASCII disc name",
        ("discs", 0, "name"),
        "b\u00e4ll",
        ["disc name", "'b\u00e4ll'", "ASCII"],
    ),
    ("disc name with a bar", ("discs", 1, "name"), "b|c", ["disc name", "'b|c'"]),
    ("disc name with a space", ("discs", 1, "name"), "b c", ["disc name", "'b c'"]),
    ("disc name from a digit", ("discs", 1, "name"), "2b", ["disc name", "'2b'"]),
    ("non-ASCII wall name", ("walls", 0, "name"), "\u5e8a", ["wall name", "'\u5e8a'", "ASCII"]),
    # a typo such as 1e20 steps failed late with an OverflowError traceback
    ("steps huge", ("steps",), 10**20, ["steps", "at most 1000000"]),
]


@pytest.mark.parametrize(
    ("path", "value", "words"), [c[1:] for c in CASES], ids=[c[0] for c in CASES]
)
def test_scene_error_names_the_problem(path, value, words):
    data = edit(path, value)
    if path == ("discs", 0, "actuated"):  # the guess belongs to an actuated disc only
        del data["discs"][0]["initial_control"]
    with pytest.raises(SceneError) as info:
        Scene.from_dict(data)
    msg = str(info.value)
    for w in words:
        assert w in msg, f"{w!r} not in {msg!r}"
    assert "\n" not in msg


def test_names_with_hyphens_and_underscores_are_valid():
    data = base()
    data["discs"][0]["name"] = "ball-1"
    data["discs"][1]["name"] = "_Ball_2"
    data["walls"][0]["name"] = "left-wall_0"
    ocp = Scene.from_dict(data).to_ocp()
    assert [g.name for g in ocp.guards] == [
        "ball-1|_Ball_2",
        "ball-1|left-wall_0",
        "_Ball_2|left-wall_0",
    ]
    assert ocp.control_labels == ["ball-1.ux", "ball-1.uy"]
    assert np.isfinite(hybridoc.evaluate(ocp).cost)


def test_steps_limit_in_every_problem():
    from hybridoc.ocp import MAX_STEPS

    assert Scene.from_dict(edit(("steps",), MAX_STEPS)).steps == MAX_STEPS
    ocp = load_scene("head-on").to_ocp()
    with pytest.raises(SceneError, match="at most 1000000"):
        ocp.replace(steps=MAX_STEPS + 1)  # was a numpy ValueError from the resampling


def test_initial_control_on_unactuated_disc():
    data = base()
    data["discs"][1]["initial_control"] = [1.0, 0.0]
    with pytest.raises(SceneError, match="'b'.*initial_control.*not actuated"):
        Scene.from_dict(data)


def test_duplicate_wall_names():
    data = base()
    data["walls"].append({"name": "floor", "point": [0.0, 5.0], "normal": [0.0, -1.0]})
    with pytest.raises(SceneError, match="wall names must be unique.*floor"):
        Scene.from_dict(data)


def test_bad_toml_syntax(tmp_path: Path):
    path = tmp_path / "bad.toml"
    path.write_text("horizon = 1.0\n[[discs]\nname = 'a'\n")
    with pytest.raises(SceneError, match="bad.toml.*not valid TOML"):
        load_scene(path)


def test_toml_nan_and_inf_literals(tmp_path: Path):
    text = Scene.from_dict(base()).to_toml().replace("radius = 0.2", "radius = nan", 1)
    path = tmp_path / "nan.toml"
    path.write_text(text)
    with pytest.raises(SceneError, match="nan.toml.*radius must be finite"):
        load_scene(path)
    path.write_text(text.replace("radius = nan", "radius = inf"))
    with pytest.raises(SceneError, match="radius must be finite"):
        load_scene(path)


def test_file_error_message_names_the_file(tmp_path: Path):
    data = base()
    data["discs"][0]["mass"] = -1.0
    path = tmp_path / "heavy.toml"
    path.write_text(Scene.from_dict(base()).to_toml().replace("mass = 1.0", "mass = -1.0", 1))
    with pytest.raises(SceneError, match=r"heavy\.toml.*'a'.*mass must be positive"):
        load_scene(str(path))


def test_not_utf8_file(tmp_path: Path):
    path = tmp_path / "latin1.toml"
    path.write_bytes("name = 'caf\xe9'\n".encode("latin-1"))
    with pytest.raises(SceneError, match="not UTF-8"):
        load_scene(path)


def test_missing_file(tmp_path: Path):
    with pytest.raises(SceneError, match="does not exist"):
        load_scene(tmp_path / "nowhere.toml")
    with pytest.raises(SceneError, match="cannot read"):
        Scene.from_toml(tmp_path / "nowhere.toml")


def test_unknown_builtin_name():
    with pytest.raises(SceneError, match="unknown scene 'single-colision'.*single-collision"):
        load_scene("single-colision")


def test_scene_error_is_a_hybridoc_error():
    assert issubclass(SceneError, hybridoc.HybridocError)


# ---------------------------------------------------------------------------- good scenes
@pytest.mark.parametrize("name", hybridoc.builtin_names())
def test_builtin_loads_and_compiles(name):
    sc = load_scene(name)
    assert sc.name == name
    assert sc.description
    ocp = sc.to_ocp()
    assert ocp.nx == 4 * sc.n_discs
    assert ocp.nu == sc.n_controls > 0
    assert sc.initial_controls().shape == (sc.steps, sc.n_controls)
    np.testing.assert_array_equal(ocp.u_guess, sc.initial_controls())
    n_pairs = sc.n_discs * (sc.n_discs - 1) // 2
    assert len(ocp.guards) == n_pairs + sc.n_discs * len(sc.walls)
    assert sc.to_ocp() is ocp  # cached


def test_builtins_include_the_paper_problems():
    names = hybridoc.builtin_names()
    assert {"single-collision", "multiple-collision"} <= set(names)
    assert len(names) >= 4
    sc = load_scene("single-collision")
    assert (sc.horizon, sc.steps, sc.control_weight, sc.restitution) == (1.0, 480, 0.01, 1.0)
    assert [d.position for d in sc.discs] == [(-1.0, -2.0), (-1.0, -1.0)]
    np.testing.assert_array_equal(sc.initial_controls(), np.tile([0.0, 3.0], (480, 1)))
    mc = load_scene("multiple-collision")
    assert [d.position for d in mc.discs] == [(0.25, -0.3), (-0.5, 0.6)]
    assert mc.walls[0].point == (0.0, 1.0) and mc.walls[0].normal == (0.0, -1.0)
    np.testing.assert_array_equal(mc.initial_controls(), np.tile([-3.5, 3.0], (480, 1)))


def test_defaults_applied():
    data = {
        "horizon": 2.0,
        "discs": [
            {"name": "a", "position": [0, 0], "radius": 0.1, "actuated": True},
            {"name": "b", "position": [1, 0], "radius": 0.1, "target": [0, 0]},
        ],
        "walls": [{"point": [0, -1], "normal": [0, 3]}],
    }
    sc = Scene.from_dict(data, default_name="fallback")
    assert sc.name == "fallback"
    assert sc.description == ""
    assert sc.steps == 480
    assert sc.control_weight == 0.01
    assert sc.restitution == 1.0
    a, b = sc.discs
    assert a.velocity == (0.0, 0.0) and a.mass == 1.0 and a.target is None
    assert b.actuated is False and b.initial_control is None
    assert sc.walls[0].name == "wall0"
    np.testing.assert_array_equal(sc.initial_controls(), np.zeros((480, 2)))
    assert sc.dt == 2.0 / 480
    np.testing.assert_allclose(sc.time_grid(), np.linspace(0, 2, 481), rtol=0, atol=0)
    assert sc.control_labels() == ["a.ux", "a.uy"]


def test_file_name_is_the_default_name(tmp_path: Path):
    data = base()
    del data["name"]
    text = Scene.from_dict(data).to_toml().replace('name = "scene"\n', "", 1)
    path = tmp_path / "my-scene.toml"
    path.write_text(text)
    assert load_scene(path).name == "my-scene"


def test_wall_normal_normalised():
    w = Wall(point=(0, 0), normal=(3.0, -4.0))
    assert w.normal == pytest.approx((0.6, -0.8), abs=1e-16)
    assert math.hypot(*w.normal) == pytest.approx(1.0, abs=1e-15)
    with pytest.raises(SceneError, match="zero length"):
        Wall(point=(0, 0), normal=(0.0, 0.0))


@pytest.mark.parametrize("name", hybridoc.builtin_names())
def test_to_toml_round_trip_builtin(name, tmp_path: Path):
    sc = load_scene(name)
    path = tmp_path / f"{name}.toml"
    path.write_text(sc.to_toml())
    back = load_scene(path)
    assert back == sc
    assert hash(back) == hash(sc)
    assert back.to_toml() == sc.to_toml()


def test_to_toml_round_trip_python_scene():
    steps = 6
    u = np.linspace(0, 1, 2 * steps).reshape(steps, 2) * (1 / 3)
    sc = Scene(
        horizon=0.75,
        discs=[
            Disc(
                "a-q",  # disc names are identifiers (NAME_PATTERN); quotes: the scene name
                (0.1, 0.2),
                0.05,
                velocity=(1 / 3, -2 / 7),
                mass=1.7,
                actuated=True,
                initial_control=u,
            ),
            Disc("b", (1.0, 1.0), 0.3, target=(np.pi, np.e)),
            Disc("c", (-1.0, 1.0), 0.1, actuated=True),
        ],
        walls=[Wall((0.0, -2.0), (1.0, 1.0), name="slope")],
        steps=steps,
        control_weight=1e-3,
        restitution=0.25,
        name='py"thon',
        description='multi\nline "text"',
    )
    back = Scene.from_dict(tomllib.loads(sc.to_toml()))
    assert back == sc
    np.testing.assert_array_equal(back.initial_controls(), sc.initial_controls())
    np.testing.assert_array_equal(back.initial_state(), sc.initial_state())


def test_equality_sees_control_differences():
    a = Scene.from_dict(base())
    data = base()
    data["discs"][0]["initial_control"] = [1.0, 1e-12]
    assert Scene.from_dict(data) != a
    assert Scene.from_dict(base()) == a


def test_python_object_scene_evaluates():
    sc = Scene(
        horizon=1.0,
        steps=20,
        discs=(
            Disc("a", (0.0, 0.0), 0.2, actuated=True, initial_control=(2.0, 0.0)),
            Disc("b", (1.0, 0.0), 0.2, mass=3.0, target=(1.5, 0.0)),
        ),
    )
    assert load_scene(sc) is sc
    np.testing.assert_array_equal(sc.initial_state(), [0, 0, 1, 0, 0, 0, 0, 0])
    ev = hybridoc.evaluate(sc)
    # x_a = t^2 reaches the contact gap 0.6 at t = sqrt(0.6)
    assert [e.bodies for e in ev.events] == [("a", "b")]
    assert ev.events[0].time == pytest.approx(math.sqrt(0.6), abs=1e-14)
    ocp = sc.to_ocp()
    assert ocp.source_scene is sc and ocp.scene is sc
    np.testing.assert_array_equal(ocp.meta["masses"], [1.0, 3.0])


def test_python_object_errors():
    with pytest.raises(SceneError, match="Disc objects"):
        Scene(horizon=1.0, discs=({"name": "a"},))
    with pytest.raises(SceneError, match="Wall objects"):
        Scene(
            horizon=1.0,
            discs=(Disc("a", (0, 0), 0.1, actuated=True, target=(1, 1)),),
            walls=("floor",),
        )
    with pytest.raises(SceneError, match="disc name"):
        Disc("", (0, 0), 0.1)
    with pytest.raises(SceneError, match="initial_control must be"):
        Disc("a", (0, 0), 0.1, actuated=True, initial_control=np.zeros((2, 2, 2)))


def test_with_steps_resamples_the_guess():
    data = base()
    data["discs"][0]["initial_control"] = [[float(k), 0.0] for k in range(10)]
    sc = Scene.from_dict(data)
    fine = sc.with_steps(20)
    assert fine.steps == 20 and fine.horizon == sc.horizon
    np.testing.assert_array_equal(fine.initial_controls()[:, 0], np.repeat(np.arange(10.0), 2))
    coarse = load_scene("single-collision").with_steps(48)
    np.testing.assert_array_equal(coarse.initial_controls(), np.tile([0.0, 3.0], (48, 1)))
    assert coarse.with_steps(480) == load_scene("single-collision")


def test_base_is_valid():
    sc = Scene.from_dict(copy.deepcopy(base()))
    assert sc.n_discs == 2 and sc.actuated_indices == [0] and sc.n_controls == 2


def test_touching_at_t0_is_allowed_overlap_is_not():
    def scene(y: float) -> Scene:
        return Scene(
            horizon=1.0,
            discs=(Disc("a", (0.0, y), 0.2, actuated=True, target=(0, 0)),),
            walls=(Wall((0.0, -1.0), (0.0, 1.0), name="floor"),),
        )

    # (-0.8 + 1) - 0.2 rounds to -5.6e-17: touching up to rounding, accepted
    assert scene(-0.8).discs[0].position == (0.0, -0.8)
    with pytest.raises(SceneError, match="overlaps wall 'floor'.*penetration 1e-09"):
        scene(-0.8 - 1e-9)
    a = Disc("a", (0.0, 0.0), 0.2, actuated=True)
    Scene(horizon=1.0, discs=(a, Disc("b", (0.4, 0.0), 0.2, target=(0, 0))))
    with pytest.raises(SceneError, match="discs 'a' and 'b' overlap"):
        Scene(horizon=1.0, discs=(a, Disc("b", (0.4 - 1e-9, 0.0), 0.2, target=(0, 0))))


def test_first_overlap_matches_the_pairwise_loop() -> None:
    """The vectorised overlap check (blocks of rows) finds the same first pair as a loop
    over the pairs in scene order, on random crowded scenes (block sizes that split rows)."""
    from hybridoc.problems.scene import Disc, _first_overlap

    rng = np.random.default_rng(5)
    for trial in range(40):
        n = int(rng.integers(2, 30))
        discs = [
            Disc(
                name=f"d{k}",
                position=tuple(rng.uniform(-3, 3, 2)),
                radius=float(rng.uniform(0.05, 0.6)),
            )
            for k in range(n)
        ]
        want = None
        for i in range(n):
            for j in range(i + 1, n):
                a, b = discs[i], discs[j]
                gap = math.dist(a.position, b.position) - (a.radius + b.radius)
                sl = 1e-12 * max(*map(abs, a.position), *map(abs, b.position), a.radius + b.radius)
                if gap < -sl:
                    want = (i, j)
                    break
            if want:
                break
        for block in (1, 3, 256):
            got = _first_overlap(discs, block=block)
            assert (None if got is None else got[:2]) == want, (trial, block)
