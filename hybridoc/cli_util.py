"""Helpers shared by the ``hybridoc`` command and its plugin subcommands.

A plugin module defines ``register(subparsers)``, adds its parsers with
``parser.set_defaults(func=handler)``, and writes ``handler(args) -> int``. With ``--json``,
stdout must carry exactly one JSON object (use :func:`emit_json`) and everything else goes to
stderr (use :func:`say`). User errors are raised as :class:`~hybridoc.errors.HybridocError`;
the command turns them into one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hybridoc.errors import HybridocError

__all__ = [
    "HybridocArgumentParser",
    "add_controls_arg",
    "add_json_out",
    "emit_json",
    "ensure_dir",
    "fmt",
    "format_table",
    "load_controls_arg",
    "nonnegative_int",
    "positive_float",
    "positive_int",
    "resolve_scene",
    "say",
    "scene_arg",
    "to_jsonable",
]


class HybridocArgumentParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line, like every other user error.

    ``hybridoc: error: <command>: <message> (see 'hybridoc <command> --help')`` on stderr and
    exit code 2, instead of argparse's usage block followed by the message.
    """

    def error(self, message: str) -> Any:
        command = self.prog.removeprefix("hybridoc").strip()
        where = f"{command}: " if command else ""
        message = " ".join(message.split())
        self.exit(2, f"hybridoc: error: {where}{message} (see '{self.prog} --help')\n")


def _number(text: str, kind: type, test: Any, what: str) -> Any:
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not test(value):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    return _number(text, float, lambda x: math.isfinite(x) and x > 0, "a finite number > 0")


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    return _number(text, int, lambda n: n >= 1, "an integer >= 1")


def nonnegative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    return _number(text, int, lambda n: n >= 0, "an integer >= 0")


def to_jsonable(obj: Any) -> Any:
    """Numpy scalars and arrays, tuples and paths -> plain JSON types (floats unchanged)."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj


def emit_json(obj: Any) -> None:
    """Print ``obj`` as one JSON object on stdout.

    Floats are written with Python's shortest round-tripping repr, so a reader gets the
    identical float64 values.
    """
    sys.stdout.write(json.dumps(to_jsonable(obj)) + "\n")
    sys.stdout.flush()


def say(args: argparse.Namespace | None, text: str = "") -> None:
    """Print human text: to stdout normally, to stderr when ``--json`` is on."""
    stream = sys.stderr if getattr(args, "json", False) else sys.stdout
    print(text, file=stream, flush=True)


def scene_arg(parser: argparse.ArgumentParser) -> None:
    """Add the positional ``SCENE`` argument."""
    parser.add_argument(
        "scene",
        metavar="SCENE",
        help="built-in scene name (see 'hybridoc problems') or path to a .toml scene file",
    )


def resolve_scene(text: str) -> Any:
    """A :class:`~hybridoc.problems.Scene` from a built-in name or a TOML path."""
    from hybridoc.problems import load_scene

    return load_scene(text)


def add_json_out(parser: argparse.ArgumentParser, *, out_help: str | None = None) -> None:
    """Add ``--json`` (one JSON object on stdout) and ``--out DIR``."""
    parser.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object on stdout (messages go to stderr)",
    )
    parser.add_argument(
        "--out",
        metavar="DIR",
        type=Path,
        default=None,
        help=out_help or "also write results and figures to this directory",
    )


def add_controls_arg(parser: argparse.ArgumentParser) -> None:
    """Add ``--controls FILE`` (.npy or .csv; default: the scene's initial guess)."""
    parser.add_argument(
        "--controls",
        metavar="FILE",
        type=Path,
        default=None,
        help="controls as .npy or .csv, shape (N, nu) (default: the scene's initial guess)",
    )


def load_controls_arg(args: argparse.Namespace, scene: Any) -> tuple[np.ndarray, str]:
    """The controls named by ``--controls`` (or the initial guess) and a description."""
    if getattr(args, "controls", None) is None:
        return scene.initial_controls(), "initial guess"
    from hybridoc.io import load_controls

    return load_controls(args.controls, scene), str(args.controls)


def ensure_dir(path: str | Path) -> Path:
    """Create an output directory; an unwritable path is a user error."""
    p = Path(path)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise HybridocError(f"cannot create output directory {str(p)!r}: {exc.strerror}") from None
    if not p.is_dir():
        raise HybridocError(f"output path {str(p)!r} is not a directory")
    return p


def fmt(x: float, digits: int = 10) -> str:
    """A float with ``digits`` significant digits (``-`` for NaN)."""
    x = float(x)
    return "-" if math.isnan(x) else f"{x:.{digits}g}"


def format_table(
    headers: Sequence[str], rows: Sequence[Sequence[Any]], *, right: Sequence[bool] | None = None
) -> str:
    """A plain-text table; ``right[k]`` right-aligns column ``k`` (default: numbers)."""
    cells = [[str(c) for c in row] for row in rows]
    widths = [len(h) for h in headers]
    for row in cells:
        widths = [max(w, len(c)) for w, c in zip(widths, row, strict=True)]
    if right is None:
        right = [
            all(isinstance(r[k], int | float | np.number) for r in rows) and bool(rows)
            for k in range(len(headers))
        ]

    def line(row: Sequence[str]) -> str:
        parts = [
            c.rjust(w) if r else c.ljust(w) for c, w, r in zip(row, widths, right, strict=True)
        ]
        return "  ".join(parts).rstrip()

    out = [line(list(headers)), line(["-" * w for w in widths])]
    out += [line(row) for row in cells]
    return "\n".join(out)
