"""Outputs that never write through a link or over a user's file (issue #32).

Measured before the fix: ``evaluate``, ``solve --method dt``, ``train-policy`` and ``export``
wrote through a symbolic link planted at an output name (a file outside ``--out`` was
overwritten); a user's own ``dataset.npz`` in ``--out`` was overwritten by ``dataset`` and
by ``validate-policy``; an unwritable output folder failed only after the whole work. The
rules are :mod:`hybridoc.outputs`'s.
"""

from __future__ import annotations

import errno
import json
import os
import stat
from pathlib import Path

import numpy as np
import pytest
from cli_here import run_here
from conftest import examples
from hypothesis import given, settings
from hypothesis import strategies as st
from small_scenes import strike_scene

from hybridoc import outputs
from hybridoc.errors import HybridocError
from hybridoc.outputs import OutputRefused, check_folder, check_targets, write_text

posix = pytest.mark.skipif(os.name != "posix", reason="POSIX links and FIFOs")

SCENE_TOML = strike_scene("sc-out")

PRECIOUS = b"the user's own bytes\n"


def _plant(at: Path, kind: str, outside: Path) -> None:
    """Something at an output name that hybridoc must not replace or write through."""
    if kind == "user-file":
        at.write_bytes(PRECIOUS)
    elif kind == "link-to-file":
        at.symlink_to(outside)
    elif kind == "dangling-link":
        at.symlink_to(outside.parent / "nowhere" / "file")
    elif kind == "link-to-dir":
        at.symlink_to(outside.parent)
    elif kind == "fifo":
        os.mkfifo(at)
    elif kind == "directory":
        at.mkdir()
    else:  # pragma: no cover
        raise AssertionError(kind)


def _unchanged(at: Path, kind: str, outside: Path) -> None:
    assert outside.read_bytes() == PRECIOUS  # nothing outside the folder was written
    if kind == "user-file":
        assert at.read_bytes() == PRECIOUS
    elif kind.endswith("link"):
        assert at.is_symlink()
    elif kind == "fifo":
        assert stat.S_ISFIFO(at.lstat().st_mode)
    elif kind == "directory":
        assert at.is_dir() and not at.is_symlink()


NAME_CHARS = st.characters(categories=["L", "N"], max_codepoint=0x2FF)
KINDS = ["user-file", "link-to-file", "dangling-link", "link-to-dir", "fifo", "directory"]


@pytest.fixture
def outside(tmp_path: Path) -> Path:
    o = tmp_path / "elsewhere" / "precious.txt"
    o.parent.mkdir()
    o.write_bytes(PRECIOUS)
    return o


# ---------------------------------------------------------------------------- the helper


def test_a_file_hybridoc_wrote_is_replaced_atomically(tmp_path: Path) -> None:
    out = check_folder(tmp_path / "a" / "b")
    target = out / "r.json"
    write_text(target, "one\n")
    write_text(target, "two\n")  # its own file: replaced
    assert target.read_text() == "two\n"
    # no temporary left behind, and the record is a hidden file of its own
    assert sorted(p.name for p in out.iterdir()) == [outputs.RECORD, "r.json"]


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temporary(tmp_path: Path) -> None:
    target = tmp_path / "r.bin"
    outputs.write_bytes(target, b"old")

    def broken(fh: object) -> None:
        raise ValueError("the writer broke")

    with pytest.raises(ValueError, match="the writer broke"):
        outputs.write_with(target, broken)
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == [outputs.RECORD, "r.bin"]


def test_a_file_changed_or_replaced_after_hybridoc_wrote_it_is_the_users(tmp_path: Path) -> None:
    target = tmp_path / "r.txt"
    write_text(target, "hybridoc's\n")
    target.unlink()
    target.write_bytes(PRECIOUS)  # the user's own file now, at the same name
    with pytest.raises(OutputRefused, match=r"r\.txt' exists and was not written by hybridoc"):
        write_text(target, "again\n")
    assert target.read_bytes() == PRECIOUS


