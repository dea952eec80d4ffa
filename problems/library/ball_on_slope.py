"""A 2-D ball with a 2-D thrust bouncing on an inclined plane."""

from __future__ import annotations

import math
from collections.abc import Sequence

import casadi as ca
import numpy as np

from hybridoc.ocp import Guard, HybridOCP
from hybridoc.problems.library.registry import library_problem

from ._common import affine_flow_map, check_positive, check_restitution, verified_claim

__all__ = ["ball_on_slope", "free_flight_on_slope"]

#: (bounces, restitution) -> optimal number of impacts, checked in tests/library_optima.py
_VERIFIED = {(1.0, 0.9): 1, (2.0, 0.9): 2}


def _slope_normal(slope_deg: float) -> np.ndarray:
    a = math.radians(slope_deg)
    return np.array([-math.sin(a), math.cos(a)])


def free_flight_on_slope(
    position: Sequence[float],
    velocity: Sequence[float],
    *,
    slope_deg: float,
    restitution: float,
    gravity: float,
    count: int,
) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """The first ``count`` impacts of the ball without thrust: ``(time, p-, v-)`` each.

    Between impacts ``p(t)`` is a parabola; the guard ``psi = p . n`` is a quadratic in time
    whose larger root is the next impact.
    """
    n = _slope_normal(slope_deg)
    acc = np.array([0.0, -gravity])
    p, v = np.asarray(position, float), np.asarray(velocity, float)
    t, out = 0.0, []
    for _ in range(count):
        a2, a1, a0 = 0.5 * (n @ acc), n @ v, n @ p
        tau = (-a1 - math.sqrt(a1 * a1 - 4 * a2 * a0)) / (2 * a2)
        p = p + v * tau + 0.5 * acc * tau**2
        v = v + acc * tau
        t += tau
        out.append((t, p.copy(), v.copy()))
        v = v - (1 + restitution) * (v @ n) * n
    return out


