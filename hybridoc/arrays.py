"""Checked numeric input: a value a user gives as an array of real numbers.

The one conversion that the model (:class:`~hybridoc.ocp.HybridOCP`, its modes and time
lifting) and the layers above use for states, bounds and controls, so that a complex, boolean
or text array fails with one clear message naming what it was.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hybridoc.errors import SceneError

__all__ = ["as_float_array"]


def as_float_array(value: Any, what: str, *, error: type[Exception] = SceneError) -> np.ndarray:
    """``value`` as a float64 array; only real numbers are accepted.

    Torch tensors (also ones that require grad) are detached and copied to the CPU. Complex,
    boolean, string and object data raise ``error`` with a message naming ``what``.
    """
    if hasattr(value, "detach") and hasattr(value, "cpu"):  # a torch tensor, without torch
        value = value.detach().cpu().numpy()
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise error(f"{what}: not a numeric array ({exc})") from None
    if raw.dtype.kind == "O":
        try:
            raw = np.array(value, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise error(f"{what}: not a numeric array ({exc})") from None
    if raw.dtype.kind == "b":
        raise error(f"{what}: expected real numbers, got a boolean array")
    if raw.dtype.kind == "c":
        raise error(f"{what}: expected real numbers, got complex values")
    if raw.dtype.kind in "USV":
        raise error(f"{what}: not a numeric array (got text)")
    if raw.dtype.kind not in "iuf":
        raise error(f"{what}: not a numeric array (data of type {raw.dtype})")
    return np.array(raw, dtype=np.float64)
