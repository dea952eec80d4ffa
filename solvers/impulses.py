"""Frictionless contact impulses for several simultaneous contacts, batched and differentiable.

All solvers take the same inputs for a batch of ``B`` steps with ``C`` potential contacts each:

* ``W`` (B, C, C): the Delassus matrix ``J M^-1 J^T`` (row ``c`` of ``J`` maps body velocities to
  the normal relative velocity of contact ``c``; positive means separating);
* ``w_minus`` (B, C): the pre-impact normal relative velocities ``J v-`` (negative = approaching);
* ``active`` (B, C) bool: which contacts the collision detection reports (touching or penetrating);
* ``restitution``: a float or a tensor broadcastable to (B, C).

They return impulses ``lambda >= 0`` (B, C), zero on inactive contacts; the caller applies
``v+ = v- + M^-1 J^T lambda`` so that ``w+ = w- + W lambda``.

Methods
-------
``"direct"``
    Every active approaching contact on its own, ``lambda_c = -(1 + e) w_c / W_cc`` (the closed
    form of a two-body collision). Simultaneous contacts are not coupled: their impulses add up.
``"lcp"``
    All active contacts together, the frictionless linear complementarity problem with Newton's
    restitution law per contact, ``0 <= lambda  _|_  w+ + e w- >= 0``. Solved exactly by Murty's
    principal pivoting method (finite for the P-matrices that a full-rank ``W`` gives) and
    differentiated through the identified active set.
``"convex"``
    A MuJoCo-style velocity-level convex QP,
    ``min 1/2 lambda^T (W + R) lambda + lambda^T (1 + e) w-`` s.t. ``lambda >= 0``, i.e. the
    impulse that best reaches the reference velocity ``w_ref = -e w-`` with a small diagonal
    regulariser ``R = regularization * diag(W)``. Solved by projected Newton and differentiated by
    implicit differentiation of its KKT conditions (a custom backward).

Degenerate cases
----------------
* A contact with ``lambda_c = 0`` and zero complementary velocity (grazing, or a resting contact
  that another impulse does not push) is weakly active: the impulse map has a kink there. All
  methods treat it as *inactive* (``lambda_c`` pinned at zero) and return the one-sided
  derivative of that branch.
* A singular active-set system (redundant contacts, e.g. a disc squeezed between two parallel
  walls) is solved with a tiny diagonal shift ``1e-12 * diag`` so the impulse stays finite; the
  post-impact velocities remain correct to that order but the split of the impulse between the
  redundant contacts is arbitrary. ``"convex"`` with its regulariser is the well-posed choice
  for such configurations.
* Non-finite inputs raise :class:`~hybridoc.errors.EvaluationError`; a pivoting or Newton
  iteration that does not terminate raises :class:`~hybridoc.errors.ConvergenceError`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hybridoc.errors import ConvergenceError, EvaluationError
from hybridoc.solvers.contacts.base import SIGN_TOLERANCE
from hybridoc.solvers.contacts.convex import REGULARIZATION

__all__ = ["IMPULSE_METHODS", "solve_impulses", "solve_direct", "solve_lcp", "solve_convex"]

IMPULSE_METHODS: tuple[str, ...] = ("direct", "lcp", "convex")

# Relative shift added to the diagonal of a singular active-set system (see module docstring).
_SINGULAR_SHIFT = 1e-12


def _tolerance(dtype: torch.dtype) -> float:
    """Relative tolerance for sign decisions (active set, complementarity) in ``dtype``."""
    return SIGN_TOLERANCE * torch.finfo(dtype).eps


def _broadcast_restitution(restitution: float | Tensor, like: Tensor) -> Tensor:
    e = torch.as_tensor(restitution, dtype=like.dtype, device=like.device)
    if e.dim() == 1 and e.shape[0] == like.shape[0]:
        e = e.unsqueeze(-1)  # one restitution per batch element
    try:
        return torch.broadcast_to(e, like.shape)
    except RuntimeError as exc:
        raise EvaluationError(
            f"restitution of shape {tuple(e.shape)} does not broadcast to {tuple(like.shape)}"
        ) from exc


def _check_inputs(W: Tensor, w_minus: Tensor, active: Tensor) -> None:
    if W.dim() != 3 or W.shape[-1] != W.shape[-2]:
        raise EvaluationError(f"W must have shape (B, C, C), got {tuple(W.shape)}")
    if w_minus.shape != W.shape[:2]:
        raise EvaluationError(
            f"w_minus must have shape {tuple(W.shape[:2])}, got {tuple(w_minus.shape)}"
        )
    if active.shape != w_minus.shape or active.dtype != torch.bool:
        raise EvaluationError(f"active must be a bool tensor of shape {tuple(w_minus.shape)}")
    if not (torch.isfinite(W).all() and torch.isfinite(w_minus).all()):
        raise EvaluationError("non-finite Delassus matrix or contact velocity")


def masked_solve(A: Tensor, b: Tensor, mask: Tensor) -> Tensor:
    """Solve ``A[S, S] x[S] = b[S]`` with ``x = 0`` outside ``S = mask``, batched.

    The reduced systems of different batch elements have different sizes, so the solve is done
    on the full (C, C) system with the rows and columns outside ``S`` replaced by the identity.
    Differentiable in ``A`` and ``b`` (the derivative of the reduced solve; zero outside ``S``).
    A singular reduced system gets a relative diagonal shift of ``1e-12`` (module docstring).
    """
    both = mask.unsqueeze(-1) & mask.unsqueeze(-2)
    eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
    M = torch.where(both, A, torch.zeros((), dtype=A.dtype, device=A.device))
    M = M + torch.diag_embed((~mask).to(A.dtype))
    rhs = torch.where(mask, b, torch.zeros((), dtype=b.dtype, device=b.device))
    x, info = torch.linalg.solve_ex(M, rhs)
    bad = info != 0
    if bad.any() or not torch.isfinite(x).all():
        scale = torch.diagonal(M, dim1=-2, dim2=-1).abs().amax(-1, keepdim=True).clamp_min(1e-300)
        shifted = M + _SINGULAR_SHIFT * scale.unsqueeze(-1) * eye
        x = torch.linalg.solve(shifted, rhs)
    return torch.where(mask, x, torch.zeros((), dtype=x.dtype, device=x.device))


def solve_direct(W: Tensor, w_minus: Tensor, active: Tensor, e: Tensor) -> Tensor:
    """Independent closed-form impulse per active approaching contact (see module docstring)."""
    diag = torch.diagonal(W, dim1=-2, dim2=-1)
    hit = active & (w_minus < 0) & (diag > 0)
    safe = torch.where(hit, diag, torch.ones((), dtype=W.dtype, device=W.device))
    lam = -(1.0 + e) * w_minus / safe
    return torch.where(hit, lam, torch.zeros((), dtype=lam.dtype, device=lam.device))


@torch.no_grad()
def _murty(M: Tensor, q: Tensor, active: Tensor) -> Tensor:
    """Active set of ``LCP(M, q)`` restricted to ``active`` by Murty's least-index pivoting.

    Returns the bool mask ``S`` of strictly positive impulses. Murty's rule terminates for any
    P-matrix; the iteration cap (``2**C`` bounded by 10000) only guards degenerate inputs.
    """
    B, C = q.shape
    scale = q.abs().amax(-1, keepdim=True).clamp_min(torch.finfo(q.dtype).tiny)
    tol = _tolerance(q.dtype) * scale
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
    """Simultaneous frictionless LCP impulses with Newton restitution (module docstring)."""
    q = (1.0 + e) * w_minus
    # contacts with zero diagonal (no mobile body) cannot take an impulse
    act = active & (torch.diagonal(W, dim1=-2, dim2=-1) > 0)
    S = _murty(W.detach(), q.detach(), act)
    # the exact re-solve with autograd on: its derivative is the active-set derivative
    return masked_solve(W, -q, S)


class _ActiveSetQP(torch.autograd.Function):
    """``lambda = argmin 1/2 l^T H l + q^T l, l >= 0, l = 0 off active``; KKT backward."""

    @staticmethod
    def forward(ctx, H: Tensor, q: Tensor, active: Tensor, max_iter: int) -> Tensor:
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


@torch.no_grad()
def _projected_newton(H: Tensor, q: Tensor, active: Tensor, max_iter: int):
    """Bertsekas' projected Newton method for ``min 1/2 l^T H l + q^T l, l >= 0`` (batched).

    Returns the solution and its free set; each iterate ends with the exact Newton step on the
    current free face, so convergence is finite once the active set is identified.
    """
    B, C = q.shape
    scale = q.abs().amax(-1, keepdim=True).clamp_min(torch.finfo(q.dtype).tiny)
    tol = _tolerance(q.dtype) * scale
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
    impulse.
    """
    Hs = 0.5 * (W + W.transpose(-1, -2))
    H = Hs + regularization * torch.diag_embed(torch.diagonal(Hs, dim1=-2, dim2=-1))
    q = (1.0 + e) * w_minus
    # contacts with zero diagonal (no mobile body) cannot take an impulse
    act = active & (torch.diagonal(Hs, dim1=-2, dim2=-1) > 0)
    return _ActiveSetQP.apply(H, q, act, max_iter)


