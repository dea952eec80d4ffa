"""The judge's broad phase: which contact guards of a scene of round bodies can be near zero.

A scene of ``n`` discs has ``n (n - 1) / 2`` pair guards; sampling every one on every grid
interval (the all-pairs judge) costs memory and time quadratic in ``n``. Between events a
body of a problem with a closed-form flow (:class:`~hybridoc.capabilities.LinearControlFlow`,
``f = (v, A u)``) moves as ``p + v t + a t^2 / 2`` with ``a = (A u)`` constant over a grid
interval, so the box it sweeps over ``[0, h]`` is exact from the endpoints and the interior
extremum ``t* = -v / a`` of each coordinate. Two discs whose boxes, each widened by its
radius and a margin, do not overlap stay apart by more than the margin over the whole
interval: their guard is far from zero and cannot fire there. Sweep and prune (the boxes
sorted by their lower ``x``) lists the overlapping pairs in ``O(n log n + k)``; a disc and a
wall are candidates when the widened box reaches the wall's half-plane.

The margin (:data:`MARGIN`, relative to the magnitudes the flow adds up and to the length
unit) is many orders of magnitude above the rounding of the boxes and of the guards'
values, so the phase is conservative: every guard that the all-pairs judge could see at or
below its rounding level is a candidate (``tests/test_broadphase.py`` checks the events and
costs of both on random crowded scenes).

:func:`contact_table` reads which guard is which from the problem's capabilities
(:attr:`~hybridoc.capabilities.Capabilities.geometry` and ``flow``) and the guards' ``kind``
and ``bodies``; a problem that does not describe its guards so has no table and is judged
all pairs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["MARGIN", "THRESHOLD", "ContactTable", "contact_table", "swept_boxes", "overlapping"]

MARGIN = 2.0**-20
"""Widening of every box, relative to the magnitudes of its body's flow (``|p| + |v| h +
|a| h^2 / 2``) plus the problem's length unit: about ``1e-6``, ten orders of magnitude above
their rounding."""
THRESHOLD = 64
"""The judge uses the broad phase for problems with more guards than this (the paper's and
the library's problems have fewer, and keep the all-pairs kernels, bit for bit)."""


def swept_boxes(
    p: np.ndarray, v: np.ndarray, a: np.ndarray, h: float, widen: np.ndarray, unit: float
) -> tuple[np.ndarray, np.ndarray]:
    """The boxes ``(lo, hi)``, each ``(n, 2)``, that bodies moving as ``p + v t + a t^2 / 2``
    sweep over ``[0, h]``, widened by ``widen`` (per body: its radius) and the margin.

    Parameters
    ----------
    p, v, a
        ``(n, 2)`` positions, velocities and accelerations.
    h
        The interval's length (``0``: the boxes of the positions).
    widen
        ``(n,)`` added on every side (the radii).
    unit
        The problem's length unit (the floor of the margin).
    """
    end = p + v * h + (0.5 * h * h) * a
    lo, hi = np.minimum(p, end), np.maximum(p, end)
    with np.errstate(divide="ignore", invalid="ignore"):
        ts = np.where(a != 0.0, -v / np.where(a != 0.0, a, 1.0), -1.0)
    inside = (ts > 0.0) & (ts < h)
    if inside.any():
        tc = np.where(inside, ts, 0.0)
        mid = np.where(inside, p + v * tc + (0.5 * tc * tc) * a, p)
        lo, hi = np.minimum(lo, mid), np.maximum(hi, mid)
    mag = np.abs(p) + np.abs(v) * h + (0.5 * h * h) * np.abs(a)
    pad = MARGIN * (mag.max(axis=1) + unit) + widen
    return lo - pad[:, None], hi + pad[:, None]


def overlapping(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The pairs ``(i, j)``, ``i < j``, of closed boxes that overlap, ``(k, 2)`` in
    lexicographic order, by sweep and prune on ``x``."""
    n = len(lo)
    if n < 2:
        return np.zeros((0, 2), dtype=np.int64)
    order = np.argsort(lo[:, 0], kind="stable")
    lo_x = lo[order, 0]
    # for box order[k], the boxes after it in x order that start before it ends
    ends = np.searchsorted(lo_x, hi[order, 0], side="right")
    counts = ends - np.arange(1, n + 1)
    counts = np.maximum(counts, 0)
    if not counts.any():
        return np.zeros((0, 2), dtype=np.int64)
    first = np.repeat(np.arange(n), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    second = first + 1 + offsets
    i, j = order[first], order[second]
    keep = (lo[i, 1] <= hi[j, 1]) & (lo[j, 1] <= hi[i, 1])
    i, j = i[keep], j[keep]
    pairs = np.stack([np.minimum(i, j), np.maximum(i, j)], axis=1)
    if len(pairs) > 1:
        pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    return pairs


@dataclass(frozen=True, eq=False)
class ContactTable:
    """Which guard is which contact, for the broad phase.

    Attributes
    ----------
    n
        The number of bodies; body ``i`` is at ``s[2 i : 2 i + 2]``, its velocity at
        ``s[2 n + 2 i : 2 n + 2 i + 2]``.
    radii
        ``(n,)``.
    A
        The map from controls to the accelerations ``(2 n, nu)``.
    pair_guard
        ``(n, n)``: the guard of the pair ``(i, j)`` (both orders), ``-1`` for none.
    wall_guards
        Per plane, ``(guard per body)`` (``-1`` for none), its point and unit normal.
    unit
        The problem's length unit.
    """

    n: int
    radii: np.ndarray
    A: np.ndarray
    pair_guard: np.ndarray
    wall_guards: tuple[tuple[np.ndarray, np.ndarray, np.ndarray], ...]
    unit: float

    def _motion(self, s: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n = self.n
        p = s[: 2 * n].reshape(n, 2)
        v = s[2 * n : 4 * n].reshape(n, 2)
        a = (self.A @ u).reshape(n, 2) if self.A.size else np.zeros((n, 2))
        return p, v, a

    def candidates(self, s: np.ndarray, u: np.ndarray, h: float) -> np.ndarray:
        """The guards (ascending indices) whose bodies may come within the margin of
        contact over ``[0, h]`` from ``s`` under the control ``u`` (``h = 0``: at ``s``)."""
        p, v, a = self._motion(np.asarray(s, dtype=float), np.asarray(u, dtype=float))
        lo, hi = swept_boxes(p, v, a, float(h), self.radii, self.unit)
        pairs = overlapping(lo, hi)
        out = [self.pair_guard[pairs[:, 0], pairs[:, 1]]] if len(pairs) else []
        for guards, point, normal in self.wall_guards:
            # the lowest point of each box along the normal, relative to the plane
            low = np.minimum(normal * lo, normal * hi).sum(axis=1) - normal @ point
            out.append(guards[low <= 0.0])
        if not out:
            return np.zeros(0, dtype=np.int64)
        g = np.concatenate(out)
        return np.unique(g[g >= 0])


def contact_table(ocp: Any) -> ContactTable | None:
    """The :class:`ContactTable` of a problem whose every guard is a contact of its
    :attr:`~hybridoc.capabilities.Capabilities.geometry` (``kind`` ``"disc-disc"`` or
    ``"disc-wall"``, ``bodies`` the names of two bodies or of a body and a plane) and whose
    flow is a :class:`~hybridoc.capabilities.LinearControlFlow`; ``None`` otherwise."""
    caps = getattr(ocp, "capabilities", None)
    geo = getattr(caps, "geometry", None)
    flow = getattr(caps, "flow", None)
    if geo is None or flow is None or ocp.flow_map is None:
        return None
    n = geo.n_bodies
    if ocp.nx != 4 * n or flow.A.shape != (2 * n, ocp.nu):
        return None
    body = {b.name: i for i, b in enumerate(geo.bodies)}
    plane = {pl.name: k for k, pl in enumerate(geo.planes)}
    if len(body) != n or len(plane) != len(geo.planes) or set(body) & set(plane):
        return None
    pair_guard = np.full((n, n), -1, dtype=np.int64)
    walls = np.full((len(geo.planes), n), -1, dtype=np.int64)
    for j, g in enumerate(ocp.guards):
        names = tuple(getattr(g, "bodies", ()) or ())
        if len(names) != 2 or names[0] not in body:
            return None
        i = body[names[0]]
        if g.kind == "disc-disc" and names[1] in body:
            k = body[names[1]]
            if k == i or pair_guard[i, k] >= 0:
                return None
            pair_guard[i, k] = pair_guard[k, i] = j
        elif g.kind == "disc-wall" and names[1] in plane:
            k = plane[names[1]]
            if walls[k, i] >= 0:
                return None
            walls[k, i] = j
        else:
            return None
    wall_guards = tuple(
        (walls[k], np.array(pl.point, dtype=float), np.array(pl.normal, dtype=float))
        for k, pl in enumerate(geo.planes)
    )
    radii = np.array([b.radius for b in geo.bodies], dtype=float)
    return ContactTable(
        n, radii, np.array(flow.A, dtype=float), pair_guard, wall_guards, ocp.scales.length
    )
