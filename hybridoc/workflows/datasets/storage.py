"""Reference datasets, their files (:mod:`hybridoc.workflows.datasets`): reproducible
``.npz`` bytes, atomic writes, the run's lock, the shard folder and its chunk files."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import io
import os
import re
import secrets
import warnings
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from hybridoc.errors import HybridocError

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: runs are not locked
    fcntl = None  # type: ignore[assignment]

DATA_FILE = "dataset.npz"
MANIFEST_FILE = "manifest.json"
SHARD_DIR = "shards"
SHARD_MARK = ".hybridoc-shards"
_MARK_TEXT = (
    "hybridoc-dataset-shards/1\n"
    "Unfinished chunks of 'hybridoc dataset'; it removes them when the dataset is written.\n"
)
LOCK_FILE = ".hybridoc-dataset.lock"
SPEC_KEY = "_spec"
"""A shard's extra column: the SHA-256 of the settings and nominal solution it was
computed with."""
CHUNK_NAME = re.compile(r"chunk-\d{6}\.npz")
_TMP_NAME = re.compile(r"\.(?P<name>.+)\.\d+\.[0-9a-f]{8}\.tmp")
"""Names of :func:`atomic_write`'s temporaries (and of a shard folder being made)."""
COLUMNS = frozenset(
    "index x0 targets status method message cost terminal_cost running_cost residual "
    "sequence n_events event_times multipliers approach_speeds controls "
    "control_coefficients phase_starts phase_states phase_costates states_minus "
    "costates_minus final_state final_costate lambda0".split()
)
"""The columns of a dataset (module notes)."""


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """``arrays`` as ``.npz`` bytes, byte for byte reproducibly (fixed zip timestamps,
    sorted names)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for name in sorted(arrays):
            arr = np.ascontiguousarray(arrays[name])
            body = io.BytesIO()
            np.lib.format.write_array(body, arr, allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.external_attr = 0o644 << 16
            zf.writestr(info, body.getvalue())
    return buf.getvalue()


def write_npz(path: Path, arrays: dict[str, np.ndarray]) -> str:
    """Write ``arrays`` as ``.npz`` (:func:`npz_bytes`) atomically; returns the SHA-256 of
    the file."""
    data = npz_bytes(arrays)
    atomic_write(path, data)
    return hashlib.sha256(data).hexdigest()


def parse_npz(data: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _tmp_name(path: Path) -> Path:
    """A temporary name next to ``path`` that no other process or call uses."""
    return path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):  # not every file system syncs a directory
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file of a unique name in the same
    directory, synced and renamed over it: readers and concurrent writers see the old file
    or the new one, never a part; a crash leaves at most a temporary (:func:`sweep`)."""
    tmp = _tmp_name(path)
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise HybridocError(f"cannot write {str(path)!r}: {exc.strerror or exc}") from None
    _fsync_dir(path.parent)


def sweep(folder: Path, files: Callable[[str], bool], dirs: Callable[[str], bool]) -> None:
    """Remove the temporaries a killed run left in ``folder``: files ``.NAME.PID.HEX.tmp``
    with ``files(NAME)`` true and, with ``dirs(NAME)`` true, shard folders that were being
    made (only our marker inside). Called with the lock held, so no run is writing them."""
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return
    for e in entries:
        m = _TMP_NAME.fullmatch(e.name)
        if m is None:
            continue
        with contextlib.suppress(OSError):
            if e.is_dir(follow_symlinks=False) and dirs(m["name"]):
                sweep(Path(e.path), lambda n: n == SHARD_MARK, lambda n: False)
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(os.path.join(e.path, SHARD_MARK))
                os.rmdir(e.path)  # fails, and keeps it, if anything else is inside
            elif e.is_file(follow_symlinks=False) and files(m["name"]):
                os.unlink(e.path)


# ---------------------------------------------------------------------------- files we own

_HELD_LOCKS: set[int] = set()


def _drop_inherited_locks() -> None:
    # a forked child (pool worker, the reference's search pool) shares the lock's open file
    # description; closing its copy keeps a child that outlives the run from holding the lock
    for fd in _HELD_LOCKS:
        with contextlib.suppress(OSError):
            os.close(fd)
    _HELD_LOCKS.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_drop_inherited_locks)


_NO_LOCKS = {errno.ENOSYS, errno.EOPNOTSUPP, errno.ENOLCK}
"""``flock`` errors of a file system without locks (not of a lock held by another run)."""


