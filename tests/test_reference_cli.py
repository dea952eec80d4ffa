"""``hybridoc reference``: JSON keys, outputs, errors."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest

import hybridoc
import hybridoc.solvers  # noqa: F401  (registers the candidate sources the reference uses)
from hybridoc.cli import main


def test_reference_json(capsys):
    rc = main(["reference", "single-collision", "--json", "--sequence", "ball1|ball2"])
    out = capsys.readouterr()
    assert rc == 0
    data = json.loads(out.out)  # exactly one JSON object on stdout
    for key in ("cost", "terminal_cost", "running_cost", "events", "status", "info", "timings"):
        assert key in data
    # a given sequence: its extremal, no claim of optimality (exit 0, success false)
    assert data["status"] == "extremal" and data["success"] is False
    assert "given sequence" in data["message"]
    assert abs(data["cost"] - data["terminal_cost"] - data["running_cost"]) < 1e-14
    assert data["events"][0]["kind"] == "disc-disc"
    assert set(data["events"][0]) == {"time", "kind", "bodies", "guard"}
    assert data["info"]["residual"] < 1e-10 and data["timings"]["solve_time_s"] > 0


@pytest.fixture(scope="module")
def head_on_out(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int, str]:
    """``hybridoc reference head-on --out DIR`` run once for the module (its discovery and
    three figures cost seconds): the folder, the exit code and stdout."""
    out = tmp_path_factory.mktemp("head-on")
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        rc = main(["reference", "head-on", "--out", str(out)])
    return out, rc, text.getvalue()


def test_reference_out_writes_solution_and_figures(head_on_out):
    tmp_path, rc, text = head_on_out
    # issue #29: best-found (exit 1): striker|target twice has no extremal, so the sequences
    # of 2 events are not all covered
    assert rc == 1 and "best-found" in text
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

    # the known optimal sequence: this test is about the Newton log, not the discovery
    ref = solve_reference(hybridoc.load_scene("single-collision"), sequence=["ball1|ball2"])
    np.save(tmp_path / "u.npy", ref.controls)
    rc = main(["reference", "single-collision", "--controls", str(tmp_path / "u.npy"), "--verbose"])
    err = capsys.readouterr().err
    assert rc == 0
    res = [float(line.split("=")[1].split()[0]) for line in err.splitlines() if "|R|_inf" in line]
    assert res[0] > 1e-6 and min(res) < 1e-13
    rc = main(["reference", "single-collision", "--controls", str(tmp_path / "missing.npy")])
    assert rc == 2 and "missing.npy" in capsys.readouterr().err


def test_given_sequence_is_an_extremal_not_a_success(capsys):
    # this sequence's extremal costs about twice the optimum 0.3114 and was reported success
    rc = main(["reference", "single-collision", "--sequence", "ball1|ball2,ball1|ball2"])
    out = capsys.readouterr()
    assert rc == 0 and out.err == ""
    status = next(line for line in out.out.splitlines() if line.startswith("status"))
    assert status.split()[1] == "extremal:" and "not compared with other sequences" in status
    assert "cost      0.617" in out.out


def test_given_sequence_with_search(capsys):
    # the search runs without the sequence: it beats the double collision (exit 1) ...
    args = ["reference", "single-collision", "--search", "2", "--json", "--sequence"]
    rc = main([*args, "ball1|ball2,ball1|ball2"])
    out = capsys.readouterr()
    data = json.loads(out.out)
    assert rc == 1 and data["status"] == "not-optimal"
    assert data["info"]["cheaper"]["sequence"] == ["ball1|ball2"]
    assert abs(data["info"]["cheaper"]["cost"] - 0.311416870358) < 1e-9
    assert out.err.startswith("hybridoc: warning: not-optimal:")
    assert {tuple(r["sequence"]) for r in data["info"]["landscape"]} >= {
        ("ball1|ball2",),
        ("ball1|ball2", "ball1|ball2"),
    }
    # ... and confirms the single collision: then it is the optimum
    rc = main([*args, "ball1|ball2"])
    data = json.loads(capsys.readouterr().out)
    assert rc == 0 and data["status"] == "success" and data["success"] is True
    assert "nothing cheaper" in data["message"]


def test_given_sequence_beaten_by_a_known_control():
    # the initial guess (one collision, 1.18) is cheaper than the empty sequence's extremal
    from hybridoc.reference import solve_reference

    sol = solve_reference("single-collision", sequence="")
    assert sol.status is hybridoc.Status.NOT_OPTIMAL and abs(sol.cost - 2.0) < 1e-12
    assert sol.info["cheaper"]["source"] == "the initial guess"


def test_reference_search_out_writes_the_landscape(tmp_path, capsys, head_on_out):
    rc = main(["reference", "single-collision", "--search", "2", "--out", str(tmp_path)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "landscape of extremals" in text
    assert "coverage" in text and "every sequence of up to" in text
    png = tmp_path / "single-collision_reference_landscape.png"
    assert png.stat().st_size > 10_000
    # without --search there is no landscape, and no figure of it
    plain, rc, text = head_on_out
    assert rc == 1 and "landscape" not in text
    assert list(plain.glob("*.png")) and not list(plain.glob("*_landscape.png"))


def test_reference_budget_flag(capsys):
    rc = main(["reference", "single-collision", "--budget", "0.001", "--json"])
    data = json.loads(capsys.readouterr().out)
    cov = data["info"]["coverage"]
    assert cov["budget_s"] == 0.001 and cov["budget_stopped"] is True
    assert rc == (0 if data["status"] == "success" else 1)
    try:
        main(["reference", "single-collision", "--budget", "0"])
    except SystemExit as exc:
        assert exc.code == 2
    assert "budget must be" in capsys.readouterr().err


def test_landscape_figure_marks_the_chosen_sequence():
    from hybridoc.plotting import plot_landscape

    rows = [
        {"sequence": ["a|b"], "cost": 0.3, "verdict": "verified"},
        {"sequence": [], "cost": 0.9, "verdict": "verified"},
        {"sequence": ["a|b", "a|w"], "cost": None, "verdict": "failed: x"},
        {"sequence": ["a|w"], "cost": 0.2, "verdict": "not verified: re-simulation ..."},
    ]
    fig = plot_landscape(rows, ["a|b"], title="t")
    ax = fig.axes[0]
    texts = [t.get_text() for t in ax.texts]
    assert texts == ["a|w", "a|b", "(no event)"]  # sorted by cost, failed ones left out
    labels = ax.get_legend_handles_labels()[1]
    assert "the reference's optimum" in labels


@pytest.mark.parametrize("bad", [2.5, -1, True, "4"])
def test_reference_multistart_is_a_whole_number(bad):
    """multistart was truncated deep in the search (2.5 -> 2) or failed inside gd (-1):
    now one OptionError naming it, before any work."""
    from hybridoc.errors import OptionError
    from hybridoc.reference.options import ReferenceOptions

    with pytest.raises(OptionError, match="multistart must be an integer >= 0"):
        ReferenceOptions(multistart=bad)
    assert ReferenceOptions(multistart=3).multistart == 3
