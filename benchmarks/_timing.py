"""Helpers shared by the benchmark scripts (run as ``python benchmarks/NAME.py``).

Timings in process (:func:`time_calls`, :func:`median_ms`), whole processes with their own
peak memory (:func:`run_process`, ``os.wait4``), the machine line every script prints first
(:func:`machine_line`), and PASS/MISS verdicts.
"""

from __future__ import annotations

import datetime
import os
import platform
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
"""The project's root (the folder above ``benchmarks/``)."""

PEER_DEFAULT = ROOT.parent / "shared" / "peer"
"""Where the paper's public implementation is looked for (``../shared/peer`` from the root)."""


def time_calls(fn: Callable[[], Any], runs: int, warmup: int = 1) -> list[float]:
    """Wall times in seconds of ``runs`` calls of ``fn()`` after ``warmup`` untimed calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return times


def median_ms(fn: Callable[[], Any], runs: int) -> float:
    """Median wall time of ``fn()`` over ``runs`` calls (no warm-up), in milliseconds."""
    return 1e3 * statistics.median(time_calls(fn, runs, warmup=0))


@dataclass
class ProcResult:
    """One finished process: wall and CPU time, peak memory, exit status and output."""

    wall_s: float
    cpu_s: float
    maxrss_mb: float
    returncode: int
    stdout: str
    stderr: str
    timed_out: bool = False


def run_process(
    cmd: Sequence[str],
    *,
    env: Mapping[str, str] | None = None,
    cwd: str | Path | None = None,
    timeout: float | None = None,
) -> ProcResult:
    """Run ``cmd`` to the end; its wall time, CPU time and own peak RSS (``os.wait4``).

    ``cwd`` defaults to a scratch folder: started in the repository root, ``python -c``
    would import the bare ``hybridoc/`` directory instead of the installed package.
    """
    with tempfile.TemporaryDirectory(prefix="hybridoc-bench-") as tmp:
        out_path, err_path = Path(tmp) / "stdout", Path(tmp) / "stderr"
        with open(out_path, "wb") as out, open(err_path, "wb") as err:
            full_env = dict(os.environ if env is None else env)
            t0 = time.perf_counter()
            proc = subprocess.Popen(
                list(cmd), stdout=out, stderr=err, env=full_env, cwd=str(cwd or tmp)
            )
            timed_out = False
            while True:
                pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
                if pid:
                    break
                if timeout is not None and time.perf_counter() - t0 > timeout:
                    proc.send_signal(signal.SIGKILL)
                    timed_out = True
                    pid, status, usage = os.wait4(proc.pid, 0)
                    break
                time.sleep(0.005)
            wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)  # Popen must not wait again
        return ProcResult(
            wall_s=wall,
            cpu_s=usage.ru_utime + usage.ru_stime,
            maxrss_mb=usage.ru_maxrss / 1024.0,
            returncode=proc.returncode,
            stdout=out_path.read_text(errors="replace"),
            stderr=err_path.read_text(errors="replace"),
            timed_out=timed_out,
        )


def hybridoc_command() -> list[str]:
    """The ``hybridoc`` command of this interpreter's environment."""
    exe = Path(sys.executable).parent / "hybridoc"
    if exe.exists():
        return [str(exe)]
    found = shutil.which("hybridoc")
    return [found] if found else [sys.executable, "-m", "hybridoc"]


def load_average() -> str:
    """The 1, 5 and 15 minute load averages, as ``uptime`` prints them."""
    try:
        return ", ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:  # pragma: no cover - not available
        return "unknown"


def machine_line() -> str:
    """Date, host, cores, load and versions: the first line of every benchmark's output."""
    import hybridoc

    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        usable = os.cpu_count() or 1
    now = datetime.datetime.now().isoformat(timespec="seconds")
    return (
        f"{now}  {platform.node()}  {usable} usable cores  load average {load_average()}  "
        f"Python {platform.python_version()}  hybridoc {hybridoc.__version__}"
    )


def verdict(ok: bool | None) -> str:
    """``PASS``, ``MISS`` or ``-`` (no target)."""
    return "-" if ok is None else ("PASS" if ok else "MISS")


def fmt_ms(seconds: float) -> str:
    """Seconds as milliseconds with a sensible number of digits."""
    ms = 1e3 * seconds
    return f"{ms:.3g}" if ms < 10 else f"{ms:.0f}"
