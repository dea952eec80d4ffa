"""The ``hybridoc`` command: round trips in a subprocess, user errors, plugins.

One subprocess round trip per command (``problems``, ``show``, ``evaluate --json``,
``gradient --json``); the other cases run the same entry point in this process
(``tests/cli_here.py``, output captured at the descriptors too), which answers the same
(``tests/test_cli_errors.py``): a subprocess each cost seconds of start-up under load.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from cli_here import run_here

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


def here(tmp_path, *args):
    """``run`` in this process."""
    return run_here(*args, cwd=tmp_path)


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
    proc = ok(here(tmp_path, "evaluate", "single-collision", "--controls", f"u{suffix}", "--json"))
    data = json.loads(proc.stdout)
    ev = hybridoc.evaluate(single, u)
    assert data["cost"] == ev.cost and data["events"] == ev.event_dicts()
    assert data["cost"] != hybridoc.evaluate(single).cost


def test_evaluate_text_and_scene_file(tmp_path, single):
    (tmp_path / "mine.toml").write_text(single.to_toml())
    out = ok(here(tmp_path, "evaluate", "mine.toml")).stdout
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
    lam0 = np.array(data["d_cost_d_initial_state"])
    du = np.array(data["d_cost_d_controls"])
    assert lam0.shape == (8,) and du.shape == (480, 2)
    assert data["state_labels"][:2] == ["ball1.x", "ball1.y"]
    assert np.array_equal(lam0, g.d_initial_state)
    assert np.array_equal(du, g.d_controls)
    assert data["cost"] == g.cost


def test_evaluate_out_json_mode(tmp_path):
    proc = ok(here(tmp_path, "evaluate", "multiple-collision", "--json", "--out", "res"))
    data = json.loads(proc.stdout)  # the "wrote ..." lines went to stderr
    assert "wrote" in proc.stderr
    res = tmp_path / "res"
    stem = "multiple-collision_evaluate"
    for name in (".npz", ".json", "_trajectory.png", "_controls.png"):
        assert (res / f"{stem}{name}").stat().st_size > 0
    sol = Solution.load(res / stem)
    assert sol.method == "evaluate" and sol.scene == "multiple-collision"
    assert sol.cost == data["cost"] and sol.events == data["events"]
    scene = hybridoc.load_scene("multiple-collision")
    assert np.array_equal(sol.controls, scene.initial_controls())
    assert sol.states is not None and sol.states.shape[1] == 8


BAD_SCENE = "horizon = 1.0\n[[discs]\nname = 'a'\n"


@pytest.mark.parametrize(
    ("args", "setup", "message"),
    [
        (["evaluate", "no-such-scene"], None, "unknown problem 'no-such-scene'"),
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
    proc = here(tmp_path, *args)
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
    from hybridoc.cli.evaluate import DEMO_SCENES

    for name in DEMO_SCENES:
        cost = hybridoc.evaluate(hybridoc.load_scene(name)).cost
        assert name in out and f"{cost:.6f}" in out
        for kind in ("trajectory", "controls"):
            png = tmp_path / "out" / f"{name}_demo_{kind}.png"
            assert png.stat().st_size > 0 and str(png) in out


def test_a_registered_method_is_a_solve_choice(capsys):
    """A new solver is one registration: ``hybridoc solve --method`` reads the registry
    (tests/test_methods.py adds one with an option)."""
    from hybridoc.methods import Method, register_method, unregister_method

    def run_guess(ocp, *, initial=None, progress=None):
        ev = hybridoc.evaluate(ocp, initial)
        return Solution.from_evaluation(ev, method="guess", scene=ocp.name)

    register_method(Method("guess", "the initial guess", run_guess))
    try:
        assert cli.main(["solve", "head-on", "--method", "guess", "--json"]) == 0
        data = json.loads(capsys.readouterr().out)
        assert data["method"] == "guess" and data["status"] == "success"
        assert data["cost"] == hybridoc.evaluate("head-on").cost
    finally:
        unregister_method("guess")


def test_usage_error_exits_2(capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["evaluate"])
    assert info.value.code == 2
    assert "required: PROBLEM" in capsys.readouterr().err
