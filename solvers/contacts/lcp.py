"""``lcp``: all detected contacts of a step together, the frictionless linear complementarity
problem with Newton's restitution law, solved exactly by principal pivoting
(:func:`solve_lcp`); in CasADi by enumerating the active sets
(:func:`hybridoc.solvers.contacts.casadi_parts.enumerated_lcp`).

The LCP per contact is ``0 <= lambda  _|_  w+ + e w- >= 0``. Murty's principal pivoting
method is finite for the P-matrices that a full-rank ``W`` gives; the impulse is
differentiated through the identified active set.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from hybridoc.errors import ConvergenceError
from hybridoc.solvers.contacts.base import register
from hybridoc.solvers.contacts.casadi_parts import enumerated_lcp
from hybridoc.solvers.contacts.impulse import ImpulseModel
from hybridoc.solvers.contacts.lcp_solver import masked_solve, prepare_impulses, sign_tolerance

if TYPE_CHECKING:  # torch is imported where it is used: the registry must stay light
    from torch import Tensor

    from hybridoc.solvers.contacts.casadi_parts import ImpulseInputs

__all__ = ["LCP", "solve_lcp"]


@register
class LCP(ImpulseModel):
    """Coupled impulses from the LCP ``0 <= lambda _|_ w+ + e w- >= 0``."""

    name = "lcp"
    summary = "coupled impulses from the frictionless LCP (principal pivoting)"
    compiled = True
    coupled = True

    def impulses(self, W: Tensor, w: Tensor, active: Tensor, restitution: Any) -> Tensor:
        import torch

        e = prepare_impulses(W, w, active, restitution)
        if W.shape[-1] == 0:
            return torch.zeros_like(w)
        return solve_lcp(W, w, active, e)

    def casadi_impulses(self, inputs: ImpulseInputs) -> list[Any]:
        # as solve_lcp: q = (1 + e) w-, and a contact without a mobile body takes no impulse
        q = [(1.0 + inputs.restitution) * w for w in inputs.w]
        eligible = [ims > 0 for ims in inputs.inv_mass_sum]
        return enumerated_lcp(inputs.W, q, inputs.active, eligible)


def _murty(M: Tensor, q: Tensor, active: Tensor) -> Tensor:
    """Active set of ``LCP(M, q)`` restricted to ``active`` by Murty's least-index pivoting.

    Returns the bool mask ``S`` of strictly positive impulses. Murty's rule terminates for any
    P-matrix; the iteration cap (``2**C`` bounded by 10000) only guards degenerate inputs.
    Called without gradients (:func:`solve_lcp`).
    """
    import torch

    B, C = q.shape
    scale = q.abs().amax(-1, keepdim=True).clamp_min(torch.finfo(q.dtype).tiny)
    tol = sign_tolerance(q.dtype) * scale
    S = active & (q < -tol)
    done = torch.zeros(B, dtype=torch.bool, device=q.device)
    idx = torch.arange(C, device=q.device).expand(B, C)
    for _ in range(min(2**C + C, 10000)):
        lam = masked_solve(M, -q, S)
        mu = q + (M @ lam.unsqueeze(-1)).squeeze(-1)
        viol = active & ((S & (lam < -tol)) | (~S & (mu < -tol)))
        newly = ~viol.any(-1)
        done = done | newly
        if bool(done.all()):
            return S
        # least-index violated constraint flips in/out of the set (Murty's rule)
        first = torch.where(viol, idx, torch.full_like(idx, C)).amin(-1)
        flip = (idx == first.unsqueeze(-1)) & ~done.unsqueeze(-1)
        S = S ^ flip
    raise ConvergenceError("LCP impulse solver (Murty pivoting) did not terminate")


def solve_lcp(W: Tensor, w_minus: Tensor, active: Tensor, e: Tensor) -> Tensor:
    """Simultaneous frictionless LCP impulses with Newton restitution (module notes).

    The inputs are checked (:func:`~hybridoc.solvers.contacts.lcp_solver.prepare_impulses`),
    with ``e`` of shape (B, C) and at least one contact.
    """
    import torch

    q = (1.0 + e) * w_minus
    # contacts with zero diagonal (no mobile body) cannot take an impulse
    act = active & (torch.diagonal(W, dim1=-2, dim2=-1) > 0)
    with torch.no_grad():
        S = _murty(W.detach(), q.detach(), act)
    # the exact re-solve with autograd on: its derivative is the active-set derivative
    return masked_solve(W, -q, S)
