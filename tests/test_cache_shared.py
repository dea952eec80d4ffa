"""The code cache (``HYBRIDOC_CACHE``) in a shared folder, and odd files at its names.

Issue #32: a cache pointed at a shared sticky folder (mode 1777, like /tmp) was
re-permissioned to 0700, locking every other user out of it; FIFOs at the cache's record
names made ``solve`` wait forever. A folder is never re-permissioned (one that is not
private is refused, with a warning), and only regular files are opened in it.
"""

from __future__ import annotations

import hashlib
import os
import stat
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import casadi as ca
import pytest

from hybridoc import compiled
from hybridoc.solvers import codegen

posix = pytest.mark.skipif(os.name != "posix", reason="POSIX folders, modes and FIFOs")


@pytest.fixture
def fresh(monkeypatch: pytest.MonkeyPatch) -> None:
    """Compiled code on, with the one-time warnings forgotten (no compiler is needed: a
    folder is judged before anything is compiled)."""
    monkeypatch.setenv("HYBRIDOC_CODEGEN", "1")
    monkeypatch.setattr(compiled, "compiler", lambda: "cc")
    monkeypatch.setattr(compiled, "_WARNED", set())


def _fn(name: str = "shared_probe") -> ca.Function:
    x = ca.SX.sym("x")
    return ca.Function(name, [x], [ca.sin(x) + x])


@posix
@pytest.mark.parametrize("mode", [0o1777, 0o777, 0o770, 0o2775], ids=oct)
def test_a_shared_cache_folder_is_refused_and_never_re_permissioned(
    fresh: None, monkeypatch: pytest.MonkeyPatch, tmp_path: Path, mode: int
) -> None:
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(mode)
    (shared / "someone-elses.txt").write_text("theirs")
    monkeypatch.setenv("HYBRIDOC_CACHE", str(shared))
    fn = _fn()
    with pytest.warns(codegen.CacheWarning) as caught:
        acc = codegen.Accelerated(fn, hot=0)
    (w,) = caught  # one warning: why, and what to do
    text = str(w.message)
    assert "not private" in text and "other users can write" in text and "HYBRIDOC_CACHE" in text
    assert stat.S_IMODE(shared.stat().st_mode) == mode  # left as it was
    assert not acc.compiled and acc._calls_left == -1  # compiled code off: nothing built
    assert float(acc(0.25)) == float(fn(0.25))  # the virtual machine answers
    assert sorted(p.name for p in shared.iterdir()) == ["someone-elses.txt"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # said once
        codegen.Accelerated(fn, hot=0)


@posix
def test_a_new_cache_folder_is_made_private(
    fresh: None, monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    cache = tmp_path / "a" / "cache"
    monkeypatch.setenv("HYBRIDOC_CACHE", str(cache))
    with compiled._private_dir(create=True) as (dfd, refused):
        assert dfd is not None and not refused
    assert stat.S_IMODE(cache.stat().st_mode) == 0o700


def _fifo_script(cache: Path, what: str) -> str:
    return textwrap.dedent(
        f"""
        import os, warnings
        os.environ["HYBRIDOC_CACHE"] = {str(cache)!r}
        os.environ["HYBRIDOC_CODEGEN"] = "1"
        import casadi as ca
        from hybridoc import compiled
        compiled.compiler = lambda: "cc"
        x = ca.SX.sym("x")
        fn = ca.Function("fifo_probe", [x], [ca.sin(x) + x])
        warnings.simplefilter("ignore")
        if {what!r} == "load":
            acc = compiled.Accelerated(fn, hot=10**9)
            print("compiled" if acc.compiled else "vm", float(acc(0.25)))
        else:
            print("libraries", compiled.cache_info()["libraries"])
        """
    )


@posix
@pytest.mark.parametrize("what", ["load", "info"])
@pytest.mark.parametrize("at", ["record", "library"])
def test_a_fifo_at_a_cache_name_never_blocks(tmp_path: Path, what: str, at: str) -> None:
    cache = tmp_path / "cache"
    cache.mkdir(mode=0o700)
    key = hashlib.sha256(_fn("fifo_probe").serialize().encode()).hexdigest()[:24]
    lib = cache / f"fifo_probe_{key}.so"
    record = cache / f"{lib.name}.sha256"
    if at == "record":
        lib.write_bytes(b"\x7fELF not really")
        os.mkfifo(record)
    else:
        os.mkfifo(lib)
        record.write_text(f"{hashlib.sha256(b'').hexdigest()}  {lib.name}\n")
    # a subprocess: on the code before the fix it waits forever in open(), which no thread
    # of this process could be stopped from
    try:
        done = subprocess.run(
            [sys.executable, "-c", _fifo_script(cache, what)],
            capture_output=True,
            text=True,
            timeout=90,
            cwd=Path(__file__).resolve().parents[1],
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"a FIFO at the {at}'s name made the cache wait ({what})")
    assert done.returncode == 0, done.stderr
    if what == "load":
        assert done.stdout.split()[0] == "vm"  # nothing loaded from a FIFO
    else:
        assert done.stdout.split() == ["libraries", "1" if at == "record" else "0"]


@posix
def test_read_own_opens_only_regular_files(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "file").write_bytes(b"data")
    os.symlink(tmp_path / "file", tmp_path / "link")
    dfd = os.open(tmp_path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        assert compiled._read_own(dfd, "fifo") is None
        assert compiled._read_own(dfd, "link") is None
        got = compiled._read_own(dfd, "file")
        assert got is not None and got[0] == b"data"
        os.close(got[1])
    finally:
        os.close(dfd)


@posix
def test_cache_info_on_a_shared_folder_says_what_to_do(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from cli_here import run_here

    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o1777)
    monkeypatch.setenv("HYBRIDOC_CACHE", str(shared))
    done = run_here("cache", "info")
    assert done.returncode == 1
    (line,) = done.stderr.strip().splitlines()
    assert "not private" in line and "never changes a folder's mode" in line
    assert "HYBRIDOC_CACHE" in line
    assert stat.S_IMODE(shared.stat().st_mode) == 0o1777
