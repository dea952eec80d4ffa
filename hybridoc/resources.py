"""Memory estimates of a run's sizes, checked before any work starts.

A size that a user gives (``--samples``, ``--starts``, a scene of many discs, a file's
declared shape) can ask for more memory than the machine has; left alone, the run allocates
until the system kills it, minutes later, or fails with an internal error. Instead each such
size is turned into an estimate of the bytes it allocates at least, *before* allocating, and
an estimate above :func:`memory_limit` is one :class:`ResourceError` naming the size, the
estimate and the limit (the command line's exit code 2).

The limit
    :data:`MEMORY_FRACTION` of the memory available to a new allocation
    (:func:`available_memory`: ``MemAvailable`` of ``/proc/meminfo``), or the
    ``HYBRIDOC_MEMORY_LIMIT`` environment variable (bytes, e.g. ``8e9``) where set.

The override
    ``--allow-large`` on any command, ``HYBRIDOC_ALLOW_LARGE=1`` in the environment, or
    :func:`allowing_large` in Python: the estimates are still made, and not enforced.

What is estimated
    :func:`judge_bytes` (a disc scene's guards compiled, which the judge's broad phase
    samples near contact only, and the trajectory of its steps), :func:`samples_bytes` (a
    dataset's draws),
    :func:`check_array_file` (a ``.npy`` file's declared shape, or a ``.csv`` file's size),
    :func:`check_npz_file` (the declared shapes of an ``.npz``'s members). Gradient
    descent's starts, iterations and hops: :mod:`hybridoc.solvers.gd`'s own estimate,
    refused through :func:`check`.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import zipfile
from collections.abc import Iterator
from pathlib import Path

from hybridoc.errors import HybridocError, SceneError

__all__ = [
    "ALLOW_ENV",
    "LIMIT_ENV",
    "MEMORY_FRACTION",
    "ResourceError",
    "allowing_large",
    "available_memory",
    "check",
    "check_array_file",
    "check_judge",
    "check_npz_file",
    "check_samples",
    "check_samples_of",
    "fmt_bytes",
    "judge_bytes",
    "judge_guard_bytes",
    "disc_guards",
    "large_allowed",
    "memory_limit",
    "samples_bytes",
]

ALLOW_ENV = "HYBRIDOC_ALLOW_LARGE"
"""Environment variable: ``1`` (or ``true``/``yes``) lets every size through."""
LIMIT_ENV = "HYBRIDOC_MEMORY_LIMIT"
"""Environment variable: the limit in bytes, instead of a share of the available memory."""
MEMORY_FRACTION = 0.5
"""The share of the available memory (:func:`available_memory`) that the memory estimate
of a run's sizes may take (:func:`memory_limit`)."""
OVERRIDE = "--allow-large or HYBRIDOC_ALLOW_LARGE=1 runs it anyway"
"""How to override a refusal, as every refusal says it."""

_ALLOW: contextvars.ContextVar[bool] = contextvars.ContextVar("allow_large", default=False)


class ResourceError(SceneError):
    """A size whose memory estimate exceeds :func:`memory_limit` (a user error: exit 2)."""


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (``MemAvailable`` of /proc/meminfo,
    else the free physical pages); ``None`` where neither can be read."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_AVPHYS_PAGES"))
    except (OSError, ValueError, AttributeError):
        return None


def memory_limit() -> int | None:
    """The bytes a run's sizes may take: :data:`MEMORY_FRACTION` of the available memory,
    or the ``HYBRIDOC_MEMORY_LIMIT`` environment variable (bytes) where set; ``None`` where
    neither is known.

    Raises
    ------
    hybridoc.errors.SceneError
        ``HYBRIDOC_MEMORY_LIMIT`` is not a number of bytes.
    """
    env = os.environ.get(LIMIT_ENV, "").strip()
    if env:
        try:
            value = float(env)
        except ValueError:
            value = float("nan")
        if not (value >= 0 and value < float("inf")):
            raise SceneError(f"{LIMIT_ENV} must be a number of bytes, got {env!r}")
        return int(value)
    avail = available_memory()
    return None if avail is None else int(MEMORY_FRACTION * avail)