@contextlib.contextmanager
def locked(out: Path) -> Iterator[None]:
    """Hold the lock of the output directory ``out`` (``flock`` on :data:`LOCK_FILE`,
    without waiting) for the block, and remove the lock file at its end.

    Raises
    ------
    HybridocError
        Another run holds it, or it cannot be taken.
    """
    path = out / LOCK_FILE
    if fcntl is None:  # pragma: no cover
        yield
        return
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise HybridocError(f"cannot create {str(path)!r}: {exc.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if isinstance(exc, BlockingIOError):
                raise HybridocError(
                    f"another hybridoc dataset run holds the lock on {str(out)!r} "
                    f"({LOCK_FILE}); wait for it to end or choose another --out"
                ) from None
            if exc.errno in _NO_LOCKS:
                # some network file systems (Lustre without -o flock, some NFS/SMB mounts)
                # have no locks at all: run, but say what is not protected
                warnings.warn(
                    f"the file system of {str(out)!r} does not support locks "
                    f"({exc.strerror}): running without the lock on the folder; do not "
                    "start a second run into it until this one ends",
                    UserWarning,
                    stacklevel=3,
                )
                with contextlib.suppress(OSError):
                    path.unlink()
                yield
                return
            raise HybridocError(f"cannot lock {str(path)!r}: {exc.strerror}") from None
        # the run before may have removed the file as it ended, after we opened it: the
        # lock counts only on the file that is at the path now
        try:
            if os.path.samestat(os.fstat(fd), os.stat(path)):
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    _HELD_LOCKS.add(fd)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            path.unlink()  # still holding it, so no other run has it
        _HELD_LOCKS.discard(fd)
        fcntl.flock(fd, fcntl.LOCK_UN)
        os.close(fd)


def is_ours(folder: Path) -> bool:
    """Whether ``folder`` is a shard folder made by :func:`shard_dir` (its marker)."""
    try:
        with open(folder / SHARD_MARK, encoding="utf-8") as f:
            return f.readline() == _MARK_TEXT.splitlines(keepends=True)[0]
    except (OSError, UnicodeDecodeError):
        return False


def shard_dir(out: Path, resuming: bool = False) -> Path:
    """The shard folder of ``out``: made with its marker in one rename (a kill leaves no
    unmarked folder of ours), or ours already.

    ``resuming``: ``out`` holds our manifest of an unfinished run with the same settings.
    A run of an older hybridoc (no marker) left a ``shards/`` there holding nothing but
    chunk files; it is adopted (marked), and its chunks are checked like any other.

    Raises
    ------
    HybridocError
        ``out/shards`` exists and is not ours: nothing in it is touched.
    """
    d = out / SHARD_DIR
    if resuming and d.is_dir() and not d.is_symlink() and not is_ours(d):
        names = os.listdir(d)
        if all(CHUNK_NAME.fullmatch(n) or _TMP_NAME.fullmatch(n) for n in names):
            (d / SHARD_MARK).write_text(_MARK_TEXT, encoding="utf-8")
    if not d.exists() and not d.is_symlink():
        tmp = _tmp_name(d)
        try:
            tmp.mkdir()
            fd = os.open(tmp / SHARD_MARK, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(_MARK_TEXT)
            os.rename(tmp, d)
        except OSError as exc:
            sweep(out, lambda n: False, lambda n: n == SHARD_DIR)
            raise HybridocError(f"cannot create {str(d)!r}: {exc.strerror or exc}") from None
    elif not (d.is_dir() and not d.is_symlink() and is_ours(d)):
        raise HybridocError(
            f"{str(d)!r} exists and was not made by 'hybridoc dataset' (it has no "
            f"{SHARD_MARK} marker); hybridoc never deletes files it did not write: move it "
            "away or choose another --out"
        )
    return d


def remove_shards(d: Path, say: Callable[[str], None]) -> None:
    """Remove what the runs wrote in the shard folder ``d`` (chunks, temporaries, the marker
    last) and then the folder if nothing else is left in it. The dataset is complete by
    then: a failure is said, not raised."""
    try:
        for e in list(os.scandir(d)):
            m = _TMP_NAME.fullmatch(e.name)
            if e.is_file(follow_symlinks=False) and (
                CHUNK_NAME.fullmatch(e.name) or (m and CHUNK_NAME.fullmatch(m["name"]))
            ):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(e.path)
        others = sorted(n for n in os.listdir(d) if n != SHARD_MARK)
        if others:
            say(f"kept {d}: it holds files that hybridoc did not write ({', '.join(others[:3])})")
            return
        os.unlink(d / SHARD_MARK)
        os.rmdir(d)
    except OSError as exc:
        say(f"cannot remove {d}: {exc.strerror or exc}")


def read_shard(
    path: Path, indices: list[int], spec_hash: str
) -> tuple[dict[str, np.ndarray] | None, str]:
    """The columns of the finished chunk ``path`` of ``indices``, or ``None`` and why it
    cannot be used ("" when it does not exist)."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        return None, ""
    except OSError as exc:
        return None, f"cannot be read ({exc.strerror})"
    try:
        cols = parse_npz(data)
    except Exception as exc:  # truncated or damaged: whatever numpy or zipfile raise
        return None, f"is damaged ({type(exc).__name__}: {exc})"
    if set(cols) != COLUMNS | {SPEC_KEY}:
        return None, "has other columns"
    if cols.pop(SPEC_KEY).tolist() != [spec_hash]:
        return None, "was computed with other settings"
    n = len(indices)
    if cols["index"].dtype.kind != "i" or not np.array_equal(cols["index"], indices):
        return None, f"holds other draws than {indices[0]} to {indices[-1]}"
    if any(a.ndim == 0 or a.shape[0] != n for a in cols.values()):
        return None, f"does not have {n} rows in every column"
    return cols, ""
