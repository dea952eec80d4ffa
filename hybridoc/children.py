"""Child processes that never outlive the process that started them (issue #32).

hybridoc starts processes in three places: the C compiler of the code cache
(:mod:`hybridoc.compiled`), the dataset's process pool (:func:`hybridoc.workflows.datasets.
run_chunks`) and the reference's fork pools. A child whose parent is killed (SIGKILL, the
out-of-memory killer, a lost terminal) runs no ``atexit`` handler and gets no signal from
it: a pool worker then waits forever on the pool's pipe (its siblings hold the other end),
and a compiler's ``cc1`` compiles on for minutes.

The rules, in one place:

- A forked Python child calls :func:`die_with_parent` first (a pool's ``initializer``, or
  the first line of a ``Process`` target): on Linux the kernel sends it SIGKILL when its
  parent dies (``prctl(PR_SET_PDEATHSIG)``); elsewhere a daemon thread notices that it was
  re-parented. A parent that died before the request was made is noticed at once.
- :func:`forks_die_with_this_process` extends the rule to every child that a process forks
  from Python later on (a dataset worker's own reference pool: grandchildren).
- :func:`popen_group` runs a command (the C compiler) under a small supervisor, the leader
  of a process group of its own, that kills the whole group when this process dies: the
  command's own children (``cc1``, ``as``) go too.
- :func:`kill_pool` ends a process pool's workers at once, for a parent that stops early
  (an error, Ctrl-C) and would otherwise wait for the running tasks.

``PR_SET_PDEATHSIG`` is tied to the *thread* that forked the child: a child is killed when
that thread ends, so a pool must be started and used by one thread (as every pool here is).
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
import threading
import time
from typing import Any

__all__ = [
    "die_with_parent",
    "forks_die_with_this_process",
    "kill_pool",
    "pdeathsig",
    "popen_group",
    "watch_parent",
]

_PR_SET_PDEATHSIG = 1

# the pid of the process that last forked, as the child sees it: written in the parent just
# before each fork (so a child knows its parent even if that parent died at once)
_FORKED_FROM: int | None = None
_INHERIT = False  # whether this process's forks die with it (forks_die_with_this_process)


def _before_fork() -> None:
    global _FORKED_FROM
    _FORKED_FROM = os.getpid()


def _after_fork_in_child() -> None:
    if _INHERIT:
        die_with_parent()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(before=_before_fork, after_in_child=_after_fork_in_child)


def pdeathsig(sig: int = signal.SIGKILL) -> bool:
    """Ask Linux to send ``sig`` to this process when its parent (the thread that forked
    it) dies; whether it could (``False`` off Linux)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return int(libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0)) == 0
    except (OSError, AttributeError):
        return False


def watch_parent(parent: int, interval: float = 0.5) -> None:
    """Exit this process as soon as its parent is no longer ``parent`` (it died and this
    process was re-parented): a daemon thread, where :func:`pdeathsig` cannot."""

    def watch() -> None:
        while True:
            time.sleep(interval)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="hybridoc-watch-parent", daemon=True).start()


def die_with_parent(parent: int | None = None) -> None:
    """In a child process: end it when its parent dies.

    Parameters
    ----------
    parent
        The parent's pid; by default the process this one was forked from (recorded at the
        fork), else the current parent.

    Notes
    -----
    SIGKILL on the parent's death where Linux offers it, else a thread that watches the
    parent. A parent already gone when this runs (it died right after the fork) ends this
    process at once.
    """
    if parent is None:
        parent = _FORKED_FROM if _FORKED_FROM not in (None, os.getpid()) else os.getppid()
    if not pdeathsig():
        watch_parent(parent)
    if os.getppid() != parent:
        os._exit(1)


def forks_die_with_this_process() -> None:
    """Every child this process forks from Python from now on (``os.fork``,
    :mod:`multiprocessing`'s fork, a fork-based pool) calls :func:`die_with_parent` first,
    and passes the rule on to its own forks.

    For processes that hybridoc runs as a whole (a pool worker, the command line), not for
    a library caller's process, whose own children are its business.
    """
    global _INHERIT
    _INHERIT = True


def kill_pool(pool: Any) -> None:
    """Kill the worker processes of a :class:`concurrent.futures.ProcessPoolExecutor` at
    once (their tasks are lost) and shut it down without waiting for them."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    for p in procs:
        try:
            p.kill()
        except (OSError, AttributeError, ValueError):
            pass  # already gone
    try:
        pool.shutdown(wait=False, cancel_futures=True)
    except Exception:  # a broken pool may complain; its workers are dead either way
        pass
    for p in procs:
        try:
            p.join(timeout=5)
        except (OSError, AttributeError, ValueError, AssertionError):
            pass


# The supervisor of popen_group: run with ``python -S -I -c`` (no site, no user paths: a
# few tens of milliseconds), argv = [parent pid, command...]. It leads the process group
# Popen made for it; the kernel sends it SIGTERM when its parent dies, on which it kills the
# whole group, the command's own children included; elsewhere it polls for re-parenting.
_SUPERVISOR = r"""
import os, signal, sys, time

def stop(*_):
    os.killpg(0, signal.SIGKILL)

signal.signal(signal.SIGTERM, stop)
parent = int(sys.argv[1])
watched = False
if sys.platform.startswith("linux"):
    try:
        import ctypes
        watched = ctypes.CDLL(None).prctl(1, int(signal.SIGTERM), 0, 0, 0) == 0
    except (OSError, AttributeError):
        pass
if os.getppid() != parent:
    stop()
pid = os.fork()
if pid == 0:
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        os.execvp(sys.argv[2], sys.argv[2:])
    except OSError as exc:
        os.write(2, f"cannot run {sys.argv[2]!r}: {exc.strerror}\n".encode())
        os._exit(127)
while True:
    if watched:
        try:
            _, status = os.waitpid(pid, 0)
        except InterruptedError:
            continue
        break
    done, status = os.waitpid(pid, os.WNOHANG)
    if done:
        break
    if os.getppid() != parent:
        stop()
    time.sleep(0.05)
code = os.waitstatus_to_exitcode(status)
sys.exit(code if code >= 0 else 128 - code)
"""


def popen_group(cmd: list[str], **kwargs: Any) -> subprocess.Popen[Any]:
    """Start ``cmd`` in a process group of its own that dies with this process.

    Parameters
    ----------
    cmd
        The command and its arguments.
    **kwargs
        Passed to :class:`subprocess.Popen` (``start_new_session`` is set).

    Returns
    -------
    subprocess.Popen
        The group's leader, a supervisor that runs ``cmd`` and exits with its status (128
        plus the signal that ended it; 127 with a message on stderr when it cannot run).
        ``os.killpg(proc.pid, SIGKILL)`` ends the command with all its children; so does
        the death of the thread that called this (module notes).
    """
    argv = [sys.executable, "-S", "-I", "-c", _SUPERVISOR, str(os.getpid()), *cmd]
    return subprocess.Popen(argv, start_new_session=True, **kwargs)
