"""CasADi functions compiled to C once, cached on disk by hash, loaded; with a fallback.

The core of hybridoc's compiled code, in the model layer so that the judge
(:mod:`hybridoc.kernels`) and the solvers (:mod:`hybridoc.solvers.codegen`, which re-exports
this module) share one cache and one set of checks.

:class:`Accelerated` wraps a CasADi Function: calls go to CasADi's virtual machine until a
C version is ready, then to the C version. The C code comes from CasADi's
``CodeGenerator``; once a function has been called :data:`HOT_CALLS` times, the system C
compiler (``cc``, ``gcc`` or ``clang``; ``-O1 -ffp-contract=off``, so that the arithmetic is
the virtual machine's, bit for bit) builds it in a background thread, one compilation at a
time, into a cache folder keyed by a hash of the function's serialisation: a later run loads
the library at once. Without a compiler,
or when compilation fails, the virtual machine simply stays in use.

The cache is private and checked: its folder is created with mode 0700, and any folder is
used only while it is owned by the user and writable by nobody else. An existing folder is
never re-permissioned (a shared folder such as ``/tmp``, mode 1777, must stay open to its
other users): one that is not private is refused, with one warning saying why and what to do,
and compiled code is then off. Only regular files are opened in it (``lstat`` first, then a
non-blocking open without following links: a FIFO planted at a record's name cannot make a
run wait forever), and a library is loaded only when its
SHA-256 matches the one hybridoc recorded beside it when it built it (``<lib>.sha256``);
anything else is not loaded. The least recently used libraries are deleted when the cache
outgrows its bound. :func:`cache_info` and :func:`clear_cache` (``hybridoc cache info`` and
``hybridoc cache clear``) show and empty it.

Once loaded, a library is also bound through :mod:`ctypes` (:class:`NativeFunction`):
:meth:`Accelerated.call_numpy` then calls the generated C function on numpy buffers with
raw pointers and preallocated work arrays, without CasADi's ``Function`` call machinery
(which converts every input and output to a ``DM`` and costs more than the C code itself on
a loss of a few hundred steps).

Settings (environment): ``HYBRIDOC_CODEGEN=0`` turns it off; ``HYBRIDOC_CACHE`` sets the
cache folder (default ``~/.cache/hybridoc``); ``HYBRIDOC_CACHE_MAX_MB`` bounds its size
(default 500; ``0`` keeps no library on disk).
"""

# Threat model. Loading a library runs its machine code (constructors included) in this
# process, so a library is loaded only when
#   1. the cache folder is owned by the effective uid and has no group or world write bit:
#      no other local user can then create, replace or rename a file in it;
#   2. its bytes hash to the SHA-256 that hybridoc wrote, in that same folder, when it built
#      it: a file hybridoc did not write (planted while the folder was open to others, left
#      by an older hybridoc, cut short by a full disk) has no record or a wrong one, is not
#      loaded, and is deleted.
# Every file operation goes through a descriptor of the folder that was checked, and on
# Linux the library is loaded through /proc/self/fd/<folder>, so renaming the folder or
# swapping a parent after the check changes nothing. A process of the same user can rewrite
# both a library and its record; that is out of scope (it could as well edit hybridoc).

from __future__ import annotations

import atexit
import ctypes
import hashlib
import hmac
import os
import re
import shutil
import signal
import stat
import subprocess
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from hybridoc.children import popen_group

__all__ = [
    "DEFAULT_MAX_MB",
    "HOT_CALLS",
    "Accelerated",
    "CacheWarning",
    "NativeFunction",
    "cache_dir",
    "cache_info",
    "cache_limit",
    "check_cache_dir",
    "clear_cache",
    "compiler",
    "enabled",
    "evict",
    "wait_for_compilations",
]

