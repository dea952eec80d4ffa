"""Thread settings of the simulation back ends: one environment variable, sensible defaults.

``HYBRIDOC_THREADS``
    Unset (the default): CasADi's batched rollouts use every usable core, and torch runs its
    intra-op work on **one** thread. hybridoc's torch tensors are small (a batch of a few
    discs per step), so a second thread buys nothing, while on a loaded machine torch's
    default of one thread per core collapses: a batch of 64 rollouts of multiple-collision
    took 8.6 s with two threads against 0.24 s with one, on two busy cores
    (``benchmarks/bench_gd.py``). ``N >= 1``: both use ``N`` threads. ``0``: hybridoc leaves
    torch's own setting alone (for programs that set ``torch.set_num_threads`` themselves)
    and CasADi uses every usable core.

torch's setting is global to the process; hybridoc applies it once, when it first builds a
torch simulation or optimiser, and says so in :func:`torch_threads`'s return value.
"""

from __future__ import annotations

import os
import signal
import threading
from typing import Any

from hybridoc.cores import usable_cores
from hybridoc.errors import SceneError

__all__ = [
    "casadi_threads",
    "configured_threads",
    "flag_interrupts",
    "torch_threads",
    "usable_cores",
]

_APPLIED: int | None = None


def configured_threads() -> int | None:
    """``HYBRIDOC_THREADS`` as a number (``None`` when unset).

    Raises
    ------
    hybridoc.errors.SceneError
        When it is set to something other than an integer >= 0.
    """
    env = os.environ.get("HYBRIDOC_THREADS", "").strip()
    if not env:
        return None
    try:
        n = int(env)
    except ValueError:
        n = -1
    if n < 0:
        raise SceneError(f"HYBRIDOC_THREADS must be an integer >= 0, got {env!r}")
    return n


def casadi_threads() -> int:
    """Threads of CasADi's mapped (batched) functions."""
    n = configured_threads()
    return usable_cores() if not n else n


def torch_threads() -> int:
    """Apply the torch intra-op thread setting (module notes) once; return torch's count."""
    global _APPLIED
    import torch

    if _APPLIED is None:
        n = configured_threads()
        if n != 0:
            torch.set_num_threads(1 if n is None else n)
        _APPLIED = torch.get_num_threads()
    return torch.get_num_threads()


def flag_interrupts(target: Any) -> Any:
    """Make SIGINT set ``target.interrupted = True`` before the handler in place runs
    (Python's raises ``KeyboardInterrupt``), so that an interrupt that CasADi swallows inside
    one of its calls (IPOPT, a compiled function) is still seen by the solver's next check.
    Returns the handler to restore with ``signal.signal(signal.SIGINT, previous)``, or
    ``None`` outside the main thread (where signal handlers cannot be set)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    previous = signal.getsignal(signal.SIGINT)

    def handler(signum: int, frame: Any) -> None:
        target.interrupted = True
        if callable(previous):
            previous(signum, frame)
        else:
            raise KeyboardInterrupt

    try:
        signal.signal(signal.SIGINT, handler)
    except ValueError:  # pragma: no cover - not the main interpreter
        return None
    return previous
