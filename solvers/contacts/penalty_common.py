"""Shared input checks of the non-impulse models (penalty and PBD)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # torch is imported where it is used: the registry must stay light
    from torch import Tensor

from hybridoc.errors import EvaluationError

__all__ = ["MIN_DISTANCE", "prepare", "pairs"]

MIN_DISTANCE = 1e-12
"""Below this distance a pair normal is undefined; the distance is clamped to avoid 0/0."""


def prepare(
    p: Any, v: Any, acc: Any, radii: Any, inv_mass: Any, wall_points: Any, wall_normals: Any
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Check shapes; return ``radii, inv_mass, wall_points, wall_normals`` as tensors."""
    import torch

    if p.dim() != 3 or p.shape[-1] != 2:
        raise EvaluationError(f"positions must have shape (B, n, 2), got {tuple(p.shape)}")
    if v.shape != p.shape or acc.shape != p.shape:
        raise EvaluationError(
            f"p, v, acc must share the shape (B, n, 2): {tuple(p.shape)}, {tuple(v.shape)}, "
            f"{tuple(acc.shape)}"
        )
    n = p.shape[1]
    kw = {"dtype": p.dtype, "device": p.device}
    radii = torch.as_tensor(radii, **kw)
    inv_mass = torch.as_tensor(inv_mass, **kw)
    if radii.shape != (n,) or inv_mass.shape != (n,):
        raise EvaluationError(f"radii and inv_mass must have shape ({n},)")
    wall_points = torch.as_tensor(wall_points, **kw).reshape(-1, 2)
    wall_normals = torch.as_tensor(wall_normals, **kw).reshape(-1, 2)
    if wall_points.shape != wall_normals.shape:
        raise EvaluationError("wall_points and wall_normals must have the same shape (W, 2)")
    return radii, inv_mass, wall_points, wall_normals


def pairs(n: int, device: Any) -> tuple[Tensor, Tensor]:
    """Indices ``(i, j)`` of the disc pairs ``i < j`` in row-major order."""
    import torch

    ij = torch.triu_indices(n, n, offset=1, device=device)
    return ij[0], ij[1]
