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
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hybridoc.errors import ControlsError

__all__ = ["load_controls", "save_controls"]

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


def load_controls(path: str | Path, problem: Any) -> np.ndarray:
    """Read controls for ``problem`` from a ``.npy`` or ``.csv`` file.

    Parameters
    ----------
    path
        A ``.npy`` or ``.csv`` file, or a saved Solution (``.npz`` or ``.json``). A CSV
        header's columns are matched to the control labels by name (module notes).
    problem
        Any problem; it fixes the expected shape ``(N, nu)``.

    Returns
    -------
    numpy.ndarray
        float64 array of shape ``(N, nu)``.

    Raises
    ------
    hybridoc.errors.ControlsError
        If the file is missing, of another type, unparsable, of the wrong shape, holds NaN
        or infinity, or is a CSV whose header does not name the problem's controls.
    """
    ocp = _ocp_of(problem)
    p = Path(path)
    where = f"controls file {str(p)!r}"
    n, nu = ocp.steps, ocp.nu
    labels = list(ocp.control_labels or [])
    expect = f"expected shape ({n}, {nu}): {n} rows (grid intervals), one column per control"
    expect += f" component ({', '.join(labels)})" if labels else ""
    if p.suffix.lower() not in _SUFFIXES:
        raise ControlsError(
            f"{where}: unsupported file type {p.suffix!r}; use .npy, .csv or a saved Solution "
            "(.npz/.json)"
        )
    if not p.is_file():
        raise ControlsError(f"{where} does not exist")
    if p.suffix.lower() in (".npz", ".json"):
        from hybridoc.errors import HybridocError
        from hybridoc.solution import Solution

        try:
            arr = np.asarray(Solution.load(p).controls, dtype=np.float64)
        except HybridocError as exc:
            raise ControlsError(str(exc)) from None
    elif p.suffix.lower() == ".npy":
        try:
            with open(p, "rb") as fh:
                magic = fh.read(6)
        except OSError as exc:
            raise ControlsError(f"{where} cannot be read: {exc.strerror or exc}") from None
        if magic != b"\x93NUMPY":
            # numpy's own message for this case talks about pickles, which misleads
            raise ControlsError(
                f"{where} is not a readable .npy file: no NumPy header (write it with numpy.save)"
            )
        try:
            raw = np.load(p, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise ControlsError(f"{where} is not a readable .npy array: {exc}") from None
        if raw.dtype.kind not in "biuf":
            raise ControlsError(f"{where}: expected a numeric array, got dtype {raw.dtype}")
        arr = raw.astype(np.float64)
    else:
        try:
            # utf-8-sig: spreadsheets ("CSV UTF-8") start the file with a byte-order mark,
            # which would otherwise stick to the first label
            text = p.read_text(encoding="utf-8-sig")
        except (OSError, UnicodeDecodeError) as exc:
            raise ControlsError(f"{where} cannot be read: {exc}") from None
        header, arr = _parse_csv(text, where)
        if header is not None and len(header) != arr.shape[1]:
            raise ControlsError(
                f"{where}: the header has {len(header)} columns but the rows have {arr.shape[1]}"
            )
        if header is not None and arr.shape[1] == nu:  # a wrong width: the shape error below
            arr = arr[:, _header_columns(header, labels, where)]
    if arr.ndim == 1 and nu == 1:
        arr = arr[:, None]
    if arr.shape != (n, nu):
        raise ControlsError(f"{where}: {expect}; got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        row, col = np.argwhere(~np.isfinite(arr))[0]
        name = labels[col] if col < len(labels) else f"column {col}"
        raise ControlsError(
            f"{where}: non-finite value {arr[row, col]} at row {row} ({name}); "
            "controls must be finite"
        )
    return ocp.check_controls(arr, what=where)


def save_controls(
    path: str | Path, controls: np.ndarray, labels: Sequence[str] | None = None
) -> Path:
    """Write controls to ``.npy`` or ``.csv`` (with a header of ``labels``).

    CSV values are written with Python's shortest round-tripping repr, so
    :func:`load_controls` reads back the identical float64 values. Parent directories are
    created.

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
    p.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".npy":
        np.save(p, arr)
    else:
        lines = [",".join(names)]
        lines += [",".join(repr(float(x)) for x in row) for row in arr]
        p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return p
