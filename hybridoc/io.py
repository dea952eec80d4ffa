"""Reading and writing control arrays (``.npy`` and ``.csv``).

A controls file holds the ``(N, nu)`` piecewise-constant values of a problem: one row per grid
interval, one column per control component, in the order of the problem's control labels
(for a scene: ``disc.ux, disc.uy`` for each actuated disc in scene order). A saved
:class:`~hybridoc.solution.Solution` (``.npz`` + ``.json``, either name) is read as its
controls.

CSV layout: comma separated, one optional header line (a first line that is not numeric),
then ``N`` rows of ``nu`` numbers::

    ball1.ux,ball1.uy
    0.0,3.0
    0.0,3.0
    ...

A header names the columns: they are matched to the problem's control labels by name, in
any order (``ball1.uy,ball1.ux`` swaps the columns back), and a header that names other
columns (an unknown, missing or repeated label) is an error rather than being ignored. The
generic names ``u0,u1,...`` that :func:`save_controls` writes without labels keep the
columns in order.

Controls from another simulator
    A simulator that takes ``K`` steps per control interval logs ``N * K`` rows (MuJoCo's
    ``ctrl`` at ``K`` substeps). ``load_controls(path, problem, substeps=K)`` reads them for
    the problem on the ``K`` times finer grid, :func:`substep_problem`, where the judge
    measures them exactly; without ``substeps`` such a file is an error that names ``K``.
    :func:`read_array` reads the other arrays that come from outside (gradients,
    trajectories) with the same rules.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.errors import ControlsError, HybridocError

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.ocp import HybridOCP

__all__ = [
    "load_controls",
    "read_array",
    "read_controls",
    "save_controls",
    "substep_problem",
    "substeps_hint",
]

_SUFFIXES = (".npy", ".csv", ".npz", ".json")


def _ocp_of(problem: Any) -> Any:
    from hybridoc.problem import as_ocp

    return as_ocp(problem)


def _parse_csv(text: str, where: str) -> tuple[list[str] | None, np.ndarray]:
    lines = [(k + 1, ln.strip()) for k, ln in enumerate(text.splitlines())]
    lines = [(k, ln) for k, ln in lines if ln]
    if not lines:
        raise ControlsError(f"{where}: the file is empty")
    header = None
    try:
        [float(x) for x in lines[0][1].split(",")]
    except ValueError:
        header = [h.strip().strip('"').strip() for h in lines[0][1].split(",")]
        lines = lines[1:]
    rows = []
    width = None
    for lineno, ln in lines:
        fields = ln.split(",")
        try:
            row = [float(x) for x in fields]
        except ValueError:
            bad = next(x for x in fields if not _is_float(x))
            raise ControlsError(
                f"{where}: line {lineno}: {bad.strip()!r} is not a number"
            ) from None
        if width is None:
            width = len(row)
        elif len(row) != width:
            raise ControlsError(
                f"{where}: line {lineno} has {len(row)} values, the first data line has {width}"
            )
        rows.append(row)
    if not rows:
        raise ControlsError(f"{where}: no data rows after the header")
    return header, np.array(rows, dtype=np.float64)


def _header_columns(header: list[str], labels: list[str], where: str) -> list[int]:
    """For each control label, the CSV column that holds it (the header names the columns)."""
    generic = [f"u{k}" for k in range(len(header))]
    if header == labels or (header == generic and set(generic) != set(labels)):
        return list(range(len(header)))  # in order: the labels, or save_controls' defaults
    repeated = sorted({h for h in header if header.count(h) > 1})
    unknown = [h for h in header if h not in labels]
    missing = [lab for lab in labels if lab not in header]
    if repeated or unknown or missing:
        parts = [
            f"{what} {', '.join(repr(x) for x in xs)}"
            for what, xs in (("unknown", unknown), ("missing", missing), ("repeated", repeated))
            if xs
        ]
        raise ControlsError(
            f"{where}: the header does not name the problem's controls ({'; '.join(parts)}); "
            f"the columns are {', '.join(labels)} in any order, or leave the header out for "
            "this order"
        )
    return [header.index(lab) for lab in labels]


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_array(
    path: str | Path,
    *,
    what: str = "array",
    labels: Sequence[str] | None = None,
    error: type[HybridocError] = ControlsError,
) -> np.ndarray:
    """Read a numeric float64 array from a ``.npy`` or ``.csv`` file, shape unchecked.

    The reader behind :func:`load_controls`, for the other arrays that come from outside:
    gradients, trajectories, times. A CSV may start with a header line; when ``labels`` are
    given and the file has that many columns, the header's names are matched to them as for
    controls (module notes) and the columns returned in the order of ``labels``.

    Parameters
    ----------
    path
        A ``.npy`` or ``.csv`` file.
    what
        What the file holds, for the messages (``"gradient"``, ``"states"``, ...).
    labels
        Column names a CSV header may use; ``None`` ignores a header.
    error
        The :class:`~hybridoc.errors.HybridocError` subclass raised.

    Returns
    -------
    numpy.ndarray
        float64; 1-D or 2-D as stored (a CSV is always 2-D).

    Raises
    ------
    hybridoc.errors.HybridocError
        ``error``: the file is missing, of another type, unparsable or not numeric.
    """
    p = Path(path)
    where = f"{what} file {str(p)!r}"
    if p.suffix.lower() not in (".npy", ".csv"):
        raise error(f"{where}: unsupported file type {p.suffix!r}; use .npy or .csv")
    if not p.is_file():
        raise error(f"{where} does not exist")
    return _read(p, where, list(labels) if labels is not None else None, error)


def _read(p: Path, where: str, labels: list[str] | None, error: type[HybridocError]) -> np.ndarray:
    """The array of a ``.npy`` or ``.csv`` file that exists (see :func:`read_array`)."""
    if p.suffix.lower() == ".npy":
        try:
            with open(p, "rb") as fh:
                magic = fh.read(6)
        except OSError as exc:
            raise error(f"{where} cannot be read: {exc.strerror or exc}") from None
        if magic != b"\x93NUMPY":
            # numpy's own message for this case talks about pickles, which misleads
            raise error(
                f"{where} is not a readable .npy file: no NumPy header (write it with numpy.save)"
            )
        try:
            raw = np.load(p, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise error(f"{where} is not a readable .npy array: {exc}") from None
        if raw.dtype.kind not in "biuf":
            raise error(f"{where}: expected a numeric array, got dtype {raw.dtype}")
        return raw.astype(np.float64)
    try:
        # utf-8-sig: spreadsheets ("CSV UTF-8") start the file with a byte-order mark,
        # which would otherwise stick to the first label
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{where} cannot be read: {exc}") from None
    try:
        header, arr = _parse_csv(text, where)
    except ControlsError as exc:
        raise error(str(exc)) from None
    if header is not None and len(header) != arr.shape[1]:
        raise error(
            f"{where}: the header has {len(header)} columns but the rows have {arr.shape[1]}"
        )
    if header is not None and labels is not None and arr.shape[1] == len(labels):
        try:  # a wrong width: the caller's shape error
            arr = arr[:, _header_columns(header, labels, where)]
        except ControlsError as exc:
            raise error(str(exc)) from None
    return arr


def substep_problem(problem: Any, substeps: int) -> HybridOCP:
    """The problem on a grid ``substeps`` times finer: ``N * substeps`` control intervals.

    Controls logged by a simulator that takes ``K`` steps per control interval (a MuJoCo
    ``ctrl`` log at ``K`` substeps) have ``N * K`` rows; they are judged exactly as the
    piecewise-constant control of this problem. Everything but the grid is the problem's
    own (same name, horizon, costs and guards); ``substeps=1`` returns the problem itself.

    Parameters
    ----------
    problem
        Any problem (:func:`hybridoc.problem.as_ocp`).
    substeps
        ``K >= 1``.

    Returns
    -------
    HybridOCP
        ``problem.replace(steps=N * K)``.

    Raises
    ------
    hybridoc.errors.ControlsError
        ``K`` is not a positive integer, or ``N * K`` is more than
        :data:`hybridoc.ocp.MAX_STEPS` intervals.
    """
    from hybridoc.ocp import MAX_STEPS

    ocp = _ocp_of(problem)
    k = _checked_substeps(substeps)
    if k == 1:
        return ocp
    if ocp.steps * k > MAX_STEPS:
        raise ControlsError(
            f"substeps {k}: N * K = {ocp.steps} * {k} = {ocp.steps * k} intervals, more than "
            f"the {MAX_STEPS} a problem may have (hybridoc.ocp.MAX_STEPS)"
        )
    return ocp.replace(steps=ocp.steps * k)


def _checked_substeps(substeps: Any) -> int:
    if isinstance(substeps, bool) or not isinstance(substeps, int | np.integer) or substeps < 1:
        raise ControlsError(f"substeps must be a positive integer, got {substeps!r}")
    return int(substeps)


def substeps_hint(rows: int, steps: int, flag: str = "substeps") -> str:
    """The hint for a file of ``N * K`` rows given where ``N`` were expected (else empty).

    Parameters
    ----------
    rows
        The rows of the file.
    steps
        ``N``, the rows expected.
    flag
        How the caller spells the option: ``"substeps"`` (Python) or ``"--substeps"``.
    """
    if steps < 1 or rows <= steps or rows % steps:
        return ""
    k = rows // steps
    setting = f"{flag}={k}" if not flag.startswith("-") else f"{flag} {k}"
    return (
        f" ({rows} rows: {k} per grid interval, as a simulator logs at {k} substeps per "
        f"control interval, e.g. MuJoCo; {setting} takes them on the {rows}-interval grid)"
    )


def load_controls(
    path: str | Path, problem: Any, *, substeps: int | None = None, flag: str = "substeps"
) -> np.ndarray:
    """Read controls for ``problem`` from a ``.npy`` or ``.csv`` file.

    Parameters
    ----------
    path
        A ``.npy`` or ``.csv`` file, or a saved Solution (``.npz`` or ``.json``). A CSV
        header's columns are matched to the control labels by name (module notes).
    problem
        Any problem; it fixes the expected shape ``(N, nu)``.
    substeps
        ``K``: the file holds ``N * K`` rows, ``K`` per grid interval (a simulator's log at
        ``K`` substeps per control interval), to be judged on the finer grid of
        :func:`substep_problem`. Default: ``N`` rows. A file of ``N * K`` rows read without
        it is an error that names ``K``.
    flag
        How the option is spelled in that error: ``"substeps"`` (the default, for Python
        callers) or ``"--substeps"`` (the command line).

    Returns
    -------
    numpy.ndarray
        float64 array of shape ``(N * K, nu)`` (``(N, nu)`` without ``substeps``), checked
        against the bounds of the (refined) problem.

    Raises
    ------
    hybridoc.errors.ControlsError
        If the file is missing, of another type, unparsable, of the wrong shape, holds NaN
        or infinity, or is a CSV whose header does not name the problem's controls.
    """
    ocp = _ocp_of(problem)
    k = 1 if substeps is None else _checked_substeps(substeps)
    fine = substep_problem(ocp, k)
    p = Path(path)
    where = f"controls file {str(p)!r}"
    n, nu = fine.steps, fine.nu
    labels = list(ocp.control_labels or [])
    per = f" ({ocp.steps} grid intervals x {k} substeps)" if k > 1 else " (grid intervals)"
    expect = f"expected shape ({n}, {nu}): {n} rows{per}, one column per control component"
    expect += f" ({', '.join(labels)})" if labels else ""
    if p.suffix.lower() not in _SUFFIXES:
        raise ControlsError(
            f"{where}: unsupported file type {p.suffix!r}; use .npy, .csv or a saved Solution "
            "(.npz/.json)"
        )
    if not p.is_file():
        raise ControlsError(f"{where} does not exist")
    if p.suffix.lower() in (".npz", ".json"):
        from hybridoc.solution import Solution

        try:
            arr = np.asarray(Solution.load(p).controls, dtype=np.float64)
        except HybridocError as exc:
            raise ControlsError(str(exc)) from None
    else:
        arr = _read(p, where, labels if labels else None, ControlsError)
    if arr.ndim == 1 and nu == 1:
        arr = arr[:, None]
    if arr.shape != (n, nu):
        hint = ""
        if arr.ndim == 2 and arr.shape[1] == nu and k == 1:
            hint = substeps_hint(arr.shape[0], n, flag)
        raise ControlsError(f"{where}: {expect}; got shape {arr.shape}{hint}")
    if not np.all(np.isfinite(arr)):
        row, col = np.argwhere(~np.isfinite(arr))[0]
        name = labels[col] if col < len(labels) else f"column {col}"
        raise ControlsError(
            f"{where}: non-finite value {arr[row, col]} at row {row} ({name}); "
            "controls must be finite"
        )
    return fine.check_controls(arr, what=where)


def read_controls(path: str | os.PathLike[str], problem: Any) -> Any:
    """A controls file for the judge: a saved Solution as a Solution, else an array.

    Parameters
    ----------
    path
        A saved :class:`~hybridoc.solution.Solution` (``stem.npz`` or ``stem.json`` of the
        pair), judged by its own control; or a ``.npy`` / ``.csv`` file of ``(N, nu)``
        controls (:func:`load_controls`).
    problem
        The problem the controls are for (it fixes the shape of an array).

    Returns
    -------
    Solution or numpy.ndarray

    Raises
    ------
    hybridoc.errors.ControlsError
        If the file is missing, unreadable or of another type, naming it.
    """
    p = Path(path)
    if p.suffix.lower() not in _SUFFIXES:
        raise ControlsError(
            f"controls {str(path)!r} is not a numeric array, nor a controls file (.npy, .csv, "
            "or a saved Solution .npz/.json)"
        )
    if p.suffix.lower() in (".npz", ".json"):
        from hybridoc.solution import Solution

        if not p.is_file():
            raise ControlsError(f"controls file {str(p)!r} does not exist")
        try:
            return Solution.load(p)
        except HybridocError as exc:
            raise ControlsError(f"controls file {str(p)!r}: {exc}") from None
    return load_controls(p, problem)


def save_controls(
    path: str | Path, controls: np.ndarray, labels: Sequence[str] | None = None
) -> Path:
    """Write controls to ``.npy`` or ``.csv`` (with a header of ``labels``).

    CSV values are written with Python's shortest round-tripping repr, so
    :func:`load_controls` reads back the identical float64 values. Parent directories are
    created. The file is written by the rules of :mod:`hybridoc.outputs` (atomically; a
    link, or a file hybridoc did not write, at ``path`` is refused).

    Parameters
    ----------
    path
        Target file; its suffix picks the format.
    controls
        ``(N, nu)`` array.
    labels
        Column names for the CSV header; default ``u0, u1, ...``.

    Returns
    -------
    pathlib.Path
        The file written.
    """
    p = Path(path)
    arr = np.asarray(controls, dtype=np.float64)
    if arr.ndim != 2:
        raise ControlsError(f"controls must be a 2-D (N, nu) array, got shape {arr.shape}")
    suffix = p.suffix.lower()
    if suffix not in _SUFFIXES:
        raise ControlsError(f"cannot write controls to {str(p)!r}: use a .npy or .csv file")
    names = list(labels) if labels is not None else [f"u{k}" for k in range(arr.shape[1])]
    if len(names) != arr.shape[1]:
        raise ControlsError(f"{len(names)} labels given for {arr.shape[1]} control columns")
    if any("," in name for name in names):
        raise ControlsError(f"labels must not contain commas: {names}")
    from hybridoc.outputs import write_text, write_with

    # by the rules of hybridoc.outputs: atomically, never through a link or over a user's file
    if suffix == ".npy":
        write_with(p, lambda fh: np.save(fh, arr))  # a file object: no suffix appended
    else:
        lines = [",".join(names)]
        lines += [",".join(repr(float(x)) for x in row) for row in arr]
        write_text(p, "\n".join(lines) + "\n")
    return p
