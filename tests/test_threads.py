"""Thread settings: HYBRIDOC_THREADS for CasADi's batched rollouts and torch."""

from __future__ import annotations

import pytest

from hybridoc.errors import SceneError
from hybridoc.solvers import threads


def _torch_threads_after_simulator(
    monkeypatch: pytest.MonkeyPatch, setting: str | None, preset: int
) -> int:
    """torch's thread count once a Simulator is built, as in a fresh process whose program
    set ``preset`` threads: hybridoc's apply-once flag is cleared (torch's setting is global
    to the process, so it is also restored after the test by ``_restore_torch_threads``)."""
    import torch

    from hybridoc.solvers.simulator import Simulator

    if setting is None:
        monkeypatch.delenv("HYBRIDOC_THREADS", raising=False)
    else:
        monkeypatch.setenv("HYBRIDOC_THREADS", setting)
    monkeypatch.setattr(threads, "_APPLIED", None)
    torch.set_num_threads(preset)
    Simulator("head-on")
    return torch.get_num_threads()


@pytest.fixture
def _restore_torch_threads():
    import torch

    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


@pytest.mark.usefixtures("_restore_torch_threads")
def test_torch_defaults_to_one_thread_and_obeys_the_setting(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # in process rather than three fresh interpreters (each paid `import torch`, 5-20 s under
    # load); a preset of 3 threads makes every expected count a change or a kept setting
    assert _torch_threads_after_simulator(monkeypatch, None, preset=3) == 1
    assert _torch_threads_after_simulator(monkeypatch, "2", preset=3) == 2
    # 0: the program's own setting is kept
    assert _torch_threads_after_simulator(monkeypatch, "0", preset=3) == 3
    # applied once: a later setting does not change it
    monkeypatch.setenv("HYBRIDOC_THREADS", "2")
    assert threads.torch_threads() == 3


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
