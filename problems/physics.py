"""Disc contact physics, written once for CasADi and for torch.

Every solver that touches discs uses these functions: the judge's compiled guards and resets
(:mod:`hybridoc.problems.compile`), the CasADi step of the differentiable simulation
(:mod:`hybridoc.solvers.casadi_step`), the torch simulator
(:mod:`hybridoc.solvers.simulator`) and the penalty and PBD contact models. They are written
against a tiny operations layer, :class:`Ops`, with one instance per backend: :data:`CASADI`
(symbols or numbers, vectors as columns) and :data:`TORCH` (batched tensors, vectors along
the last axis). Everything else is plain arithmetic that both backends share.

The physics (DESIGN.md sections 1 and 3)
    Contacts, in this order everywhere (:func:`contacts`): every disc pair ``i < j`` in scene
    order, then every disc with every wall, disc-major. A pair's gap is
    ``|p_i - p_j| - (r_i + r_j)`` with normal ``(p_i - p_j) / |p_i - p_j|``; a wall's is
    ``(p_i - a) . n - r_i`` with the wall's normal ``n``. The normal speed is
    ``w = (v_i - v_j) . n`` (``v_i . n`` for a wall), negative when approaching. The
    frictionless impulse with restitution ``e`` is ``J = -(1 + e) w / (1/m_i + 1/m_j)``
    (``1/m_j = 0`` for a wall), applied as ``v_i += J n / m_i``, ``v_j -= J n / m_j``. The
    time of impact of a penetrated step is the paper's linear estimate ``d / w`` (Eq. 3)
    and, on the exact flow, its Newton refinement. The terminal cost is the sum of
    ``|p_i(T) - target_i|^2`` over the discs with a target.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca

__all__ = [
    "CASADI",
    "TORCH",
    "Contact",
    "Ops",
    "contacts",
    "impulse",
    "normal_speed",
    "pair_detector",
    "pair_gap",
    "refine_impact_time",
    "target_cost",
    "toi_linear",
    "wall_gap",
]


class Ops:
    """The operations the physics needs from a backend."""

    name = "abstract"

    def dot(self, a: Any, b: Any) -> Any:  # pragma: no cover - interface
        raise NotImplementedError

    def sqrt(self, x: Any) -> Any:  # pragma: no cover - interface
        raise NotImplementedError

    def where(self, cond: Any, a: Any, b: Any) -> Any:  # pragma: no cover - interface
        raise NotImplementedError

    def clip(self, x: Any, lo: Any, hi: Any) -> Any:  # pragma: no cover - interface
        raise NotImplementedError

    def logical_and(self, a: Any, b: Any) -> Any:  # pragma: no cover - interface
        raise NotImplementedError

    def vec(self, x: Any) -> Any:
        """A scalar per contact broadcast against vectors (torch: a trailing axis)."""
        return x


class _CasadiOps(Ops):
    name = "casadi"

    def dot(self, a: Any, b: Any) -> Any:
        return ca.dot(a, b)

    def sqrt(self, x: Any) -> Any:
        return ca.sqrt(x)

    def where(self, cond: Any, a: Any, b: Any) -> Any:
        return ca.if_else(cond, a, b)

    def clip(self, x: Any, lo: Any, hi: Any) -> Any:
        return ca.fmin(ca.fmax(x, lo), hi)

    def logical_and(self, a: Any, b: Any) -> Any:
        return ca.logic_and(a, b)


class _TorchOps(Ops):
    name = "torch"

    def dot(self, a: Any, b: Any) -> Any:
        return (a * b).sum(-1)

    def sqrt(self, x: Any) -> Any:
        import torch

        return torch.sqrt(x)

    def where(self, cond: Any, a: Any, b: Any) -> Any:
        import torch

        return torch.where(cond, a, b)

    def clip(self, x: Any, lo: Any, hi: Any) -> Any:
        import torch

        return torch.clamp(x, lo, hi)

    def logical_and(self, a: Any, b: Any) -> Any:
        return a & b

    def vec(self, x: Any) -> Any:
        return x[..., None]


CASADI: Ops = _CasadiOps()
"""CasADi backend: SX/MX/DM symbols or numbers; vectors are columns."""
TORCH: Ops = _TorchOps()
"""Torch backend: batched tensors; vectors along the last axis."""


@dataclass(frozen=True)
class Contact:
    """One potential contact: the disc pair ``(i, j)`` or disc ``i`` with wall ``wall``."""

    i: int
    j: int | None = None
    wall: int | None = None

    @property
    def is_pair(self) -> bool:
        """Whether this is a disc-disc contact."""
        return self.j is not None


def contacts(n_discs: int, n_walls: int) -> list[Contact]:
    """Every potential contact, in the one order used everywhere (module notes)."""
    out = [Contact(i, j) for i in range(n_discs) for j in range(i + 1, n_discs)]
    out += [Contact(i, wall=k) for i in range(n_discs) for k in range(n_walls)]
    return out


# ---------------------------------------------------------------------- geometry
def pair_gap(dp: Any, R: Any, ops: Ops, *, min_distance: float = 0.0) -> tuple[Any, Any]:
    """Gap ``|dp| - R`` and unit normal ``dp / |dp|`` of a disc pair (``dp = p_i - p_j``).

    ``min_distance > 0`` clamps the distance from below, so that coincident centres give a
    finite (if arbitrary) normal; the penalty models use it.
    """
    dist = ops.sqrt(ops.dot(dp, dp))
    if min_distance > 0:
        dist = ops.clip(dist, min_distance, float("inf"))
    return dist - R, dp / ops.vec(dist)


def pair_detector(dp: Any, R: Any, ops: Ops) -> Any:
    """``|dp|^2 - R^2``: the pair gap's sign and zero set, polynomial along the flow."""
    return ops.dot(dp, dp) - R**2


