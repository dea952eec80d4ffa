"""Stage lines on stderr for the long runs of ``hybridoc reference`` and ``solve --method dt``.

A run says nothing for its first :data:`QUIET_S` seconds on a terminal, so that quick solves
stay silent (their stderr carries only warnings and errors). After that it prints the stage
it is in and every new stage as it starts, and while one stage lasts, a line every
:data:`EVERY_S` seconds with the time so far and the stage's latest detail (IPOPT's
iteration, say). When stderr is not a terminal (a log, a pipe, a script that reads the one
error line) it waits :data:`QUIET_LOG_S` and writes every :data:`EVERY_LOG_S` seconds. A
background thread prints the lines: a stage is often one long call into CasADi or IPOPT.
Lines are plain (no carriage returns).
"""

from __future__ import annotations

import sys
import threading
import time

__all__ = ["EVERY_LOG_S", "EVERY_S", "QUIET_LOG_S", "QUIET_S", "Stages"]

QUIET_S = 3.0
"""Seconds a run stays silent before its first stage line (stderr a terminal)."""
EVERY_S = 10.0
"""Seconds between the lines of one long stage (stderr a terminal)."""
QUIET_LOG_S = 60.0
"""Seconds a run stays silent before its first stage line (stderr not a terminal)."""
EVERY_LOG_S = 30.0
"""Seconds between the lines of one long stage (stderr not a terminal)."""


class Stages:
    """The stage a run is in, printed to stderr once the run has lasted :data:`QUIET_S`.

    Parameters
    ----------
    label
        The line prefix (``"reference"``, ``"dt"``).
    enabled
        ``False``: record nothing, print nothing, start no thread.

    Use it as a context manager (or call :meth:`close`) so that its thread stops.
    """

    def __init__(self, label: str, *, enabled: bool = True) -> None:
        self.label = label
        self.enabled = enabled
        self.t0 = time.perf_counter()
        # read at run time, so that tests (and callers) may change the module's values
        tty = enabled and _isatty()
        self.quiet = QUIET_S if tty else QUIET_LOG_S
        self.every = EVERY_S if tty else EVERY_LOG_S
        self._stage = ""
        self._detail = ""
        self._shown = ""  # the stage of the last line printed
        self._last = 0.0  # when it was printed
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if enabled:
            self._thread = threading.Thread(target=self._beat, name="hybridoc-stages", daemon=True)
            self._thread.start()

    def __enter__(self) -> Stages:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def elapsed(self) -> float:
        """Seconds since the run started."""
        return time.perf_counter() - self.t0

    def stage(self, text: str) -> None:
        """Enter a stage: printed now when the quiet time is over, else by the thread."""
        if not self.enabled:
            return
        with self._lock:
            self._stage, self._detail = text, ""
        self._emit(heartbeat=False)

    def detail(self, text: str) -> None:
        """The current stage's latest detail, shown by the next periodic line."""
        if self.enabled:
            with self._lock:
                self._detail = text

    def close(self) -> None:
        """Stop the thread (idempotent)."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        self._thread = None

    def _emit(self, heartbeat: bool) -> None:
        now = self.elapsed()
        if now < self.quiet:
            return
        with self._lock:
            if not self._stage:
                return
            new = self._stage != self._shown
            if not new and (not heartbeat or now - self._last < self.every):
                return
            text = self._stage + (f"; {self._detail}" if self._detail and not new else "")
            self._shown, self._last = self._stage, now
            print(f"{self.label}: {text} [{now:.0f} s]", file=sys.stderr, flush=True)

    def _beat(self) -> None:
        while not self._stop.wait(0.25):
            self._emit(heartbeat=True)


def _isatty() -> bool:
    try:
        return bool(sys.stderr.isatty())
    except (AttributeError, ValueError):  # replaced or closed
        return False
