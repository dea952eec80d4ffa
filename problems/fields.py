"""The fields of a scene file, parsed and written (:mod:`hybridoc.problems.scene`): a number,
a 2-vector and a TOML string, each one :class:`~hybridoc.errors.SceneError` line when wrong."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from hybridoc.errors import SceneError

__all__ = ["number", "toml_str", "vec2"]


def vec2(value: Any, what: str) -> tuple[float, float]:
    """``value`` as two finite floats (a list, tuple or array of 2 numbers), else one
    :class:`~hybridoc.errors.SceneError` line naming ``what``."""
    if isinstance(value, str) or not isinstance(value, Sequence | np.ndarray):
        raise SceneError(f"{what} must be a list of 2 numbers, got {value!r}")
    if len(value) != 2:
        raise SceneError(f"{what} must have 2 components, got {len(value)}")
    out = tuple(number(v, what) for v in value)
    return (out[0], out[1])


def number(value: Any, what: str) -> float:
    """``value`` as a finite float (an int or float, not a bool), else one
    :class:`~hybridoc.errors.SceneError` line naming ``what``."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise SceneError(f"{what} must be a number, got {value!r}")
    x = float(value)
    if not math.isfinite(x):
        raise SceneError(f"{what} must be finite, got {x}")
    return x


def toml_str(s: str) -> str:
    """``s`` as a TOML basic string (quoted, with backslashes, quotes and newlines escaped)."""
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
