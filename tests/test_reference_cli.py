"""``hybridoc reference``: JSON keys, outputs, errors."""

from __future__ import annotations

import json

import numpy as np

import hybridoc
from hybridoc.cli import main


def test_reference_json(capsys):
    rc = main(["reference", "single-collision", "--json", "--sequence", "ball1|ball2"])
    out = capsys.readouterr()
    assert rc == 0
    data = json.loads(out.out)  # exactly one JSON object on stdout
    for key in ("cost", "terminal_cost", "running_cost", "events", "status", "info", "timings"):
        assert key in data
    assert data["status"] == "success" and data["success"] is True
    assert abs(data["cost"] - data["terminal_cost"] - data["running_cost"]) < 1e-14
    assert data["events"][0]["kind"] == "disc-disc"
    assert set(data["events"][0]) == {"time", "kind", "bodies", "guard"}
    assert data["info"]["residual"] < 1e-10 and data["timings"]["solve_time_s"] > 0


def test_reference_out_writes_solution_and_figures(tmp_path, capsys):
    rc = main(["reference", "head-on", "--out", str(tmp_path)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "striker|target" in text
    sol = hybridoc.Solution.load(tmp_path / "head-on_reference")
    assert sol.method == "reference" and sol.info["sequence"] == ["striker|target"]
    for name in ("trajectory", "controls", "costates"):
        png = tmp_path / f"head-on_reference_{name}.png"
        assert png.stat().st_size > 10_000
    # the saved controls are the cell means: re-evaluating them is O(dt) from the optimum
    ev = hybridoc.evaluate(hybridoc.load_scene("head-on"), sol.controls)
    assert 0 <= ev.cost - sol.cost < 1e-3
    assert np.isfinite(sol.info["residual"])


def test_reference_impossible_sequence_exit_2(capsys):
    rc = main(["reference", "multiple-collision", "--sequence", "ball2|wall"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("hybridoc: error:") and "hint" in err
    assert len(err.strip().splitlines()) == 1


def test_reference_initial_verbose_shows_newton(tmp_path, capsys):
    # a piecewise-constant near-optimum as the start: the log shows Newton's iterations
    from hybridoc.reference import solve_reference

    ref = solve_reference(hybridoc.load_scene("single-collision"))
    np.save(tmp_path / "u.npy", ref.controls)
    rc = main(["reference", "single-collision", "--initial", str(tmp_path / "u.npy"), "--verbose"])
    err = capsys.readouterr().err
    assert rc == 0
    res = [float(line.split("=")[1].split()[0]) for line in err.splitlines() if "|R|_inf" in line]
    assert res[0] > 1e-6 and min(res) < 1e-13
    rc = main(["reference", "single-collision", "--initial", str(tmp_path / "missing.npy")])
    assert rc == 2 and "missing.npy" in capsys.readouterr().err
