"""No child process outlives its parent (issue #32).

The issue: a run killed from outside (``--starts 1000000000`` at 24 GB) left a process
running after its parent. A parent killed with SIGKILL runs no ``atexit`` handler: the C
compiler of the code cache, started in a session of its own, compiled on (with ``cc1`` and
the assembler); pool workers wait forever on their pool's pipe. :mod:`hybridoc.children`
makes every process hybridoc starts die with its parent. Each test here starts a parent in a
session of its own, records its descendants from ``/proc`` while they run, kills the parent
with SIGKILL and checks that, within a few seconds, none of them and nothing in its process
group is left.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from small_scenes import strike_scene

import hybridoc

linux = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")


def _table() -> dict[int, tuple[str, int, int]]:
    """pid -> (state, parent pid, process group) of every process, from ``/proc``."""
    out = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            text = Path(f"/proc/{entry}/stat").read_text()
        except OSError:
            continue  # gone meanwhile
        fields = text[text.rindex(")") + 2 :].split()
        out[int(entry)] = (fields[0], int(fields[1]), int(fields[2]))
    return out


def _descendants(root: int) -> set[int]:
    table = _table()
    found, frontier = set(), {root}
    while frontier:
        frontier = {p for p, (_, ppid, _) in table.items() if ppid in frontier} - found
        found |= frontier
    return found


def _running(pids: set[int], group: int) -> set[int]:
    """Those of ``pids``, and the members of process group ``group``, that still run (a
    zombie waits only for its new parent to reap it: it runs nothing)."""
    return {
        p
        for p, (state, _, pgrp) in _table().items()
        if (p in pids or pgrp == group) and state not in ("Z", "X")
    }


def _wait_for(what: Callable[[], bool], seconds: float, why: str) -> None:
    deadline = time.monotonic() + seconds
    while not what():
        if time.monotonic() > deadline:
            raise AssertionError(f"waited {seconds} s for {why}")
        time.sleep(0.02)


def _env() -> dict[str, str]:
    root = str(Path(hybridoc.__file__).resolve().parents[1])
    path = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONPATH": root if not path else f"{root}{os.pathsep}{path}"}


def _kill_and_check(
    p: subprocess.Popen[bytes], ready: Callable[[set[int]], bool], seconds: float = 10
) -> None:
    """Wait until ``ready(descendants)``, record the descendants a little longer, SIGKILL the
    parent and check that all of them end within ``seconds``."""
    seen: set[int] = set()
    try:

        def grown() -> bool:
            seen.update(_descendants(p.pid))
            if p.poll() is not None:
                raise AssertionError(f"the parent ended first: {p.communicate()}")
            return ready(seen)

        _wait_for(grown, 120, "the children to start")
        for _ in range(10):
            seen.update(_descendants(p.pid))
            time.sleep(0.02)
    finally:
        p.kill()
        p.wait()
    try:
        _wait_for(lambda: not _running(seen, p.pid), seconds, "the children to end")
    finally:
        for k in _running(seen, p.pid):  # never left behind by a failing test
            try:
                os.kill(k, signal.SIGKILL)
            except ProcessLookupError:
                pass


# a hybridoc command line whose dataset chunks (one draw each) wait a minute before their
# solve: the pool's workers are then alive, each in a chunk, when the parent is killed
DATASET_RUNNER = """
import sys, time
import hybridoc.workflows.datasets as d

d.CHUNK = 1
solve = d._solve_chunk

def slow(spec, idx):
    time.sleep(60)
    return solve(spec, idx)

d._solve_chunk = slow
from hybridoc.cli import main

sys.exit(main(sys.argv[1:]))
"""


@linux
def test_a_killed_parallel_dataset_build_leaves_no_process(tmp_path: Path) -> None:
    scene = tmp_path / "scene.toml"
    scene.write_text(strike_scene("sc-kids", steps=60))
    cmd = [sys.executable, "-c", DATASET_RUNNER, "dataset", str(scene), "--samples", "4",
           "--workers", "2", "--no-progress", "--out", str(tmp_path / "o")]  # fmt: skip
    p = subprocess.Popen(cmd, env=_env(), start_new_session=True, stderr=subprocess.PIPE)
    me = Path(f"/proc/{p.pid}/cmdline")

    def two_workers(seen: set[int]) -> bool:
        # the pool's workers are forks of the command: the same command line
        try:
            mine = me.read_bytes()
        except OSError:
            return False
        workers = 0
        for k in seen:
            try:
                workers += Path(f"/proc/{k}/cmdline").read_bytes() == mine
            except OSError:
                pass
        return workers >= 2

    _kill_and_check(p, two_workers)


# a process whose pool workers each start a fork pool of their own (as a dataset worker's
# reference search does), every grandchild asleep
NESTED = """
import os, sys, time
from concurrent.futures import ProcessPoolExecutor
import multiprocessing as mp
import hybridoc.workflows.datasets as d

