"""``pbd``: position-based dynamics (not an impulse model).

Mueller et al. 2007, with the restitution velocity update of Macklin et al. 2014 and Mueller
et al. 2020: predict with symplectic Euler, project the non-penetration constraints by
Gauss-Seidel sweeps with inverse-mass weighting, take the velocity from the position change,
then set the normal velocity of every contact that was projected to ``-e`` times its
predicted approach velocity. Gaps and normals come from :mod:`hybridoc.problems.physics`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # torch is imported where it is used: the registry must stay light
    from torch import Tensor

from hybridoc.errors import EvaluationError
from hybridoc.problems import physics as ph
from hybridoc.solvers.contacts._penalty_common import MIN_DISTANCE, prepare
from hybridoc.solvers.contacts.base import ContactModel, register

__all__ = ["DEFAULT_PBD_ITERATIONS", "PBD", "pbd_step"]

DEFAULT_PBD_ITERATIONS = 4
"""Gauss-Seidel sweeps of the PBD projection (enough for the few contacts of the scenes)."""


def pbd_step(
    p: Tensor,
    v: Tensor,
    acc: Tensor,
    dt: float,
    radii: Tensor,
    inv_mass: Tensor,
    wall_points: Tensor,
    wall_normals: Tensor,
    restitution: float | Tensor,
    *,
    iterations: int = DEFAULT_PBD_ITERATIONS,
) -> tuple[Tensor, Tensor]:
    """One position-based dynamics step with non-penetration constraints and restitution.

    Parameters
    ----------
    p, v, acc : Tensor
        Positions, velocities and external accelerations, each of shape (B, n, 2).
    dt : float
        Time step.
    radii, inv_mass : Tensor
        Disc radii and inverse masses, shape (n,); a disc with ``inv_mass = 0`` does not move.
    wall_points, wall_normals : Tensor
        A point on each wall and its unit normal into free space, shape (W, 2).
    restitution : float or Tensor
        Coefficient of restitution of the velocity update.
    iterations : int, optional
        Gauss-Seidel sweeps over all constraints (default :data:`DEFAULT_PBD_ITERATIONS`).

    Returns
    -------
    tuple of Tensor
        ``(p_next, v_next)``, each (B, n, 2).

    Notes
    -----
    Constraints ``C >= 0`` (gap of a pair or of a disc and a wall) are projected one after the
    other in the contact order; a violated one moves the bodies along its normal by ``-C``,
    split in proportion to the inverse masses. Every constraint that was projected at least
    once is a contact of this step: its normal relative velocity after ``v = (x - p) / dt`` is
    replaced by ``max(-e w_pred, 0)``, ``w_pred`` the normal velocity of the prediction, with the
    same inverse-mass split (the normal is taken at the projected positions).
    """
    import torch

    radii, inv_mass, wall_points, wall_normals = prepare(
        p, v, acc, radii, inv_mass, wall_points, wall_normals
    )
    if iterations < 1:
        raise EvaluationError(f"PBD needs at least one iteration, got {iterations}")
    n = p.shape[1]
    n_walls = wall_points.shape[0]
    zero = torch.zeros((), dtype=p.dtype, device=p.device)
    e = torch.as_tensor(restitution, dtype=p.dtype, device=p.device)
    v_pred = v + acc * dt
    x_pred = p + v_pred * dt
    x = list(x_pred.unbind(1))  # per-disc (B, 2), updated in constraint order
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    walls = [(i, k) for i in range(n) for k in range(n_walls)]
    B = p.shape[0]
    touched_pair = [torch.zeros(B, dtype=torch.bool, device=p.device) for _ in pairs]
    touched_wall = [torch.zeros(B, dtype=torch.bool, device=p.device) for _ in walls]

    def weights(wi: Tensor, wj: Tensor) -> tuple[Tensor, Tensor]:
        total = wi + wj
        safe = torch.where(total > 0, total, torch.ones((), dtype=p.dtype, device=p.device))
        return wi / safe, wj / safe

    for _ in range(iterations):
        any_hit = False
        for c, (i, j) in enumerate(pairs):
            C, normal = ph.pair_gap(
                x[i] - x[j], radii[i] + radii[j], ph.TORCH, min_distance=MIN_DISTANCE
            )
            hit = C < 0
            if not bool(hit.any()):
                continue  # nothing to project (also saves the autograd graph)
            any_hit = True
            touched_pair[c] = touched_pair[c] | hit
            ai, aj = weights(inv_mass[i], inv_mass[j])
            corr = torch.where(hit, -C, zero).unsqueeze(-1) * normal
            x[i] = x[i] + ai * corr
            x[j] = x[j] - aj * corr
        for c, (i, k) in enumerate(walls):
            nk = wall_normals[k]
            C = ph.wall_gap(x[i], wall_points[k], nk, radii[i], ph.TORCH)
            hit = C < 0
            if not bool(hit.any()):
                continue
            any_hit = True
            touched_wall[c] = touched_wall[c] | hit
            moves = (inv_mass[i] > 0).to(p.dtype)
            x[i] = x[i] + moves * torch.where(hit, -C, zero).unsqueeze(-1) * nk
        if not any_hit:
            break  # a sweep without violations leaves every later sweep without any
    xs = torch.stack(x, dim=1)
    # (xs - p) / dt, written so that a step without contact is exactly symplectic Euler
    vel = [vi for vi in (v_pred + (xs - x_pred) / dt).unbind(1)]
    vp = v_pred.unbind(1)
    # restitution velocity update on the contacts of this step, one after the other
    for c, (i, j) in enumerate(pairs):
        if not bool(touched_pair[c].any()):
            continue
        _, normal = ph.pair_gap(xs[:, i] - xs[:, j], 0.0, ph.TORCH, min_distance=MIN_DISTANCE)
        w_pred = ((vp[i] - vp[j]) * normal).sum(-1)
        w_now = ((vel[i] - vel[j]) * normal).sum(-1)
        target = torch.clamp(-e * w_pred, min=0.0)
        dw = torch.where(touched_pair[c], target - w_now, zero).unsqueeze(-1) * normal
        ai, aj = weights(inv_mass[i], inv_mass[j])
        vel[i] = vel[i] + ai * dw
        vel[j] = vel[j] - aj * dw
    for c, (i, k) in enumerate(walls):
        if not bool(touched_wall[c].any()):
            continue
        nk = wall_normals[k]
        w_pred = (vp[i] * nk).sum(-1)
        w_now = (vel[i] * nk).sum(-1)
        target = torch.clamp(-e * w_pred, min=0.0)
        moves = (inv_mass[i] > 0).to(p.dtype)
        vel[i] = (
            vel[i] + moves * torch.where(touched_wall[c], target - w_now, zero).unsqueeze(-1) * nk
        )
    return xs, torch.stack(vel, dim=1)


@register
class PBD(ContactModel):
    """Position-based dynamics (:func:`pbd_step`).

    Parameters
    ----------
    iterations
        Gauss-Seidel sweeps (default :data:`DEFAULT_PBD_ITERATIONS`).
    """

    name = "pbd"
    summary = "position-based dynamics with a restitution update (not an impulse model)"

    def __init__(self, iterations: int = DEFAULT_PBD_ITERATIONS, **options: Any) -> None:
        options.pop("toi", None)
        super().__init__(**options)
        self.iterations = int(iterations)

    def settings(self) -> dict[str, Any]:
        return {"contact": self.name, "iterations": self.iterations}

    def torch_step(self, sim: Any, p: Tensor, v: Tensor, acc: Tensor) -> tuple[Tensor, Tensor]:
        return pbd_step(
            p, v, acc, sim.dt, sim.radii, 1.0 / sim.masses, sim.wall_points, sim.wall_normals,
            sim.restitution, iterations=self.iterations,
        )  # fmt: skip