def _limit_source() -> str:
    if os.environ.get(LIMIT_ENV, "").strip():
        return f"{LIMIT_ENV}"
    return f"half the memory available; {LIMIT_ENV}=bytes sets another"


def large_allowed() -> bool:
    """Whether the estimates are not enforced (``--allow-large``, ``HYBRIDOC_ALLOW_LARGE``
    or :func:`allowing_large`)."""
    if _ALLOW.get():
        return True
    return os.environ.get(ALLOW_ENV, "").strip().lower() in ("1", "true", "yes", "on")


@contextlib.contextmanager
def allowing_large(allow: bool = True) -> Iterator[None]:
    """Within this context (this thread or task), sizes above the limit are let through
    when ``allow`` (what ``--allow-large`` does for one command)."""
    token = _ALLOW.set(bool(allow) or _ALLOW.get())
    try:
        yield
    finally:
        _ALLOW.reset(token)


def fmt_bytes(n: float) -> str:
    """``n`` bytes in binary units, three significant digits (``1.5 GiB``)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.3g} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.3g} PiB"  # pragma: no cover


def check(what: str, need: float, detail: str, hint: str, error: type = ResourceError) -> None:
    """Refuse ``need`` bytes above :func:`memory_limit` (unless :func:`large_allowed`).

    Parameters
    ----------
    what
        The size, as the user gave it (``"samples=9999999999"``).
    need
        The estimate in bytes.
    detail
        How the estimate is made (``"72 B per sample"``).
    hint
        What to do instead (``"use fewer samples"``).
    error
        The error class raised (a :class:`ResourceError` by default; any
        :class:`~hybridoc.errors.HybridocError` subclass that takes a message).

    Raises
    ------
    ResourceError
        ``"<what> would need about <need> of memory (<detail>), above the limit of <limit>
        (<where the limit comes from>): <hint>; --allow-large or HYBRIDOC_ALLOW_LARGE=1 runs
        it anyway"``.
    """
    if large_allowed():
        return
    limit = memory_limit()
    if limit is None or need <= limit:
        return
    raise error(
        f"{what} would need about {fmt_bytes(need)} of memory ({detail}), above the limit of "
        f"{fmt_bytes(limit)} ({_limit_source()}): {hint}; {OVERRIDE}"
    )


# ---------------------------------------------------------------------------------------
# the judge

JUDGE_GUARD_BYTES = (18432, 62)
"""``(a, b)``: a disc scene's judge takes ``a + b nx`` bytes per guard (18 KiB and 62 B per
state component), nearly all of it the scene's guards compiled (each guard's gap, detector
and reset, a function of the whole state). The judge's own kernels no longer grow with the
guards: above :data:`hybridoc.broadphase.THRESHOLD` guards its broad phase samples only the
guards whose bodies' swept boxes meet, through per-guard kernels built for those guards
alone. Measured (the peak of a fresh process less its peak at start, over the scene's
compile and one evaluation of a grid of discs 3 apart and a wall, 200 steps): 32 kB per
guard at 40 discs (26 MB), 36 at 70, 42 at 100 (214 MB), 52 at 140, 67 at 202 (20503
guards, 808 states: 1.38 GB, 49 s of CPU); the model gives 28, 36, 43, 53 and 69. With the
all-pairs kernels (before the broad phase) 202 discs took 4.26 GB and 143 s of CPU, and
before the per-guard functions were built lazily ``std::bad_alloc`` after 10.8 GB."""
JUDGE_SECONDS_PER_GUARD = (7e-4, 2.1e-6)
"""``(a, b)``: CPU seconds to compile a disc scene's guards and judge it once, ``a + b nx``
per guard (measured 1.3 s for 820 guards over 160 states, 7.8 s for 5050 over 400, 19 s
for 9870 over 560, 49 s for 20503 over 808)."""
JUDGE_STEP_BYTES = (384, 32)
"""``(a, b)``: the judge's trajectory takes ``a + b nx`` bytes per grid step (the recorded
states, the segments, the batched samples; measured peak growth 580 B per step at 8 states,
1520 at 40)."""


def disc_guards(n_discs: int, n_walls: int) -> int:
    """The guards of a disc scene: every pair, and every disc with every wall."""
    return n_discs * (n_discs - 1) // 2 + n_discs * n_walls


def judge_guard_bytes(nx: int) -> int:
    """Bytes of the judge per guard of a disc scene with ``nx`` states
    (:data:`JUDGE_GUARD_BYTES`)."""
    a, b = JUDGE_GUARD_BYTES
    return a + b * nx


def judge_bytes(guards: int, nx: int, steps: int) -> int:
    """The bytes one evaluation by the judge allocates: the scene's guards compiled into its
    kernels (:func:`judge_guard_bytes` per guard) and its trajectory
    (:data:`JUDGE_STEP_BYTES` per step)."""
    a, b = JUDGE_STEP_BYTES
    return judge_guard_bytes(nx) * guards + (a + b * nx) * steps


def check_judge(n_discs: int, n_walls: int, steps: int) -> None:
    """Refuse a disc scene whose judge would not fit (:func:`judge_bytes`).

    Raises
    ------
    ResourceError
        Naming the discs, walls and steps, the estimate, the limit and the compile time.
    """
    G, nx = disc_guards(n_discs, n_walls), 4 * n_discs
    need = judge_bytes(G, nx, steps)
    sa, sb = JUDGE_SECONDS_PER_GUARD
    secs = (sa + sb * nx) * G
    walls = f"{n_walls} wall{'' if n_walls == 1 else 's'}"
    a, b = JUDGE_STEP_BYTES
    check(
        f"a scene of {n_discs} discs and {walls} with {steps} steps",
        need,
        f"the scene compiles {G} contact guards over {nx} states, about "
        f"{fmt_bytes(judge_guard_bytes(nx))} per guard, in about {secs:.3g} s "
        f"of CPU; its trajectory takes {fmt_bytes(a + b * nx)} per step",
        "use fewer discs or steps",
    )


# ---------------------------------------------------------------------------------------
# datasets

SAMPLE_OVERHEAD = 1024
"""Bytes of a dataset's bookkeeping per draw (its status, cost, events and task record)."""


