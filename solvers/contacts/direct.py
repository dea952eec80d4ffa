"""``direct``: every detected contact on its own, the closed-form impulse of a two-body
collision (the paper's and Taichi's treatment); simultaneous contacts are not coupled."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from hybridoc.problems import physics as ph
from hybridoc.solvers.contacts.base import register
from hybridoc.solvers.contacts.impulse import ImpulseModel

if TYPE_CHECKING:  # pragma: no cover
    from torch import Tensor

    from hybridoc.solvers.contacts.casadi_parts import ImpulseInputs

__all__ = ["Direct", "direct_impulses", "solve_direct"]


@register
class Direct(ImpulseModel):
    """Independent closed-form impulse per approaching contact,
    ``lambda_c = -(1 + e) w_c / (1/m_i + 1/m_j)`` (:func:`hybridoc.problems.physics.impulse`)."""

    name = "direct"
    summary = "closed-form impulse per contact (the paper's), with TOI corrections"
    compiled = True
    per_contact = True

    def contact_impulses(self, sim: Any, nrm: Any, w: Any, active: Any) -> Any:
        import torch

        inv_mass_sum = (sim.incidence**2) @ (1.0 / sim.masses)  # (C,): 1/m_i + 1/m_j or 1/m_i
        hit = active & (w < 0)
        lam = ph.impulse(w, inv_mass_sum, sim.restitution)
        return torch.where(hit, lam, torch.zeros_like(w))

    def impulses(self, W: Tensor, w: Tensor, active: Tensor, restitution: Any) -> Tensor:
        from hybridoc.solvers.contacts.lcp_solver import prepare_impulses

        e = prepare_impulses(W, w, active, restitution)
        return solve_direct(W, w, active, e)

    def casadi_impulses(self, inputs: ImpulseInputs) -> list[Any]:
        return direct_impulses(inputs)


def direct_impulses(inputs: ImpulseInputs) -> list[Any]:
    """The ``direct`` impulses in CasADi: ``-(1 + e) w / (1/m_i + 1/m_j)`` per approaching
    contact."""
    import casadi as ca

    e = inputs.restitution
    return [
        ca.if_else(hit, ph.impulse(w, ims, e), 0.0)
        for hit, w, ims in zip(inputs.hit, inputs.w, inputs.inv_mass_sum, strict=True)
    ]


def solve_direct(W: Tensor, w_minus: Tensor, active: Tensor, e: Tensor) -> Tensor:
    """Independent closed-form impulse per active approaching contact,
    ``lambda_c = -(1 + e) w_c / W_cc`` (inputs: :mod:`hybridoc.solvers.contacts.lcp_solver`)."""
    import torch

    diag = torch.diagonal(W, dim1=-2, dim2=-1)
    hit = active & (w_minus < 0) & (diag > 0)
    safe = torch.where(hit, diag, torch.ones((), dtype=W.dtype, device=W.device))
    lam = -(1.0 + e) * w_minus / safe
    return torch.where(hit, lam, torch.zeros((), dtype=lam.dtype, device=lam.device))
