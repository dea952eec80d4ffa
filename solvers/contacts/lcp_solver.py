"""Shared pieces of the torch impulse solvers of the impulse models.

Every model's torch solve (:meth:`~hybridoc.solvers.contacts.impulse.ImpulseModel.impulses`,
in the model's own module) takes the same inputs for a batch of ``B`` steps with ``C``
potential contacts each:

* ``W`` (B, C, C): the Delassus matrix ``J M^-1 J^T`` (row ``c`` of ``J`` maps body velocities to
  the normal relative velocity of contact ``c``; positive means separating);
* ``w_minus`` (B, C): the pre-impact normal relative velocities ``J v-`` (negative = approaching);
* ``active`` (B, C) bool: which contacts the collision detection reports (touching or penetrating);
* ``restitution``: a float or a tensor broadcastable to (B, C) (a (B,) tensor is taken per batch
  element; give a per-contact restitution as (1, C) or (B, C)).

They return impulses ``lambda >= 0`` (B, C), zero on inactive contacts; the caller applies
``v+ = v- + M^-1 J^T lambda`` so that ``w+ = w- + W lambda``. This module holds what they
share: :func:`prepare_impulses` (the input checks), :func:`masked_solve` (the solve on an
active set, with which ``lcp`` and ``convex`` solve their complementarity problems) and the
sign tolerance.

Degenerate cases
----------------
* A contact with ``lambda_c = 0`` and zero complementary velocity (grazing, or a resting contact
  that another impulse does not push) is weakly active: the impulse map has a kink there. All
  solvers treat it as *inactive* (``lambda_c`` pinned at zero) and return the one-sided
  derivative of that branch.
* A singular active-set system (redundant contacts, e.g. a disc squeezed between two parallel
  walls) is solved with a tiny diagonal shift ``1e-12 * diag`` so the impulse stays finite; the
  post-impact velocities remain correct to that order but the split of the impulse between the
  redundant contacts is arbitrary. ``convex`` with its regulariser is the well-posed choice
  for such configurations.
* Non-finite inputs raise :class:`~hybridoc.errors.EvaluationError`; a pivoting or Newton
  iteration that does not terminate raises :class:`~hybridoc.errors.ConvergenceError`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from hybridoc.errors import EvaluationError
from hybridoc.solvers.contacts.base import SIGN_TOLERANCE

if TYPE_CHECKING:  # torch is imported where it is used: the registry must stay light
    import torch
    from torch import Tensor

__all__ = [
    "SINGULAR_SHIFT",
    "broadcast_restitution",
    "check_impulse_inputs",
    "masked_solve",
    "prepare_impulses",
    "sign_tolerance",
]

SINGULAR_SHIFT = 1e-12
"""Relative shift added to the diagonal of a singular active-set system (module notes)."""


def sign_tolerance(dtype: torch.dtype) -> float:
    """Relative tolerance for sign decisions (active set, complementarity) in ``dtype``."""
    import torch

    return SIGN_TOLERANCE * torch.finfo(dtype).eps


def broadcast_restitution(restitution: float | Tensor, like: Tensor) -> Tensor:
    """``restitution`` as a tensor of the shape of ``like`` (a (B,) tensor per batch element)."""
    import torch

    e = torch.as_tensor(restitution, dtype=like.dtype, device=like.device)
    if e.dim() == 1 and e.shape[0] == like.shape[0]:
        e = e.unsqueeze(-1)  # one restitution per batch element
    try:
        return torch.broadcast_to(e, like.shape)
    except RuntimeError as exc:
        raise EvaluationError(
            f"restitution of shape {tuple(e.shape)} does not broadcast to {tuple(like.shape)}"
        ) from exc


def check_impulse_inputs(W: Tensor, w_minus: Tensor, active: Tensor) -> None:
    """Raise :class:`~hybridoc.errors.EvaluationError` on wrong shapes or non-finite inputs."""
    import torch

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
    import torch

    both = mask.unsqueeze(-1) & mask.unsqueeze(-2)
    eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
    M = torch.where(both, A, torch.zeros((), dtype=A.dtype, device=A.device))
    M = M + torch.diag_embed((~mask).to(A.dtype))
    rhs = torch.where(mask, b, torch.zeros((), dtype=b.dtype, device=b.device))
    x, info = torch.linalg.solve_ex(M, rhs)
    bad = info != 0
    if bad.any() or not torch.isfinite(x).all():
        scale = torch.diagonal(M, dim1=-2, dim2=-1).abs().amax(-1, keepdim=True).clamp_min(1e-300)
        shifted = M + SINGULAR_SHIFT * scale.unsqueeze(-1) * eye
        x = torch.linalg.solve(shifted, rhs)
    return torch.where(mask, x, torch.zeros((), dtype=x.dtype, device=x.device))


def prepare_impulses(
    W: Tensor, w_minus: Tensor, active: Tensor, restitution: float | Tensor
) -> Tensor:
    """Check the inputs of an impulse solve; the restitution broadcast to ``(B, C)``.

    Raises
    ------
    hybridoc.errors.EvaluationError
        Wrong shapes, a non-bool ``active`` or non-finite ``W`` or ``w_minus``.
    """
    check_impulse_inputs(W, w_minus, active)
    return broadcast_restitution(restitution, w_minus)