_QUEUE_LOCK = threading.Lock()  # one compilation at a time: two cores are often all there is
HOT_CALLS = 50
"""Calls after which a function is compiled (see :class:`Accelerated`)."""
_BUILDS: list[threading.Thread] = []  # background compilations started, finished ones pruned
_BUILDS_LOCK = threading.Lock()
#: the C compilers running, each the leader of its own process group, with the pid of the
#: process that started it (a forked child inherits the set but must not kill them)
_COMPILERS: dict[subprocess.Popen[str], int] = {}
_COMPILE_TIMEOUT_S = 600.0
DEFAULT_MAX_MB = 500.0
"""Default bound of the cache's size in megabytes (``HYBRIDOC_CACHE_MAX_MB``)."""
_FLAGS = ["-O1", "-ffp-contract=off", "-fPIC", "-shared"]
_RECORD = ".sha256"
# the only names hybridoc writes: <function>_<24 hex>.so, its record, and their temporaries
_LIB_RE = re.compile(r"[A-Za-z_]\w*_[0-9a-f]{24}\.so")
_RECORD_RE = re.compile(_LIB_RE.pattern + re.escape(_RECORD))
_TMP_RE = re.compile(_LIB_RE.pattern + rf"(?:{re.escape(_RECORD)})?\.\d+\.tmp")
_STALE_TMP_S = 3600.0  # a temporary this old belongs to a build that died
_WARNED: set[str] = set()
_WARN_LOCK = threading.Lock()


class CacheWarning(UserWarning):
    """The code cache is not used (an unsafe folder) or a setting is ignored."""


def _warn_once(text: str) -> None:
    with _WARN_LOCK:
        if text in _WARNED:
            return
        _WARNED.add(text)
    warnings.warn(text, CacheWarning, stacklevel=2)


def enabled() -> bool:
    """Whether background compilation is on (``HYBRIDOC_CODEGEN`` not ``0``) and possible."""
    return (
        os.environ.get("HYBRIDOC_CODEGEN", "1") not in ("0", "false", "no")
        and os.name == "posix"  # the ownership checks and the .so libraries are POSIX
        and compiler() is not None
    )


