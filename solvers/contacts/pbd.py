"""``pbd``: position-based dynamics (not an impulse model).

Mueller et al. 2007, with the restitution velocity update of Macklin et al. 2014 and Mueller
et al. 2020: predict with symplectic Euler, project the non-penetration constraints by
Gauss-Seidel sweeps with inverse-mass weighting, take the velocity from the position change,
then set the normal velocity of every contact that was projected to ``-e`` times its
predicted approach velocity. Gaps and normals come from :mod:`hybridoc.problems.physics`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # torch is imported where it is used: the registry must stay light
    from torch import Tensor

    from hybridoc.problems.scene import Scene

from hybridoc.errors import EvaluationError
from hybridoc.problems import physics as ph
from hybridoc.solvers.contacts.base import ContactModel, register
from hybridoc.solvers.contacts.penalty_common import MIN_DISTANCE, prepare

__all__ = ["DEFAULT_PBD_ITERATIONS", "PBD", "pbd_casadi_step", "pbd_step"]

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
    e = torch.as_tensor(restitution, dtype=p.dtype, device=p.device)
    one = torch.ones((), dtype=p.dtype, device=p.device)

    def weights(i: int, j: int) -> tuple[Tensor, Tensor]:
        total = inv_mass[i] + inv_mass[j]
        safe = torch.where(total > 0, total, one)
        return inv_mass[i] / safe, inv_mass[j] / safe

    v_pred = v + acc * dt
    x_pred = p + v_pred * dt
    xs, vel = _pbd_core(
        list(x_pred.unbind(1)), list(v_pred.unbind(1)), dt, radii, e,
        [weights(i, j) for i in range(n) for j in range(i + 1, n)],
        [(inv_mass[i] > 0).to(p.dtype) for i in range(n)],
        list(zip(wall_points.unbind(0), wall_normals.unbind(0), strict=True)),
        iterations, ph.TORCH,
        # a constraint violated nowhere in the batch changes nothing: skip it (and its graph)
        nowhere=lambda mask: not bool(mask.any()),
        either=lambda a, b: a | b,
    )  # fmt: skip
    return torch.stack(xs, dim=1), torch.stack(vel, dim=1)


def pbd_casadi_step(
    scene: Scene, s: Any, u: Any, *, iterations: int = DEFAULT_PBD_ITERATIONS
) -> Any:
    """:func:`pbd_step` of a scene in CasADi: the next state as an expression.

    The same sweeps as the torch step (one shared algorithm); a constraint that the torch step
    skips because it is nowhere violated is a no-op here, so the two agree to rounding.

    Parameters
    ----------
    scene : Scene
        The disc scene.
    s, u : casadi.SX
        State ``(4 n,)`` and control ``(nu,)`` symbols.
    iterations : int, optional
        Gauss-Seidel sweeps (default :data:`DEFAULT_PBD_ITERATIONS`).

    Returns
    -------
    casadi.SX
        The state after one step.
    """
    import casadi as ca

    from hybridoc.solvers.contacts.casadi_parts import disc_kinematics

    if iterations < 1:
        raise EvaluationError(f"PBD needs at least one iteration, got {iterations}")
    n, dt = scene.n_discs, scene.dt
    inv_mass = [1.0 / d.mass for d in scene.discs]

    def weights(i: int, j: int) -> tuple[float, float]:
        total = inv_mass[i] + inv_mass[j]
        safe = total if total > 0 else 1.0
        return inv_mass[i] / safe, inv_mass[j] / safe

    p, v, a = disc_kinematics(scene, s, u)
    v_pred = [v[i] + a[i] * dt for i in range(n)]
    x_pred = [p[i] + v_pred[i] * dt for i in range(n)]
    xs, vel = _pbd_core(
        x_pred, v_pred, dt, [d.radius for d in scene.discs], scene.restitution,
        [weights(i, j) for i in range(n) for j in range(i + 1, n)],
        [1.0 if m > 0 else 0.0 for m in inv_mass],
        [(ca.DM(w.point), ca.DM(w.normal)) for w in scene.walls],
        iterations, ph.CASADI,
        nowhere=lambda mask: False,
        either=ca.logic_or,
    )  # fmt: skip
    return ca.vertcat(*xs, *vel)


def _pbd_core(
    x_pred: list[Any],
    v_pred: list[Any],
    dt: float,
    radii: Any,
    e: Any,
    pair_weights: list[tuple[Any, Any]],
    moves: list[Any],
    walls: list[tuple[Any, Any]],
    iterations: int,
    ops: ph.Ops,
    *,
    nowhere: Callable[[Any], bool],
    either: Callable[[Any, Any], Any],
) -> tuple[list[Any], list[Any]]:
    """The PBD algorithm on per-disc vectors of either backend (see :func:`pbd_step`).

    ``pair_weights`` holds each pair's inverse-mass split, ``moves`` 1 for a mobile disc,
    ``walls`` each wall's point and normal; ``nowhere(mask)`` may report that a constraint is
    violated nowhere (torch: the whole batch) so that it is skipped, ``either`` is a logical
    or. Returns the positions and velocities, per disc.
    """
    n = len(x_pred)
    x = list(x_pred)  # updated in constraint order
    pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    wall_contacts = [(i, k) for i in range(n) for k in range(len(walls))]
    touched_pair: list[Any] = [None] * len(pairs)
    touched_wall: list[Any] = [None] * len(wall_contacts)

    def touch(old: Any, hit: Any) -> Any:
        return hit if old is None else either(old, hit)

    for _ in range(iterations):
        any_hit = False
        for c, (i, j) in enumerate(pairs):
            C, normal = ph.pair_gap(
                x[i] - x[j], radii[i] + radii[j], ops, min_distance=MIN_DISTANCE
            )
            hit = C < 0
            if nowhere(hit):
                continue
            any_hit = True
            touched_pair[c] = touch(touched_pair[c], hit)
            ai, aj = pair_weights[c]
            corr = ops.vec(ops.where(hit, -C, 0.0)) * normal
            x[i] = x[i] + ai * corr
            x[j] = x[j] - aj * corr
        for c, (i, k) in enumerate(wall_contacts):
            point, nk = walls[k]
            C = ph.wall_gap(x[i], point, nk, radii[i], ops)
            hit = C < 0
            if nowhere(hit):
                continue
            any_hit = True
            touched_wall[c] = touch(touched_wall[c], hit)
            x[i] = x[i] + moves[i] * ops.vec(ops.where(hit, -C, 0.0)) * nk
        if not any_hit:
            break  # a sweep without violations leaves every later sweep without any
    # (x - p) / dt, written so that a step without contact is exactly symplectic Euler
    vel = [v_pred[i] + (x[i] - x_pred[i]) / dt for i in range(n)]
    # restitution velocity update on the contacts of this step, one after the other
    for c, (i, j) in enumerate(pairs):
        if touched_pair[c] is None or nowhere(touched_pair[c]):
            continue
        _, normal = ph.pair_gap(x[i] - x[j], 0.0, ops, min_distance=MIN_DISTANCE)
        w_pred = ops.dot(v_pred[i] - v_pred[j], normal)
        w_now = ops.dot(vel[i] - vel[j], normal)
        target = ops.clip(-e * w_pred, 0.0, math.inf)
        dw = ops.vec(ops.where(touched_pair[c], target - w_now, 0.0)) * normal
        ai, aj = pair_weights[c]
        vel[i] = vel[i] + ai * dw
        vel[j] = vel[j] - aj * dw
    for c, (i, k) in enumerate(wall_contacts):
        if touched_wall[c] is None or nowhere(touched_wall[c]):
            continue
        nk = walls[k][1]
        w_pred = ops.dot(v_pred[i], nk)
        w_now = ops.dot(vel[i], nk)
        target = ops.clip(-e * w_pred, 0.0, math.inf)
        vel[i] = vel[i] + moves[i] * ops.vec(ops.where(touched_wall[c], target - w_now, 0.0)) * nk
    return x, vel


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
    compiled = True

    def __init__(self, iterations: int = DEFAULT_PBD_ITERATIONS, **options: Any) -> None:
        options.pop("toi", None)
        super().__init__(**options)
        self.iterations = int(iterations)

    def torch_step(self, sim: Any, p: Tensor, v: Tensor, acc: Tensor) -> tuple[Tensor, Tensor]:
        return pbd_step(
            p, v, acc, sim.dt, sim.radii, 1.0 / sim.masses, sim.wall_points, sim.wall_normals,
            sim.restitution, iterations=self.iterations,
        )  # fmt: skip

    def casadi_next_state(self, scene: Scene, s: Any, u: Any, integrator: str) -> Any:
        return pbd_casadi_step(scene, s, u, iterations=self.iterations)