def samples_bytes(samples: int, nx: int, steps: int, nu: int) -> int:
    """The bytes a dataset of ``samples`` draws holds at least: per draw its initial state,
    its optimal controls on the grid, and :data:`SAMPLE_OVERHEAD`."""
    return samples * (8 * nx + 8 * steps * nu + SAMPLE_OVERHEAD)


def check_samples(samples: int, nx: int, steps: int, nu: int, flag: str = "samples") -> None:
    """Refuse ``samples`` draws whose data would not fit (:func:`samples_bytes`).

    Raises
    ------
    ResourceError
        Naming ``samples``, the estimate and the limit.
    """
    per = samples_bytes(1, nx, steps, nu)
    check(
        f"{flag}={samples}",
        samples * per,
        f"{fmt_bytes(per)} per sample: its initial state of {nx} components, {steps} x {nu} "
        "controls and its record",
        f"use fewer {flag}",
    )


def check_samples_of(problem: object, samples: int, flag: str = "samples") -> None:
    """:func:`check_samples` for draws of ``problem``: a
    :class:`~hybridoc.problems.Scene` (its discs, steps and controls, without compiling it)
    or a :class:`~hybridoc.HybridOCP`."""
    n_discs = getattr(problem, "n_discs", None)
    if n_discs is not None:
        nx, nu = 4 * int(n_discs), int(problem.n_controls)  # type: ignore[attr-defined]
    else:
        nx, nu = int(problem.nx), int(problem.nu)  # type: ignore[attr-defined]
    check_samples(samples, nx, int(problem.steps), nu, flag)  # type: ignore[attr-defined]


# ---------------------------------------------------------------------------------------
# files

CSV_BYTES_PER_CHAR = 24
"""Bytes of parsing per character of a CSV file (its text, the split lines and a Python
float per number, at least two characters each)."""


