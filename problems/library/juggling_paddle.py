"""An actuated paddle that drives a passive ball only through impacts."""

from __future__ import annotations

import casadi as ca
import numpy as np

from hybridoc.ocp import Guard, HybridOCP
from hybridoc.problems.library.registry import library_problem

from ._common import affine_flow_map, check_positive, check_restitution, verified_claim

__all__ = ["juggling_paddle"]

#: (restitution, mass_ratio) -> optimal number of impacts, checked in tests/library_optima.py
_VERIFIED = {(0.8, 0.0): 1, (1.0, 0.0): 1, (0.8, 0.5): 2}


@library_problem("juggling-paddle")
def juggling_paddle(
    restitution: float = 0.8,
    *,
    mass_ratio: float = 0.0,
    horizon: float = 1.0,
    target_height: float = 1.5,
    target_velocity: float = 0.0,
    ball_height: float = 1.0,
    gravity: float = 9.81,
    weight_height: float = 1.0,
    weight_velocity: float = 1.0,
    weight_paddle: float = 0.1,
    eps: float = 0.01,
    steps: int = 200,
) -> HybridOCP:
    r"""Juggling: a paddle on a vertical line hits a passive ball under gravity.

    State ``s = (y_p, v_p, y_b, v_b)`` (paddle position and velocity, ball position and
    velocity), control ``u``: the paddle's acceleration (the force on a unit-mass paddle whose
    weight is carried by its support)::

        minimise   w_h (y_b(T) - h_target)^2 + w_v (v_b(T) - v_target)^2
                   + w_p (y_p(T)^2 + v_p(T)^2) + eps int_0^T u^2 dt
        dynamics   y_p' = v_p,  v_p' = u,  y_b' = v_b,  v_b' = -g
        guard      "paddle|ball": psi = y_b - y_p   (ball above paddle; a moving guard,
                   degree 2)
        reset      frictionless impact with restitution e, mass ratio mu = m_ball / m_paddle,
                   approach speed w = v_b - v_p < 0:
                   v_b+ = v_b - (1 + e) w / (1 + mu),  v_p+ = v_p + mu (1 + e) w / (1 + mu)
                   (mu = 0, a paddle much heavier than the ball: v_b+ = v_p - e (v_b - v_p),
                   v_p unchanged)

    The paddle starts at rest at 0, the ball at rest at ``ball_height``. The control acts on
    the ball only through the impacts.

    HMP structure: ``u = -lambda_vp / (2 eps)`` is linear in time between impacts (the
    paddle's costate is that of a double integrator); at an impact the costate jumps by
    ``R^T`` (``R`` the reset's Jacobian) plus ``pi grad psi``, ``grad psi = (-1, 0, 1, 0)``,
    so the paddle's thrust jumps: ``lambda_vp(gamma-) = lambda_vp(gamma+) + (1 + e)
    lambda_vb(gamma+)`` when ``mu = 0``.

    Parameters
    ----------
    restitution
        ``e`` in ``[0, 1]``.
    mass_ratio
        ``mu = m_ball / m_paddle >= 0``.
    horizon
        ``T``.
    target_height, target_velocity
        Targets of the ball at ``T`` (default: at its apex at 1.5).
    ball_height
        ``y_b(0) > 0``.
    gravity
        ``g > 0``.
    weight_height, weight_velocity, weight_paddle
        ``w_h, w_v, w_p >= 0``.
    eps
        Control weight ``eps > 0``.
    steps
        ``N``; the initial guess ``u = 0`` (paddle at rest) gives exactly one impact with the
        defaults (and with ``mu = 0.5``, whose optimum has two).

    Returns
    -------
    HybridOCP
        ``meta``: ``"family"``, ``"params"``, ``"claimed_sequence"`` (the verified optimal
        sequence of the configurations below, where every other parameter has its default;
        else ``None``).

    Notes
    -----
    Known optimal sequences, checked independently in ``tests/library_optima.py`` by the exact
    solution of the sequence-fixed problem (0 to 3 impacts compared), all impacts transversal:

    - ``e = 0.8, mu = 0`` (defaults): one impact at ``0.446408563``, cost ``0.113526690995``;
    - ``e = 1, mu = 0``: one impact at ``0.447935187``, cost ``0.0247537036854``;
    - ``e = 0.8, mu = 0.5`` (a light paddle that recoils): *two* impacts, at ``0.326012249``
      and ``0.768633675``, cost ``0.67440037882`` (one impact costs at least ``1.1759``).
    """
    args = dict(locals())
    e = check_restitution(restitution)
    g = check_positive("gravity", gravity)
    eps = check_positive("eps", eps)
    T = check_positive("horizon", horizon)
    yb0 = check_positive("ball_height", ball_height)
    mu = float(mass_ratio)
    if not mu >= 0:
        raise ValueError(f"mass_ratio must be >= 0, got {mass_ratio}")

    s = ca.SX.sym("s", 4)
    u = ca.SX.sym("u")
    yp, vp, yb, vb = s[0], s[1], s[2], s[3]
    f = ca.vertcat(vp, u, vb, -g)
    L = eps * u**2
    phi = (
        weight_height * (yb - target_height) ** 2
        + weight_velocity * (vb - target_velocity) ** 2
        + weight_paddle * (yp**2 + vp**2)
    )
    w = vb - vp
    reset = ca.vertcat(yp, vp + mu * (1 + e) * w / (1 + mu), yb, vb - (1 + e) * w / (1 + mu))
    guard = Guard.from_expressions(
        "paddle|ball", s, yb - yp, reset, kind="impact", bodies=("paddle", "ball"), degree=2
    )
    params = {
        "restitution": e,
        "mass_ratio": mu,
        "horizon": T,
        "target_height": float(target_height),
        "target_velocity": float(target_velocity),
        "ball_height": yb0,
        "gravity": g,
        "weight_height": float(weight_height),
        "weight_velocity": float(weight_velocity),
        "weight_paddle": float(weight_paddle),
        "eps": eps,
        "steps": int(steps),
    }
    return HybridOCP.from_expressions(
        s,
        u,
        f=f,
        L=L,
        phi=phi,
        guards=[guard],
        x0=[0.0, 0.0, yb0, 0.0],
        horizon=T,
        steps=steps,
        u_guess=np.zeros((int(steps), 1)),
        flow_map=affine_flow_map(s, u, f, L),
        name=f"juggling_paddle(e={e:g})" if mu == 0 else f"juggling_paddle(e={e:g}, mu={mu:g})",
        state_labels=["y_p", "v_p", "y_b", "v_b"],
        control_labels=["u"],
        meta={
            "family": "juggling_paddle",
            "params": params,
            "claimed_sequence": verified_claim(
                juggling_paddle, args, ("restitution", "mass_ratio"), _VERIFIED, "paddle|ball"
            ),
        },
    )
