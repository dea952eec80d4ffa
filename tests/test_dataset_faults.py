"""Datasets that never lose or destroy data: runs killed at random points resume to the same
bytes, damaged shards are computed again, two runs into one folder are refused by a lock,
files hybridoc did not write survive, an edited ``dataset.npz`` is detected, and pool
workers end with their parent (issue #17)."""

from __future__ import annotations

import contextlib
import os
import random
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_datasets import SCENE_TOML as DATASET_SCENE_TOML
from test_datasets import share_nominals

import hybridoc
import hybridoc.workflows.datasets as dsmod
from hybridoc.cli import main
from hybridoc.errors import HybridocError
from hybridoc.workflows.datasets import load_dataset, make_dataset

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="uses /proc, fork and SIGKILL"
)

M = 8  # draws: four chunks of two
CHUNK = 2

# test_datasets.py's scene on a coarser grid (the same draws and events, faster)
SCENE_TOML = DATASET_SCENE_TOML.replace("steps = 480", "steps = 40")
assert "steps = 40" in SCENE_TOML

# `hybridoc dataset ...` with chunks of two draws; with HYBRIDOC_TEST_GATE set, every chunk
# waits until that file exists
RUNNER = f"""
import os, sys, time
from pathlib import Path

import hybridoc.workflows.datasets as d

d.CHUNK = {CHUNK}
gate = os.environ.get("HYBRIDOC_TEST_GATE")
if gate:
    solve = d._solve_chunk

    def gated(spec, idx):
        while not Path(gate).exists():
            time.sleep(0.02)
        return solve(spec, idx)

    d._solve_chunk = gated
from hybridoc.cli import main

sys.exit(main(sys.argv[1:]))
"""

# a pool of two workers, each on a task that sleeps a minute; argv[1] == "watch": without
# PR_SET_PDEATHSIG, so that the fallback thread has to notice the parent's death
SLEEPERS = """
import sys, time

import hybridoc.workflows.datasets as d

if sys.argv[1] == "watch":
    d._die_with_parent = lambda: False


def nap(common, idx):
    time.sleep(60)
    return idx


d.run_chunks(nap, None, [(0, [0]), (1, [1])], workers=2, on_result=lambda c, r: None)
"""


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("faults")
    (d / "scene.toml").write_text(SCENE_TOML)
    (d / "runner.py").write_text(RUNNER)
    (d / "sleepers.py").write_text(SLEEPERS)
    (d / "pol.py").write_text("import numpy as np\n\ndef zero(t, s):\n    return np.zeros(2)\n")
    return d


@pytest.fixture(scope="module")
def reference(files: Path) -> bytes:
    """The bytes of ``dataset.npz`` of an uninterrupted run (in this process); its nominal
    reference serves the in-process runs of the tests below (the subprocesses solve their
    own, and must reach the same bytes)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(dsmod, "CHUNK", CHUNK)
        share_nominals(mp)
        make_dataset(files / "scene.toml", M, files / "ref", workers=1, progress=False)
    return (files / "ref" / "dataset.npz").read_bytes()


def env() -> dict[str, str]:
    """The environment of a subprocess that imports the hybridoc this process runs."""
    root = str(Path(hybridoc.__file__).resolve().parents[1])
    path = os.environ.get("PYTHONPATH")
    return {**os.environ, "PYTHONPATH": root if not path else f"{root}{os.pathsep}{path}"}


def start(files: Path, out: Path, *extra: str, gate: Path | None = None) -> subprocess.Popen:
    cmd = [sys.executable, str(files / "runner.py"), "dataset", str(files / "scene.toml"),
           "--samples", str(M), "--out", str(out), "--no-progress", *extra]  # fmt: skip
    e = env()
    if gate is not None:
        e["HYBRIDOC_TEST_GATE"] = str(gate)
    return subprocess.Popen(cmd, env=e, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for(cond: Callable[[], bool], timeout: float, what: str) -> None:
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.02)


def children(pid: int) -> set[int]:
    out: set[int] = set()
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out |= {int(c) for c in (task / "children").read_text().split()}
        except OSError:
            pass
    return out


def alive(pid: int) -> bool:
    """Running (a zombie that nobody reaps does not count)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def kill(p: subprocess.Popen) -> set[int]:
    """SIGKILL ``p`` and check that its children (pool workers) end with it; returns them."""
    kids = children(p.pid)
    p.kill()
    p.wait()
    wait_for(lambda: not any(alive(k) for k in kids), 10, f"the workers {kids} to end")
    p.communicate(timeout=10)  # their ends of the pipes are closed
    return kids


def listing(d: Path) -> list[str]:
    return sorted(p.name for p in d.iterdir())


# ---------------------------------------------------------------------------- kills


