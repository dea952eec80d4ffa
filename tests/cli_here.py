"""``hybridoc ARGS`` run in the test's own process: the command line's entry point
(:func:`hybridoc.cli.main`) with stdout and stderr captured, answered as a
:class:`subprocess.CompletedProcess`, so that a test written against a subprocess reads the
same. A subprocess of the command line costs its start-up and imports (torch, matplotlib,
CasADi: seconds on a busy machine) for nothing where the process itself is not what is
tested; ``tests/test_cli_errors.py`` checks that in-process and subprocess answers are the
same, byte for byte.

Output is captured at the file descriptors too, as a subprocess's pipes would see it: what
compiled code (IPOPT, CasADi, CVODES) writes to descriptors 1 and 2 is part of the answer,
so that "one line on stderr" and "one JSON object on stdout" keep meaning the whole output.
"""

from __future__ import annotations

import contextlib
import ctypes
import io
import os
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _flush_c_streams() -> None:
    # C's stdio buffers what compiled code printed; flush it into the descriptor it was
    # written for before that descriptor is switched
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None).fflush(None)


@contextlib.contextmanager
def _descriptors() -> Iterator[list[str]]:
    """Descriptors 1 and 2 into temporary files for the block; their text after it."""
    texts: list[str] = []
    sys.stdout.flush()
    sys.stderr.flush()
    with tempfile.TemporaryFile() as fo, tempfile.TemporaryFile() as fe:
        saved = [os.dup(1), os.dup(2)]
        try:
            os.dup2(fo.fileno(), 1)
            os.dup2(fe.fileno(), 2)
            yield texts
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            _flush_c_streams()
            for fd, old in zip((1, 2), saved, strict=True):
                os.dup2(old, fd)
                os.close(old)
        for f in (fo, fe):
            f.seek(0)
            texts.append(f.read().decode("utf-8", errors="replace"))


def run_here(*args: str, cwd: str | Path | None = None) -> subprocess.CompletedProcess[str]:
    """What ``hybridoc ARGS`` (``sys.exit(main(ARGS))``) does, in this process.

    Parameters
    ----------
    *args
        The command line after ``hybridoc``.
    cwd
        The working directory of the command (restored afterwards); the current one when
        ``None``.

    Returns
    -------
    subprocess.CompletedProcess
        The exit code (argparse's usage errors included) and the captured stdout and stderr:
        what Python wrote, followed by what was written to the descriptors directly (the
        interleaving of the two is not kept).
    """
    from hybridoc.cli import main

    out, err = io.StringIO(), io.StringIO()
    old = os.getcwd()
    if cwd is not None:
        os.chdir(cwd)
    try:
        with _descriptors() as fds:
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                try:
                    code = main(list(args))
                except SystemExit as exc:  # argparse's usage errors
                    code = exc.code if isinstance(exc.code, int) else int(exc.code is not None)
    finally:
        os.chdir(old)
    stdout, stderr = out.getvalue() + fds[0], err.getvalue() + fds[1]
    return subprocess.CompletedProcess(["hybridoc", *args], code, stdout, stderr)
