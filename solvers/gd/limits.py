"""The limits of one gd run: its time limit and interrupts (:class:`Watch`, the best iterate
so far) and a loss that became non-finite (:class:`NonFinite`)."""

from __future__ import annotations

import contextvars
import math
import time

import numpy as np


class NonFinite(Exception):
    """The loss or its gradient became NaN or infinite."""


class OutOfTime(Exception):
    """The run passed its ``time_limit``."""


class Watch:
    """The time limit of one :func:`solve_gd` run and its best iterate so far, which a stop
    at the limit or by an interrupt returns."""

    def __init__(self, time_limit: float | None) -> None:
        self.t0 = time.perf_counter()
        self.time_limit = time_limit
        self.deadline = None if time_limit is None else self.t0 + time_limit
        self.loss = math.inf
        self.u: np.ndarray | None = None
        self.horizon: float | None = None
        self.evaluations = 0
        self.iterations = 0  # of the optimisers that report them (not the batched ones)
        self.history: list[float] = []
        self.interrupted = False  # set by SIGINT (solvers.threads.flag_interrupts)

    def check(self) -> None:
        """Raise :class:`OutOfTime` past the deadline, ``KeyboardInterrupt`` after a SIGINT
        (also one that CasADi swallowed)."""
        if self.interrupted:
            raise KeyboardInterrupt
        if self.deadline is not None and time.perf_counter() > self.deadline:
            raise OutOfTime

    def offer(self, loss: float, u: np.ndarray, horizon: float | None = None, *,
              latest: bool = False) -> None:  # fmt: skip
        """An iterate of the problem's grid and its loss (without smoothing penalties):
        kept when it is the lowest so far, or always (``latest``: the augmented
        Lagrangian's, whose lower values may be infeasible)."""
        self.evaluations += 1
        if math.isfinite(loss) and (latest or loss < self.loss):
            self.loss, self.u, self.horizon = float(loss), np.array(u, dtype=float), horizon
            self.history.append(float(loss))


WATCH: contextvars.ContextVar[Watch | None] = contextvars.ContextVar("gd_watch", default=None)


def current_watch() -> Watch | None:
    """The :class:`Watch` of the run in progress (``None`` outside :func:`solve_gd`)."""
    return WATCH.get()
