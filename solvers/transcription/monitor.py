"""The run in progress: its progress reports, its time limit and interrupts, reached from
IPOPT's iteration callback.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from contextvars import ContextVar
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np

from hybridoc.errors import HybridocError
from hybridoc.progress import NullProgress, Progress
from hybridoc.solvers.transcription.options import MAX_ITER
from hybridoc.solvers.transcription.result import sequence_matches

if TYPE_CHECKING:
    from hybridoc.solvers.transcription.judging import Judged

__all__ = ["IterationCallback", "MONITOR", "Monitor", "Stopped", "short_sequence"]


class Stopped(HybridocError):
    """A :func:`solve_dt` run stopped by its time limit (what :func:`solve_dt` raises when no
    candidate was judged yet; otherwise it returns the best one as ``not-converged``)."""


class Monitor:
    """Progress, the time limit and the candidates judged so far of one :func:`solve_dt`
    run (what a stopped or interrupted run returns)."""

    def __init__(self, progress: Progress, time_limit: float | None) -> None:
        self.progress = progress
        self.reporting = not isinstance(progress, NullProgress)
        self.time_limit = time_limit
        self.deadline = None if time_limit is None else time.perf_counter() + time_limit
        self.interrupted = False  # SIGINT arrived in IPOPT's iteration callback
        self.judged: list[Judged] = []
        self.tried: list[dict[str, Any]] = []
        self.perturbation = 0.0

    def expired(self) -> bool:
        return self.deadline is not None and time.perf_counter() > self.deadline

    def best(self) -> Judged | None:
        """The best candidate judged so far: the cheapest feasible one that reproduces its
        events, else the cheapest that reproduces them, else the cheapest re-simulated."""
        ranked = [j for j in self.judged if j.ev is not None]
        if not ranked:
            return None

        def rank(j: Judged) -> tuple[int, float]:
            assert j.ev is not None
            ok = sequence_matches(j.result._nlp.ocp, j.result, j.ev)
            return (0 if ok and j.feasible else 1 if ok else 2, float(j.ev.cost))

        return min(ranked, key=rank)

    def stop(self, where: str) -> HybridocError:
        """The error of a run stopped by its time limit ``where``."""
        return Stopped(
            f"dt: stopped at the time limit of {self.time_limit:g} s {where}; raise "
            "--time-limit, or make the NLP smaller and easier: a smaller --mesh, fewer events "
            "(--sequence, another --controls), fewer bodies, or --method gd"
        )


# the solve_dt run in progress: its IPOPT solves report to it, however deep they are called
MONITOR: ContextVar[Monitor | None] = ContextVar("hybridoc_dt_monitor", default=None)


class IterationCallback(ca.Callback):
    """IPOPT's iteration callback: reports the iteration to the run's :class:`Monitor` and
    asks IPOPT to stop (``User_Requested_Stop``) once its time limit has passed."""

    def __init__(
        self, n_w: int, n_g: int, lbg: np.ndarray, ubg: np.ndarray, cost_scale: float = 1.0
    ) -> None:
        ca.Callback.__init__(self)
        self.n_w, self.n_g, self.lbg, self.ubg = n_w, n_g, lbg, ubg
        self.cost_scale = cost_scale
        self.monitor: Monitor | None = None
        self.iteration = 0
        self.construct("dt_iteration", {})

    def get_n_in(self) -> int:
        return ca.nlpsol_n_out()

    def get_n_out(self) -> int:
        return 1

    def get_name_in(self, i: int) -> str:
        return ca.nlpsol_out(i)

    def get_name_out(self, i: int) -> str:
        return "stop"

    def get_sparsity_in(self, i: int) -> Any:
        name = ca.nlpsol_out(i)
        if name == "f":
            return ca.Sparsity.scalar()
        if name in ("x", "lam_x"):
            return ca.Sparsity.dense(self.n_w)
        if name in ("g", "lam_g"):
            return ca.Sparsity.dense(self.n_g)
        return ca.Sparsity(0, 0)

    def eval(self, arg: list[Any]) -> list[int]:
        try:
            return self._eval(arg)
        except KeyboardInterrupt:
            # SIGINT during IPOPT surfaces here, the first Python code it runs: ask IPOPT
            # to stop, and let the run return what it has judged (solve_dt)
            if self.monitor is None:
                raise
            self.monitor.interrupted = True
            return [1]

    def _eval(self, arg: list[Any]) -> list[int]:
        self.iteration += 1
        mon = self.monitor
        if mon is None:
            return [0]
        if mon.reporting:
            g = np.asarray(arg[ca.nlpsol_out().index("g")], dtype=float).ravel()
            viol = float(np.max(np.maximum(self.lbg - g, g - self.ubg), initial=0.0))
            f = float(arg[ca.nlpsol_out().index("f")]) * self.cost_scale
            mon.progress.detail(
                f"IPOPT iteration {self.iteration} of at most {MAX_ITER}, objective {f:.6g}, "
                f"constraint violation {viol:.1e}"
            )
        return [1 if mon.expired() else 0]


def short_sequence(sequence: Sequence[str], most: int = 6) -> str:
    """A sequence for a message: the first few guards and how many more."""
    seq = list(sequence)
    if len(seq) <= most:
        return str(seq)
    return str(seq[:most])[:-1] + f", ... {len(seq) - most} more]"
