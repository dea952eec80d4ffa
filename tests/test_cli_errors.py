"""Bad input on the command line and in the Python API: one clear error, never a traceback.

Each CLI case runs ``python -m hybridoc`` in a subprocess and requires exit code 2, exactly one
line ``hybridoc: error: ...`` on stderr and nothing on stdout. The cases fail before any
solver runs, so the file stays fast; the slow commands (ablation, full solves) are only fed
arguments that are rejected up front.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import hybridoc
from hybridoc.errors import ControlsError, SceneError

OVERLAP_TOML = """\
horizon = 1.0
steps = 10
control_weight = 0.01
[[discs]]
name = "a"
position = [0.0, 0.0]
radius = 0.5
actuated = true
target = [1.0, 1.0]
[[discs]]
name = "b"
position = [0.5, 0.0]
radius = 0.5
"""


def _run(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "hybridoc", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


def _one_error(proc: subprocess.CompletedProcess[str], *fragments: str) -> str:
    lines = proc.stderr.splitlines()
    assert proc.returncode == 2, proc.stderr
    assert proc.stdout == ""
    assert len(lines) == 1 and lines[0].startswith("hybridoc: error: "), proc.stderr
    for f in fragments:
        assert f in lines[0], lines[0]
    return lines[0]


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("cli_errors")
    (d / "overlap.toml").write_text(OVERLAP_TOML)
    (d / "bad.toml").write_text("horizon = [\n")
    (d / "a_file").write_text("x")
    (d / "garbage.npy").write_bytes(b"not numpy at all")
    np.save(d / "short.npy", np.ones((10, 2)))
    return d


# ----------------------------------------------------------------- argparse usage errors
@pytest.mark.parametrize(
    ("args", "fragments"),
    [
        (("solve", "head-on", "--contact", "foo"), ("solve:", "--contact", "'foo'")),
        (("solve", "head-on", "--toi", "foo"), ("--toi", "invalid choice")),
        (("solve", "head-on", "--optimizer", "foo"), ("--optimizer",)),
        (("solve", "head-on", "--iters", "-1"), ("--iters", "integer >= 0")),
        (("solve", "head-on", "--iters", "x"), ("--iters",)),
        (("solve", "head-on", "--lr", "-1"), ("--lr", "> 0")),
        (("solve", "head-on", "--lr", "nan"), ("--lr", "finite")),
        (("compare-contacts", "head-on", "--iters", "-2"), ("--iters",)),
        (("compare-contacts", "head-on", "--lr", "0"), ("--lr",)),
        (("convergence", "head-on", "--steps", "0"), ("--steps", "integer >= 1")),
        (("evaluate",), ("evaluate:", "PROBLEM", "hybridoc evaluate --help")),
        (("no-such-command",), ("COMMAND",)),
    ],
)
def test_usage_errors_are_one_line(work: Path, args: tuple[str, ...], fragments) -> None:
    _one_error(_run(work, *args), *fragments)


# ----------------------------------------------------------------- user errors (exit 2)
@pytest.mark.parametrize(
    ("args", "fragments"),
    [
        # an unwritable --out fails before the (slow) work, not after it
        (("solve", "head-on", "--out", "a_file"), ("a_file",)),
        (("ablation", "--out", "a_file"), ("a_file",)),
        (("crossval", "head-on", "--out", "a_file"), ("a_file",)),
        (("convergence", "head-on", "--no-gd", "--out", "a_file"), ("a_file",)),
        (("compare-contacts", "head-on", "--out", "a_file"), ("a_file",)),
        (("reference", "head-on", "--out", "a_file"), ("a_file",)),
        # the transcription has no gd options: say so instead of ignoring them
        (
            ("solve", "head-on", "--method", "dt", "--iters", "3"),
            ("--iters applies to --method gd",),
        ),
        (
            ("solve", "head-on", "--method", "dt", "--toi", "both", "--lr", "1"),
            ("--toi applies to --method gd", "--lr", "not to --method dt"),
        ),
        (("solve", "head-on", "--method", "gd", "--mesh", "8"), ("--mesh applies to --method dt",)),
        # event sequences
        (("reference", "head-on", "--sequence", "nosuch"), ("unknown guard", "striker|target")),
        (("reference", "head-on", "--sequence", "striker|target,,"), ("empty event name",)),
        # a file that is not .npy, behind a .npy name: no talk about pickles
        (("evaluate", "head-on", "--controls", "garbage.npy"), ("no NumPy header",)),
        (("gradcheck", "head-on", "--gd-iters", "x"), ("--gd-iters",)),
        (("show", "overlap.toml"), ("overlap",)),
        (("evaluate", "bad.toml"), ("not valid TOML",)),
        (("validate", "nosuch", "short.npy"), ("unknown problem",)),
        (("evaluate", "nope.py:problem"), ("does not exist",)),
        (("evaluate", "a_file:problem"), ("unknown problem",)),
        (("evaluate", "head-on", "--controls", "nope.npz"), ("nope.npz", "does not exist")),
        (("validate", "head-on", "short.npy"), ("expected shape (240, 2)",)),
    ],
)
def test_user_errors_are_one_line(work: Path, args: tuple[str, ...], fragments) -> None:
    _one_error(_run(work, *args), *fragments)


def test_solve_out_checked_before_solving(work: Path) -> None:
    # before the fix the gd solve ran to the end (progress bar on stderr) and failed after
    proc = _run(work, "solve", "head-on", "--iters", "1", "--out", "a_file")
    assert "gd/" not in proc.stderr
    _one_error(proc, "a_file")


# ----------------------------------------------------------------- the Python API
def test_gd_rejects_bad_numbers() -> None:
    from hybridoc.solvers.gd import solve_gd

    for kwargs, match in [
        ({"iters": 1.5}, "iters"),  # was silently truncated to 1
        ({"iters": "3"}, "iters"),
        ({"lr": "x"}, "lr"),  # was a bare ValueError from float()
        ({"max_step": -1.0}, "max_step"),  # was accepted and stepped backwards
        ({"max_step": float("nan")}, "max_step"),
        ({"smoothing": "1e-4"}, "smoothing"),  # a string was iterated character by character
        ({"smoothing": 5}, "smoothing"),
    ]:
        with pytest.raises(SceneError, match=match):
            solve_gd("head-on", optimizer="gd", **kwargs)
    with pytest.raises(ControlsError, match="not a numeric array"):
        solve_gd("head-on", initial="abc")


def test_simulator_batch_mismatch_is_a_controls_error() -> None:
    from hybridoc.solvers.simulator import Simulator

    sim = Simulator(hybridoc.load_scene("head-on"))
    u = torch.zeros(4, 240, 2, dtype=torch.float64)
    with pytest.raises(ControlsError, match="batch size 3"):
        sim.loss(u, torch.zeros(3, sim.nx, dtype=torch.float64))
    # one row or one state for all batch entries still works
    assert sim.loss(u, torch.zeros(1, sim.nx, dtype=torch.float64) + sim.x0).shape == (4,)
    assert sim.loss(u, sim.x0).shape == (4,)


def test_reference_bad_arguments_are_scene_errors() -> None:
    from hybridoc.reference import solve_reference

    for seq, match in [
        ("nosuch", "unknown guard"),
        (5, "expected guard names"),  # was a TypeError
        (["striker|target", ""], "empty event name"),
        ("striker|target,,striker|target", "empty event name"),  # was silently dropped
    ]:
        with pytest.raises(SceneError, match=match):
            solve_reference("head-on", sequence=seq)
    with pytest.raises(SceneError, match="tol"):  # was a misleading ConvergenceError
        solve_reference("head-on", tol=-1.0)


def test_transcription_takes_names_and_sequence_strings() -> None:
    from hybridoc.solvers.transcription import solve_dt

    # a string sequence was split into characters, a scene name was a TypeError
    with pytest.raises(SceneError, match="unknown guard"):
        solve_dt("head-on", sequence="nosuch")
    with pytest.raises(SceneError, match="expected guard names"):
        solve_dt("head-on", sequence=5)
    sol = solve_dt("head-on", sequence="striker|target")
    assert sol.info["sequence"] == ["striker|target"]


def test_check_sequence() -> None:
    ocp = hybridoc.load_scene("multiple-collision").to_ocp()
    assert ocp.check_sequence("ball1|ball2, ball2|wall") == ["ball1|ball2", "ball2|wall"]
    assert ocp.check_sequence(["ball1|ball2"]) == ["ball1|ball2"]
    assert ocp.check_sequence("") == [] and ocp.check_sequence("  ") == []
    assert ocp.check_sequence([]) == []
    with pytest.raises(SceneError, match="ball2\\|ball1"):
        ocp.check_sequence("ball2|ball1")


def test_convergence_rejects_bad_steps() -> None:
    from hybridoc.solvers.validation import convergence

    for steps in [(), (1.5,), (0,)]:
        with pytest.raises(SceneError, match="steps"):
            convergence("head-on", steps=steps, include_gd=False)
