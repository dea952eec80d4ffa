"""Every file hybridoc writes: atomically, never through a link, never over a user's file.

The rules (:doc:`/trust`, "Files hybridoc writes and reads"):

* A file is written to a temporary file of a unique name in its own folder
  (``.NAME.PID.HEX.tmp``), synced, then renamed over its name: a reader, or a run killed at
  any point, sees the old file or the new one, never a part of one.
* A symbolic link at an output's name is refused (one line naming it): hybridoc never writes
  through a link, nor replaces one. So is anything else that is not a regular file.
* An existing regular file is replaced only if hybridoc wrote it: each folder hybridoc
  writes into holds a record, :data:`RECORD` (``.hybridoc-outputs``), of the files it wrote
  there, each with its inode, size and modification time as written. A file that is not in
  the record, or no longer as recorded (replaced, edited or copied in since), is the user's
  and is refused, with one line naming it; nothing is written.
* :func:`check_folder` makes the output folder and checks that a file can be created in it,
  and :func:`check_targets` checks the output names, before a command starts its work: an
  unwritable folder or a refused name fails at once, not after a long solve. A write that
  fails at the end anyway (a full disk) is one :class:`~hybridoc.errors.HybridocError`
  naming the file.

Writers in the same folder take turns (``flock`` on the folder) to update the record.

Every JSON file hybridoc reads from a user (Solutions, dataset manifests, policies) is read
by :func:`read_json`: a regular file only (a FIFO cannot make it wait), bounded in size
(:data:`MAX_JSON_BYTES` unless a reader says less) and nesting (:data:`MAX_JSON_DEPTH`).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
import stat
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

from hybridoc.errors import HybridocError

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

__all__ = [
    "MAX_JSON_BYTES",
    "MAX_JSON_DEPTH",
    "RECORD",
    "OutputRefused",
    "check_folder",
    "check_subfolder",
    "check_targets",
    "parse_json",
    "read_json",
    "write_bytes",
    "write_text",
    "write_with",
]

#: The record of the files hybridoc wrote in a folder (a JSON object in that folder).
RECORD = ".hybridoc-outputs"
_RECORD_FORMAT = "hybridoc-outputs"
_MAX_RECORD_BYTES = 16 << 20
_DIR_FD = os.open in os.supports_dir_fd and hasattr(os, "O_DIRECTORY")
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


class OutputRefused(HybridocError):
    """An output name holds something hybridoc must not replace: a link, a file that is not
    a regular one, or a file hybridoc did not write."""


def check_folder(path: str | Path) -> Path:
    """Make the output folder ``path`` (and its parents) and check that hybridoc can create
    a file in it: what a command calls right after parsing, before its work.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    HybridocError
        It cannot be made, is not a folder, or no file can be created in it.
    """
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise HybridocError(f"output path {str(p)!r} is not a directory") from None
    except OSError as exc:
        raise HybridocError(
            f"cannot create output directory {str(p)!r}: {exc.strerror or exc}"
        ) from None
    if not p.is_dir():
        raise HybridocError(f"output path {str(p)!r} is not a directory")
    probe = p / _tmp_name("probe")
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW, 0o600)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise HybridocError(
            f"cannot write in output directory {str(p)!r}: {exc.strerror or exc}"
        ) from None
    return p


def check_subfolder(path: str | Path) -> Path:
    """:func:`check_folder` for a folder that hybridoc names inside an output folder
    (``validate-policy``'s ``<name>_dataset``): refused when a symbolic link or something
    other than a folder holds its name, since hybridoc would write through it (files outside
    the output folder).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    OutputRefused
        A link, or something that is not a folder, at ``path``.
    HybridocError
        As :func:`check_folder`.
    """
    p = Path(path)
    try:
        st = os.lstat(p)
    except FileNotFoundError:
        return check_folder(p)
    except OSError as exc:  # a parent that is a file, one that cannot be read
        raise HybridocError(f"cannot write in {str(p)!r}: {exc.strerror or exc}") from None
    if stat.S_ISLNK(st.st_mode):
        raise OutputRefused(
            f"{str(p)!r} is a symbolic link: hybridoc never writes through a link; remove it "
            "or choose another output folder"
        )
    if not stat.S_ISDIR(st.st_mode):
        raise OutputRefused(
            f"{str(p)!r} exists and is not a directory: hybridoc writes no output there; "
            "remove it or choose another output folder"
        )
    return check_folder(p)


def check_targets(*paths: str | Path) -> None:
    """Check, before the work, that each of ``paths`` may be written: nothing there, or a
    regular file hybridoc wrote (module notes). Folders that do not exist yet pass.

    Raises
    ------
    OutputRefused
        The first name that holds a link, something that is not a regular file, or a file
        hybridoc did not write.
    """
    for path in paths:
        p = Path(path)
        try:
            with _folder(p.parent, create=False, lock=False) as dfd:
                _check(dfd, p)
        except FileNotFoundError:
            continue  # made when it is written
        except OSError as exc:  # a parent that is a file, one that cannot be read
            raise HybridocError(f"cannot write {str(p)!r}: {exc.strerror or exc}") from None


def write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` by the rules of the module notes; returns ``path``."""
    return write_with(path, lambda fh: fh.write(data))


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` by the rules of the module notes; returns ``path``."""
    return write_bytes(path, text.encode("utf-8"))


def write_with(path: str | Path, writer: Callable[[IO[bytes]], Any]) -> Path:
    """Write ``path`` by the rules of the module notes with ``writer(file)``, which writes
    the contents to a binary file object (``np.savez``, ``Figure.savefig``...); the parent
    folders are made.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    OutputRefused
        ``path`` holds a link, something that is not a regular file, or a file hybridoc did
        not write: nothing is written.
    HybridocError
        The file cannot be written (the message names it; the old file, if any, stays).
    """
    p = Path(path)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise HybridocError(
            f"cannot create output directory {str(p.parent)!r}: {exc.strerror or exc}"
        ) from None
    try:
        with _folder(p.parent, create=True, lock=True) as dfd:
            _check(dfd, p)
            tmp = _tmp_name(p.name)
            try:
                fd = _open(dfd, p.parent, tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
                with os.fdopen(fd, "wb") as fh:
                    writer(fh)
                    fh.flush()
                    os.fsync(fh.fileno())
                    st = os.fstat(fh.fileno())
                _replace(dfd, p.parent, tmp, p.name)
            except BaseException:
                with contextlib.suppress(OSError):
                    _unlink(dfd, p.parent, tmp)
                raise
            _record(dfd, p.parent, p.name, st)
            if dfd is not None:
                with contextlib.suppress(OSError):  # not every file system syncs a folder
                    os.fsync(dfd)
    except OSError as exc:
        raise HybridocError(f"cannot write {str(p)!r}: {exc.strerror or exc}") from None
    return p


# ---------------------------------------------------------------------------- reading JSON
#: The deepest nesting of arrays and objects accepted in a JSON file hybridoc reads from a
#: user (Solutions, dataset manifests, policies): hybridoc writes at most a few levels.
MAX_JSON_DEPTH = 64
#: The largest JSON file hybridoc reads from a user, by default.
MAX_JSON_BYTES = 64 << 20

_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"', re.DOTALL)


def _json_depth(raw: bytes) -> int:
    """The deepest nesting of ``[``/``{`` in JSON text, outside strings (no recursion)."""
    import numpy as np  # here: the command line's parser imports this module, not numpy

    skeleton = np.frombuffer(_JSON_STRING.sub(b'""', raw), dtype=np.uint8)
    steps = np.zeros(skeleton.shape, dtype=np.int64)
    steps[(skeleton == ord("[")) | (skeleton == ord("{"))] = 1
    steps[(skeleton == ord("]")) | (skeleton == ord("}"))] = -1
    return int(np.cumsum(steps).max(initial=0))


def parse_json(
    raw: bytes,
    where: str,
    *,
    max_bytes: int = MAX_JSON_BYTES,
    max_depth: int = MAX_JSON_DEPTH,
    error: type[HybridocError] = HybridocError,
) -> Any:
    """Parse JSON from a user, bounded in size and nesting.

    Parameters
    ----------
    raw
        The file's bytes (UTF-8).
    where
        What it is, for the messages (``"policy file 'p.json'"``).
    max_bytes, max_depth
        The bounds: more bytes, or arrays and objects nested deeper, are refused before
        parsing (a file nested 200 000 deep would exhaust the parser's recursion).
    error
        The exception class raised.

    Raises
    ------
    HybridocError
        ``error``: too large, too deeply nested, or not valid UTF-8 JSON; one line.
    """
    if len(raw) > max_bytes:
        raise error(f"{where} is larger than {max_bytes} bytes: refused")
    depth = _json_depth(raw)
    if depth > max_depth:
        raise error(
            f"{where} nests arrays and objects {depth} deep, more than the {max_depth} "
            "accepted: not a file hybridoc wrote"
        )
    try:
        return json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise error(f"{where} is not valid JSON: {first}") from None


def read_json(
    path: str | Path,
    where: str | None = None,
    *,
    max_bytes: int = MAX_JSON_BYTES,
    max_depth: int = MAX_JSON_DEPTH,
    error: type[HybridocError] = HybridocError,
) -> Any:
    """Read a JSON file from a user: a regular file only (``lstat`` first, then a
    non-blocking open, so that a FIFO cannot make hybridoc wait), bounded in size and
    nesting (:func:`parse_json`).

    Raises
    ------
    HybridocError
        ``error``: missing, not a regular file, unreadable, too large, too deeply nested or
        not valid JSON; one line naming the file.
    """
    p = Path(path)
    where = where or f"{str(p)!r}"
    try:
        st = os.stat(p)  # a link to a regular file is read: reading through it is harmless
    except FileNotFoundError:
        raise error(f"{where} does not exist") from None
    except OSError as exc:
        raise error(f"cannot read {where}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{where} is not a regular file")
    if st.st_size > max_bytes:
        raise error(f"{where} is larger than {max_bytes} bytes: refused")
    try:
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as fh:
            if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
                raise error(f"{where} is not a regular file")
            raw = fh.read(max_bytes + 1)
    except OSError as exc:
        raise error(f"cannot read {where}: {exc.strerror or exc}") from None
    return parse_json(raw, where, max_bytes=max_bytes, max_depth=max_depth, error=error)


# ---------------------------------------------------------------------------- internals


def _tmp_name(name: str) -> str:
    return f".{name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"


@contextlib.contextmanager
def _folder(folder: Path, *, create: bool, lock: bool) -> Iterator[int | None]:
    """A descriptor of ``folder`` (``None`` without directory descriptors), with the
    folder's ``flock`` held when ``lock``."""
    if not _DIR_FD:  # pragma: no cover - Windows: paths instead of descriptors
        if not folder.is_dir():
            raise FileNotFoundError(str(folder))
        yield None
        return
    dfd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        if lock and fcntl is not None:
            with contextlib.suppress(OSError):  # a file system without locks: no turns
                fcntl.flock(dfd, fcntl.LOCK_EX)
        yield dfd
    finally:
        os.close(dfd)  # releases the lock


def _open(dfd: int | None, folder: Path, name: str, flags: int, mode: int = 0o666) -> int:
    if dfd is None:  # pragma: no cover
        return os.open(folder / name, flags | _NOFOLLOW, mode)
    return os.open(name, flags | _NOFOLLOW, mode, dir_fd=dfd)


def _lstat(dfd: int | None, folder: Path, name: str) -> os.stat_result | None:
    try:
        if dfd is None:  # pragma: no cover
            return os.lstat(folder / name)
        return os.stat(name, dir_fd=dfd, follow_symlinks=False)
    except FileNotFoundError:
        return None


def _replace(dfd: int | None, folder: Path, src: str, dst: str) -> None:
    if dfd is None:  # pragma: no cover
        os.replace(folder / src, folder / dst)
    else:
        os.replace(src, dst, src_dir_fd=dfd, dst_dir_fd=dfd)


def _unlink(dfd: int | None, folder: Path, name: str) -> None:
    if dfd is None:  # pragma: no cover
        os.unlink(folder / name)
    else:
        os.unlink(name, dir_fd=dfd)


def _identity(st: os.stat_result) -> list[int]:
    return [int(st.st_ino), int(st.st_size), int(st.st_mtime_ns)]


def _check(dfd: int | None, path: Path) -> None:
    """Refuse (:class:`OutputRefused`) what must not be replaced at ``path``."""
    st = _lstat(dfd, path.parent, path.name)
    if st is None:
        return
    if stat.S_ISLNK(st.st_mode):
        raise OutputRefused(
            f"{str(path)!r} is a symbolic link: hybridoc never writes through a link nor "
            "replaces one; remove it or choose another output folder"
        )
    if not stat.S_ISREG(st.st_mode):
        raise OutputRefused(
            f"{str(path)!r} exists and is not a regular file: hybridoc writes no output "
            "there; remove it or choose another output folder"
        )
    if _read_record(dfd, path.parent).get(path.name) != _identity(st):
        raise OutputRefused(
            f"{str(path)!r} exists and was not written by hybridoc (or was changed since): "
            "hybridoc never overwrites a file it did not write; move it away or choose "
            "another output folder"
        )


def _read_record(dfd: int | None, folder: Path) -> dict[str, list[int]]:
    """The folder's record of the files hybridoc wrote there (empty if there is none, or if
    it is not a regular file of hybridoc's format)."""
    st = _lstat(dfd, folder, RECORD)
    if st is None or not stat.S_ISREG(st.st_mode) or st.st_size > _MAX_RECORD_BYTES:
        return {}
    try:
        fd = _open(dfd, folder, RECORD, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as fh:
            data = fh.read(_MAX_RECORD_BYTES + 1)
        obj = json.loads(data.decode("utf-8"))
    except (OSError, ValueError, RecursionError):
        return {}
    if not isinstance(obj, dict) or obj.get("format") != _RECORD_FORMAT:
        return {}
    files = obj.get("files")
    if not isinstance(files, dict):
        return {}
    return {
        k: v
        for k, v in files.items()
        if isinstance(k, str)
        and isinstance(v, list)
        and len(v) == 3
        and all(isinstance(x, int) for x in v)
    }


def _record(dfd: int | None, folder: Path, name: str, st: os.stat_result) -> None:
    """Add ``name`` as written (``st``) to the folder's record; entries whose files are gone
    or changed are dropped. Called with the folder's lock held."""
    files = _read_record(dfd, folder)
    files[name] = _identity(st)
    kept = {}
    for k, v in sorted(files.items()):
        now = _lstat(dfd, folder, k)
        if now is not None and stat.S_ISREG(now.st_mode) and _identity(now) == v:
            kept[k] = v
    at = _lstat(dfd, folder, RECORD)
    if at is not None and not stat.S_ISREG(at.st_mode):
        raise OutputRefused(
            f"{str(folder / RECORD)!r} (hybridoc's record of its outputs) is not a regular "
            "file; remove it"
        )
    text = json.dumps({"format": _RECORD_FORMAT, "version": 1, "files": kept})
    tmp = _tmp_name(RECORD)
    fd = _open(dfd, folder, tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(text.encode() + b"\n")
            fh.flush()
            os.fsync(fh.fileno())
        _replace(dfd, folder, tmp, RECORD)
    except BaseException:
        with contextlib.suppress(OSError):
            _unlink(dfd, folder, tmp)
        raise
