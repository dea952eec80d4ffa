"""Every command that writes, against whatever can stand at each name it writes (issue #32).

The issue's examples (a symbolic link planted at an output name of ``evaluate``, ``solve
--method dt``, ``train-policy`` and ``export``; a user's own ``dataset.npz`` overwritten by
``dataset`` and ``validate-policy``; an unwritable output folder failing after the whole
solve) are single cases in ``test_outputs_safe.py``. Here they are generated: each command
that writes (``evaluate``, ``solve`` with each method, ``reference``, ``train-policy``,
``export``, ``dataset``, ``validate-policy``), each name it writes (found by running it
once: :func:`test_the_names_are_the_ones_a_run_writes`), and each thing that may stand
there (a user's file, a link to a file, a dangling link, a link to a folder, a FIFO, a
folder). The rules, the same for every case:

- exit 2, one line on stderr naming the file, refused before the work (nothing on stdout);
- nothing outside ``--out`` changed, the planted thing left as it was, nothing written;
- an output folder where no file can be created: refused before the work, one line;
- a write that fails only at the end (a full disk): the answer printed all the same, one
  line naming the file, exit 2, no temporary file left.

Found by these tests and fixed: ``validate-policy`` wrote its dataset through a symbolic
link planted at ``<out>/<name>_dataset`` (``dataset.npz`` and ``manifest.json`` landed in the
folder the link pointed to, outside ``--out``); ``crossval``, ``validate`` and
``convergence`` refused a planted name only after their solves, and lost their answer
when a write failed at the end.
"""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import numpy as np
import pytest
from cli_here import run_here
from conftest import examples
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from small_scenes import strike_scene
from test_outputs_safe import KINDS, PRECIOUS, _plant, _unchanged, _unwritable

from hybridoc import outputs

posix = pytest.mark.skipif(os.name != "posix", reason="POSIX links and FIFOs")

SLUG = "sc-rel2"


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small strike scene (60 steps) and a zero policy, shared by the module."""
    d = tmp_path_factory.mktemp("inputs")
    (d / "scene.toml").write_text(strike_scene(SLUG, steps=60))
    (d / "pol.py").write_text("import numpy as np\n\ndef p(t, s):\n    return np.zeros(2)\n")
    import hybridoc

    np.save(d / "u.npy", np.asarray(hybridoc.as_ocp("bouncing-ball").u_guess, dtype=float))
    return d


def _commands(d: Path) -> dict[str, tuple[list[str], list[str]]]:
    """Command -> (its arguments before ``--out``, the names it writes under ``--out``);
    ``export``'s ``--out`` is a file, ``model.xml``."""
    scene, pol = str(d / "scene.toml"), f"{d / 'pol.py'}:p"
    b = "bouncing-ball"
    few = ["--samples", "2", "--workers", "1", "--no-progress"]

    def solve(m: str, *extra: str) -> tuple[list[str], list[str]]:
        figs = ["controls", "trajectory", *(["learning_curve"] if m == "gd" else [])]
        names = [f"{b}_solve_{m}.json", f"{b}_solve_{m}.npz"]
        return ["solve", b, "--method", m, *extra], names + [f"{b}_solve_{m}_{f}.png" for f in figs]

    return {
        "evaluate": (["evaluate", b], [f"{b}_evaluate.{x}" for x in ("json", "npz")]
                     + [f"{b}_evaluate_{f}.png" for f in ("controls", "trajectory")]),
        "solve-dt": solve("dt"),
        "solve-gd": solve("gd", "--iters", "20", "--starts", "1"),
        "solve-reference": solve("reference"),
        "reference": (["reference", b], [f"{b}_reference.{x}" for x in ("json", "npz")]
                      + [f"{b}_reference_{f}.png" for f in ("controls", "costates", "trajectory")]),
        "train-policy": (["train-policy", scene, "--samples", "2", "--iters", "1",
                          "--no-progress"],
                         [f"{SLUG}_train-policy.{x}" for x in ("json", "npz")]
                         + [f"{SLUG}_train-policy_report.json"]),
        "export": (["export", "mjcf", "single-collision"], ["model.xml"]),
        "crossval": (["crossval", b, "--no-progress"],
                     [f"{b}_crossval{e}" for e in (".json", "_controls.png",
                                                   "_trajectories.png", "_learning_curve.png")]),
        "validate": (["validate", b, "--controls", str(d / "u.npy")],
                     [f"{b}_validate{e}" for e in (".json", "_controls.png", "_trajectories.png")]),
        "convergence": (["convergence", b, "--steps", "20", "40", "--methods", "dt"],
                        [f"{b}_convergence{e}" for e in (".json", ".png")]),
        "dataset": (["dataset", scene, *few], ["dataset.npz", "manifest.json"]),
        "validate-policy": (["validate-policy", scene, "--policy", pol, *few],
                            [f"{SLUG}_dataset", f"{SLUG}_dataset/dataset.npz",
                             f"{SLUG}_dataset/manifest.json",
                             f"{SLUG}_validate-policy.json", f"{SLUG}_validate-policy.npz",
                             f"{SLUG}_validate-policy_gap_hist.png",
                             f"{SLUG}_validate-policy_gap_scatter.png"]),
    }  # fmt: skip