# over 80 lines: one problem stated whole; most lines are its keyword parameters, listed
# in the signature, checked, and recorded in meta["params"]
@library_problem("ball-on-slope")
def ball_on_slope(
    bounces: int = 1,
    restitution: float = 0.9,
    *,
    slope_deg: float = 20.0,
    horizon: float | None = None,
    target: Sequence[float] | None = None,
    target_velocity: Sequence[float] = (0.0, 0.0),
    initial_position: Sequence[float] = (0.0, 1.0),
    gravity: float = 9.81,
    weight_position: float = 1.0,
    weight_velocity: float = 0.0,
    eps: float = 0.01,
    steps: int = 200,
) -> HybridOCP:
    r"""A ball in the vertical plane with a 2-D thrust, bouncing on an inclined plane.

    State ``s = (x, y, vx, vy)``, control ``u = (ux, uy)`` (thrust per unit mass). The plane
    passes through the origin at ``slope_deg`` (rising to the right); its unit normal
    ``n = (-sin a, cos a)`` points into free space::

        minimise   w_p |p(T) - target|^2 + w_v |v(T) - v_target|^2 + eps int_0^T |u|^2 dt
        dynamics   p' = v,  v' = u - (0, g)
        guard      "slope": psi = p . n = -x sin a + y cos a   (mixes x and y; degree 2)
        reset      p+ = p-,  v+ = v- - (1 + e) (v- . n) n      (reflects the normal part)

    The ball starts at rest at ``initial_position``.

    HMP structure: ``lambda_p`` constant and ``lambda_v`` linear on each phase, so
    ``u = -lambda_v / (2 eps)`` is linear in time between impacts; at an impact
    ``lambda_v(gamma-) = (I - (1 + e) n n^T) lambda_v(gamma+)``: the normal component of the
    thrust is multiplied by ``-e`` across the impact, the tangential one is continuous.

    Parameters
    ----------
    bounces
        The number of impacts the defaults make optimal (1 and 2 are verified).
    restitution
        ``e`` in ``[0, 1]``.
    slope_deg
        Inclination ``a`` of the plane in degrees, in ``(-90, 90)``.
    horizon
        ``T``. Default: midway in time between impact ``bounces`` and the next impact of the
        free motion (no thrust; :func:`free_flight_on_slope`), or half the first fall time
        when ``bounces = 0``.
    target
        Target position. Default: the free motion's position at ``T`` raised by ``0.3``.
    target_velocity
        ``v_target`` (only used when ``weight_velocity > 0``).
    initial_position
        ``p(0)``, above the plane.
    gravity
        ``g > 0``.
    weight_position, weight_velocity
        ``w_p, w_v >= 0``.
    eps
        Control weight ``eps > 0``.
    steps
        ``N``; the initial guess ``u = 0`` reproduces the claimed sequence with the default
        horizon.

    Returns
    -------
    HybridOCP
        ``meta``: ``"family"``, ``"params"`` (defaults resolved), ``"claimed_sequence"``
        (``["slope"] * bounces`` for the verified configurations below, else ``None``).

    Notes
    -----
    Known optimal sequence (checked independently in ``tests/library_optima.py`` by the exact
    solution of the sequence-fixed problem, 0 to 3 impacts compared) for the defaults with
    ``bounces`` in 1, 2: exactly ``bounces`` impacts, all transversal (normal approach speed
    above 4 m/s). ``bounces=1``: ``T = 0.857895``, cost ``0.0146228663898``, impact at
    ``0.433113881``; ``bounces=2``: ``T = 1.630000``, cost ``0.0145988870406``, impacts at
    ``0.438515473`` and ``1.274977359``.
    """
    args = dict(locals())
    bounces = int(bounces)
    if bounces < 0:
        raise ValueError(f"bounces must be >= 0, got {bounces}")
    e = check_restitution(restitution)
    g = check_positive("gravity", gravity)
    eps = check_positive("eps", eps)
    if not -90.0 < float(slope_deg) < 90.0:
        raise ValueError(f"slope_deg must lie in (-90, 90), got {slope_deg}")
    n = _slope_normal(slope_deg)
    p0 = np.asarray(initial_position, dtype=float).ravel()
    if p0.shape != (2,) or p0 @ n <= 0:
        raise ValueError(f"initial_position must be 2 numbers above the plane, got {p0}")
    acc = np.array([0.0, -g])
    if horizon is None or target is None:
        hits = free_flight_on_slope(
            p0, (0.0, 0.0), slope_deg=slope_deg, restitution=e, gravity=g, count=bounces + 1
        )
        times = [0.0] + [h[0] for h in hits]
        if horizon is None:
            horizon = 0.5 * (times[bounces] + times[bounces + 1])
        # free state at T: replay from the last impact before T
        t_last, p, v = 0.0, p0.copy(), np.zeros(2)
        for t_k, p_k, v_k in hits:
            if t_k > horizon:
                break
            t_last, p, v = t_k, p_k, v_k - (1 + e) * (v_k @ n) * n
        tau = float(horizon) - t_last
        free_p = p + v * tau + 0.5 * acc * tau**2
        if target is None:
            target = free_p + np.array([0.0, 0.3])
    T = check_positive("horizon", horizon)
    target = np.asarray(target, dtype=float).ravel()
    v_target = np.asarray(target_velocity, dtype=float).ravel()

    s = ca.SX.sym("s", 4)
    u = ca.SX.sym("u", 2)
    p, v = s[:2], s[2:]
    nn = ca.DM(n)
    f = ca.vertcat(v, u + ca.DM(acc))
    L = eps * ca.sumsqr(u)
    phi = weight_position * ca.sumsqr(p - ca.DM(target)) + weight_velocity * ca.sumsqr(
        v - ca.DM(v_target)
    )
    psi = ca.dot(p, nn)
    reset = ca.vertcat(p, v - (1 + e) * ca.dot(v, nn) * nn)
    slope = Guard.from_expressions(
        "slope", s, psi, reset, kind="ball-plane", bodies=("ball", "slope"), degree=2
    )
    params = {
        "bounces": bounces,
        "restitution": e,
        "slope_deg": float(slope_deg),
        "horizon": T,
        "target": target.tolist(),
        "target_velocity": v_target.tolist(),
        "initial_position": p0.tolist(),
        "gravity": g,
        "weight_position": float(weight_position),
        "weight_velocity": float(weight_velocity),
        "eps": eps,
        "steps": int(steps),
    }
    return HybridOCP.from_expressions(
        s,
        u,
        f=f,
        L=L,
        phi=phi,
        guards=[slope],
        x0=[p0[0], p0[1], 0.0, 0.0],
        horizon=T,
        steps=steps,
        u_guess=np.zeros((int(steps), 2)),
        flow_map=affine_flow_map(s, u, f, L),
        name=f"ball_on_slope(bounces={bounces}, e={e:g})",
        state_labels=["x", "y", "vx", "vy"],
        control_labels=["ux", "uy"],
        meta={
            "family": "ball_on_slope",
            "params": params,
            "claimed_sequence": verified_claim(
                ball_on_slope, args, ("bounces", "restitution"), _VERIFIED, "slope"
            ),
        },
    )