def test_killed_runs_resume_to_the_same_bytes(files: Path, reference: bytes) -> None:
    seed = int.from_bytes(os.urandom(4), "little")
    rng = random.Random(seed)
    out = files / "killed"
    # an uninterrupted run of the command, for the scale of the random delays
    t0 = time.monotonic()
    p = start(files, files / "whole", "--workers", "2")
    _, err = p.communicate(timeout=120)
    whole = time.monotonic() - t0
    assert p.returncode == 0, err
    assert (files / "whole" / "dataset.npz").read_bytes() == reference
    # killed once some chunks are done (the pool's workers with it), then at random times
    p = start(files, out, "--workers", "2")
    wait_for(lambda: any((out / "shards").glob("chunk-*.npz")) or p.poll() is not None, 60,
             "a first shard")  # fmt: skip
    assert kill(p), "no pool workers"
    assert not (out / "dataset.npz").exists(), "the run finished before it was killed"
    delays = [rng.uniform(0.05, 1.1) * whole for _ in range(3)]
    for i, delay in enumerate(delays):
        p = start(files, out, "--workers", str(1 + i % 2))
        # a resumed run skips the nominal solve and may end before its delay: no waiting on
        # a process that is done (killing it then is a no-op, as it was after a sleep)
        with contextlib.suppress(subprocess.TimeoutExpired):
            p.wait(timeout=delay)
        kill(p)
    p = start(files, out, "--workers", "2")
    _, err = p.communicate(timeout=120)
    why = f"seed {seed}, delays {delays}: {err}"
    assert p.returncode == 0, why
    assert (out / "dataset.npz").read_bytes() == reference, why
    # nothing of the runs is left but the dataset
    assert listing(out) == ["dataset.npz", "manifest.json"], why
    assert load_dataset(out).manifest["sha256"] == load_dataset(files / "whole").manifest["sha256"]


def test_pool_workers_end_with_their_parent(files: Path) -> None:
    for how in ("prctl", "watch"):
        p = subprocess.Popen([sys.executable, str(files / "sleepers.py"), how], env=env())
        try:
            wait_for(lambda: len(children(p.pid)) >= 2, 60, "two workers")  # noqa: B023
            kids = children(p.pid)
        finally:
            p.kill()
            p.wait()
        try:
            wait_for(lambda: not any(alive(k) for k in kids), 10, f"the workers to end ({how})")  # noqa: B023
        finally:
            for k in kids:  # not left behind when the test fails
                if alive(k):
                    os.kill(k, signal.SIGKILL)


# ---------------------------------------------------------------------------- two runs


def test_a_second_run_into_the_folder_fails_at_once(
    files: Path,
    reference: bytes,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out, gate = files / "twice", files / "twice-gate"
    first = start(files, out, "--workers", "1", gate=gate)
    try:
        # the shard folder is made under the lock; the first run then waits at the gate
        wait_for(lambda: (out / "shards").is_dir() or first.poll() is not None, 60,
                 "the first run to take the lock")  # fmt: skip
        assert first.poll() is None, first.communicate()[1]
        # the second run in this process (flock conflicts between open file descriptions,
        # so the other process's lock refuses it as it would refuse a third process)
        monkeypatch.setattr(dsmod, "CHUNK", CHUNK)  # the same command as the runner's
        capsys.readouterr()
        code = main(["dataset", str(files / "scene.toml"), "--samples", str(M), "--out",
                     str(out), "--no-progress", "--workers", "1"])  # fmt: skip
        err = capsys.readouterr().err
        assert code == 2, err
        assert "another hybridoc dataset run holds the lock on" in err and str(out) in err, err
        assert err.count("\n") == 1, err
    finally:
        gate.touch()
    _, err = first.communicate(timeout=120)
    assert first.returncode == 0, err
    assert (out / "dataset.npz").read_bytes() == reference
    assert listing(out) == ["dataset.npz", "manifest.json"]


def test_the_lock_is_held_and_released(files: Path, tmp_path: Path) -> None:
    with dsmod._locked(tmp_path):
        assert (tmp_path / dsmod.LOCK_FILE).exists()
        with pytest.raises(HybridocError, match="another hybridoc dataset run holds the lock"):
            make_dataset(files / "scene.toml", 1, tmp_path, workers=1, progress=False)
        assert listing(tmp_path) == [dsmod.LOCK_FILE]  # the refused run wrote nothing
    assert listing(tmp_path) == []
    with dsmod._locked(tmp_path):  # free again
        pass


@pytest.mark.parametrize("code", ["ENOSYS", "EOPNOTSUPP", "ENOLCK"])
def test_a_file_system_without_locks_runs_with_a_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, code: str
) -> None:
    # Lustre without -o flock answers ENOSYS: a run goes on, saying what is not protected
    import errno
    import fcntl

    def no_locks(fd: int, op: int) -> None:
        raise OSError(getattr(errno, code), os.strerror(getattr(errno, code)))

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with pytest.warns(UserWarning, match="does not support locks"):
        with dsmod._locked(tmp_path):
            pass
    assert listing(tmp_path) == []
    # any other failure to lock is an error
    monkeypatch.setattr(fcntl, "flock", lambda fd, op: (_ for _ in ()).throw(OSError(5, "EIO")))
    with pytest.raises(HybridocError, match="cannot lock"):
        with dsmod._locked(tmp_path):
            pass