COMMANDS = sorted(_commands(Path("x")))


def _precious(root: Path) -> Path:
    """A user's file outside the output folder, ``root/elsewhere/precious.txt``, that no
    command may touch."""
    outside = root / "elsewhere" / "precious.txt"
    outside.parent.mkdir()
    outside.write_bytes(PRECIOUS)
    return outside


def _run(d: Path, command: str, out: Path) -> tuple[object, list[str]]:
    args, _ = _commands(d)[command]
    target = out / "model.xml" if command == "export" else out
    done = run_here(*args, "--out", str(target))
    return done, done.stderr.strip().splitlines()


def _files_under(root: Path) -> set[Path]:
    """Every entry under ``root`` that is not a folder (links included)."""
    return {p for p in root.rglob("*") if p.is_symlink() or not p.is_dir()}


# (command, name, kind); a folder (or a link to one) where a folder goes is used: the
# dataset's folder of validate-policy, export's --out (FILE/<problem>.xml, its --help)
PLANTS = [
    (c, n, k)
    for c in COMMANDS
    for n in _commands(Path("x"))[c][1]
    for k in KINDS
    if not (k == "directory" and n == f"{SLUG}_dataset")
    and not (c == "export" and k in ("directory", "link-to-dir"))
]


@posix
@settings(
    max_examples=examples(30),
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(case=st.sampled_from(PLANTS))
def test_whatever_stands_at_an_output_name_is_refused_before_the_work(
    tmp_path_factory: pytest.TempPathFactory, files: Path, case: tuple[str, str, str]
) -> None:
    command, name, kind = case
    root = tmp_path_factory.mktemp("plant")
    outside = _precious(root)
    out = root / "out"
    at = out / name
    at.parent.mkdir(parents=True)
    _plant(at, kind, outside)
    before = _files_under(out)
    done, lines = _run(files, command, out)
    assert done.returncode == 2, (command, name, kind, done.stderr)
    assert len(lines) == 1 and str(at) in lines[0], lines  # one line naming the file
    assert lines[0].startswith("hybridoc: error: ")
    assert done.stdout == ""  # refused before the work
    _unchanged(at, kind, outside)
    assert sorted(p.name for p in outside.parent.iterdir()) == ["precious.txt"]
    assert _files_under(out) == before  # nothing written


@posix
@pytest.mark.parametrize("kind", ["link-to-dir", "dangling-link", "user-file"])
def test_validate_policy_never_writes_its_dataset_through_a_link(
    tmp_path: Path, files: Path, kind: str
) -> None:
    # found by the test above: a link at <out>/<name>_dataset took dataset.npz and
    # manifest.json into the folder it pointed to (exit 0)
    outside = _precious(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    at = out / f"{SLUG}_dataset"
    _plant(at, kind, outside)
    done, lines = _run(files, "validate-policy", out)
    assert done.returncode == 2 and done.stdout == ""
    assert len(lines) == 1 and str(at) in lines[0], lines
    assert sorted(p.name for p in outside.parent.iterdir()) == ["precious.txt"]
    _unchanged(at, kind, outside)


@posix
@pytest.mark.parametrize("command", ["crossval", "validate", "convergence"])
def test_the_validation_commands_refuse_a_link_before_their_solves(
    tmp_path: Path, files: Path, command: str
) -> None:
    # found by the tests above: they solved first (crossval: three methods) and then
    # refused, losing the answer
    outside = _precious(tmp_path)
    out = tmp_path / "out"
    out.mkdir()
    at = out / _commands(files)[command][1][0]
    _plant(at, "link-to-file", outside)
    done, lines = _run(files, command, out)
    assert done.returncode == 2 and done.stdout == ""
    assert len(lines) == 1 and str(at) in lines[0], lines  # no "solving ..." line before it
    _unchanged(at, "link-to-file", outside)


@posix
@pytest.mark.parametrize("command", COMMANDS)
def test_an_unwritable_output_folder_is_refused_before_the_work(
    tmp_path: Path, files: Path, command: str
) -> None:
    d = _unwritable(tmp_path)
    done, lines = _run(files, command, d)
    assert done.returncode == 2, done.stderr
    assert done.stdout == ""
    assert len(lines) == 1 and "cannot write in" in lines[0] and str(d) in lines[0], lines


ERRNOS = [errno.ENOSPC, errno.EIO, errno.EDQUOT, errno.EROFS]
# the commands whose answer is the result of work, printed whatever becomes of the files
# (export's answer is its file; the dataset's, its files: tested below)
ANSWERS = [
    c for c in COMMANDS if c not in ("export", "dataset", "crossval", "convergence")
] + [pytest.param(c, marks=pytest.mark.slow) for c in ("crossval", "convergence")]  # fmt: skip


def _failing_writes(monkeypatch: pytest.MonkeyPatch, code: int) -> None:
    def failing(*args: object, **kwargs: object) -> None:
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(outputs, "_replace", failing)  # every rename of an output fails


@pytest.mark.parametrize("command", ANSWERS)
def test_a_write_that_fails_at_the_end_still_prints_the_answer(
    tmp_path: Path, files: Path, command: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    code = ERRNOS[COMMANDS.index(command) % len(ERRNOS)]
    _failing_writes(monkeypatch, code)
    out = tmp_path / "out"
    args, _ = _commands(files)[command]
    done = run_here(*args, "--json", "--out", str(out))
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2, done.stderr
    assert json.loads(done.stdout)  # the answer is out, whole
    assert "cannot write" in lines[-1] and os.strerror(code) in lines[-1], lines
    assert str(out) in lines[-1]
    assert not [p for p in out.rglob("*") if p.name.endswith(".tmp")]


def test_export_that_cannot_write_its_file_says_so_in_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _failing_writes(monkeypatch, errno.ENOSPC)
    done = run_here("export", "mjcf", "single-collision", "--out", str(tmp_path / "m.xml"))
    assert done.returncode == 2
    (line,) = done.stderr.strip().splitlines()
    assert str(tmp_path / "m.xml") in line and os.strerror(errno.ENOSPC) in line
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_dataset_whose_last_write_fails_is_completed_by_a_rerun(
    tmp_path: Path, files: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from hybridoc.workflows import datasets as dsmod

    atomic = dsmod._atomic_write

    def full_at_the_end(path: Path, data: bytes) -> None:
        if path.name == dsmod.DATA_FILE:
            raise dsmod.HybridocError(f"cannot write {str(path)!r}: {os.strerror(errno.ENOSPC)}")
        atomic(path, data)

    args, _ = _commands(files)["dataset"]
    out = tmp_path / "ds"
    with monkeypatch.context() as mp:
        mp.setattr(dsmod, "_atomic_write", full_at_the_end)
        done = run_here(*args, "--out", str(out))
    assert done.returncode == 2
    line = done.stderr.strip().splitlines()[-1]
    assert str(out / "dataset.npz") in line and os.strerror(errno.ENOSPC) in line
    assert not (out / "dataset.npz").exists()
    done = run_here(*args, "--json", "--out", str(out))  # the shards kept: resumed
    assert done.returncode in (0, 1), done.stderr
    assert json.loads(done.stdout)["samples"] == 2 and (out / "dataset.npz").is_file()


@pytest.mark.slow
@pytest.mark.parametrize("command", COMMANDS)
def test_the_names_are_the_ones_a_run_writes(tmp_path: Path, files: Path, command: str) -> None:
    # the table above against a clean run (slow: every command's whole work)
    out = tmp_path / "out"
    out.mkdir()
    done, _ = _run(files, command, out)
    assert done.returncode in (0, 1), done.stderr
    written = {str(p.relative_to(out)) for p in out.rglob("*") if p.name != outputs.RECORD}
    assert written == set(_commands(files)[command][1])