def _npy_shape(fh: object, where: str, error: type) -> tuple[tuple[int, ...], int]:
    import numpy as np
    from numpy.lib import format as npformat

    try:
        version = npformat.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = npformat.read_array_header_1_0(fh)
        else:
            shape, _, dtype = npformat.read_array_header_2_0(fh)
    except (ValueError, OSError, EOFError) as exc:
        raise error(f"{where} is not a readable .npy array: {exc}") from None
    return tuple(int(n) for n in shape), int(np.dtype(dtype).itemsize)


def _declared(shape: tuple[int, ...], itemsize: int) -> int:
    n = itemsize
    for d in shape:
        n *= d
    return n


def check_array_file(path: str | os.PathLike[str], where: str, error: type = HybridocError) -> None:
    """Check a ``.npy`` or ``.csv`` file's size before it is read.

    A ``.npy`` file's header declares its shape: a declared size larger than the file
    holds is a damaged file (``error``), and one whose float64 copy passes the limit is a
    :class:`ResourceError`, both before anything is allocated. A ``.csv`` file's parsing
    takes :data:`CSV_BYTES_PER_CHAR` per byte. Other files, and files that cannot be
    opened, are left to the reader's own errors.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    try:
        size = p.stat().st_size
    except OSError:
        return
    if suffix == ".csv":
        check(
            f"{where} ({fmt_bytes(size)})",
            size * CSV_BYTES_PER_CHAR,
            f"{CSV_BYTES_PER_CHAR} B of parsing per character",
            "use a .npy file or a smaller file",
        )
        return
    if suffix != ".npy":
        return
    try:
        fh = open(p, "rb")  # noqa: SIM115
    except OSError:
        return
    with fh:
        if fh.read(6) != b"\x93NUMPY":
            return  # the reader says what it is not
        fh.seek(0)
        shape, itemsize = _npy_shape(fh, where, error)
        header = fh.tell()
    declared = _declared(shape, itemsize)
    if declared > size - header:
        raise error(
            f"{where} is not a readable .npy array: its header declares shape {shape} "
            f"({fmt_bytes(declared)}) but the file holds {fmt_bytes(max(size - header, 0))} "
            "of data (a truncated or damaged file)"
        )
    check(
        f"{where} of shape {shape}",
        _declared(shape, 8) * 2,
        "its data and a float64 copy",
        "use a smaller file",
    )


def check_npz_file(path: str | os.PathLike[str], where: str, error: type = HybridocError) -> None:
    """Check the members of an ``.npz`` file before they are read: each member's header
    declares its shape, which must fit in the member's recorded size (else ``error``: a
    damaged file), and all of them together within the limit (else :class:`ResourceError`).
    A file that is not a zip archive is left to the reader's own error."""
    try:
        zf = zipfile.ZipFile(path)
    except (OSError, zipfile.BadZipFile, ValueError):
        return
    total = 0
    with zf:
        for info in zf.infolist():
            if not info.filename.endswith(".npy"):
                continue
            name = f"{where}, member {info.filename!r}"
            try:
                with zf.open(info) as fh:
                    if fh.read(6) != b"\x93NUMPY":
                        continue
                    import io

                    head = fh.read(65536 + 16)
                    buf = io.BytesIO(b"\x93NUMPY" + head)
                    shape, itemsize = _npy_shape(buf, name, error)
                    header = buf.tell()
            except (OSError, zipfile.BadZipFile, EOFError, RuntimeError) as exc:
                raise error(f"{name} cannot be read: {exc}") from None
            declared = _declared(shape, itemsize)
            if declared > info.file_size - header:
                raise error(
                    f"{name} is damaged: its header declares shape {shape} "
                    f"({fmt_bytes(declared)}) but it holds "
                    f"{fmt_bytes(max(info.file_size - header, 0))} of data"
                )
            total += declared
    check(
        f"{where} ({fmt_bytes(Path(path).stat().st_size)} on disk)",
        total,
        "the declared shapes of its arrays",
        "use a smaller file",
    )
