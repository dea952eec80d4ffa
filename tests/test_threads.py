"""Thread settings: HYBRIDOC_THREADS for CasADi's batched rollouts and torch."""

from __future__ import annotations

import subprocess
import sys

import pytest

from hybridoc.errors import SceneError
from hybridoc.solvers import threads


def _torch_threads_after_simulator(env: dict[str, str], preset: int | None = None) -> int:
    code = (
        "import torch\n"
        + (f"torch.set_num_threads({preset})\n" if preset else "")
        + "from hybridoc.solvers.simulator import Simulator\n"
        "Simulator('head-on')\n"
        "print(torch.get_num_threads())\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True
    )
    return int(out.stdout.strip())


def test_torch_defaults_to_one_thread_and_obeys_the_setting(monkeypatch) -> None:
    import os

    base = {k: v for k, v in os.environ.items() if k != "HYBRIDOC_THREADS"}
    assert _torch_threads_after_simulator(base) == 1
    assert _torch_threads_after_simulator({**base, "HYBRIDOC_THREADS": "2"}) == 2
    # 0: the program's own setting is kept
    assert _torch_threads_after_simulator({**base, "HYBRIDOC_THREADS": "0"}, preset=3) == 3


def test_casadi_threads(monkeypatch) -> None:
    monkeypatch.delenv("HYBRIDOC_THREADS", raising=False)
    assert threads.casadi_threads() == threads.usable_cores()
    monkeypatch.setenv("HYBRIDOC_THREADS", "3")
    assert threads.casadi_threads() == 3
    monkeypatch.setenv("HYBRIDOC_THREADS", "0")
    assert threads.casadi_threads() == threads.usable_cores()


@pytest.mark.parametrize("bad", ["x", "-1", "1.5"])
def test_bad_setting_is_one_clear_error(monkeypatch, bad: str) -> None:
    monkeypatch.setenv("HYBRIDOC_THREADS", bad)
    with pytest.raises(SceneError, match="HYBRIDOC_THREADS must be an integer >= 0"):
        threads.configured_threads()