def nap(_):
    time.sleep(60)

def chunk(common, idx):
    with ProcessPoolExecutor(2, mp_context=mp.get_context("fork")) as pool:
        list(pool.map(nap, range(2)))
    return idx

print(os.getpid(), flush=True)
d.run_chunks(chunk, None, [(0, [0]), (1, [1])], workers=2, on_result=lambda c, r: None)
"""


@linux
def test_the_pools_that_pool_workers_fork_end_with_them(tmp_path: Path) -> None:
    p = subprocess.Popen([sys.executable, "-c", NESTED], env=_env(), start_new_session=True)
    # two workers, each with two workers of its own
    _kill_and_check(p, lambda seen: len(seen) >= 6)


# a process that compiles in a background thread, as the code cache does: the "compiler"
# (a shell) runs a child of its own, both asleep
COMPILING = """
import threading, time
from hybridoc import compiled

threading.Thread(
    target=compiled._run_compiler, args=(["sh", "-c", "sleep 60 & sleep 60; wait"],),
    daemon=True,
).start()
time.sleep(120)
"""


@linux
def test_a_compiler_and_its_children_end_with_a_killed_parent() -> None:
    p = subprocess.Popen([sys.executable, "-c", COMPILING], env=_env(), start_new_session=True)

    def sleeping(seen: set[int]) -> bool:
        names = []
        for k in seen:
            try:
                names.append(Path(f"/proc/{k}/comm").read_text().strip())
            except OSError:
                pass
        return names.count("sleep") >= 2

    _kill_and_check(p, sleeping)


@linux
def test_a_supervised_command_keeps_its_status_output_and_errors(tmp_path: Path) -> None:
    from hybridoc.children import popen_group

    p = popen_group(["sh", "-c", "echo out; echo err >&2; exit 5"], stdout=subprocess.PIPE,
                    stderr=subprocess.PIPE, text=True)  # fmt: skip
    out, err = p.communicate(timeout=30)
    assert (p.returncode, out, err) == (5, "out\n", "err\n")
    p = popen_group(["sh", "-c", "kill -TERM $$"], stderr=subprocess.PIPE, text=True)
    p.communicate(timeout=30)
    assert p.returncode == 128 + signal.SIGTERM
    missing = str(tmp_path / "no-such-compiler")
    p = popen_group([missing], stderr=subprocess.PIPE, text=True)
    _, err = p.communicate(timeout=30)
    assert p.returncode == 127 and missing in err and len(err.splitlines()) == 1


def test_a_child_whose_parent_is_already_gone_ends_at_once() -> None:
    # the race between the fork and the request: the parent died in between
    code = textwrap.dedent(
        """
        import os
        from hybridoc import children
        children.die_with_parent(parent=os.getppid() + 10**7)
        print("still here")
        """
    )
    done = subprocess.run([sys.executable, "-c", code], env=_env(), capture_output=True,
                          text=True, timeout=60)  # fmt: skip
    assert (done.returncode, done.stdout, done.stderr) == (1, "", "")


# a fork pool as the reference's search starts one (the lines proposed for
# reference/solve.py: initializer=die_with_parent), its workers asleep; argv[1] == "bare":
# without the initializer, the control case
FORK_POOL = """
import sys, time
from concurrent.futures import ProcessPoolExecutor
import multiprocessing as mp
from hybridoc.children import die_with_parent

def nap(_):
    time.sleep(60)

init = None if sys.argv[1] == "bare" else die_with_parent
with ProcessPoolExecutor(2, mp_context=mp.get_context("fork"), initializer=init) as pool:
    list(pool.map(nap, range(2)))
"""


@linux
@pytest.mark.parametrize("how", ["die_with_parent", "bare"])
def test_a_fork_pool_ends_with_its_parent_only_with_die_with_parent(how: str) -> None:
    p = subprocess.Popen([sys.executable, "-c", FORK_POOL, how], env=_env(), start_new_session=True)
    if how == "die_with_parent":
        _kill_and_check(p, lambda seen: len(seen) >= 2)
        return
    # the control: without it, the workers outlive their parent (killed here by the test)
    with pytest.raises(AssertionError, match="the children to end"):
        _kill_and_check(p, lambda seen: len(seen) >= 2, seconds=2)
