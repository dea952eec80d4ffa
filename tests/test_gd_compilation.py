"""``hybridoc solve`` keeps the C compilation it started (issue #18, the whole gd solve).

The loss of gd is compiled to C in a background thread once it is hot; a process that ended
before the compilation lost it (no library written), so that every later run started on
CasADi's virtual machine again, fifty times slower per call: the "warm" whole solve of
single-collision measured 3.7 s where the warm process takes about 1 s. ``hybridoc solve``
now waits for the compilations in flight after printing its result.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import casadi as ca
import pytest

from hybridoc import cli, compiled
from hybridoc.cli import solve as cli_solve


def _small_function() -> ca.Function:
    x = ca.SX.sym("x", 2)
    return ca.Function("wait_probe", [x], [ca.sin(x) * ca.sum1(x)])


def test_wait_for_compilations_lets_a_background_build_finish(compiling: None) -> None:
    acc = compiled.Accelerated(_small_function(), hot=0)  # builds in the background now
    assert compiled.wait_for_compilations(120.0)
    assert acc.compiled, acc.error
    # a later object of the same function (a later run) loads the library at once
    again = compiled.Accelerated(_small_function())
    assert again.compiled and again.native is not None
    assert compiled.wait_for_compilations(0.0)  # nothing in flight: no wait


def test_solve_waits_for_compilations_after_its_output(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    calls: list[tuple[float | None, str, str]] = []

    def wait(timeout: float | None = None) -> bool:
        printed = capsys.readouterr()  # what was printed before it
        calls.append((timeout, printed.out, printed.err))
        return len(calls) > 1  # one compilation in flight, finished by the second call

    monkeypatch.setattr(compiled, "wait_for_compilations", wait)
    code = cli.main(["solve", "head-on", "--method", "gd", "--iters", "2", "--json"])
    assert code in (0, 2)  # two iterations may not converge: either way it waits
    assert [t for t, _, _ in calls] == [0.0, cli_solve.COMPILATION_WAIT_S]
    assert json.loads(calls[0][1])["method"] == "gd"  # the result came first
    assert "finishing the C compilation" in calls[1][2]  # and says why it lingers
    if code == 2:  # the reason for the exit code stays the last line, after the wait
        last = capsys.readouterr().err.splitlines()[-1]
        assert last.startswith("hybridoc: error: not-converged"), last


@pytest.mark.slow
def test_a_cold_solve_leaves_its_loss_compiled(tmp_path: Path) -> None:
    # a whole process from an empty cache: the next run must find the loss's library
    # (before, a solve shorter than the compilation left none: about 4 s of CPU at load 7)
    from hybridoc.compiled import compiler

    if compiler() is None:
        pytest.skip("no C compiler on this machine")
    cache = tmp_path / "cache"
    env = dict(os.environ, HYBRIDOC_CACHE=str(cache), HYBRIDOC_CODEGEN="1")
    cmd = [sys.executable, "-m", "hybridoc", "solve", "damped-walls", "--method", "gd"]
    res = subprocess.run(
        [*cmd, "--iters", "15", "--json"], env=env, cwd=tmp_path, capture_output=True, text=True
    )
    assert res.returncode in (0, 2), res.stderr
    assert list(cache.glob("loss_grad_*.so")), res.stderr
