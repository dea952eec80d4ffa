"""CasADi functions compiled to C in the background, cached on disk, with a fallback.

:class:`Accelerated` wraps a CasADi Function: calls go to CasADi's virtual machine until a
C version is ready, then to the C version. The C code comes from CasADi's
``CodeGenerator``; once a function has been called :data:`HOT_CALLS` times, the system C
compiler (``cc``, ``gcc`` or ``clang``; ``-O1 -ffp-contract=off``, so that the arithmetic is
the virtual machine's, bit for bit) builds it in a background thread, one compilation at a
time, into a cache folder keyed by a hash of the function's serialisation: a later run loads
the library at once. Without a compiler,
or when compilation fails, the virtual machine simply stays in use.

Settings (environment): ``HYBRIDOC_CODEGEN=0`` turns it off; ``HYBRIDOC_CACHE`` sets the
cache folder (default ``~/.cache/hybridoc``).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path
from typing import Any

import casadi as ca

__all__ = ["HOT_CALLS", "Accelerated", "cache_dir", "compiler", "enabled"]

_QUEUE_LOCK = threading.Lock()  # one compilation at a time: two cores are often all there is
HOT_CALLS = 50
"""Calls after which a function is compiled (see :class:`Accelerated`)."""
_FLAGS = ["-O1", "-ffp-contract=off", "-fPIC", "-shared"]


def enabled() -> bool:
    """Whether background compilation is on (``HYBRIDOC_CODEGEN`` not ``0``) and possible."""
    return os.environ.get("HYBRIDOC_CODEGEN", "1") not in ("0", "false", "no") and (
        compiler() is not None
    )


def compiler() -> str | None:
    """The C compiler to use, or ``None``."""
    for name in (os.environ.get("CC", ""), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return name
    return None


def cache_dir() -> Path:
    """The folder of compiled libraries."""
    root = os.environ.get("HYBRIDOC_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "hybridoc"


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
        compilation that competes for the cores); a library already in the cache is loaded
        at once.
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
        self._calls_left = -1  # counting down to the background compilation; -1: never
        if not enabled():
            return
        key = hashlib.sha256(fn.serialize().encode()).hexdigest()[:24]
        self._lib = cache_dir() / f"{fn.name()}_{key}.so"
        if self._lib.exists():
            self._load()
            return
        if wait:
            self._build()
        elif hot <= 0:
            self._start()
        else:
            self._calls_left = int(hot)

    def __call__(self, *args: Any) -> Any:
        if self._calls_left > 0:
            self._calls_left -= 1
            if self._calls_left == 0:
                self._start()
        return self.fn(*args)

    def _start(self) -> None:
        self._calls_left = -1
        threading.Thread(target=self._build, daemon=True).start()

    def _load(self) -> None:
        try:
            self.fn = ca.external(self.vm.name(), str(self._lib))
            self.compiled = True
        except RuntimeError as exc:  # a broken or foreign library: compile it again
            self.error = str(exc)

    def _build(self) -> None:
        cc = compiler()
        if cc is None:
            return
        with _QUEUE_LOCK:
            if self._lib.exists():
                self._load()
                return
            try:
                self._lib.parent.mkdir(parents=True, exist_ok=True)
                with tempfile.TemporaryDirectory() as tmp:
                    src = Path(tmp) / "f.c"
                    gen = ca.CodeGenerator("f.c", {"with_header": False})
                    gen.add(self.vm)
                    gen.generate(str(Path(tmp)) + os.sep)
                    out = Path(tmp) / "f.so"
                    res = subprocess.run(
                        [cc, *_FLAGS, str(src), "-o", str(out), "-lm"],
                        capture_output=True,
                        text=True,
                        timeout=600,
                    )
                    if res.returncode != 0:
                        self.error = res.stderr[-500:]
                        return
                    # atomic: a concurrent process never loads a half-written library
                    tmp_lib = self._lib.with_suffix(f".{os.getpid()}.tmp")
                    shutil.copyfile(out, tmp_lib)
                    os.replace(tmp_lib, self._lib)
            except (OSError, subprocess.SubprocessError, RuntimeError) as exc:
                self.error = str(exc)
                return
            self._load()
