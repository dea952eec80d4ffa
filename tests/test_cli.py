"""The ``hybridoc`` command: round trips in a subprocess, user errors, plugins."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import hybridoc
from hybridoc import cli
from hybridoc.io import save_controls
from hybridoc.solution import Solution


def run(tmp_path, *args):
    # cwd = tmp_path so that the repository's bare hybridoc/ does not shadow the install
    return subprocess.run(
        [sys.executable, "-m", "hybridoc", *args],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )


def ok(proc):
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    return proc


@pytest.fixture(scope="module")
def single():
    return hybridoc.load_scene("single-collision")


def test_problems(tmp_path):
    out = ok(run(tmp_path, "problems")).stdout
    for name in hybridoc.builtin_names():
        assert name in out
    assert "Paper problem 1" in out


def test_show_with_plot(tmp_path):
    out = ok(run(tmp_path, "show", "multiple-collision", "--plot", "fig/scene.png")).stdout
    assert "ball1" in out and "wall" in out and "(0, -1)" in out
    assert "initial guess: ball1: constant (-3.5, 3)" in out
    assert "3 event(s)" in out
    png = tmp_path / "fig" / "scene.png"
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_evaluate_json_equals_library(tmp_path, single):
    proc = ok(run(tmp_path, "evaluate", "single-collision", "--json"))
    data = json.loads(proc.stdout)  # stdout holds exactly one JSON object
    ev = hybridoc.evaluate(single)
    assert data["cost"] == ev.cost
    assert data["terminal_cost"] == ev.terminal_cost
    assert data["running_cost"] == ev.running_cost
    assert data["events"] == ev.event_dicts()
    assert len(data["events"]) == 1 and data["events"][0]["kind"] == "disc-disc"


@pytest.mark.parametrize("suffix", [".npy", ".csv"])
def test_evaluate_controls_file(tmp_path, single, suffix):
    u = single.initial_controls() + np.linspace(-0.5, 0.5, single.steps)[:, None]
    save_controls(tmp_path / f"u{suffix}", u, single.control_labels())
    proc = ok(run(tmp_path, "evaluate", "single-collision", "--controls", f"u{suffix}", "--json"))
    data = json.loads(proc.stdout)
    ev = hybridoc.evaluate(single, u)
    assert data["cost"] == ev.cost and data["events"] == ev.event_dicts()
    assert data["cost"] != hybridoc.evaluate(single).cost


def test_evaluate_text_and_scene_file(tmp_path, single):
    (tmp_path / "mine.toml").write_text(single.to_toml())
    out = ok(run(tmp_path, "evaluate", "mine.toml")).stdout
    ev = hybridoc.evaluate(single)
    assert f"cost      {ev.cost!r}" in out
    assert "disc-disc" in out and repr(float(ev.events[0].time)) in out


def test_gradient_json_equals_library(tmp_path, single):
    u = single.initial_controls() * 1.1
    np.save(tmp_path / "u.npy", u)
    data = json.loads(
        ok(run(tmp_path, "gradient", "single-collision", "--controls", "u.npy", "--json")).stdout
    )
    g = hybridoc.gradient(single, u)
    pos = np.array(data["d_cost_d_initial_position"])
    vel = np.array(data["d_cost_d_initial_velocity"])
    du = np.array(data["d_cost_d_controls"])
    assert pos.shape == (2, 2) and vel.shape == (2, 2) and du.shape == (480, 2)
    assert np.array_equal(pos.ravel(), g.d_initial_state[:4])
    assert np.array_equal(vel.ravel(), g.d_initial_state[4:])
    assert np.array_equal(du, g.d_controls)
    assert data["cost"] == g.cost


def test_evaluate_out_json_mode(tmp_path):
    proc = ok(run(tmp_path, "evaluate", "multiple-collision", "--json", "--out", "res"))
    data = json.loads(proc.stdout)  # the "wrote ..." lines went to stderr
    assert "wrote" in proc.stderr
    res = tmp_path / "res"
    for name in ("solution.npz", "solution.json", "trajectory.png", "controls.png"):
        assert (res / name).stat().st_size > 0
    sol = Solution.load(res / "solution")
    assert sol.method == "evaluate" and sol.scene == "multiple-collision"
    assert sol.cost == data["cost"] and sol.events == data["events"]
    scene = hybridoc.load_scene("multiple-collision")
    assert np.array_equal(sol.controls, scene.initial_controls())
    assert sol.states is not None and sol.states.shape[1] == 8


BAD_SCENE = "horizon = 1.0\n[[discs]\nname = 'a'\n"


@pytest.mark.parametrize(
    ("args", "setup", "message"),
    [
        (["evaluate", "no-such-scene"], None, "unknown scene 'no-such-scene'"),
        (["evaluate", "bad.toml"], "toml", "not valid TOML"),
        (["evaluate", "single-collision", "--controls", "u.npy"], "short", r"\(480, 2\)"),
        (["gradient", "single-collision", "--controls", "u.npy", "--json"], "nan", "non-finite"),
        (["evaluate", "single-collision", "--controls", "gone.csv"], None, "does not exist"),
    ],
)
def test_user_errors(tmp_path, args, setup, message):
    if setup == "toml":
        (tmp_path / "bad.toml").write_text(BAD_SCENE)
    elif setup == "short":
        np.save(tmp_path / "u.npy", np.zeros((479, 2)))
    elif setup == "nan":
        u = np.zeros((480, 2))
        u[7, 0] = np.nan
        np.save(tmp_path / "u.npy", u)
    proc = run(tmp_path, *args)
    assert proc.returncode == 2
    assert proc.stdout == ""
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("hybridoc: error: ")
    assert "Traceback" not in proc.stderr
    import re

    assert re.search(message, lines[0])


def test_demo_in_process(tmp_path, capsys):
    assert cli.main(["demo", "--out", str(tmp_path / "out")]) == 0
    out = capsys.readouterr().out
    for name in cli.DEMO_SCENES:
        cost = hybridoc.evaluate(hybridoc.load_scene(name)).cost
        assert name in out and f"{cost:.6f}" in out
        for kind in ("trajectory", "controls"):
            png = tmp_path / "out" / f"{name}_{kind}.png"
            assert png.stat().st_size > 0 and str(png) in out


def test_plugins(tmp_path, monkeypatch, capsys):
    (tmp_path / "hyb_good_plugin.py").write_text(
        textwrap.dedent(
            """
            def register(subparsers):
                p = subparsers.add_parser("hello")
                p.add_argument("--json", action="store_true")
                p.set_defaults(func=lambda args: print("hi from plugin") or 0)
            """
        )
    )
    (tmp_path / "hyb_broken_plugin.py").write_text("import hyb_no_such_dependency\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(cli, "PLUGINS", ("hyb_missing_plugin", "hyb_good_plugin"))
    assert cli.main(["hello"]) == 0
    assert capsys.readouterr().out == "hi from plugin\n"
    monkeypatch.setattr(cli, "PLUGINS", ("hyb_broken_plugin",))
    with pytest.raises(ModuleNotFoundError, match="hyb_no_such_dependency"):
        cli.build_parser()


def test_usage_error_exits_2(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["evaluate"])
    assert info.value.code == 2
    assert "required: SCENE" in capsys.readouterr().err
