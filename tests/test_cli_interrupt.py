"""``hybridoc solve`` interrupted by SIGINT (issue #29): it printed "interrupted", wrote
nothing and lost the iterate it had. Now gd returns its best iterate as not-converged
("interrupted"), and the command prints it, writes every output it would have written and
exits with 2."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent

PROBLEM = """
import pathlib, sys
sys.path.insert(0, {tests!r})
from kink_problems import thermostat

def problem():
    pathlib.Path({marker!r}).write_text("loaded")
    return thermostat(steps=400)
"""


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_sigint_writes_the_best_iterate(tmp_path):
    marker = tmp_path / "loaded"
    src = tmp_path / "thermo.py"
    src.write_text(PROBLEM.format(tests=str(TESTS), marker=str(marker)))
    out = tmp_path / "out"
    env = dict(os.environ, HYBRIDOC_CODEGEN="0", OPENBLAS_NUM_THREADS="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "hybridoc", "solve", f"{src}:problem", "--method", "gd",
         "--optimizer", "adam", "--iters", "10000000", "--out", str(out), "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while not marker.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert marker.exists(), proc.stderr.read() if proc.poll() is not None else "slow"
        time.sleep(1.5)  # into the descent
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 2, stderr
    res = json.loads(stdout)
    assert res["status"] == "not-converged"
    assert res["info"]["stopped"] == "interrupted"
    assert res["message"].startswith("interrupted after")
    assert stderr.strip().splitlines()[-1].startswith("hybridoc: error: not-converged: interrupted")
    files = sorted(str(p) for p in out.iterdir() if not p.name.startswith("."))
    names = [Path(f).name for f in files]
    for tail in (".json", ".npz", "_controls.png", "_trajectory.png", "_learning_curve.png"):
        assert any(n.endswith(tail) for n in names), (tail, names)
    assert sorted(res["files"]) == files
    saved = json.loads(next(out.glob("*.json")).read_text())
    assert saved["status"] == "not-converged" and saved["cost"] == res["cost"]
