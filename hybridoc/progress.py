"""One progress protocol for every long run: gd, the reference's search, dt, crossval,
datasets and training.

A long computation takes a ``progress`` argument: ``False``/``None`` (silent, the library's
default), ``True`` (a :class:`ProgressMeter` on stderr, what the CLI passes) or any object
with the methods of :class:`Progress` (a caller's own display, a logger, a test recorder).
:func:`as_progress` turns the argument into a :class:`Progress`.

A run reports three kinds of things:

``stage(text)``
    It enters a named stage ("transcription", "search of 2-event sequences").
``detail(text)``
    The current stage's latest detail (IPOPT's iteration, the best cost so far).
``count(done, total, text)``
    Countable work: iterations, samples, candidate sequences. ``total`` is the real total,
    or ``None`` when the work stops at a test rather than a count (an optimiser's
    iterations up to convergence): an iteration limit is no total, and a bar drawn to it
    would run short of it or restart with every stage.

:class:`ProgressMeter` is the one implementation. On a terminal it draws a bar that is
redrawn in place (at most :data:`REDRAW_S` apart) and stage lines; when stderr is a log or a
pipe it writes plain lines (no carriage returns) every :data:`EVERY_LOG_S` seconds. It says
nothing for the first :data:`QUIET_S` seconds (:data:`QUIET_LOG_S` in a log), so that quick
runs leave stderr to warnings and errors. A background thread repeats the current stage with
its detail every :data:`EVERY_S` seconds, since a stage is often one long call into CasADi
or IPOPT.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import IO, Any, Protocol, runtime_checkable

__all__ = [
    "EVERY_LOG_S",
    "EVERY_S",
    "QUIET_LOG_S",
    "QUIET_S",
    "REDRAW_S",
    "NullProgress",
    "Progress",
    "ProgressLike",
    "ProgressMeter",
    "as_progress",
    "progress_scope",
]

QUIET_S = 1.0
"""Seconds a run stays silent on a terminal before its first line."""
EVERY_S = 10.0
"""Seconds between the lines of one long stage (terminal)."""
REDRAW_S = 0.1
"""Seconds between redraws of a bar on a terminal."""
QUIET_LOG_S = 60.0
"""Seconds a run stays silent before its first line (stderr not a terminal)."""
EVERY_LOG_S = 30.0
"""Seconds between lines (stderr not a terminal)."""


@runtime_checkable
class Progress(Protocol):
    """What a long run calls to report progress (any object with these methods)."""

    def stage(self, text: str) -> None:
        """Enter a named stage."""

    def detail(self, text: str) -> None:
        """The current stage's latest detail."""

    def count(self, done: int, total: int | None, text: str = "") -> None:
        """``done`` of ``total`` units of countable work (``total`` ``None``: not known in
        advance); ``text`` is a short status."""

    def close(self) -> None:
        """The run is over (idempotent)."""


ProgressLike = Progress | bool | None
"""What a ``progress`` argument accepts (:func:`as_progress`)."""


class NullProgress:
    """A :class:`Progress` that records and prints nothing."""

    def stage(self, text: str) -> None:
        pass

    def detail(self, text: str) -> None:
        pass

    def count(self, done: int, total: int | None, text: str = "") -> None:
        pass

    def close(self) -> None:
        pass

    def __enter__(self) -> NullProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        pass


