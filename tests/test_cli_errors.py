"""Bad input on the command line and in the Python API: one clear error, never a traceback.

Each CLI case requires exit code 2, exactly one line ``hybridoc: error: ...`` on stderr and
nothing on stdout. Hostile inputs (files that run code, huge values) run ``python -m
hybridoc`` in a subprocess; the plain usage and user errors run the same entry point,
:func:`hybridoc.cli.main`, in this process (``_run_here``: a subprocess each cost about
0.5 s of start-up), and a few of them also as subprocesses, so that the two stay alike. The
cases fail before any solver runs, so the file stays fast; the slow commands (ablation, full
solves) are only fed arguments that are rejected up front.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from cli_here import run_here

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


def _run_here(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """What ``python -m hybridoc ARGS`` does (``sys.exit(main())``), in this process, in
    ``cwd`` (:func:`cli_here.run_here`)."""
    return run_here(*args, cwd=cwd)


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
        (("solve", "head-on", "--smoothing", "x"), ("--smoothing", "'x'")),
        (("solve", "head-on", "--mesh", "0"), ("--mesh", "from 1 to 1000", "'0'")),
        (("solve", "head-on", "--search", "-1"), ("--search", "integer >= 0")),
        (("solve", "head-on", "--time-limit", "0"), ("--time-limit", "> 0")),
        (("compare-contacts", "head-on", "--iters", "-2"), ("--iters",)),
        (("compare-contacts", "head-on", "--lr", "0"), ("--lr",)),
        (("convergence", "head-on", "--steps", "0"), ("--steps", "integer >= 1")),
        (("evaluate",), ("evaluate:", "PROBLEM", "hybridoc evaluate --help")),
        (("no-such-command",), ("COMMAND",)),
    ],
)
def test_usage_errors_are_one_line(work: Path, args: tuple[str, ...], fragments) -> None:
    _one_error(_run_here(work, *args), *fragments)


# ----------------------------------------------------------------- user errors (exit 2)
@pytest.mark.parametrize(
    ("args", "fragments"),
    [
        # an unwritable --out fails before the (slow) work, not after it
        (("solve", "head-on", "--out", "a_file"), ("a_file",)),
        (("ablation", "--out", "a_file"), ("a_file",)),
        (("crossval", "head-on", "--out", "a_file"), ("a_file",)),
        (("convergence", "head-on", "--methods", "dt", "--out", "a_file"), ("a_file",)),
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
        (("gradcheck", "head-on", "--iters", "x"), ("--iters", "'x'")),
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
    _one_error(_run_here(work, *args), *fragments)


@pytest.mark.parametrize(
    "args",
    [
        ("solve", "head-on", "--lr", "nan"),
        ("evaluate",),
        ("reference", "head-on", "--sequence", "nosuch"),
        ("validate", "head-on", "short.npy"),
    ],
)
def test_in_process_errors_are_the_subprocess_errors(work: Path, args: tuple[str, ...]) -> None:
    here, there = _run_here(work, *args), _run(work, *args)
    assert (here.returncode, here.stdout, here.stderr) == (
        there.returncode,
        there.stdout,
        there.stderr,
    )


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
    from hybridoc.workflows.validation import convergence

    for steps in [(), (1.5,), (0,)]:
        with pytest.raises(SceneError, match="steps"):
            convergence("head-on", steps=steps, include_gd=False)


# ----------------------------------------------------------------- issue #17: no tracebacks
def _scene_text(**changes: str) -> str:
    """single-collision's scene with some lines replaced (key -> new right-hand side)."""
    text = hybridoc.load_scene("single-collision").to_toml()
    for old, new in changes.items():
        text = text.replace(old, new)
    return text


