"""``convex``: a MuJoCo-style velocity-level convex QP for the impulses of a step, with a
small regulariser (:func:`hybridoc.solvers.impulses.solve_convex`)."""

from __future__ import annotations

from hybridoc.solvers.contacts.base import ImpulseModel, register

__all__ = ["Convex"]


@register
class Convex(ImpulseModel):
    """Impulses minimising ``1/2 lambda^T (W + R) lambda + lambda^T (1 + e) w-`` over
    ``lambda >= 0``."""

    name = "convex"
    summary = "impulses from a regularised convex QP (MuJoCo-style)"
