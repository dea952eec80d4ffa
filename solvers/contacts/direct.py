"""``direct``: every detected contact on its own, the closed-form impulse of a two-body
collision (the paper's and Taichi's treatment); simultaneous contacts are not coupled."""

from __future__ import annotations

from typing import Any

from hybridoc.problems import physics as ph
from hybridoc.solvers.contacts.base import ImpulseModel, register

__all__ = ["Direct"]


@register
class Direct(ImpulseModel):
    """Independent closed-form impulse per approaching contact,
    ``lambda_c = -(1 + e) w_c / (1/m_i + 1/m_j)`` (:func:`hybridoc.problems.physics.impulse`)."""

    name = "direct"
    summary = "closed-form impulse per contact (the paper's), with TOI corrections"
    compiled = True

    def contact_impulses(self, sim: Any, nrm: Any, w: Any, active: Any) -> Any:
        import torch

        inv_mass_sum = (sim.incidence**2) @ (1.0 / sim.masses)  # (C,): 1/m_i + 1/m_j or 1/m_i
        hit = active & (w < 0)
        lam = ph.impulse(w, inv_mass_sum, sim.restitution)
        return torch.where(hit, lam, torch.zeros_like(w))

    def casadi_impulses(self, inputs: Any) -> list[Any]:
        from hybridoc.solvers.casadi_step import direct_impulses

        return direct_impulses(inputs)