# ---------------------------------------------------------------------------- shards


def test_bad_shards_are_computed_again(
    files: Path,
    reference: bytes,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setattr(dsmod, "CHUNK", CHUNK)
    share_nominals(monkeypatch)  # the reference's nominal: this test is about the shards
    solve = dsmod._solve_chunk
    seen: list[list[int]] = []

    def interrupted(spec: Any, idx: list[int]) -> Any:
        if len(seen) == 3:
            raise KeyboardInterrupt
        seen.append(idx)
        return solve(spec, idx)

    monkeypatch.setattr(dsmod, "_solve_chunk", interrupted)
    with pytest.raises(KeyboardInterrupt):
        make_dataset(files / "scene.toml", M, tmp_path, workers=1, progress=False)
    shards = tmp_path / "shards"
    assert listing(shards) == [".hybridoc-shards", *(f"chunk-00000{i}.npz" for i in range(3))]
    # chunk 0 truncated, chunk 1 holding chunk 2's draws, chunk 2 good, chunk 3 missing with
    # the temporary of a killed write; a file of the user's in the folder
    c0 = shards / "chunk-000000.npz"
    c0.write_bytes(c0.read_bytes()[:1000])
    (shards / "chunk-000001.npz").write_bytes((shards / "chunk-000002.npz").read_bytes())
    (shards / ".chunk-000003.npz.4242.0badc0de.tmp").write_bytes(b"PK\x03\x04")
    (shards / "notes.txt").write_text("mine")
    # and in the output folder, a manifest and a shard folder whose writes were killed
    (tmp_path / ".manifest.json.4242.0badc0de.tmp").write_text("{")
    (tmp_path / ".shards.4242.0badc0de.tmp").mkdir()
    (tmp_path / ".shards.4242.0badc0de.tmp" / ".hybridoc-shards").write_text("hybr")
    seen.clear()
    capsys.readouterr()
    monkeypatch.setattr(dsmod, "_solve_chunk", lambda s, i: seen.append(i) or solve(s, i))
    make_dataset(files / "scene.toml", M, tmp_path, workers=1, progress=False)
    err = capsys.readouterr().err
    assert seen == [[0, 1], [2, 3], [6, 7]], err
    assert "shard chunk-000000.npz is damaged (BadZipFile" in err, err
    assert "shard chunk-000001.npz holds other draws than 2 to 3: computing it again" in err, err
    assert "resuming: 2 of 8 samples already done" in err, err
    assert (tmp_path / "dataset.npz").read_bytes() == reference
    # the user's file stays, and so does the folder with it
    assert "kept" in err and "notes.txt" in err, err
    assert listing(shards) == [".hybridoc-shards", "notes.txt"]
    assert listing(tmp_path) == ["dataset.npz", "manifest.json", "shards"]


def test_an_older_versions_unfinished_run_is_resumed(
    files: Path, reference: bytes, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # hybridoc before the marker left shards/ with chunk files only: with our manifest of
    # the same settings beside it, the folder is adopted and the run finishes to the same
    # bytes; with a file of anyone else's in it, it is still refused and left alone
    monkeypatch.setattr(dsmod, "CHUNK", CHUNK)
    share_nominals(monkeypatch)  # the reference's nominal: this test is about the folder
    solve = dsmod._solve_chunk

    def interrupted(spec: Any, idx: list[int]) -> Any:
        if idx[0] >= 4:
            raise KeyboardInterrupt
        return solve(spec, idx)

    monkeypatch.setattr(dsmod, "_solve_chunk", interrupted)
    with pytest.raises(KeyboardInterrupt):
        make_dataset(files / "scene.toml", M, tmp_path, workers=1, progress=False)
    monkeypatch.setattr(dsmod, "_solve_chunk", solve)
    shards = tmp_path / "shards"
    (shards / ".hybridoc-shards").unlink()  # as the older version left it
    (shards / "keep.txt").write_text("x")
    with pytest.raises(HybridocError, match="was not made by 'hybridoc dataset'"):
        make_dataset(files / "scene.toml", M, tmp_path, workers=1, progress=False)
    assert (shards / "keep.txt").read_text() == "x"
    (shards / "keep.txt").unlink()
    make_dataset(files / "scene.toml", M, tmp_path, workers=1, progress=False)
    assert (tmp_path / "dataset.npz").read_bytes() == reference
    assert listing(tmp_path) == ["dataset.npz", "manifest.json"]


def test_read_shard_rejects_every_kind_of_bad_shard(files: Path, tmp_path: Path) -> None:
    cols = {k: np.zeros(2) for k in dsmod.COLUMNS}
    cols["index"] = np.array([4, 5], dtype=np.int64)
    good = {**cols, dsmod._SPEC_KEY: np.array(["h"])}
    p = tmp_path / "chunk-000002.npz"
    dsmod._write_npz(p, good)
    data = p.read_bytes()
    back, why = dsmod._read_shard(p, [4, 5], "h")
    assert why == "" and back is not None and set(back) == dsmod.COLUMNS
    assert dsmod._read_shard(tmp_path / "nope.npz", [4, 5], "h") == (None, "")
    variants: list[tuple[Any, list[int], str, str]] = [
        (data[: len(data) // 2], [4, 5], "h", "is damaged (BadZipFile"),
        (b"", [4, 5], "h", "is damaged"),
        (b"garbage" * 20, [4, 5], "h", "is damaged"),
        (data, [4, 5], "other", "was computed with other settings"),
        (data, [2, 3], "h", "holds other draws than 2 to 3"),
        ({k: v for k, v in good.items() if k != "cost"}, [4, 5], "h", "has other columns"),
        ({**good, "extra": np.zeros(2)}, [4, 5], "h", "has other columns"),
        ({**good, "cost": np.zeros(3)}, [4, 5], "h", "does not have 2 rows"),
        ({**good, "cost": np.float64(0)}, [4, 5], "h", "does not have 2 rows"),
    ]
    for body, idx, spec, words in variants:
        if isinstance(body, dict):
            dsmod._write_npz(p, body)
        else:
            p.write_bytes(body)
        cols_, why = dsmod._read_shard(p, idx, spec)
        assert cols_ is None and why.startswith(words), (words, why)


def test_a_folder_shards_that_is_not_ours_is_never_touched(
    files: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "shards").mkdir()
    (tmp_path / "shards" / "keep.txt").write_text("x\n")
    (tmp_path / "shards" / "chunk-000000.npz").write_text("not ours either\n")

    def nominal(*args: Any) -> Any:
        raise AssertionError("refused only after the nominal solve")

    monkeypatch.setattr(dsmod, "_nominal", nominal)
    with pytest.raises(HybridocError, match=r"shards' exists and was not made by 'hybridoc"):
        make_dataset(files / "scene.toml", 3, tmp_path, workers=1, progress=False)
    code = main(["dataset", str(files / "scene.toml"), "--samples", "3", "--out", str(tmp_path),
                 "--workers", "1"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "move it away or choose another --out" in err and err.count("\n") == 1
    assert (tmp_path / "shards" / "keep.txt").read_text() == "x\n"
    assert (tmp_path / "shards" / "chunk-000000.npz").read_text() == "not ours either\n"
    assert listing(tmp_path) == ["shards"]


# ---------------------------------------------------------------------------- hashes


def test_an_edited_or_truncated_dataset_is_detected(
    files: Path, reference: bytes, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import shutil

    out = tmp_path / "ds"
    shutil.copytree(files / "ref", out)
    expected = load_dataset(out).manifest["sha256"]
    data = out / "dataset.npz"
    cols = dsmod._parse_npz(reference)
    cols["cost"][0] *= 1e4
    tampered = dsmod._npz_bytes(cols)
    for body in (tampered, reference[: len(reference) // 2]):
        data.write_bytes(body)
        actual = dsmod.hashlib.sha256(body).hexdigest()
        words = f"SHA-256 expected {expected}, actual {actual}"
        with pytest.raises(HybridocError, match=words) as exc:
            load_dataset(out)
        assert str(data) in str(exc.value)
        # the same command finds it complete: the damage is reported, never computed over
        argv = ["dataset", str(files / "scene.toml"), "--samples", str(M), "--out", str(out)]
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(dsmod, "CHUNK", CHUNK)
            code = main(argv)
        err = capsys.readouterr().err
        assert code == 2 and words in err and "remove it" in err and err.count("\n") == 1, err
        code = main(["validate-policy", str(files / "scene.toml"), f"{files / 'pol.py'}:zero",
                     "--samples", "2", "--dataset", str(out)])  # fmt: skip
        err = capsys.readouterr().err
        assert code == 2 and words in err, err
        assert data.read_bytes() == body
    # removed, it is computed again (from the manifest's nominal solution) to the same bytes
    data.unlink()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(dsmod, "CHUNK", CHUNK)
        make_dataset(files / "scene.toml", M, out, workers=1, progress=False)
    assert data.read_bytes() == reference
    assert load_dataset(out).manifest["sha256"] == expected
