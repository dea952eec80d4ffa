"""The dense output of a generic extremal from the shooting's own nodes (private to
:mod:`hybridoc.reference`): ``(s, lambda, u)`` at any times, one DOP853 step from the node
of the step that holds each time (:func:`dense_from_nodes`), the scalar ``u(t)`` the judge
calls (:func:`control_from_nodes`, through CasADi's buffer API: :func:`buffer_call`), and
the bit-for-bit comparison of node arrays (:func:`same_arrays`)."""

from __future__ import annotations

import bisect
import threading
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

__all__ = ["buffer_call", "control_from_nodes", "dense_from_nodes", "locate", "same_arrays"]


def locate(
    levels: Sequence[int], starts: np.ndarray, horizon: float, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Phase, step and time into that step of each time (generic problems' dense output)."""
    k = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, None)
    lengths = np.diff(np.append(starts, horizon))
    n = np.asarray(levels, dtype=float)[k]
    dh = lengths[k] / n
    tau = t - starts[k]
    with np.errstate(divide="ignore", invalid="ignore"):
        i = np.where(dh > 0, np.floor(tau / np.where(dh > 0, dh, 1.0)), 0.0)
    i = np.clip(i, 0, n - 1).astype(int)
    return k, i, tau - i * dh


def dense_from_nodes(
    dense: Any,
    nodes: Sequence[np.ndarray],
    levels: Sequence[int],
    starts: np.ndarray,
    horizon: float,
    t: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(s, lambda, u)`` at times ``t``: one DOP853 step from the node of the step that
    holds each time. The nodes are the shooting's own, so ``u(t)`` is continuous across
    them, and each time costs one step, not a whole phase."""
    k, i, dt = locate(levels, starts, horizon, t)
    X = np.stack([nodes[a][b] for a, b in zip(k, i, strict=True)])
    if not isinstance(dense, (list, tuple)):
        s, lam, u = dense.map(t.size)(X.T, dt)
        return np.asarray(s).T.copy(), np.asarray(lam).T.copy(), np.asarray(u).T.copy()
    # one law per piece (pure state rows: each arc's own)
    out = [np.zeros((t.size, 0))] * 3
    for piece in np.unique(k):
        rows = np.flatnonzero(k == piece)
        parts = dense[int(piece)].map(rows.size)(X[rows].T, dt[rows])
        if out[0].shape[1] == 0:
            out = [np.empty((t.size, int(p.shape[0]))) for p in parts]
        for o, p in zip(out, parts, strict=True):
            o[rows] = np.asarray(p).T
    return out[0], out[1], out[2]


def control_from_nodes(
    u_at: Any, nodes: Sequence[np.ndarray], levels: Sequence[int], starts: np.ndarray,
    horizon: float,
) -> Callable[[float], np.ndarray]:  # fmt: skip
    """A scalar ``u(t)`` (see :func:`dense_from_nodes`; ``u_at(node, tau) -> u``, or one
    such function per piece) for the judge, which calls it at every stage of its
    integrator: plain floats and one compiled call per time."""
    first = [float(a) for a in np.asarray(starts, dtype=float)]
    given = list(u_at) if isinstance(u_at, (list, tuple)) else [u_at] * len(first)
    calls: dict[int, Callable[[np.ndarray, float], np.ndarray]] = {}
    for fn in given:
        if id(fn) not in calls:
            calls[id(fn)] = buffer_call(fn)
    laws = [calls[id(fn)] for fn in given]
    ends = [*first[1:], float(horizon)]
    steps = [(b - a) / int(n) for a, b, n in zip(first, ends, levels, strict=True)]
    last = [int(n) - 1 for n in levels]

    def u_generic(t: float) -> np.ndarray:
        k = max(bisect.bisect_right(first, t) - 1, 0)
        tau = t - first[k]
        dh = steps[k]
        i = min(max(int(tau // dh), 0), last[k]) if dh > 0 else 0
        return laws[k](nodes[k][i], tau - i * dh)

    # what this u(t) is a function of (ReferenceResult._judged_as_saved compares them)
    u_generic.pieces = (  # type: ignore[attr-defined]
        given, [np.asarray(n) for n in nodes], tuple(int(n) for n in levels),
        np.asarray(starts, dtype=float), float(horizon),
    )  # fmt: skip
    return u_generic


def same_arrays(a: Sequence[Any], b: Sequence[Any]) -> bool:
    """Whether two lists of float arrays hold the same shapes and the same bits."""
    if len(a) != len(b):
        return False
    for x, y in zip(a, b, strict=True):
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        if x.shape != y.shape or not np.array_equal(
            np.ascontiguousarray(x).view(np.int64), np.ascontiguousarray(y).view(np.int64)
        ):
            return False
    return True


def buffer_call(fn: Any) -> Callable[[np.ndarray, float], np.ndarray]:
    """``(node, tau) -> u`` (flat) of a dense law ``fn`` through CasADi's buffer API
    (:class:`hybridoc.kernels.Num`, one per thread: its buffers are its own): the same
    evaluation as ``fn(node, tau)``, bit for bit, without the ``DM`` conversions of that
    call (30 to 40 us of it, 4 us left; the judge calls ``u(t)`` at every stage of its
    integrator, 2400 to 4000 times per re-simulation on pendulum-wall and the hopper).
    A function the buffer API does not take (not dense) is called as before."""
    from hybridoc.kernels import Num

    try:
        first = Num(fn)
    except (ValueError, RuntimeError, AttributeError):
        return lambda node, tau: np.asarray(fn(node, tau), dtype=float).ravel()
    local = threading.local()
    local.num = first

    def call(node: np.ndarray, tau: float) -> np.ndarray:
        num = getattr(local, "num", None)
        if num is None:
            num = local.num = Num(fn)
        return num(node, tau)[0]

    return call