def solve_impulses(
    method: str,
    W: Tensor,
    w_minus: Tensor,
    active: Tensor,
    restitution: float | Tensor,
    *,
    regularization: float = REGULARIZATION,
) -> Tensor:
    """Normal contact impulses of ``C`` simultaneous frictionless contacts (batched).

    Parameters
    ----------
    method : {"direct", "lcp", "convex"}
        Impulse solver (see the module docstring).
    W : Tensor
        Delassus matrices ``J M^-1 J^T``, shape (B, C, C).
    w_minus : Tensor
        Pre-impact normal relative velocities, shape (B, C); negative means approaching.
    active : Tensor
        Bool mask (B, C) of the contacts reported by collision detection; the others get zero.
    restitution : float or Tensor
        Coefficient of restitution, a scalar or a tensor broadcastable to (B, C) (a (B,) tensor
        is taken per batch element; give a per-contact restitution as (1, C) or (B, C)).
    regularization : float, optional
        Relative diagonal regulariser of the ``"convex"`` QP (default ``1e-9``); ignored by the
        other methods.

    Returns
    -------
    Tensor
        Impulses ``lambda >= 0`` of shape (B, C), in the dtype and on the device of ``W``.
        Differentiable with respect to ``W``, ``w_minus`` and ``restitution``.
    """
    if method not in IMPULSE_METHODS:
        raise EvaluationError(
            f"unknown impulse method {method!r}; choose one of {', '.join(IMPULSE_METHODS)}"
        )
    _check_inputs(W, w_minus, active)
    e = _broadcast_restitution(restitution, w_minus)
    if W.shape[-1] == 0:
        return torch.zeros_like(w_minus)
    if method == "direct":
        return solve_direct(W, w_minus, active, e)
    if method == "lcp":
        return solve_lcp(W, w_minus, active, e)
    return solve_convex(W, w_minus, active, e, regularization=regularization)