@pytest.fixture(scope="module")
def hostile(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("hostile")
    (d / "umlaut.toml").write_text(_scene_text(ball1="b\u00e4ll1"), encoding="utf-8")
    (d / "huge_steps.toml").write_text(_scene_text(**{"steps = 480": "steps = 1e20"}))
    (d / "huge_int_steps.toml").write_text(
        _scene_text(**{"steps = 480": "steps = 100000000000000000000"})
    )
    (d / "exits_on_import.py").write_text("import sys\nsys.exit(0)\n")
    (d / "exits_in_problem.py").write_text("import sys\n\n\ndef problem():\n    sys.exit(0)\n")
    (d / "exits_in_policy.py").write_text("import sys\n\n\ndef pol(t, s):\n    sys.exit(4)\n")
    return d


@pytest.mark.parametrize(
    ("args", "fragments"),
    [
        # a non-ASCII disc name became a CasADi function name: RuntimeError traceback, exit 1
        *[
            ((command, "umlaut.toml", *extra), ("disc name", "'b\u00e4ll1'", "ASCII"))
            for command, *extra in (
                ("evaluate",),
                ("show",),
                ("gradient",),
                ("crossval",),
                ("convergence", "--methods", "dt"),
            )
        ],
        # unbounded sizes: tracebacks (OverflowError, ValueError, CasADi) or a silent hang
        (("show", "huge_int_steps.toml"), ("steps must be at most 1000000",)),
        (("show", "huge_steps.toml"), ("steps must be a positive integer",)),
        (("solve", "head-on", "--method", "dt", "--degree", "99"), ("degree", "1 to 9")),
        (("solve", "head-on", "--method", "dt", "--mesh", "10000000"), ("mesh", "1000")),
        (
            ("convergence", "head-on", "--steps", "99999999999999999999"),
            ("--steps", "at most 1000000"),
        ),
        (("reference", "head-on", "--search", "1000000"), ("search must be at most 8",)),
        (("solve", "head-on", "--method", "reference", "--search", "9"), ("at most 8",)),
        # sys.exit in a user's file ended hybridoc with exit 0 and no answer
        (("evaluate", "exits_on_import.py:problem"), ("exits_on_import.py", "sys.exit(0)")),
        (("evaluate", "exits_in_problem.py"), ("exits_in_problem.py:problem", "sys.exit(0)")),
        (
            ("evaluate", "head-on", "--policy", "exits_in_policy.py:pol"),
            ("exits_in_policy.py:pol", "sys.exit(4)"),
        ),
    ],
)
def test_hostile_input_is_one_error_line(hostile: Path, args: tuple[str, ...], fragments) -> None:
    _one_error(_run(hostile, *args), *fragments)


def test_show_plot_names_the_file_written(hostile: Path) -> None:
    # "wrote plotout" while matplotlib wrote plotout.png
    proc = _run(hostile, "show", "head-on", "--plot", "plotout")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines()[-1] == "wrote plotout.png"
    assert (hostile / "plotout.png").read_bytes()[:4] == b"\x89PNG"
    assert not (hostile / "plotout").exists()
    _one_error(_run(hostile, "show", "head-on", "--plot", "plot.nope"), "'.nope'", ".png")


def test_internal_error_exit_3(monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    from hybridoc import cli
    from hybridoc.cli import evaluate as evaluate_cli

    def broken(args):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(evaluate_cli, "cmd_evaluate", broken)
    monkeypatch.delenv("HYBRIDOC_DEBUG", raising=False)
    assert cli.main(["evaluate", "head-on"]) == 3
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert captured.out == "" and len(lines) == 2, captured.err
    assert lines[0] == "hybridoc: internal error: ZeroDivisionError: a bug"
    assert "please report" in lines[1] and "HYBRIDOC_DEBUG=1" in lines[1]
    monkeypatch.setenv("HYBRIDOC_DEBUG", "1")
    assert cli.main(["evaluate", "head-on"]) == 3
    err = capsys.readouterr().err
    assert "Traceback" in err and "raise ZeroDivisionError" in err
    assert err.splitlines()[-2] == "hybridoc: internal error: ZeroDivisionError: a bug"


def test_interrupt_and_stray_system_exit(monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    from hybridoc import cli
    from hybridoc.cli import evaluate as evaluate_cli

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(evaluate_cli, "cmd_evaluate", interrupted)
    assert cli.main(["evaluate", "head-on"]) == 130
    assert capsys.readouterr().err == "hybridoc: interrupted\n"

    def exits(args):
        raise SystemExit(0)  # user code that no loader wrapped

    monkeypatch.setattr(evaluate_cli, "cmd_evaluate", exits)
    assert cli.main(["evaluate", "head-on"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("hybridoc: error: ") and "sys.exit(0)" in err


def test_repeated_warnings_print_once_with_a_count(monkeypatch, capsys) -> None:
    import warnings

    from hybridoc import cli
    from hybridoc.cli import evaluate as evaluate_cli

    def noisy(args):
        for _ in range(1440):
            warnings.warn("invalid value encountered in matmul", RuntimeWarning, stacklevel=1)
        warnings.warn("another one", UserWarning, stacklevel=1)
        return 0

    monkeypatch.setattr(evaluate_cli, "cmd_evaluate", noisy)
    assert cli.main(["evaluate", "head-on"]) == 0
    assert capsys.readouterr().err.splitlines() == [
        "hybridoc: warning: invalid value encountered in matmul (repeated 1440 times)",
        "hybridoc: warning: another one",
    ]


def test_huge_values_warn_once(hostile: Path) -> None:
    # a disc at x = -2e300: the answer (it reaches nothing) is right, but numpy's warning
    # was printed 1440 times
    path = hostile / "far.toml"
    path.write_text(_scene_text(**{"position = [-1.0, -2.0]": "position = [-2e300, -2.0]"}))
    proc = _run(hostile, "evaluate", "far.toml", "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["cost"] == pytest.approx(2.09)
    lines = proc.stderr.splitlines()
    assert len(lines) == len(set(lines)) <= 3, proc.stderr


def test_non_finite_gradient_is_an_error(monkeypatch, capsys) -> None:
    # NaN entries were printed as '-' (and inf as a norm) with exit 0
    from types import SimpleNamespace

    import hybridoc.evaluator
    from hybridoc import cli

    real = hybridoc.evaluator.gradient

    def overflowing(ocp, controls):
        g = real(ocp, controls)
        du = np.array(g.d_controls, dtype=float)
        du[3, 1] = np.nan
        return SimpleNamespace(
            cost=g.cost, evaluation=g.evaluation, d_controls=du, d_initial_state=g.d_initial_state
        )

    monkeypatch.setattr(hybridoc.evaluator, "gradient", overflowing)
    for extra in ([], ["--json"]):
        assert cli.main(["gradient", "head-on", *extra]) == 2
        captured = capsys.readouterr()
        assert captured.out == ""
        assert captured.err.startswith("hybridoc: error: the gradient is not finite")
        assert "dJ/du" in captured.err and "dJ/ds0" not in captured.err


def test_gradient_norms_do_not_overflow(capsys) -> None:
    from hybridoc.cli.evaluate import _norm

    x = np.array([[3e300, 4e300], [0.0, 0.0]])
    assert _norm(x) == pytest.approx(5e300) and _norm(np.zeros(3)) == 0.0
