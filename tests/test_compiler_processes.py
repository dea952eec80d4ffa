"""The C compilers started by hybridoc.compiled never outlive their process or time limit.

``cc`` runs ``cc1`` and the assembler as children: killing ``cc`` alone (the former
``subprocess.run(..., timeout=)``), or exiting while a daemon thread waited for it, left them
running without a parent for minutes.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time

import pytest

from hybridoc import compiled


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def _wait_gone(pgid: int, seconds: float = 10.0) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if not _group_alive(pgid):
            return True
        time.sleep(0.05)
    return False


def test_a_compiler_past_its_time_limit_is_ended_with_its_children(monkeypatch) -> None:
    monkeypatch.setattr(compiled, "_COMPILE_TIMEOUT_S", 0.5)
    started = time.monotonic()
    # a "compiler" whose child would run on: the whole process group must go
    code, err = compiled._run_compiler(["sh", "-c", "sleep 30 & sleep 30; wait"])
    assert time.monotonic() - started < 10
    assert code != 0 and "longer than" in err
    assert not compiled._COMPILERS


def test_a_compiler_that_fails_reports_its_error() -> None:
    code, err = compiled._run_compiler(["sh", "-c", "echo broken >&2; exit 3"])
    assert (code, err.strip()) == (3, "broken")


@pytest.mark.skipif(compiled.compiler() is None, reason="no C compiler on this machine")
def test_a_process_that_exits_while_compiling_leaves_no_compiler(tmp_path) -> None:
    # a function big enough that cc1 runs for a while; the child prints the compiler's
    # process group as soon as it runs, then exits
    program = textwrap.dedent(
        """
        import sys, time
        import casadi as ca
        from hybridoc import compiled
        x = ca.SX.sym("x", 40)
        y = x
        for k in range(300):
            y = ca.sin(y * (1 + k * 1e-3)) + ca.cos(ca.sum1(y) * y)
        compiled.Accelerated(ca.Function("big", [x], [y]), hot=0)
        deadline = time.monotonic() + 120
        while not compiled._COMPILERS and time.monotonic() < deadline:
            time.sleep(0.01)
        print(next(iter(compiled._COMPILERS)).pid, flush=True)
        """
    )
    env = dict(os.environ, HYBRIDOC_CODEGEN="1", HYBRIDOC_CACHE=str(tmp_path / "cache"))
    out = subprocess.run(
        [sys.executable, "-c", program], capture_output=True, text=True, env=env, timeout=300
    )
    assert out.returncode == 0, out.stderr
    pgid = int(out.stdout.split()[-1])
    assert _wait_gone(pgid), f"compiler group {pgid} still running after its process exited"
    assert not list((tmp_path / "cache").glob("*.so"))  # the compilation was given up