class ProgressMeter:
    """Progress on a stream (stderr by default): a bar on a terminal, plain lines otherwise.

    Parameters
    ----------
    label
        The line prefix (``"gd"``, ``"reference"``, ``"dataset"``).
    stream
        Where to write; default ``sys.stderr`` at the time of each write.
    tty
        Draw in place (``True``) or write plain lines (``False``); default: whether the stream
        is a terminal.

    Use it as a context manager (or call :meth:`close`): that ends a bar's line and stops the
    thread that repeats long stages.
    """

    def __init__(self, label: str, *, stream: IO[str] | None = None, tty: bool | None = None):
        self.label = label
        self._stream = stream
        self.t0 = time.perf_counter()
        self.tty = _isatty(stream) if tty is None else bool(tty)
        # read at run time, so that tests (and callers) may change the module's values
        self.quiet = QUIET_S if self.tty else QUIET_LOG_S
        self.every = EVERY_S if self.tty else EVERY_LOG_S
        self._stage = ""
        self._detail = ""
        self._shown = ""  # the stage of the last stage line
        self._last = -math.inf  # when any line was last written
        self._count: tuple[int, int | None, str] | None = None
        self._count_t0: tuple[float, int] | None = None  # (time, done) of the first count
        self._open_bar = False  # a bar is drawn and its line not yet ended
        self._drawn = 0  # the length of the bar's last draw
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False

    def __enter__(self) -> ProgressMeter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ the protocol
    def elapsed(self) -> float:
        """Seconds since the meter was made."""
        return time.perf_counter() - self.t0

    def stage(self, text: str) -> None:
        with self._lock:
            self._stage, self._detail = text, ""
            self._count = self._count_t0 = None  # a stage counts afresh (its rate too)
            self._emit_stage(heartbeat=False)
        if self._thread is None and not self._closed:
            self._thread = threading.Thread(
                target=self._beat, name="hybridoc-progress", daemon=True
            )
            self._thread.start()

    def detail(self, text: str) -> None:
        with self._lock:
            self._detail = text

    def count(self, done: int, total: int | None, text: str = "") -> None:
        now = self.elapsed()
        with self._lock:
            if self._count_t0 is None or (self._count is not None and done < self._count[0]):
                self._count_t0 = (now, done)  # the first count, or counting started again
            self._count = (done, total, text)
            if now < self.quiet:
                return
            final = total is not None and done >= total
            wait = REDRAW_S if self.tty else self.every
            if not final and now - self._last < wait:
                return
            line = self._bar_line(now)
            if self.tty:
                # pad over the end of a longer previous draw (a rate that got shorter)
                pad = " " * (self._drawn - len(line)) if self._open_bar else ""
                self._write("\r" + line + pad + ("\n" if final else ""))
                self._drawn = len(line)
                self._open_bar = not final
            else:
                self._write(line + "\n")
            self._last = now

    def close(self) -> None:
        self._closed = True
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        self._thread = None
        with self._lock:
            self._end_bar()

    # ------------------------------------------------------------------ drawing
    def _bar_line(self, now: float) -> str:
        assert self._count is not None
        done, total, text = self._count
        stage = f" {self._stage}" if self._stage else ""
        tail = f" {text}" if text else ""
        if total is None:  # no bar and no time left: the rate is all that is known
            rate = ""
            if self._count_t0 is not None and now > self._count_t0[0]:
                per_s = (done - self._count_t0[1]) / (now - self._count_t0[0])
                rate = f" ({per_s:.3g}/s)" if per_s > 0 else ""
            where = f"{stage}:" if stage else ""
            return f"{self.label}:{where} {done}{tail}{rate} [{now:.0f} s]"
        width = 24
        fill = int(width * min(done, total) / max(total, 1))
        bar = "#" * fill + "." * (width - fill)
        rate = ""
        if self._count_t0 is not None and now > self._count_t0[0]:
            per_s = (done - self._count_t0[1]) / (now - self._count_t0[0])
            if per_s > 0 and done < total:
                rate = f", {(total - done) / per_s:.0f} s left"
        return f"{self.label}:{stage} [{bar}] {done}/{total}{tail}{rate} [{now:.0f} s]"

    def _end_bar(self) -> None:
        if self._open_bar:
            self._write("\n")
            self._open_bar = False

    def _emit_stage(self, heartbeat: bool) -> None:
        now = self.elapsed()
        if now < self.quiet or not self._stage:
            return
        new = self._stage != self._shown
        if not new and (not heartbeat or now - self._last < self.every):
            return
        if heartbeat and self._count is not None and self.tty:
            return  # a live bar shows the stage already
        text = self._stage + (f"; {self._detail}" if self._detail and not new else "")
        self._end_bar()
        self._write(f"{self.label}: {text} [{now:.0f} s]\n")
        self._shown, self._last = self._stage, now

    def _beat(self) -> None:
        while not self._stop.wait(0.25):
            with self._lock:
                self._emit_stage(heartbeat=True)

    def _write(self, text: str) -> None:
        stream = self._stream if self._stream is not None else sys.stderr
        try:
            stream.write(text)
            stream.flush()
        except (OSError, ValueError):  # a closed or broken stream must not end the run
            pass


def as_progress(progress: Any, label: str) -> Progress:
    """The :class:`Progress` for a ``progress`` argument.

    Parameters
    ----------
    progress
        ``None`` or ``False``: :class:`NullProgress`; ``True``: a new :class:`ProgressMeter`
        labelled ``label``; a :class:`Progress`: itself.
    label
        The label of a new meter.

    Raises
    ------
    TypeError
        For anything else.
    """
    if progress is None or progress is False:
        return NullProgress()
    if progress is True:
        return ProgressMeter(label)
    if isinstance(progress, Progress):
        return progress
    raise TypeError(
        f"progress must be True, False, None or an object with stage/detail/count/close "
        f"methods, got {type(progress).__name__}"
    )


def _isatty(stream: Any = None) -> bool:
    try:
        return bool((stream if stream is not None else sys.stderr).isatty())
    except (AttributeError, ValueError):  # replaced or closed
        return False


@contextmanager
def progress_scope(progress: Any, label: str) -> Iterator[Progress]:
    """``with progress_scope(progress, "gd") as p:``: :func:`as_progress`, closed at the end
    when it was made here (a caller's own :class:`Progress` stays open for its next stage)."""
    meter = as_progress(progress, label)
    try:
        yield meter
    finally:
        if meter is not progress:
            meter.close()