@posix
@pytest.mark.parametrize("kind", KINDS)
def test_what_hybridoc_did_not_write_is_refused_with_one_line(
    tmp_path: Path, outside: Path, kind: str
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    at = out / "result.json"
    _plant(at, kind, outside)
    for call in (lambda: check_targets(at), lambda: write_text(at, "{}\n")):
        with pytest.raises(OutputRefused) as err:
            call()
        text = str(err.value)
        assert str(at) in text and "\n" not in text
    _unchanged(at, kind, outside)


@posix
@settings(max_examples=examples(12))
@given(
    kind=st.sampled_from(KINDS),
    name=st.text(NAME_CHARS, min_size=1, max_size=12),
    ext=st.sampled_from([".json", ".npz", ".png", ".csv", ".xml", ""]),
    body=st.binary(max_size=64),
)
def test_never_through_a_link_nor_over_a_users_file(
    tmp_path_factory: pytest.TempPathFactory, kind: str, name: str, ext: str, body: bytes
) -> None:
    root = tmp_path_factory.mktemp("prop")
    outside = root / "precious.txt"
    outside.write_bytes(PRECIOUS)
    out = root / "out"
    out.mkdir()
    ours, theirs = out / f"{name}-ours{ext}", out / f"{name}{ext}"
    outputs.write_bytes(ours, body)  # the folder holds a record of hybridoc's own files
    _plant(theirs, kind, outside)
    with pytest.raises(OutputRefused):
        outputs.write_bytes(theirs, body + b"x")
    _unchanged(theirs, kind, outside)
    outputs.write_bytes(ours, body + b"y")  # its own file is still replaced
    assert ours.read_bytes() == body + b"y"


def test_check_folder_refuses_a_file_and_an_unmakeable_folder(tmp_path: Path) -> None:
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(HybridocError, match="is not a directory"):
        check_folder(f)
    with pytest.raises(HybridocError, match="cannot create output directory"):
        check_folder(f / "sub")
    with pytest.raises(HybridocError, match=r"cannot write .*x\.json'"):
        check_targets(f / "x.json")  # one line, not an internal error


def _unwritable(tmp_path: Path) -> Path:
    """An existing folder in which no file can be created, even by root (skips without)."""
    if hasattr(os, "geteuid") and os.geteuid() != 0:
        d = tmp_path / "ro"
        d.mkdir()
        d.chmod(0o555)
        return d
    for d in (Path("/sys/kernel"), Path("/proc/sys")):
        probe = d / ".hybridoc-probe"
        try:
            os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        except OSError:
            if d.is_dir():
                return d
            continue
        os.unlink(probe)  # pragma: no cover
    pytest.skip("no folder that this user cannot write")  # pragma: no cover


def test_an_unwritable_folder_fails_before_the_work(tmp_path: Path) -> None:
    d = _unwritable(tmp_path)
    with pytest.raises(HybridocError, match="cannot write in output directory"):
        check_folder(d)
    done = run_here(*["evaluate", "bouncing-ball", "--out", str(d)])
    assert done.returncode == 2
    assert done.stdout == ""  # refused before the evaluation: no answer, no internal error
    (line,) = done.stderr.strip().splitlines()
    assert "cannot write in output directory" in line and str(d) in line


def test_a_write_that_fails_at_the_end_still_prints_the_answer(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def full(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(outputs, "_replace", full)  # the rename of every output fails
    done = run_here(*["evaluate", "bouncing-ball", "--json", "--out", str(tmp_path)])
    assert done.returncode == 2
    import json

    assert np.isfinite(json.loads(done.stdout)["cost"])  # the answer is out
    (line,) = done.stderr.strip().splitlines()
    assert "cannot write" in line and "No space left on device" in line
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


# ---------------------------------------------------------------------------- the commands


@posix
def test_evaluate_never_writes_through_a_link(tmp_path: Path, outside: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    link = out / "bouncing-ball_evaluate.json"
    link.symlink_to(outside)
    done = run_here(*["evaluate", "bouncing-ball", "--out", str(out)])
    assert done.returncode == 2, done.stderr
    (line,) = done.stderr.strip().splitlines()
    assert str(link) in line and "symbolic link" in line
    assert outside.read_bytes() == PRECIOUS and link.is_symlink()
    assert not (out / "bouncing-ball_evaluate.npz").exists()  # neither file of the pair
    # with the link gone, the command writes, and a rerun replaces its own files
    link.unlink()
    for _ in range(2):
        assert run_here(*["evaluate", "bouncing-ball", "--out", str(out)]).returncode == 0
    assert (out / "bouncing-ball_evaluate.json").read_text().startswith("{")


@posix
def test_solve_dt_never_writes_through_a_link(tmp_path: Path, outside: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    link = out / "bouncing-ball_solve_dt.npz"
    link.symlink_to(outside)
    done = run_here(*["solve", "bouncing-ball", "--method", "dt", "--out", str(out)])
    assert done.returncode == 2
    # refused before the solve: one line, no answer computed for nothing
    (line,) = done.stderr.strip().splitlines()
    assert str(link) in line and done.stdout == ""
    assert outside.read_bytes() == PRECIOUS and link.is_symlink()


@posix
def test_solve_prints_its_answer_when_writing_fails_at_the_end(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from hybridoc import outputs
    from hybridoc.errors import HybridocError

    def refuse(*args: object, **kw: object) -> None:
        raise HybridocError("cannot write 'x': disk full")

    monkeypatch.setattr(outputs, "write_with", refuse)
    done = run_here(*["solve", "bouncing-ball", "--method", "dt", "--json", "--out", str(tmp_path)])
    assert done.returncode == 2
    assert json.loads(done.stdout)["cost"] > 0  # the answer is out
    assert done.stderr.strip().splitlines()[-1] == "hybridoc: error: cannot write 'x': disk full"


@posix
def test_export_never_writes_through_a_link(tmp_path: Path, outside: Path) -> None:
    link = tmp_path / "model.xml"
    link.symlink_to(outside)
    done = run_here(*["export", "mjcf", "single-collision", "--out", str(link)])
    assert done.returncode == 2
    (line,) = done.stderr.strip().splitlines()
    assert str(link) in line
    assert outside.read_bytes() == PRECIOUS and link.is_symlink()
    mine = tmp_path / "mine.xml"
    mine.write_bytes(PRECIOUS)  # a user's own file at the name given
    assert run_here(*["export", "mjcf", "single-collision", "--out", str(mine)]).returncode == 2
    assert mine.read_bytes() == PRECIOUS


@pytest.fixture
def scene(tmp_path: Path) -> Path:
    p = tmp_path / "scene.toml"
    p.write_text(SCENE_TOML)
    return p


@posix
def test_train_policy_never_writes_through_a_link(
    tmp_path: Path, outside: Path, scene: Path
) -> None:
    out = tmp_path / "out"
    out.mkdir()
    link = out / "sc-out_train-policy.npz"
    link.symlink_to(outside)
    done = run_here(*["train-policy", str(scene), "--samples", "2", "--iters", "1",
                    "--no-progress", "--out", str(out)])  # fmt: skip
    assert done.returncode == 2
    (line,) = done.stderr.strip().splitlines()
    assert str(link) in line
    assert outside.read_bytes() == PRECIOUS and link.is_symlink()
    assert not (out / "sc-out_train-policy.json").exists()  # refused before the training


def test_dataset_never_overwrites_a_users_dataset_npz(tmp_path: Path, scene: Path) -> None:
    out = tmp_path / "o"
    out.mkdir()
    (out / "dataset.npz").write_bytes(PRECIOUS)
    done = run_here(*["dataset", str(scene), "--samples", "2", "--workers", "1",
                    "--no-progress", "--out", str(out)])  # fmt: skip
    assert done.returncode == 2
    line = done.stderr.strip().splitlines()[-1]
    assert "dataset.npz' exists and was not written by 'hybridoc dataset'" in line
    assert (out / "dataset.npz").read_bytes() == PRECIOUS


def test_validate_policy_never_overwrites_a_users_dataset_npz(tmp_path: Path, scene: Path) -> None:
    pol = tmp_path / "pol.py"
    pol.write_text("import numpy as np\ndef p(t, s):\n    return np.zeros(2)\n")
    out = tmp_path / "o"
    (out / "sc-out_dataset").mkdir(parents=True)
    mine = out / "sc-out_dataset" / "dataset.npz"
    mine.write_bytes(PRECIOUS)
    done = run_here(*["validate-policy", str(scene), "--policy", f"{pol}:p", "--samples", "2",
                    "--workers", "1", "--no-progress", "--out", str(out)])  # fmt: skip
    assert done.returncode == 2
    assert "was not written by 'hybridoc dataset'" in done.stderr.strip().splitlines()[-1]
    assert mine.read_bytes() == PRECIOUS


@posix
def test_a_link_at_a_datasets_file_is_refused(tmp_path: Path, outside: Path, scene: Path) -> None:
    out = tmp_path / "o"
    out.mkdir()
    (out / "dataset.npz").symlink_to(outside)
    done = run_here(*["dataset", str(scene), "--samples", "2", "--workers", "1",
                    "--no-progress", "--out", str(out)])  # fmt: skip
    assert done.returncode == 2
    assert outside.read_bytes() == PRECIOUS


def test_writers_in_one_folder_take_turns_on_the_record(tmp_path: Path) -> None:
    # each write reads, extends and replaces the folder's record under its flock: writers
    # side by side lose no entry, so every file stays replaceable by hybridoc
    import threading

    def writer(k: int) -> None:
        for j in range(5):
            outputs.write_bytes(tmp_path / f"w{k}-{j}.bin", bytes([k, j]))

    threads = [threading.Thread(target=writer, args=(k,)) for k in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for k in range(8):
        for j in range(5):
            outputs.write_bytes(tmp_path / f"w{k}-{j}.bin", b"again")  # recorded: replaced
    assert len(list(tmp_path.glob("w*.bin"))) == 40


def _writers() -> dict[str, tuple[str, object]]:
    """Every library function that writes a file: (the file name, a call writing it)."""
    import hybridoc
    from hybridoc.io import save_controls
    from hybridoc.plotting import save_figure
    from hybridoc.workflows.policy_format import MLP, save_mlp_policy

    def solution(p: Path) -> object:
        from hybridoc.solution import Solution

        ocp = hybridoc.as_ocp("bouncing-ball")
        ev = hybridoc.evaluate(ocp, ocp.u_guess)
        return Solution.from_evaluation(ev, method="evaluate", scene=ocp.name).save(p)

    def figure(p: Path) -> object:
        from matplotlib.figure import Figure

        return save_figure(Figure(), p)

    def policy(p: Path) -> object:
        mlp = MLP((np.ones((2, 3)), np.ones((1, 2))), (np.zeros(2), np.zeros(1)))
        return save_mlp_policy(mlp, p)

    return {
        "Solution.save": ("s.json", solution),
        "save_controls npy": ("u.npy", lambda p: save_controls(p, np.zeros((4, 1)))),
        "save_controls csv": ("u.csv", lambda p: save_controls(p, np.zeros((4, 1)))),
        "save_figure": ("f.png", figure),
        "save_mlp_policy": ("p.json", policy),
    }


@posix
@pytest.mark.parametrize("writer", sorted(_writers()))
def test_every_library_writer_follows_the_rules(tmp_path: Path, outside: Path, writer: str) -> None:
    name, write = _writers()[writer]
    out = tmp_path / "out"
    out.mkdir()
    (out / name).symlink_to(outside)
    with pytest.raises(OutputRefused, match="symbolic link"):
        write(out / name)
    assert outside.read_bytes() == PRECIOUS and (out / name).is_symlink()
    (out / name).unlink()
    (out / name).write_bytes(PRECIOUS)
    with pytest.raises(OutputRefused, match="not written by hybridoc"):
        write(out / name)
    assert (out / name).read_bytes() == PRECIOUS
    (out / name).unlink()
    write(out / name)
    write(out / name)  # its own file: replaced
    assert (out / name).read_bytes() != PRECIOUS
