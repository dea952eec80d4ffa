"""``compliant``: a penalty spring-damper contact (not an impulse model).

A spring-damper along the contact normal acts while two bodies overlap,
``f = max(k * depth - c * w, 0)`` (no adhesion), ``w`` the normal relative velocity (negative
approaching), then symplectic Euler. For a contact of effective mass ``m`` the contact lasts
about ``pi * sqrt(m / k)`` and symplectic Euler is stable for ``dt < 2 sqrt(m / k)``. The
default ``k = 2e4`` gives, for the paper's unit masses at ``dt = 1/480``, disc-disc contacts
(``m = 1/2``) of about 7.5 steps and wall contacts of about 11 steps,
``sqrt(k / m) dt = 0.42`` and 0.29, and a penetration of about 1 cm at 2 m/s (5% of the
radius). Stiffer springs resolve the contact in fewer steps but the on/off switch of the force
inside a step then injects energy: at ``k = 1e5`` a head-on elastic collision at 2 m/s ends
up to 5% off the exact exchange of velocities, at ``k = 2e4`` about 1%. The default damping 0
is elastic (restitution 1); :func:`damping_for_restitution` gives the damping of a chosen
restitution.

The step is a batched torch function, differentiable with respect to every tensor input, on
the simulator's layout: positions ``p``, velocities ``v`` and external accelerations ``acc``
of shape (B, n, 2); ``radii`` and ``inv_mass`` (n,) (``inv_mass = 0`` pins a disc); walls as
points and unit normals (W, 2) pointing into free space. Gaps and normals come from
:mod:`hybridoc.problems.physics`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # torch is imported where it is used: the registry must stay light
    from torch import Tensor

    from hybridoc.problems.scene import Scene

from hybridoc.errors import EvaluationError
from hybridoc.problems import physics as ph
from hybridoc.solvers.contacts.base import ContactModel, register
from hybridoc.solvers.contacts.penalty_common import MIN_DISTANCE, pairs, prepare

__all__ = [
    "Compliant",
    "DEFAULT_DAMPING",
    "DEFAULT_STIFFNESS",
    "compliant_casadi_step",
    "compliant_step",
    "damping_for_restitution",
    "penalty_force",
]

DEFAULT_STIFFNESS = 2.0e4
"""Penalty stiffness k (force per unit depth); see the module docstring for the choice."""
DEFAULT_DAMPING = 0.0
"""Penalty damping c (force per unit normal speed); 0 is elastic."""


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


def penalty_force(depth: Any, w: Any, stiffness: Any, damping: Any, ops: ph.Ops) -> Any:
    """The contact force ``max(k depth - c w, 0)`` where ``depth > 0``, else 0 (either backend).

    The one force law of :func:`compliant_step` (torch) and :func:`compliant_casadi_step`.
    """
    return ops.where(depth > 0, ops.clip(stiffness * depth - damping * w, 0.0, math.inf), 0.0)


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
    import torch

    radii, inv_mass, wall_points, wall_normals = prepare(
        p, v, acc, radii, inv_mass, wall_points, wall_normals
    )
    n = p.shape[1]
    force = torch.zeros_like(p)
    if n > 1:
        i, j = pairs(n, p.device)
        gap, normal = ph.pair_gap(
            p[:, i] - p[:, j], radii[i] + radii[j], ph.TORCH, min_distance=MIN_DISTANCE
        )
        depth = -gap
        w = ph.normal_speed(v[:, i] - v[:, j], normal, ph.TORCH)
        fn = penalty_force(depth, w, stiffness, damping, ph.TORCH).unsqueeze(-1) * normal
        force = force.index_add(1, i, fn).index_add(1, j, -fn)
    if wall_points.shape[0] > 0:
        # (B, n, W): gap of each disc to each wall
        gap = ph.wall_gap(p[:, :, None, :], wall_points, wall_normals, radii[:, None], ph.TORCH)
        depth = -gap
        w = torch.einsum("bnk,wk->bnw", v, wall_normals)
        f = penalty_force(depth, w, stiffness, damping, ph.TORCH)
        force = force + torch.einsum("bnw,wk->bnk", f, wall_normals)
    v_next = v + (acc + inv_mass.unsqueeze(-1) * force) * dt
    p_next = p + v_next * dt
    return p_next, v_next


def compliant_casadi_step(
    scene: Scene,
    s: Any,
    u: Any,
    *,
    stiffness: float = DEFAULT_STIFFNESS,
    damping: float = DEFAULT_DAMPING,
) -> Any:
    """:func:`compliant_step` of a scene in CasADi: the next state as an expression.

    Parameters
    ----------
    scene : Scene
        The disc scene.
    s, u : casadi.SX
        State ``(4 n,)`` and control ``(nu,)`` symbols.
    stiffness, damping : float, optional
        As in :func:`compliant_step`.

    Returns
    -------
    casadi.SX
        The state after one step; the forces are summed in :func:`compliant_step`'s order
        (pairs on their first disc, then on their second, then the walls).
    """
    import casadi as ca

    from hybridoc.solvers.contacts.casadi_parts import disc_kinematics

    ops = ph.CASADI
    n, dt = scene.n_discs, scene.dt
    p, v, a = disc_kinematics(scene, s, u)
    radii = [d.radius for d in scene.discs]
    plus: list[list[Any]] = [[] for _ in range(n)]
    minus: list[list[Any]] = [[] for _ in range(n)]
    for i in range(n):
        for j in range(i + 1, n):
            gap, normal = ph.pair_gap(
                p[i] - p[j], radii[i] + radii[j], ops, min_distance=MIN_DISTANCE
            )
            w = ph.normal_speed(v[i] - v[j], normal, ops)
            fn = penalty_force(-gap, w, stiffness, damping, ops) * normal
            plus[i].append(fn)
            minus[j].append(-fn)
    p_next, v_next = [], []
    for i in range(n):
        force: Any = 0.0
        for f in plus[i] + minus[i]:
            force = force + f
        if scene.walls:
            wall_sum: Any = 0.0
            for wall in scene.walls:
                nw = ca.DM(wall.normal)
                gap = ph.wall_gap(p[i], ca.DM(wall.point), nw, radii[i], ops)
                w = ph.normal_speed(v[i], nw, ops)
                wall_sum = wall_sum + penalty_force(-gap, w, stiffness, damping, ops) * nw
            force = force + wall_sum
        vi = v[i] + (a[i] + (1.0 / scene.discs[i].mass) * force) * dt
        v_next.append(vi)
        p_next.append(p[i] + vi * dt)
    return ca.vertcat(*p_next, *v_next)


@register
class Compliant(ContactModel):
    """Penalty spring-damper contacts (:func:`compliant_step`).

    Parameters
    ----------
    stiffness, damping
        Spring constant ``k`` and damping ``c`` (defaults :data:`DEFAULT_STIFFNESS`,
        :data:`DEFAULT_DAMPING`).
    """

    name = "compliant"
    summary = "penalty spring-damper (not an impulse model)"
    compiled = True

    def __init__(
        self, stiffness: float = DEFAULT_STIFFNESS, damping: float = DEFAULT_DAMPING, **options: Any
    ) -> None:
        options.pop("toi", None)  # no time of impact: accepted and ignored for uniform calls
        super().__init__(**options)
        self.stiffness = float(stiffness)
        self.damping = float(damping)

    def torch_step(self, sim: Any, p: Tensor, v: Tensor, acc: Tensor) -> tuple[Tensor, Tensor]:
        return compliant_step(
            p, v, acc, sim.dt, sim.radii, 1.0 / sim.masses, sim.wall_points, sim.wall_normals,
            stiffness=self.stiffness, damping=self.damping,
        )  # fmt: skip

    def casadi_next_state(self, scene: Scene, s: Any, u: Any, integrator: str) -> Any:
        return compliant_casadi_step(scene, s, u, stiffness=self.stiffness, damping=self.damping)
