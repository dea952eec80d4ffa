"""Shared helpers of the problem library (not public API)."""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from typing import Any

import casadi as ca
import numpy as np

__all__ = ["affine_flow_map", "check_positive", "check_restitution", "verified_claim"]


def affine_flow_map(s: ca.SX, u: ca.SX, f: ca.SX, L: ca.SX) -> ca.Function:
    """Exact flow map ``(s, u, h) -> (s(h), integral_0^h L dt)`` under a constant control.

    For a flow ``f = A s + b(u)`` with a nilpotent ``A`` (double integrators) and a running
    cost ``L(u)`` that does not depend on the state,
    ``s(h) = s + sum_k A^k f(s, u) h^(k+1) / (k+1)!`` (a polynomial in ``h``) and the cost is
    ``L(u) h``.
    """
    jac = ca.jacobian(f, s)
    if ca.depends_on(jac, ca.vertcat(s, u)):
        raise ValueError("affine_flow_map: f must be affine in s with a constant Jacobian")
    if ca.depends_on(L, s):
        raise ValueError("affine_flow_map: L must not depend on the state")
    nx = s.numel()
    A = np.array(ca.evalf(jac), dtype=float).reshape(nx, nx)
    if np.any(np.linalg.matrix_power(A, nx) != 0):
        raise ValueError("affine_flow_map: the Jacobian of f must be nilpotent")
    h = ca.SX.sym("h")
    term, s_end = f, s
    for k in range(nx):
        s_end = s_end + term * h ** (k + 1) / math.factorial(k + 1)
        term = ca.mtimes(ca.DM(A), term)
    return ca.Function("flow_map", [s, u, h], [s_end, L * h], ["s", "u", "h"], ["s_end", "cost"])


def check_restitution(e: float) -> float:
    """``e`` as a float in ``[0, 1]``."""
    e = float(e)
    if not (math.isfinite(e) and 0.0 <= e <= 1.0):
        raise ValueError(f"restitution must lie in [0, 1], got {e}")
    return e


def check_positive(name: str, value: float) -> float:
    """``value`` as a positive finite float."""
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be positive and finite, got {value}")
    return value


def _same(a: Any, b: Any) -> bool:
    if a is None or b is None:
        return a is b
    try:
        return bool(np.array_equal(np.asarray(a, dtype=float), np.asarray(b, dtype=float)))
    except (TypeError, ValueError):
        return False


def verified_claim(
    fn: Callable[..., Any],
    args: dict[str, Any],
    keys: tuple[str, ...],
    table: dict[tuple[Any, ...], int],
    guard: str,
) -> list[str] | None:
    """The verified optimal sequence of a configuration, or ``None``.

    ``table`` maps the values of the parameters named in ``keys`` to the number of events of
    the optimum, for configurations whose every other parameter has its default (those that
    ``tests/library_optima.py`` checks). Any other configuration gets ``None``: no claim.
    """
    for name, p in inspect.signature(fn).parameters.items():
        if name not in keys and not _same(args[name], p.default):
            return None
    key = tuple(float(args[k]) for k in keys)
    count = table.get(key)
    return None if count is None else [guard] * count
