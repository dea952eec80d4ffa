"""A 1-D ball with a thrust force bouncing on the floor."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from hybridoc.ocp import Guard, HybridOCP
from hybridoc.problems.library.registry import library_problem

from ._common import affine_flow_map, check_positive, check_restitution, verified_claim

__all__ = ["bouncing_ball", "free_drop_times"]

#: (bounces, restitution) -> optimal number of bounces, checked in tests/library_optima.py
_VERIFIED = {(float(k), e): k for k in (0, 1, 2) for e in (1.0, 0.8)}


def free_drop_times(height: float, gravity: float, restitution: float, count: int) -> list[float]:
    """Impact times of a ball dropped from rest at ``height`` with no thrust.

    The first impact is at ``t_1 = sqrt(2 height / gravity)`` with speed ``v_1 = gravity t_1``;
    the flight after impact ``k`` lasts ``2 e^k v_1 / gravity``.
    """
    t = math.sqrt(2.0 * height / gravity)
    v1 = gravity * t
    out = []
    for k in range(count):
        out.append(t)
        t += 2.0 * restitution ** (k + 1) * v1 / gravity
    return out


# over 80 lines: one problem stated whole; most lines are its keyword parameters, listed
# in the signature, checked, and recorded in meta["params"]
@library_problem("bouncing-ball-2", bounces=2, note="two bounces")
@library_problem("bouncing-ball")
def bouncing_ball(
    bounces: int = 1,
    restitution: float = 0.8,
    *,
    horizon: float | None = None,
    target_height: float | None = None,
    target_velocity: float = 0.0,
    initial_height: float = 1.0,
    gravity: float = 9.81,
    weight_height: float = 1.0,
    weight_velocity: float = 1.0,
    eps: float = 0.01,
    steps: int = 200,
) -> HybridOCP:
    r"""A ball on a vertical line, pushed by a thrust force, bouncing on the floor.

    State ``s = (h, v)`` (height, velocity), control ``u`` (thrust per unit mass)::

        minimise   w_h (h(T) - h_target)^2 + w_v (v(T) - v_target)^2 + eps int_0^T u^2 dt
        dynamics   h' = v,  v' = u - g
        guard      "floor": psi = h            (degree 2 in time under a constant thrust)
        reset      h+ = h-,  v+ = -e v-

    The ball starts at rest at ``h(0) = initial_height``.

    HMP structure: ``lambda_h`` is constant and ``lambda_v`` linear on each phase, so the
    optimal thrust ``u = -lambda_v / (2 eps)`` is linear in time between bounces; at a bounce
    ``lambda_v(gamma-) = -e lambda_v(gamma+)``, i.e. ``u(gamma-) = -e u(gamma+)`` (the thrust
    changes sign across an impact), and ``lambda_h`` jumps by the multiplier ``pi``.

    Parameters
    ----------
    bounces
        The number of bounces the defaults make optimal (0, 1 or 2 are verified; any
        non-negative count builds). It sets the default horizon and target.
    restitution
        ``e`` in ``[0, 1]`` (``e > 0`` when ``bounces > 0`` and the horizon is defaulted).
    horizon
        ``T``. Default: for ``bounces = 0`` half the free fall time ``sqrt(2 h0 / g) / 2``;
        otherwise the time of the apex that follows bounce number ``bounces`` of the free drop
        (no thrust), ``t_k + e^k v_1 / g`` with ``t_k`` from :func:`free_drop_times`.
    target_height
        ``h_target``. Default: the height of the free drop at ``T`` plus ``0.3``, so that
        the optimal thrust is not zero (``1.05`` for ``bounces = 0``, ``e^(2k) h0 + 0.3`` for
        ``bounces = k > 0`` when ``h0 = 1``).
    target_velocity
        ``v_target``.
    initial_height
        ``h0 > 0``.
    gravity
        ``g > 0``.
    weight_height, weight_velocity
        ``w_h, w_v >= 0``.
    eps
        Control weight ``eps > 0``.
    steps
        ``N``; the initial guess is ``u = 0`` on every step, which reproduces the claimed
        sequence (the free drop has exactly ``bounces`` bounces before the default ``T``).

    Returns
    -------
    HybridOCP
        ``meta`` holds ``"family"``, ``"params"`` (every parameter, defaults resolved) and
        ``"claimed_sequence"`` (``["floor"] * bounces`` for the verified configurations
        below, where every other parameter has its default; else ``None``).

    Notes
    -----
    Known optimal sequences (checked independently in ``tests/library_optima.py`` by the
    exact solution of the sequence-fixed problem, with the 0 to 3 bounce alternatives
    costlier) for ``bounces`` in 0, 1, 2 and ``restitution`` in 1.0 and 0.8: exactly
    ``bounces`` bounces, every impact transversal (approach speed above 3.8 m/s):

    =======  ====  =========  ===============  ==============================
    bounces  e     T          optimal cost     bounce times
    =======  ====  =========  ===============  ==============================
    0        any   0.225762   0.211363514661   (none)
    1        1.0   0.903047   0.0208886202784  0.417429559
    1        0.8   0.812743   0.0327194823975  0.412921471
    2        1.0   1.806095   0.0161130583575  0.438765468, 1.302794477
    2        0.8   1.462937   0.0388269073544  0.433676138, 1.114700785
    =======  ====  =========  ===============  ==============================
    """
    args = dict(locals())
    bounces = int(bounces)
    if bounces < 0:
        raise ValueError(f"bounces must be >= 0, got {bounces}")
    e = check_restitution(restitution)
    g = check_positive("gravity", gravity)
    h0 = check_positive("initial_height", initial_height)
    eps = check_positive("eps", eps)
    if weight_height < 0 or weight_velocity < 0:
        raise ValueError("weights must be non-negative")
    t_fall = math.sqrt(2.0 * h0 / g)
    if horizon is None:
        if bounces == 0:
            horizon = 0.5 * t_fall
            free_height = h0 - 0.5 * g * horizon**2
        else:
            if e == 0.0:
                raise ValueError("the default horizon needs restitution > 0 when bounces > 0")
            t_k = free_drop_times(h0, g, e, bounces)[-1]
            horizon = t_k + e**bounces * t_fall
            free_height = e ** (2 * bounces) * h0
    else:
        horizon = check_positive("horizon", horizon)
        free_height = None
    if target_height is None:
        if free_height is None:
            raise ValueError("give target_height together with horizon")
        target_height = free_height + 0.3
    T = float(horizon)

    s = ca.SX.sym("s", 2)
    u = ca.SX.sym("u")
    h, v = s[0], s[1]
    f = ca.vertcat(v, u - g)
    L = eps * u**2
    phi = weight_height * (h - target_height) ** 2 + weight_velocity * (v - target_velocity) ** 2
    floor = Guard.from_expressions(
        "floor", s, h, ca.vertcat(h, -e * v), kind="bounce", bodies=("ball", "floor"), degree=2
    )
    params = {
        "bounces": bounces,
        "restitution": e,
        "horizon": T,
        "target_height": float(target_height),
        "target_velocity": float(target_velocity),
        "initial_height": h0,
        "gravity": g,
        "weight_height": float(weight_height),
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
        guards=[floor],
        x0=[h0, 0.0],
        horizon=T,
        steps=steps,
        u_guess=np.zeros((int(steps), 1)),
        flow_map=affine_flow_map(s, u, f, L),
        name=f"bouncing_ball(bounces={bounces}, e={e:g})",
        state_labels=["h", "v"],
        control_labels=["u"],
        meta={
            "family": "bouncing_ball",
            "params": params,
            "claimed_sequence": verified_claim(
                bouncing_ball, args, ("bounces", "restitution"), _VERIFIED, "floor"
            ),
        },
    )
