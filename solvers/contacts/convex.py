"""``convex``: a MuJoCo-style velocity-level convex QP for the impulses of a step, with a
small regulariser (:func:`solve_convex`); in CasADi its KKT conditions, an LCP, by
enumerating the active sets (:func:`hybridoc.solvers.contacts.casadi_parts.enumerated_lcp`).

The QP is ``min 1/2 lambda^T (W + R) lambda + lambda^T (1 + e) w-`` s.t. ``lambda >= 0``, the
impulse that best reaches the reference velocity ``w_ref = -e w-`` with a small diagonal
regulariser ``R = regularization * diag(W)``. It is solved by projected Newton and
differentiated by implicit differentiation of its KKT conditions (a custom backward).
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

__all__ = ["Convex", "REGULARIZATION", "solve_convex"]

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

    def impulses(self, W: Tensor, w: Tensor, active: Tensor, restitution: Any) -> Tensor:
        import torch

        e = prepare_impulses(W, w, active, restitution)
        if W.shape[-1] == 0:
            return torch.zeros_like(w)
        return solve_convex(W, w, active, e)

    def casadi_impulses(self, inputs: ImpulseInputs) -> list[Any]:
        # the QP's KKT conditions are LCP(H, q) with H = W + R, as in solve_convex
        W = inputs.W
        C = len(W)
        H = [[W[c][d] + (REGULARIZATION * W[c][c] if c == d else 0.0) for d in range(C)]
             for c in range(C)]  # fmt: skip
        q = [(1.0 + inputs.restitution) * w for w in inputs.w]
        eligible = [ims > 0 for ims in inputs.inv_mass_sum]
        return enumerated_lcp(H, q, inputs.active, eligible)


_ACTIVE_SET_QP: Any = None


def _active_set_qp() -> Any:
    """The torch autograd Function of the QP (built on first use: torch is imported lazily)."""
    global _ACTIVE_SET_QP
    if _ACTIVE_SET_QP is not None:
        return _ACTIVE_SET_QP
    import torch

    class _ActiveSetQP(torch.autograd.Function):
        """``lambda = argmin 1/2 l^T H l + q^T l, l >= 0, l = 0 off active``; KKT backward."""

        @staticmethod
        def forward(ctx, H: Tensor, q: Tensor, active: Tensor, max_iter: int) -> Tensor:
            with torch.no_grad():
                lam, free = _projected_newton(H, q, active, max_iter)
            ctx.save_for_backward(H, lam, free)
            ctx.mark_non_differentiable(free)
            return lam

        @staticmethod
        def backward(ctx, grad: Tensor):
            # At the solution, with F = free (lambda > 0) and strict complementarity, the KKT
            # conditions read H_FF lambda_F + q_F = 0 and lambda_B = 0. Implicit differentiation:
            # d lambda_F = -H_FF^-1 (dH_FF lambda_F + dq_F), so with a = H_FF^-T g_F:
            # dL/dq = -a, dL/dH = -a lambda^T (both zero off F).
            H, lam, free = ctx.saved_tensors
            a = masked_solve(H.transpose(-1, -2), grad, free)
            grad_q = -a
            grad_H = -a.unsqueeze(-1) * lam.unsqueeze(-2)
            return grad_H, grad_q, None, None

    _ACTIVE_SET_QP = _ActiveSetQP
    return _ACTIVE_SET_QP


def _projected_newton(H: Tensor, q: Tensor, active: Tensor, max_iter: int) -> tuple[Tensor, Tensor]:
    """Bertsekas' projected Newton method for ``min 1/2 l^T H l + q^T l, l >= 0`` (batched).

    Returns the solution and its free set; each iterate ends with the exact Newton step on the
    current free face, so convergence is finite once the active set is identified. Called
    without gradients (the QP's forward).
    """
    import torch

    B, C = q.shape
    scale = q.abs().amax(-1, keepdim=True).clamp_min(torch.finfo(q.dtype).tiny)
    tol = sign_tolerance(q.dtype) * scale
    zero = torch.zeros((), dtype=q.dtype, device=q.device)

    def objective(x: Tensor) -> Tensor:
        return 0.5 * (x * (H @ x.unsqueeze(-1)).squeeze(-1)).sum(-1) + (q * x).sum(-1)

    lam = torch.zeros_like(q)
    for _ in range(max_iter):
        g = (H @ lam.unsqueeze(-1)).squeeze(-1) + q
        # a bound is binding when the variable is (numerically) at zero and the gradient
        # pushes it further out; inactive contacts are always pinned
        binding = ~active | ((lam <= tol) & (g > -tol))
        free = ~binding
        proj_grad = torch.where(binding, torch.clamp(g, max=0.0), g)
        proj_grad = torch.where(active, proj_grad, zero)
        if bool((proj_grad.abs() <= tol).all()):
            return lam, free & (lam > 0)
        step = masked_solve(H, -g, free)  # Newton direction on the free face: lam + step = argmin
        f0 = objective(lam)
        alpha = torch.ones(B, 1, dtype=q.dtype, device=q.device)
        accepted = torch.zeros(B, dtype=torch.bool, device=q.device)
        new = lam
        for _ls in range(40):
            trial = torch.clamp(lam + alpha * step, min=0.0)
            trial = torch.where(active, trial, zero)
            decrease = objective(trial) <= f0 + 1e-4 * (g * (trial - lam)).sum(-1) + tol[:, 0]
            take = decrease & ~accepted
            new = torch.where(take.unsqueeze(-1), trial, new)
            accepted = accepted | decrease
            if bool(accepted.all()):
                break
            alpha = torch.where(accepted.unsqueeze(-1), alpha, 0.5 * alpha)
        lam = new
    raise ConvergenceError(
        f"convex impulse QP (projected Newton) not converged in {max_iter} steps"
    )


def solve_convex(
    W: Tensor,
    w_minus: Tensor,
    active: Tensor,
    e: Tensor,
    *,
    regularization: float = REGULARIZATION,
    max_iter: int = 100,
) -> Tensor:
    """MuJoCo-style convex impulse QP with regulariser ``R = regularization * diag(W)``.

    The QP only sees the symmetric part of ``W`` (it is built in torch here, so gradients with
    respect to a non-symmetric perturbation of ``W`` are consistent). ``R`` makes the problem
    strictly convex for redundant contacts; it softens every contact by the relative amount
    ``regularization``: a single contact receives ``1 / (1 + regularization)`` of the exact
    impulse. The inputs are checked
    (:func:`~hybridoc.solvers.contacts.lcp_solver.prepare_impulses`), with ``e`` of shape
    (B, C) and at least one contact.
    """
    import torch

    Hs = 0.5 * (W + W.transpose(-1, -2))
    H = Hs + regularization * torch.diag_embed(torch.diagonal(Hs, dim1=-2, dim2=-1))
    q = (1.0 + e) * w_minus
    # contacts with zero diagonal (no mobile body) cannot take an impulse
    act = active & (torch.diagonal(Hs, dim1=-2, dim2=-1) > 0)
    return _active_set_qp().apply(H, q, act, max_iter)
