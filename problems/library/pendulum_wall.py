"""A torque-controlled pendulum bouncing on a wall: a non-polynomial flow."""

from __future__ import annotations

import casadi as ca
import numpy as np

from hybridoc.ocp import Guard, HybridOCP
from hybridoc.problems.library.registry import library_problem

from ._common import check_positive, check_restitution, verified_claim

__all__ = ["pendulum_wall"]

#: (restitution,) -> optimal number of impacts, checked in tests/library_optima.py
_VERIFIED = {(0.8,): 1, (1.0,): 1}


@library_problem("pendulum-wall")
def pendulum_wall(
    restitution: float = 0.8,
    *,
    wall_angle: float = 0.2,
    initial_angle: float = -1.0,
    horizon: float = 1.5,
    target_angle: float = -1.2,
    target_velocity: float = 0.0,
    gravity: float = 9.81,
    length: float = 1.0,
    mass: float = 1.0,
    weight_angle: float = 1.0,
    weight_velocity: float = 0.1,
    eps: float = 0.01,
    steps: int = 200,
) -> HybridOCP:
    r"""A pendulum with a torque motor swinging against a wall.

    State ``s = (theta, omega)`` (angle from the downward vertical, angular velocity), control
    ``u`` (torque)::

        minimise   w_theta (theta(T) - theta_target)^2 + w_omega (omega(T) - omega_target)^2
                   + eps int_0^T u^2 dt
        dynamics   theta' = omega,  omega' = -(g / l) sin(theta) + u / (m l^2)
        guard      "wall": psi = theta_w - theta   (free space theta < theta_w; the flow is
                   not polynomial: degree None)
        reset      theta+ = theta-,  omega+ = -e omega-

    The pendulum starts at rest at ``initial_angle < wall_angle``.

    HMP structure: ``u = -lambda_omega / (2 eps m l^2)``, with ``lambda_theta' =
    (g / l) cos(theta) lambda_omega`` and ``lambda_omega' = -lambda_theta``; at an impact
    ``lambda_omega(gamma-) = -e lambda_omega(gamma+)``, so ``u(gamma-) = -e u(gamma+)``.

    Parameters
    ----------
    restitution
        ``e`` in ``[0, 1]``.
    wall_angle
        ``theta_w``.
    initial_angle
        ``theta(0) < theta_w``; ``omega(0) = 0``.
    horizon
        ``T``.
    target_angle, target_velocity
        ``theta_target``, ``omega_target``: by default, back on the starting side at rest,
        beyond where the free swing returns after the bounce, so that the bounce helps.
    gravity, length, mass
        ``g, l, m > 0``.
    weight_angle, weight_velocity
        ``w_theta, w_omega >= 0``.
    eps
        Control weight ``eps > 0``.
    steps
        ``N``; the initial guess ``u = 0`` (free swing) gives exactly one impact with the
        defaults.

    Returns
    -------
    HybridOCP
        ``meta``: ``"family"``, ``"params"``, ``"claimed_sequence"`` (``["wall"]`` for the
        verified configurations below, where every other parameter has its default; else
        ``None``).

    Notes
    -----
    Known optimal sequence for the defaults with ``e`` in 0.8 and 1.0: one impact, checked in
    ``tests/library_optima.py`` by a sequence-fixed multiple-shooting NLP (own RK4) polished by
    indirect HMP shooting, against the no-impact and two-impact alternatives (both about
    ``0.42``: the best no-impact motion touches the wall tangentially, and the two impacts of
    the best two-impact motion merge into such a touch):

    - ``e = 0.8``: impact at ``0.692771509`` (approach speed 2.64 rad/s), cost
      ``0.0750509873945``;
    - ``e = 1``: impact at ``0.721544468`` (approach speed 2.46 rad/s), cost
      ``0.0671968844381``.
    """
    args = dict(locals())
    e = check_restitution(restitution)
    g = check_positive("gravity", gravity)
    ell = check_positive("length", length)
    m = check_positive("mass", mass)
    eps = check_positive("eps", eps)
    T = check_positive("horizon", horizon)
    if not initial_angle < wall_angle:
        raise ValueError("initial_angle must be below wall_angle (free space theta < theta_w)")

    s = ca.SX.sym("s", 2)
    u = ca.SX.sym("u")
    th, om = s[0], s[1]
    f = ca.vertcat(om, -(g / ell) * ca.sin(th) + u / (m * ell**2))
    L = eps * u**2
    phi = weight_angle * (th - target_angle) ** 2 + weight_velocity * (om - target_velocity) ** 2
    wall = Guard.from_expressions(
        "wall",
        s,
        wall_angle - th,
        ca.vertcat(th, -e * om),
        kind="bounce",
        bodies=("pendulum", "wall"),
        degree=None,
    )
    params = {
        "restitution": e,
        "wall_angle": float(wall_angle),
        "initial_angle": float(initial_angle),
        "horizon": T,
        "target_angle": float(target_angle),
        "target_velocity": float(target_velocity),
        "gravity": g,
        "length": ell,
        "mass": m,
        "weight_angle": float(weight_angle),
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
        guards=[wall],
        x0=[float(initial_angle), 0.0],
        horizon=T,
        steps=steps,
        u_guess=np.zeros((int(steps), 1)),
        name=f"pendulum_wall(e={e:g})",
        state_labels=["theta", "omega"],
        control_labels=["u"],
        meta={
            "family": "pendulum_wall",
            "params": params,
            "claimed_sequence": verified_claim(
                pendulum_wall, args, ("restitution",), _VERIFIED, "wall"
            ),
        },
    )
