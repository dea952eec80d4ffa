"""A block sliding on a floor with Coulomb friction, pushed to reverse its motion."""

from __future__ import annotations

import casadi as ca
import numpy as np

from hybridoc.ocp import Guard, HybridOCP, Mode
from hybridoc.problems.library.registry import library_problem

from ._common import affine_flow_map, check_positive

__all__ = ["coulomb_block"]

_DEFAULTS = {
    "friction": 1.0,
    "initial_velocity": 1.0,
    "target_position": -1.0,
    "weight_position": 10.0,
    "weight_velocity": 10.0,
    "eps": 0.1,
    "horizon": 2.0,
    "steps": 200,
    "push": -2.0,
}


@library_problem("coulomb-block")
def coulomb_block(
    *,
    friction: float = 1.0,
    initial_velocity: float = 1.0,
    target_position: float = -1.0,
    weight_position: float = 10.0,
    weight_velocity: float = 10.0,
    eps: float = 0.1,
    horizon: float = 2.0,
    steps: int = 200,
    push: float = -2.0,
) -> HybridOCP:
    r"""A block with Coulomb friction, pushed back past where it started (two modes).

    State ``(x, v, mode)``, control ``u`` (force per unit mass); the friction force
    ``mu g`` (``friction``) opposes the motion, so each direction of sliding is a mode::

        right (mode 0):  x' = v,  v' = u - mu g
        left  (mode 1):  x' = v,  v' = u + mu g
        reverse  right -> left  when v reaches 0 from above      (identity reset)
        forward  left -> right  when -v reaches 0 from above     (identity reset)
        minimise   w_x (x(T) - x_target)^2 + w_v v(T)^2 + eps int_0^T u^2 dt

    The block starts at ``x = 0`` sliding right at ``v(0) = initial_velocity``. A reversal
    is an event only when the push overcomes the friction (``u < -mu g`` at ``v = 0``);
    a weaker push makes the block stick, which the model leaves out: the judge then reports
    guards that fire again and again at one instant. The initial guess pushes with ``u =
    push`` throughout (``-2``: the block reverses once, at ``t = 1/3``).

    HMP structure: both flows are double integrators with a constant friction term, so the
    costate is linear in time on each phase and the optimal force ``u = -lambda_v / (2 eps)``
    is linear in time between reversals; at a reversal the friction force jumps by ``2 mu g``
    and ``lambda_v`` jumps with it (the guard's gradient is ``(0, 1)``), while ``lambda_x``
    is continuous.

    Parameters
    ----------
    friction
        ``mu g > 0``.
    initial_velocity
        ``v(0) > 0``.
    target_position
        ``x_target``.
    weight_position, weight_velocity
        ``w_x, w_v >= 0``.
    eps
        Control weight.
    horizon, steps
        ``T`` and ``N``.
    push
        The constant force of the initial guess.

    Returns
    -------
    HybridOCP
        With modes ``("right", "left")``; ``meta`` holds ``"family"``, ``"params"`` and
        ``"claimed_sequence"`` (``["reverse"]`` for the defaults, checked independently in
        ``tests/library_optima.py``; ``None`` otherwise).
    """
    args = dict(locals())
    mu = check_positive("friction", friction)
    v0 = check_positive("initial_velocity", initial_velocity)
    eps = check_positive("eps", eps)
    T = check_positive("horizon", horizon)
    if weight_position < 0 or weight_velocity < 0:
        raise ValueError("weights must be non-negative")
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u")
    x, v = s[0], s[1]
    L = eps * u**2

    def mode(name: str, accel: ca.SX) -> Mode:
        f = ca.vertcat(v, accel)
        return Mode(
            name,
            f=ca.Function(f"f_{name}", [s, u], [f]),
            L=ca.Function(f"L_{name}", [s, u], [L]),
            flow_map=affine_flow_map(s, u, f, L),
        )

    reverse = Guard.from_expressions(
        "reverse", s, v, s, kind="reversal", bodies=("block", "floor"), degree=1,
        source="right", target="left",
    )  # fmt: skip
    forward = Guard.from_expressions(
        "forward", s, -v, s, kind="reversal", bodies=("block", "floor"), degree=1,
        source="left", target="right",
    )  # fmt: skip
    params = {
        "friction": mu,
        "initial_velocity": v0,
        "target_position": float(target_position),
        "weight_position": float(weight_position),
        "weight_velocity": float(weight_velocity),
        "eps": eps,
        "horizon": T,
        "steps": int(steps),
        "push": float(push),
    }
    defaults = all(args[k] == val for k, val in _DEFAULTS.items())
    return HybridOCP.from_modes(
        s,
        u,
        modes=[mode("right", u - mu), mode("left", u + mu)],
        transitions=[reverse, forward],
        initial_mode="right",
        phi=float(weight_position) * (x - float(target_position)) ** 2
        + float(weight_velocity) * v**2,
        x0=[0.0, v0],
        horizon=T,
        steps=steps,
        u_guess=np.full((int(steps), 1), float(push)),
        name="coulomb_block",
        state_labels=["x", "v"],
        control_labels=["u"],
        meta={
            "family": "coulomb_block",
            "params": params,
            "claimed_sequence": ["reverse"] if defaults else None,
        },
    )
