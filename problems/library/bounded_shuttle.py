"""A block with a bounded force that bounces off a wall to come home moving."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from hybridoc.ocp import Guard, HybridOCP
from hybridoc.problems.library.registry import library_problem

from ._common import affine_flow_map, check_positive

__all__ = ["bounded_shuttle", "bounded_shuttle_optimum"]

#: the optimal event sequence of the defaults, checked in the tests
_CLAIMED = ["wall"]


def bounded_shuttle_optimum(
    force_limit: float = 1.2, wall: float = 0.5, return_speed: float = 1.5, horizon: float = 2.0
) -> dict[str, float]:
    """The closed-form optimum of :func:`bounded_shuttle` with one bounce (derivation in its
    notes), valid when the force saturates once, after a free arc, and the bounce follows.

    Returns
    -------
    dict
        ``cost``, ``saturation`` (``t_1``, where the force reaches the limit), ``slope``
        (``c_1``), ``c0`` (the force at ``t = 0``) and ``bounce`` (the impact time).
    """
    a, w, V, T = (float(x) for x in (force_limit, wall, return_speed, horizon))
    t1 = 3.0 * (2.0 * w - a * T**2 / 2.0 + T * (a * T - V)) / (a * T - V)
    c1 = 2.0 * (a * T - V) / t1**2
    c0 = a - c1 * t1
    cost = a**2 * T - a * c1 * t1**2 + c1**2 * t1**3 / 3.0
    # the unfolded position y(t) = c0 t^2/2 + c1 t^3/6 up to t1, then a parabola at +a
    y1 = c0 * t1**2 / 2.0 + c1 * t1**3 / 6.0
    v1 = c0 * t1 + c1 * t1**2 / 2.0
    if y1 >= w:
        raise ValueError("these parameters bounce before the force saturates")
    tau = (-v1 + math.sqrt(v1**2 + 2.0 * a * (w - y1))) / a
    return {"cost": cost, "saturation": t1, "slope": c1, "c0": c0, "bounce": t1 + tau}


@library_problem("bounded-shuttle")
def bounded_shuttle(
    force_limit: float = 1.2,
    wall: float = 0.5,
    return_speed: float = 1.5,
    horizon: float = 2.0,
    steps: int = 200,
) -> HybridOCP:
    r"""A block pushed by a bounded force bounces off a wall and comes home moving.

    State ``s = (x, v)``, control ``u`` with ``|u| <= a`` (``force_limit``)::

        minimise   int_0^T u^2 dt
        dynamics   x' = v,  v' = u
        guard      "wall": psi = w - x       (an elastic wall at x = w)
        reset      x+ = x-,  v+ = -v-
        terminal   x(T) = 0,  v(T) = -V      (home, moving away from the wall)

    from rest at ``x(0) = 0``. The bound is active: the optimal force saturates at ``+a``
    before the bounce and stays at the (mirrored) limit ``-a`` after it.

    Parameters
    ----------
    force_limit
        ``a > 0``; the defaults' unconstrained optimum would reach 1.5.
    wall
        ``w > 0``.
    return_speed
        ``V > 0``.
    horizon
        ``T``.
    steps
        ``N``; the initial guess is a constant push ``u = a / 2``, which reaches the wall.

    Returns
    -------
    HybridOCP
        ``meta`` holds ``"family"``, ``"params"`` and ``"claimed_sequence"`` (``["wall"]``
        for the defaults, else ``None``).

    Notes
    -----
    Unfolding the wall (``y = x`` before the bounce, ``y = 2 w - x`` after) turns the
    problem into a double integrator ``y'' = u~`` with the same bound and cost, from rest to
    ``y(T) = 2 w``, ``y'(T) = V``. Its minimum principle gives
    ``u~ = clip(c0 + c1 t, -a, a)``; with one saturation at ``t_1`` (``u~ = a`` after it),
    ``y'(T) = V`` and ``y(T) = 2 w`` give in closed form::

        c1 t1^2 = 2 (a T - V),
        t1 = 3 (2 w - a T^2 / 2 + T (a T - V)) / (a T - V),
        J* = a^2 T - a c1 t1^2 + c1^2 t1^3 / 3

    (:func:`bounded_shuttle_optimum`). The defaults give ``t_1 = 4/3``, ``c1 = 1.0125``,
    ``c0 = -0.15`` (so ``u~ >= -a`` holds), ``J* = 1.53`` against 1.5 without the bound, the
    bounce at ``t = 1.6039`` on the saturated arc, and the force jumps from ``+a`` to
    ``-a`` across it. Without a bounce the block must reach ``(0, -V)`` directly, which
    costs at least ``4 V^2 / T = 4.5`` even unbounded.
    """
    a = check_positive("force_limit", force_limit)
    w = check_positive("wall", wall)
    V = check_positive("return_speed", return_speed)
    T = check_positive("horizon", horizon)
    s = ca.SX.sym("s", 2)
    u = ca.SX.sym("u")
    x, v = s[0], s[1]
    f = ca.vertcat(v, u)
    L = u**2
    guard = Guard.from_expressions(
        "wall", s, w - x, ca.vertcat(x, -v), kind="bounce", bodies=("block", "wall"), degree=2
    )
    defaults = (a, w, V, T, int(steps)) == (1.2, 0.5, 1.5, 2.0, 200)
    params = {"force_limit": a, "wall": w, "return_speed": V, "horizon": T, "steps": int(steps)}
    return HybridOCP.from_expressions(
        s,
        u,
        f=f,
        L=L,
        phi=ca.SX(0),
        guards=[guard],
        x0=[0.0, 0.0],
        horizon=T,
        steps=steps,
        terminal_eq=ca.vertcat(x, v + V),
        u_guess=np.full((int(steps), 1), a / 2),
        u_min=[-a],
        u_max=[a],
        flow_map=affine_flow_map(s, u, f, L),
        name=f"bounded_shuttle(a={a:g})",
        state_labels=["x", "v"],
        control_labels=["u"],
        meta={
            "family": "bounded_shuttle",
            "params": params,
            "claimed_sequence": list(_CLAIMED) if defaults else None,
        },
    )