def wall_gap(p: Any, point: Any, normal: Any, r: Any, ops: Ops) -> Any:
    """Signed distance of a disc of radius ``r`` to a wall through ``point`` with ``normal``.

    ``(p - a) . n - r`` with ``a`` the point and ``n`` the unit normal into free space.
    """
    return ops.dot(p - point, normal) - r


def normal_speed(dv: Any, normal: Any, ops: Ops) -> Any:
    """The relative normal speed, negative when approaching.

    ``dv . n`` for the relative velocity ``dv`` and the unit normal ``n``.
    """
    return ops.dot(dv, normal)


def target_cost(p: Any, target: Any, ops: Ops) -> Any:
    """A disc's share of the terminal cost, ``|p(T) - target|^2``."""
    d = p - target
    return ops.dot(d, d)


def impulse(w: Any, inv_mass_sum: Any, restitution: Any) -> Any:
    """The frictionless impulse ``-(1 + e) w / (1/m_i + 1/m_j)`` of an approaching contact."""
    return -(1.0 + restitution) * w / inv_mass_sum


# ---------------------------------------------------------------------- time of impact
def toi_linear(d_hat: Any, w_hat: Any, dt: float, active: Any, ops: Ops) -> Any:
    """The paper's time of impact (Eq. 3): ``d^ / w^`` clipped to ``[0, dt]`` where ``active``.

    The collision happened ``dt - toi`` after the step start. Inactive contacts get 0 (with a
    safe denominator, so that the unused branch has finite derivatives).
    """
    w_safe = ops.where(active, w_hat, -1.0 + 0.0 * w_hat)
    return ops.where(active, ops.clip(d_hat / w_safe, 0.0, dt), 0.0 * w_hat)


def refine_impact_time(
    rel_p: Any,
    rel_v: Any,
    rel_a: Any,
    tau: Any,
    active: Any,
    dt: float,
    ops: Ops,
    *,
    R: Any = None,
    normal: Any = None,
    offset: Any = None,
    iterations: int = 4,
) -> Any:
    """Newton's method for the contact time ``tau`` (after the step start) on the exact flow.

    The relative position moves as ``D(t) = D_p + D_v t + D_a t^2 / 2``; the root is that of
    ``|D|^2 - R^2`` for a pair (give ``R``) or ``D . n - offset`` for a wall (give ``normal``
    and ``offset = a . n + r``), kept in ``[0, dt]``. Quadratic convergence from the linear
    estimate, whose error is O(a dt^2).
    """
    for _ in range(iterations):
        t_ = ops.vec(tau)
        D = rel_p + (rel_v + 0.5 * rel_a * t_) * t_
        dD = rel_v + rel_a * t_
        if R is not None:
            g, dg = ops.dot(D, D) - R**2, 2.0 * ops.dot(D, dD)
        else:
            g, dg = ops.dot(D, normal) - offset, ops.dot(dD, normal)
        ok = ops.logical_and(active, dg < 0)
        dg = ops.where(ok, dg, -1.0 + 0.0 * dg)
        tau = ops.where(ok, ops.clip(tau - g / dg, 0.0, dt), tau)
    return tau
