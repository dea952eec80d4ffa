"""Non-impulse contact models for discs: a penalty spring-damper and position-based dynamics.

Both steps are batched torch functions, differentiable with respect to every tensor input, on the
layout used by the simulator: positions ``p``, velocities ``v`` and external accelerations
``acc`` of shape (B, n, 2); ``radii`` and ``inv_mass`` of shape (n,) (``inv_mass = 0`` pins a
disc); walls as points and unit normals (W, 2) pointing into free space (``W`` may be 0).
Contacts are the disc pairs ``i < j`` (row-major order) and then the disc-wall pairs
(disc-major), as in :class:`hybridoc.HybridOCP`.

``compliant_step``
    Penalty contact: a spring-damper along the contact normal acts while two bodies overlap,
    ``f = max(k * depth - c * w, 0)`` (no adhesion), ``w`` the normal relative velocity
    (negative approaching), then symplectic Euler. For a contact of effective mass ``m`` the
    contact lasts about ``pi * sqrt(m / k)`` and symplectic Euler is stable for
    ``dt < 2 sqrt(m / k)``. The default ``k = 2e4`` gives, for the paper's unit masses at
    ``dt = 1/480``, disc-disc contacts (``m = 1/2``) of about 7.5 steps and wall contacts of about
    11 steps, ``sqrt(k / m) dt = 0.42`` and 0.29, and a penetration of about 1 cm at 2 m/s
    (5% of the radius). Stiffer springs resolve the contact in fewer steps but the on/off switch
    of the force inside a step then injects energy: at ``k = 1e5`` a head-on elastic collision
    at 2 m/s ends up to 5% off the exact exchange of velocities, at ``k = 2e4`` about 1%.
    The default damping 0 is elastic (restitution 1); :func:`damping_for_restitution` gives the
    damping of a chosen restitution.
``pbd_step``
    Position-based dynamics (Mueller et al. 2007; the restitution velocity update of Macklin
    et al. 2014 and Mueller et al. 2020): predict with symplectic Euler, project the
    non-penetration constraints by Gauss-Seidel sweeps with inverse-mass weighting, take the
    velocity from the position change, then set the normal velocity of every contact that was
    projected to ``-e`` times its predicted approach velocity.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hybridoc.errors import EvaluationError

__all__ = [
    "DEFAULT_STIFFNESS",
    "DEFAULT_DAMPING",
    "DEFAULT_PBD_ITERATIONS",
    "compliant_step",
    "damping_for_restitution",
    "pbd_step",
]

DEFAULT_STIFFNESS = 2.0e4
"""Penalty stiffness k (force per unit depth); see the module docstring for the choice."""
DEFAULT_DAMPING = 0.0
"""Penalty damping c (force per unit normal speed); 0 is elastic."""
DEFAULT_PBD_ITERATIONS = 4
"""Gauss-Seidel sweeps of the PBD projection (enough for the few contacts of the scenes)."""

# Below this distance a pair normal is undefined; the distance is clamped to avoid 0/0.
_MIN_DISTANCE = 1e-12


def _clamped_restitution(zeta: float) -> float:
    """Restitution of ``x'' + 2 zeta x' + x = 0`` from ``x = 0, x' = 1`` until the force vanishes.

    The underdamped solution is ``x = exp(-a t) sin(b t) / b`` with ``a = zeta``,
    ``b = sqrt(1 - zeta^2)``; the non-adhesive contact ends when ``x + 2 a x' = 0``, i.e. at
    ``b t = pi - atan2(2 a b, 1 - 2 a^2)``, before the spring is back at its rest length.
    """
    a, b = zeta, math.sqrt(1.0 - zeta * zeta)
    bt = math.pi - math.atan2(2.0 * a * b, 1.0 - 2.0 * a * a)
    return -math.exp(-a * bt / b) * (math.cos(bt) - (a / b) * math.sin(bt))


_ZETA_MAX = 0.999
_MIN_RESTITUTION = _clamped_restitution(_ZETA_MAX)


def damping_for_restitution(restitution: float, stiffness: float, effective_mass: float) -> float:
    """Damping ``c`` that gives the penalty contact a chosen coefficient of restitution.

    For the contact force ``max(k x - c x', 0)`` of :func:`compliant_step` on an effective mass
    ``m`` the restitution depends only on the damping ratio ``zeta = c / (2 sqrt(k m))``. The
    contact ends when the force returns to zero, earlier than the spring's rest length, so the
    textbook relation ``e = exp(-zeta pi / sqrt(1 - zeta^2))`` of the adhesive spring-damper
    underestimates ``e`` (for ``zeta`` giving 0.5 there, the clamped contact rebounds with
    0.58). This function inverts the clamped relation exactly (bisection on ``zeta < 1``);
    the discrete step adds an error of order ``sqrt(k / m) dt``.

    Parameters
    ----------
    restitution : float
        Target coefficient of restitution, from about 0.136 (``zeta`` close to 1) to 1.
    stiffness : float
        Penalty stiffness ``k``.
    effective_mass : float
        ``1 / (1/m_i + 1/m_j)`` for a pair, ``m_i`` for a wall contact.

    Returns
    -------
    float
        The damping ``c``.
    """
    if not _MIN_RESTITUTION <= restitution <= 1.0:
        raise EvaluationError(
            f"a non-adhesive spring-damper reaches restitutions in [{_MIN_RESTITUTION:.3f}, 1], "
            f"got {restitution}; use an impulse model or pbd for smaller ones"
        )
    lo, hi = 0.0, _ZETA_MAX  # e(zeta) decreases from 1 at zeta = 0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if _clamped_restitution(mid) > restitution:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-15:
            break
    zeta = 0.5 * (lo + hi)
    return 2.0 * zeta * math.sqrt(stiffness * effective_mass)


def _prepare(p, v, acc, radii, inv_mass, wall_points, wall_normals):
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


def _pairs(n: int, device) -> tuple[Tensor, Tensor]:
    ij = torch.triu_indices(n, n, offset=1, device=device)
    return ij[0], ij[1]


def compliant_step(
    p: Tensor,
    v: Tensor,
    acc: Tensor,
    dt: float,
    radii: Tensor,
    inv_mass: Tensor,
    wall_points: Tensor,
    wall_normals: Tensor,
    *,
    stiffness: float | Tensor = DEFAULT_STIFFNESS,
    damping: float | Tensor = DEFAULT_DAMPING,
) -> tuple[Tensor, Tensor]:
    """One symplectic Euler step with penalty spring-damper contact forces.

    Parameters
    ----------
    p, v, acc : Tensor
        Positions, velocities and external accelerations (forces times inverse masses), each
        of shape (B, n, 2).
    dt : float
        Time step.
    radii, inv_mass : Tensor
        Disc radii and inverse masses, shape (n,).
    wall_points, wall_normals : Tensor
        A point on each wall and its unit normal into free space, shape (W, 2).
    stiffness : float or Tensor, optional
        Spring constant ``k`` (default :data:`DEFAULT_STIFFNESS`).
    damping : float or Tensor, optional
        Damping ``c`` on the normal relative velocity (default :data:`DEFAULT_DAMPING`).

    Returns
    -------
    tuple of Tensor
        ``(p_next, v_next)``, each (B, n, 2).
    """
    radii, inv_mass, wall_points, wall_normals = _prepare(
        p, v, acc, radii, inv_mass, wall_points, wall_normals
    )
    n = p.shape[1]
    force = torch.zeros_like(p)
    zero = torch.zeros((), dtype=p.dtype, device=p.device)
    if n > 1:
        i, j = _pairs(n, p.device)
        d = p[:, i] - p[:, j]  # (B, P, 2)
        dist = d.norm(dim=-1).clamp_min(_MIN_DISTANCE)
        normal = d / dist.unsqueeze(-1)
        depth = radii[i] + radii[j] - dist
        w = ((v[:, i] - v[:, j]) * normal).sum(-1)
        f = torch.where(depth > 0, torch.clamp(stiffness * depth - damping * w, min=0.0), zero)
        fn = f.unsqueeze(-1) * normal
        force = force.index_add(1, i, fn).index_add(1, j, -fn)
    if wall_points.shape[0] > 0:
        # (B, n, W): signed distance of each disc to each wall
        gap = torch.einsum("bnk,wk->bnw", p, wall_normals) - (wall_points * wall_normals).sum(-1)
        depth = radii.unsqueeze(-1) - gap
        w = torch.einsum("bnk,wk->bnw", v, wall_normals)
        f = torch.where(depth > 0, torch.clamp(stiffness * depth - damping * w, min=0.0), zero)
        force = force + torch.einsum("bnw,wk->bnk", f, wall_normals)
    v_next = v + (acc + inv_mass.unsqueeze(-1) * force) * dt
    p_next = p + v_next * dt
    return p_next, v_next


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
    radii, inv_mass, wall_points, wall_normals = _prepare(
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
            d = x[i] - x[j]
            dist = d.norm(dim=-1).clamp_min(_MIN_DISTANCE)
            normal = d / dist.unsqueeze(-1)
            C = dist - (radii[i] + radii[j])
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
            C = ((x[i] - wall_points[k]) * nk).sum(-1) - radii[i]
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
        d = xs[:, i] - xs[:, j]
        normal = d / d.norm(dim=-1, keepdim=True).clamp_min(_MIN_DISTANCE)
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
