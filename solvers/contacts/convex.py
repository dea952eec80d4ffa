"""``convex``: a MuJoCo-style velocity-level convex QP for the impulses of a step, with a
small regulariser (:func:`hybridoc.solvers.impulses.solve_convex`); in CasADi its KKT
conditions, an LCP, by enumerating the active sets
(:func:`hybridoc.solvers.casadi_step.enumerated_lcp`)."""

from __future__ import annotations

from typing import Any

from hybridoc.solvers.contacts.base import ImpulseModel, register

__all__ = ["Convex", "REGULARIZATION"]

REGULARIZATION = 1e-9
"""Relative diagonal regulariser ``R = REGULARIZATION * diag(W)`` of the QP."""


@register
class Convex(ImpulseModel):
    """Impulses minimising ``1/2 lambda^T (W + R) lambda + lambda^T (1 + e) w-`` over
    ``lambda >= 0``."""

    name = "convex"
    summary = "impulses from a regularised convex QP (MuJoCo-style)"
    compiled = True
    coupled = True

    def casadi_impulses(self, inputs: Any) -> list[Any]:
        from hybridoc.solvers.casadi_step import enumerated_lcp

        # the QP's KKT conditions are LCP(H, q) with H = W + R, as in solve_convex
        W = inputs.W
        C = len(W)
        H = [[W[c][d] + (REGULARIZATION * W[c][c] if c == d else 0.0) for d in range(C)]
             for c in range(C)]  # fmt: skip
        q = [(1.0 + inputs.restitution) * w for w in inputs.w]
        eligible = [ims > 0 for ims in inputs.inv_mass_sum]
        return enumerated_lcp(H, q, inputs.active, eligible)