def compiler() -> str | None:
    """The C compiler to use, or ``None``."""
    for name in (os.environ.get("CC", ""), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return name
    return None


def cache_dir() -> Path:
    """The folder of compiled libraries (``HYBRIDOC_CACHE``, default ``~/.cache/hybridoc``)."""
    root = os.environ.get("HYBRIDOC_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "hybridoc"


def cache_limit() -> int:
    """The bound of the cache's size in bytes (``HYBRIDOC_CACHE_MAX_MB``, default 500)."""
    text = os.environ.get("HYBRIDOC_CACHE_MAX_MB", "").strip()
    if not text:
        return int(DEFAULT_MAX_MB * 1e6)
    try:
        mb = float(text)
    except ValueError:
        mb = -1.0
    if not (0.0 <= mb < float("inf")):
        _warn_once(
            f"HYBRIDOC_CACHE_MAX_MB={text!r} is not a number of megabytes >= 0; "
            f"using {DEFAULT_MAX_MB:g}"
        )
        mb = DEFAULT_MAX_MB
    return int(mb * 1e6)


def _unsafe(st: os.stat_result) -> str | None:
    """Why a folder with this status must not be loaded from, or ``None``."""
    if not stat.S_ISDIR(st.st_mode):
        return "it is not a directory"
    if not hasattr(os, "geteuid"):
        return "its owner cannot be checked on this system"
    if st.st_uid != os.geteuid():
        return f"it is owned by uid {st.st_uid}, not by this user (uid {os.geteuid()})"
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return f"other users can write to it (mode {stat.S_IMODE(st.st_mode):04o})"
    return None


def check_cache_dir(path: str | Path | None = None) -> str | None:
    """Why the cache folder is unsafe to load libraries from, or ``None`` when it is safe.

    Parameters
    ----------
    path
        The folder; default :func:`cache_dir`. A folder that does not exist yet is safe
        (hybridoc creates it with mode 0700); an existing one is never re-permissioned.
    """
    p = cache_dir() if path is None else Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        return None
    except OSError as exc:
        return f"it cannot be read: {exc.strerror or exc}"
    return _unsafe(st)


@contextmanager
def _private_dir(create: bool) -> Iterator[tuple[int | None, bool]]:
    """A descriptor of the checked cache folder and whether it was refused: ``(fd, False)``,
    ``(None, False)`` when it does not exist, ``(None, True)`` when it is unsafe or
    unreadable (warned once)."""
    path = cache_dir()
    try:
        if create:
            # 0700: the libraries are nobody else's business, and nobody else may add one
            path.mkdir(mode=0o700, parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    except FileNotFoundError:
        yield None, False
        return
    except OSError as exc:
        _warn_once(f"the code cache {str(path)!r} cannot be opened ({exc}); compiled code is off")
        yield None, True
        return
    try:
        # never chmod an existing folder: it may be shared (a sticky /tmp, mode 1777), and
        # narrowing it would lock its other users out; a folder others can write is refused
        reason = _unsafe(os.fstat(fd))
        if reason is not None:
            _warn_once(
                f"the code cache {str(path)!r} is not private: {reason}; compiled code is "
                "not loaded from it (fix it with 'chmod 700' on a folder of your own, or "
                "set HYBRIDOC_CACHE to another folder)"
            )
            yield None, True
        else:
            yield fd, False
    finally:
        os.close(fd)


def _load_path(dfd: int, name: str) -> str:
    """The path that loads ``name`` from the folder open as ``dfd``: through /proc/self/fd
    where it exists (Linux), so that it is that folder and not whatever sits at its path now."""
    proc = f"/proc/self/fd/{dfd}"
    return f"{proc}/{name}" if os.path.isdir(proc) else str(cache_dir() / name)


def _read_own(dfd: int, name: str) -> tuple[bytes, int] | None:
    """The bytes of a regular file of this user in the folder, and its descriptor (open).

    Anything else at ``name`` is not opened: ``lstat`` first, then a non-blocking open that
    does not follow a link (a FIFO swapped in between cannot block), and the opened file must
    be the one that was checked."""
    try:
        before = os.stat(name, dir_fd=dfd, follow_symlinks=False)
        if not stat.S_ISREG(before.st_mode):
            return None
        fd = os.open(name, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK, dir_fd=dfd)
    except OSError:
        return None
    try:
        st = os.fstat(fd)
        if (
            not stat.S_ISREG(st.st_mode)
            or not os.path.samestat(st, before)
            or st.st_uid != os.geteuid()
            or st.st_mode & (stat.S_IWGRP | stat.S_IWOTH)
        ):
            os.close(fd)
            return None
        chunks = []
        while chunk := os.read(fd, 1 << 20):
            chunks.append(chunk)
        return b"".join(chunks), fd
    except OSError:
        os.close(fd)
        return None


def _verified(dfd: int, name: str, *, touch: bool = True) -> bool:
    """Whether library ``name`` matches the SHA-256 recorded when hybridoc built it; with
    ``touch``, a verified library's mtime is set to now (eviction goes by it)."""
    record = _read_own(dfd, name + _RECORD)
    if record is None:
        return False
    os.close(record[1])
    expected = record[0].split(b" ", 1)[0].strip()
    lib = _read_own(dfd, name)
    if lib is None:
        return False
    data, fd = lib
    try:
        ok = hmac.compare_digest(hashlib.sha256(data).hexdigest().encode(), expected)
        if ok and touch:
            try:
                os.utime(fd)
            except OSError:
                pass  # a read-only cache still works; its eviction order is then by age
        return ok
    finally:
        os.close(fd)


def _unlink(dfd: int, name: str) -> int:
    """Remove ``name`` from the folder; its size in bytes (0 if it was not there)."""
    try:
        size = os.stat(name, dir_fd=dfd, follow_symlinks=False).st_size
        os.unlink(name, dir_fd=dfd)
        return size
    except OSError:
        return 0


def _write_atomic(dfd: int, name: str, data: bytes) -> None:
    """Write ``name`` so that no reader ever sees it half-written."""
    tmp = f"{name}.{os.getpid()}.tmp"
    _unlink(dfd, tmp)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600, dir_fd=dfd)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]
    finally:
        os.close(fd)
    os.replace(tmp, name, src_dir_fd=dfd, dst_dir_fd=dfd)


def _entries(dfd: int) -> Iterator[tuple[str, os.stat_result]]:
    """The files hybridoc made in the folder (libraries, records, temporaries) that belong to
    this user, with their status."""
    with os.scandir(dfd) as it:
        for entry in it:
            name = entry.name
            if not (
                _LIB_RE.fullmatch(name) or _RECORD_RE.fullmatch(name) or _TMP_RE.fullmatch(name)
            ):
                continue
            try:
                st = entry.stat(follow_symlinks=False)
            except OSError:
                continue
            if stat.S_ISREG(st.st_mode) and st.st_uid == os.geteuid():
                yield name, st


def _evict(dfd: int, limit: int) -> list[str]:
    now = time.time()
    libs: dict[str, os.stat_result] = {}
    records: dict[str, os.stat_result] = {}
    removed: list[str] = []
    for name, st in list(_entries(dfd)):
        if _TMP_RE.fullmatch(name):
            if now - st.st_mtime > _STALE_TMP_S:
                _unlink(dfd, name)
                removed.append(name)
        elif name.endswith(_RECORD):
            records[name[: -len(_RECORD)]] = st
        else:
            libs[name] = st
    for lib, st in list(records.items()):
        # a record without its library: a build that died (the record is written first)
        if lib not in libs and now - st.st_mtime > _STALE_TMP_S:
            _unlink(dfd, lib + _RECORD)
            removed.append(lib + _RECORD)
            del records[lib]
    total = sum(st.st_size for st in (*libs.values(), *records.values()))
    for name in sorted(libs, key=lambda n: (libs[n].st_mtime, n)):  # least recently used first
        if total <= limit:
            break
        total -= _unlink(dfd, name) + _unlink(dfd, name + _RECORD)
        removed.append(name)
    return removed


def evict(limit: int | None = None) -> list[str]:
    """Delete the least recently used libraries until the cache holds at most ``limit``.

    A library's last use is its modification time, which a load sets to now. Runs after
    every compilation; only files hybridoc made are counted and deleted.

    Parameters
    ----------
    limit
        Bytes; default :func:`cache_limit`.

    Returns
    -------
    list of str
        The names of the files deleted (their records go with them).
    """
    limit = cache_limit() if limit is None else int(limit)
    with _private_dir(create=False) as (dfd, _):
        return [] if dfd is None else _evict(dfd, limit)


def cache_info() -> dict[str, Any]:
    """The state of the cache: what ``hybridoc cache info`` prints.

    Returns
    -------
    dict
        ``path``, ``exists``, ``mode`` (octal text or ``None``), ``safe`` and ``problem`` (why
        it is not safe, or ``None``), ``libraries`` (count), ``unverified`` (libraries
        without a matching record: they would not be loaded), ``size_bytes`` (libraries and
        records), ``limit_bytes``, ``other_files`` (files hybridoc did not make, left alone),
        ``enabled`` (whether compilation is on).
    """
    path = cache_dir()
    problem = check_cache_dir(path)
    info: dict[str, Any] = {
        "path": str(path),
        "exists": path.is_dir(),
        "mode": None,
        "safe": problem is None,
        "problem": problem,
        "libraries": 0,
        "unverified": 0,
        "size_bytes": 0,
        "limit_bytes": cache_limit(),
        "other_files": 0,
        "enabled": enabled(),
    }
    if not info["exists"] or not hasattr(os, "O_DIRECTORY"):
        return info  # without directory descriptors (Windows) nothing is compiled either
    try:
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    except OSError as exc:
        info.update(safe=False, problem=f"it cannot be read: {exc.strerror or exc}")
        return info
    try:
        info["mode"] = f"{stat.S_IMODE(os.fstat(fd).st_mode):04o}"
        ours = dict(_entries(fd))
        info["other_files"] = sum(1 for e in os.scandir(fd) if e.name not in ours)
        for name, st in ours.items():
            if _LIB_RE.fullmatch(name) or _RECORD_RE.fullmatch(name):
                info["size_bytes"] += st.st_size
            if _LIB_RE.fullmatch(name):
                info["libraries"] += 1
                info["unverified"] += not _verified(fd, name, touch=False)
    finally:
        os.close(fd)
    return info


def clear_cache() -> dict[str, Any]:
    """Delete the libraries hybridoc compiled and their records; nothing else.

    Only regular files of this user whose names are hybridoc's (``<function>_<hash>.so``,
    ``.so.sha256`` and their temporaries) are deleted, also from a folder that is not
    private; other files and the folder itself stay.

    Returns
    -------
    dict
        ``path``, ``removed`` (files deleted), ``freed_bytes``, ``other_files`` (left).
    """
    path = cache_dir()
    out: dict[str, Any] = {"path": str(path), "removed": 0, "freed_bytes": 0, "other_files": 0}
    if not hasattr(os, "O_DIRECTORY"):
        return out  # Windows: hybridoc compiles nothing there, so made nothing to clear
    try:
        fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    except FileNotFoundError:
        return out
    try:
        for name, _ in list(_entries(fd)):
            size = _unlink(fd, name)
            out["removed"] += 1
            out["freed_bytes"] += size
        out["other_files"] = sum(1 for _ in os.scandir(fd))
    finally:
        os.close(fd)
    return out


class NativeFunction:
    """A CasADi-generated C function called through :mod:`ctypes` on numpy arrays.

    The generated ``<name>(arg, res, iw, w, mem)`` is called with the data pointers of the
    numpy inputs and of freshly allocated outputs, and work arrays allocated once: no
    ``DM`` conversion, no per-call allocation inside CasADi. The numbers are the library's,
    bit for bit (it is the same machine code :func:`casadi.external` runs).

    Parameters
    ----------
    lib
        The loaded library.
    fn
        The CasADi function it was generated from (its name, input and output sparsity).

    Raises
    ------
    ValueError
        The library does not export the function as expected, uses another integer or
        float size, or an input is not dense (then the caller keeps CasADi's own call).
    """

    def __init__(self, lib: ctypes.CDLL, fn: ca.Function) -> None:
        name = fn.name()
        try:
            self._f = getattr(lib, name)
            work = getattr(lib, f"{name}_work")
            int_size = getattr(lib, "f_casadi_int_size", None)
            real_size = getattr(lib, "f_casadi_real_size", None)
        except AttributeError as exc:
            raise ValueError(f"the library does not export {name}: {exc}") from None
        # the generated code's casadi_int is long long unless redefined: check, never assume
        sizes = (8, 8)
        if int_size is not None and real_size is not None:
            int_size.restype = real_size.restype = ctypes.c_int
            sizes = (int(int_size()), int(real_size()))
        if sizes != (ctypes.sizeof(ctypes.c_longlong), 8):
            raise ValueError(f"casadi_int/real sizes {sizes} differ from long long/double")
        sz = [ctypes.c_longlong() for _ in range(4)]
        work.restype = ctypes.c_int
        if work(*[ctypes.byref(v) for v in sz]):
            raise ValueError(f"{name}_work failed")
        n_arg, n_res, n_iw, n_w = (int(v.value) for v in sz)
        self.n_in, self.n_out = fn.n_in(), fn.n_out()
        if n_arg < self.n_in or n_res < self.n_out:
            raise ValueError(f"{name}: work sizes smaller than its inputs and outputs")
        self._in_shapes: list[tuple[int, int]] = []
        for i in range(self.n_in):
            sp = fn.sparsity_in(i)
            if not sp.is_dense():
                raise ValueError(f"{name}: input {i} is not dense")
            self._in_shapes.append((sp.size1(), sp.size2()))
        # outputs: (shape, None) when dense, else the column-major positions of the nonzeros
        self._outs: list[tuple[tuple[int, int], np.ndarray | None]] = []
        for i in range(self.n_out):
            sp = fn.sparsity_out(i)
            where = None if sp.is_dense() else np.array(sp.find(), dtype=np.intp)
            self._outs.append(((sp.size1(), sp.size2()), where))
        self._sizes = (n_arg, n_res, n_iw, n_w)
        self._f.restype = ctypes.c_int
        self._f.argtypes = [ctypes.c_void_p] * 4 + [ctypes.c_int]
        self._lock = threading.Lock()
        # the lock holder's buffers, their pointers bound once (see __call__)
        self._in_bufs = [np.zeros(max(r * c, 1)) for r, c in self._in_shapes]
        self._out_bufs = [
            np.zeros(max(r * c if where is None else len(where), 1)) for (r, c), where in self._outs
        ]
        self._bound = self._bind(self._in_bufs, self._out_bufs)

    def _new_work(self) -> tuple[Any, Any, np.ndarray, np.ndarray]:
        n_arg, n_res, n_iw, n_w = self._sizes
        return (
            (ctypes.c_void_p * n_arg)(),
            (ctypes.c_void_p * n_res)(),
            np.zeros(max(n_iw, 1), dtype=np.longlong),
            np.zeros(max(n_w, 1)),
        )

    def bind(self, inputs: list[np.ndarray], outputs: list[np.ndarray]) -> Callable[[], int]:
        """A call of the C function on fixed buffers: what :class:`hybridoc.kernels.Num`
        does through CasADi's buffer API, without the per-call conversions of
        :meth:`__call__` (which cost 20 us, ten times a small kernel's arithmetic).

        Parameters
        ----------
        inputs, outputs
            One contiguous float64 array per input and per output, of its number of values
            (column-major); every output must be dense. They are kept alive by the returned
            callable, which reads and writes them in place, with work arrays of its own (one
            caller at a time: one per thread).

        Returns
        -------
        callable
            ``call() -> int``: evaluates, and returns the function's status (0: success).

        Raises
        ------
        ValueError
            A buffer of the wrong size, type or layout, or a sparse output.
        """
        if len(inputs) != self.n_in or len(outputs) != self.n_out:
            raise ValueError(f"expected {self.n_in} inputs and {self.n_out} outputs")
        sizes = [r * c for r, c in self._in_shapes] + [r * c for (r, c), _ in self._outs]
        for buf, size in zip([*inputs, *outputs], sizes, strict=True):
            if buf.dtype != np.float64 or buf.size != size or not buf.flags.c_contiguous:
                raise ValueError(f"a buffer of {buf.size} {buf.dtype} where {size} float64")
        if any(where is not None for _, where in self._outs):
            raise ValueError("a sparse output cannot be bound")
        return self._bind(inputs, outputs)

    def _bind(self, inputs: list[np.ndarray], outputs: list[np.ndarray]) -> Callable[[], int]:
        """:meth:`bind` without its checks (``outputs``: each output's nonzeros)."""
        n_arg, n_res, n_iw, n_w = self._sizes
        arg = (ctypes.c_void_p * n_arg)(*[b.ctypes.data for b in inputs])
        res = (ctypes.c_void_p * n_res)(*[b.ctypes.data for b in outputs])
        iw = np.zeros(max(n_iw, 1), dtype=np.longlong)
        w = np.zeros(max(n_w, 1))
        pointers = (ctypes.addressof(arg), ctypes.addressof(res), iw.ctypes.data, w.ctypes.data)
        keep = (arg, res, iw, w, list(inputs), list(outputs))
        f = self._f

        def call(_keep: tuple[Any, ...] = keep) -> int:  # _keep: the buffers outlive the call
            return int(f(*pointers, 0))

        return call

    def __call__(self, *inputs: np.ndarray) -> list[np.ndarray]:
        """The outputs, as column-major float64 arrays of the function's output shapes.

        Each input is anything that reshapes, in column-major order, to the function's
        input of the same place (a scalar, a vector, or an ``(n, m)`` array that is
        ``(m, n)`` C-ordered and transposed: no copy then).
        """
        if len(inputs) != self.n_in:
            raise TypeError(f"expected {self.n_in} inputs, got {len(inputs)}")
        if self._lock.acquire(blocking=False):
            try:
                return self._call_bound(inputs)
            finally:
                self._lock.release()
        # a concurrent caller (threads): buffers and work arrays of its own
        ins = []
        for x, shape in zip(inputs, self._in_shapes, strict=True):
            a = np.asarray(x, dtype=np.float64)
            if a.size != shape[0] * shape[1]:
                raise ValueError(f"an input of {a.size} values where {shape} was expected")
            ins.append(np.asfortranarray(a.reshape(shape, order="F")))
        outs = []
        bufs = []
        for shape, where in self._outs:
            if where is None:
                out = np.empty(shape, order="F")
                outs.append(out)
                bufs.append(out)
            else:
                outs.append(np.zeros(shape, order="F"))
                bufs.append(np.empty(max(len(where), 1)))
        arg, res, iw, w = self._new_work()
        for i, a in enumerate(ins):
            arg[i] = a.ctypes.data
        for i, b in enumerate(bufs):
            res[i] = b.ctypes.data
        rc = self._f(ctypes.addressof(arg), ctypes.addressof(res), iw.ctypes.data, w.ctypes.data, 0)
        if rc:
            raise RuntimeError(f"the compiled function returned the error code {rc}")
        for out, b, (_, where) in zip(outs, bufs, self._outs, strict=True):
            if where is not None and len(where):
                out.reshape(-1, order="F")[where] = b[: len(where)]
        return outs

    def _call_bound(self, inputs: tuple[Any, ...]) -> list[np.ndarray]:
        """:meth:`__call__` through the buffers bound once (the lock held): the inputs copied
        in, the outputs copied out; no pointer to take per call (each costs 1.5 us)."""
        for x, buf, shape in zip(inputs, self._in_bufs, self._in_shapes, strict=True):
            a = np.asarray(x, dtype=np.float64)
            if a.size != shape[0] * shape[1]:
                raise ValueError(f"an input of {a.size} values where {shape} was expected")
            buf[: a.size].reshape(shape, order="F")[...] = a.reshape(shape, order="F")
        rc = self._bound()
        if rc:
            raise RuntimeError(f"the compiled function returned the error code {rc}")
        outs = []
        for buf, (shape, where) in zip(self._out_bufs, self._outs, strict=True):
            if where is None:
                outs.append(buf[: shape[0] * shape[1]].reshape(shape, order="F").copy(order="F"))
            else:
                out = np.zeros(shape, order="F")
                out.reshape(-1, order="F")[where] = buf[: len(where)]
                outs.append(out)
        return outs


def _as_tuple(out: Any) -> tuple[Any, ...]:
    """A CasADi call's outputs as a tuple (one output comes back bare)."""
    return out if isinstance(out, tuple) else (out,)


def _run_compiler(cmd: list[str]) -> tuple[int, str]:
    """Run the C compiler in a process group of its own; its exit status and stderr.

    ``cc`` runs ``cc1`` and the assembler as children: a timeout, the exit of this process
    while it compiles (:func:`_stop_compilers`), or its death, even by SIGKILL
    (:func:`hybridoc.children.popen_group`), ends the whole group, where killing ``cc``
    alone left them running without a parent, loading the cores for minutes.
    """
    # under a supervisor that kills the group when this process dies, even by SIGKILL (no
    # atexit then): cc1 and the assembler must not compile on without it (issue #32)
    proc = popen_group(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    with _BUILDS_LOCK:
        _COMPILERS[proc] = os.getpid()
    try:
        _, stderr = proc.communicate(timeout=_COMPILE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        _kill_group(proc)
        proc.communicate()
        return -1, f"the C compiler took longer than {_COMPILE_TIMEOUT_S:.0f} s"
    finally:
        with _BUILDS_LOCK:
            _COMPILERS.pop(proc, None)
    return proc.returncode, stderr


def _kill_group(proc: subprocess.Popen[str]) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass  # already gone


@atexit.register
def _stop_compilers() -> None:
    """At exit, end the compilations this process started (its daemon threads die with it,
    and the library they would have written with them): the compilers must not outlive it."""
    with _BUILDS_LOCK:
        mine = [proc for proc, owner in _COMPILERS.items() if owner == os.getpid()]
    for proc in mine:
        _kill_group(proc)


def wait_for_compilations(timeout: float | None = None) -> bool:
    """Wait for the background compilations in flight, at most ``timeout`` seconds in all.

    A compilation runs in a daemon thread, so a process that exits before it ends loses it
    (no library is written) and its next run starts on the virtual machine again. A
    command about to exit calls this, after its output, so that the next run loads the
    library at once.

    Returns
    -------
    bool
        Whether no compilation is left running.
    """
    deadline = None if timeout is None else time.monotonic() + timeout
    with _BUILDS_LOCK:
        started = list(_BUILDS)
    for thread in started:
        left = None if deadline is None else max(deadline - time.monotonic(), 0.0)
        thread.join(left)
    with _BUILDS_LOCK:
        _BUILDS[:] = [t for t in _BUILDS if t.is_alive()]
        return not _BUILDS


class Accelerated:
    """A CasADi Function that switches to compiled C code once it is available.

    Parameters
    ----------
    fn
        The function.
    wait
        Compile in the foreground and use the result at once (benchmarks); default: in the
        background.
    vm
        What to call until the C version is ready, if not ``fn`` itself (e.g. ``fn`` mapped
        over threads, when ``fn`` is its serial map).
    hot
        Start compiling after this many calls (a function called a few times is not worth a
        compilation that competes for the cores); a verified library already in the cache is
        loaded at once.
    """

    def __init__(
        self,
        fn: ca.Function,
        *,
        wait: bool = False,
        vm: ca.Function | None = None,
        hot: int = HOT_CALLS,
    ) -> None:
        self.vm = fn
        self.fn = fn if vm is None else vm
        self.compiled = False
        self.error: str | None = None
        self.native: NativeFunction | None = None
        self._calls_left = -1  # counting down to the background compilation; -1: never
        if not enabled():
            return
        key = hashlib.sha256(fn.serialize().encode()).hexdigest()[:24]
        self._lib = cache_dir() / f"{fn.name()}_{key}.so"
        with _private_dir(create=False) as (dfd, refused):
            if refused:
                return  # an unsafe folder (warned): the virtual machine only
            if dfd is not None and not self._load(dfd) and _unlink(dfd, self._lib.name):
                # a library hybridoc did not record (or not as it is now): never loaded, and
                # made again; its record goes too
                _unlink(dfd, self._lib.name + _RECORD)
            if self.compiled:
                return
        if wait:
            self._build()
        elif hot <= 0:
            self._start()
        else:
            self._calls_left = int(hot)

    def __call__(self, *args: Any) -> Any:
        self.count()
        return self.fn(*args)

    def count(self) -> None:
        """Count one call made elsewhere (e.g. through CasADi's buffer API on ``vm``)
        towards the compilation: the :data:`HOT_CALLS`-th starts it in the background."""
        if self._calls_left > 0:
            self._calls_left -= 1
            if self._calls_left == 0:
                self._start()

    def call_numpy(self, *args: Any) -> list[np.ndarray]:
        """The outputs as numpy arrays (column-major, the function's shapes): through
        :class:`NativeFunction` once the C version is loaded and bound, else
        ``self(*args)`` (CasADi's call, counted towards the compilation)."""
        native = self.native
        if native is not None:
            return native(*args)
        return [np.asarray(out) for out in _as_tuple(self(*args))]

    def _start(self) -> None:
        self._calls_left = -1
        thread = threading.Thread(target=self._build, daemon=True)
        with _BUILDS_LOCK:  # started inside: a thread in the list can be joined
            _BUILDS[:] = [t for t in _BUILDS if t.is_alive()]
            thread.start()
            _BUILDS.append(thread)

    def _load(self, dfd: int) -> bool:
        """Load the library if the folder ``dfd`` holds a verified one."""
        name = self._lib.name
        if not _verified(dfd, name):
            return False
        path = _load_path(dfd, name)
        try:
            self.fn = ca.external(self.vm.name(), path)
        except RuntimeError as exc:  # verified yet not loadable (another compiler's ABI)
            self.error = str(exc)
            return False
        try:
            # the file casadi.external just loaded (dlopen hands back the same object)
            self.native = NativeFunction(ctypes.CDLL(path), self.vm)
        except (OSError, ValueError):
            self.native = None  # CasADi's own call of the library still serves
        self.compiled, self.error = True, None
        return True

    def _build(self) -> None:
        cc = compiler()
        if cc is None:
            return
        with _QUEUE_LOCK, _private_dir(create=True) as (dfd, _):
            if dfd is None:
                self.error = f"the code cache {str(cache_dir())!r} is not private"
                return
            if self._load(dfd):  # another process or object built it meanwhile
                return
            try:
                with tempfile.TemporaryDirectory() as tmp:
                    src = Path(tmp) / "f.c"
                    gen = ca.CodeGenerator("f.c", {"with_header": False})
                    gen.add(self.vm)
                    gen.generate(str(Path(tmp)) + os.sep)
                    out = Path(tmp) / "f.so"
                    returncode, stderr = _run_compiler(
                        [cc, *_FLAGS, str(src), "-o", str(out), "-lm"]
                    )
                    if returncode != 0:
                        self.error = stderr[-500:]
                        return
                    data = out.read_bytes()
                name = self._lib.name
                # the record first: a reader that sees the new library also sees its hash
                record = f"{hashlib.sha256(data).hexdigest()}  {name}\n".encode()
                _write_atomic(dfd, name + _RECORD, record)
                _write_atomic(dfd, name, data)
            except (OSError, subprocess.SubprocessError, RuntimeError) as exc:
                self.error = str(exc)
                return
            if not self._load(dfd) and self.error is None:
                self.error = f"the library {name} changed between its build and its load"
            _evict(dfd, cache_limit())
