"""A block on a floor whose viscous friction changes at ``x = 0``, steered to rest at a point."""

from __future__ import annotations

import casadi as ca
import numpy as np

from hybridoc.ocp import Guard, HybridOCP, Mode
from hybridoc.problems.library.registry import library_problem

from ._common import check_positive

__all__ = ["friction_patch"]

_DEFAULTS = {
    "smooth_friction": 0.2,
    "rough_friction": 3.0,
    "initial_position": -1.0,
    "target_position": 1.0,
    "horizon": 2.0,
    "steps": 200,
    "push": 1.5,
}
#: the optimal event sequence of the defaults (both variants), checked in the tests
_CLAIMED = ["enter-rough"]


def _mode(name: str, s: ca.SX, u: ca.SX, c: float, L: ca.SX) -> Mode:
    """A mode ``x' = v``, ``v' = u - c v`` with its exact flow map under a constant ``u``:
    ``v`` relaxes to ``u / c`` at the rate ``c``."""
    x, v = s[0], s[1]
    h = ca.SX.sym("h")
    v_inf = u / c
    # 1 - exp(-c h) through expm1: exact to rounding for the short steps of event location
    decay = -ca.expm1(-c * h)
    end = ca.vertcat(x + v_inf * h + (v - v_inf) * decay / c, v - (v - v_inf) * decay)
    return Mode(
        name,
        f=ca.Function(f"f_{name}", [s, u], [ca.vertcat(v, u - c * v)]),
        L=ca.Function(f"L_{name}", [s, u], [L]),
        flow_map=ca.Function(f"flow_{name}", [s, u, h], [end, L * h]),
    )


@library_problem(
    "friction-patch-free-time", note="T free in [0.5, 5], J = int 1 + u^2", free_time=True
)
@library_problem("friction-patch")
def friction_patch(
    *,
    smooth_friction: float = 0.2,
    rough_friction: float = 3.0,
    initial_position: float = -1.0,
    target_position: float = 1.0,
    horizon: float = 2.0,
    steps: int = 200,
    push: float = 1.5,
    free_time: bool = False,
    horizon_bounds: tuple[float, float] = (0.5, 5.0),
) -> HybridOCP:
    r"""A block pushed across a patch of rough floor to rest at a point (two modes, hard end).

    State ``(x, v, mode)``, control ``u`` (force per unit mass); the viscous friction
    changes where the floor does, at ``x = 0``::

        smooth (mode 0, x < 0):  x' = v,  v' = u - c_s v
        rough  (mode 1, x > 0):  x' = v,  v' = u - c_r v
        enter-rough  smooth -> rough  when -x reaches 0 from above   (identity reset)
        leave-rough  rough -> smooth  when  x reaches 0 from above   (identity reset)
        subject to   x(T) = x_target,  v(T) = 0                       (hard)
        minimise     int_0^T u^2 dt      (free_time: int_0^T (1 + u^2) dt, T in bounds)

    The block starts at rest at ``x(0) = initial_position < 0`` on the smooth floor. Both
    modes have exact flow maps (``v`` relaxes exponentially to ``u / c``), so the judge
    needs no integrator; the guards are not polynomials along the flow. The initial guess
    pushes with ``u = push`` throughout (``1.5``: the block reaches the rough floor once,
    near ``t = 1.15``).

    HMP structure: ``u = -lambda_v / 2``; ``lambda_x`` is constant on each phase and jumps
    at the switch (the guard's gradient is ``(1, 0)``), ``lambda_v`` is continuous and
    follows ``lambda_v' = c lambda_v - lambda_x``, so on each phase the optimal force is
    ``a + b exp(c tau)`` (``tau`` the time in the phase). With a free final time the
    Hamiltonian ``1 + u^2 + lambda^T f`` vanishes at ``T``.

    Parameters
    ----------
    smooth_friction, rough_friction
        ``c_s, c_r > 0``.
    initial_position
        ``x(0) < 0``.
    target_position
        ``x_target``.
    horizon
        ``T`` (with ``free_time``: the initial guess of ``T``).
    steps
        ``N``.
    push
        The constant force of the initial guess.
    free_time
        Free final time in ``horizon_bounds`` and the running cost ``1 + u^2`` (time is
        charged).
    horizon_bounds
        ``(T_min, T_max)`` with ``free_time``.

    Returns
    -------
    HybridOCP
        With modes ``("smooth", "rough")`` and terminal equalities ``(x - x_target, v)``;
        ``meta`` holds ``"family"``, ``"params"`` and ``"claimed_sequence"``
        (``["enter-rough"]`` for the defaults of both variants, checked against an
        independent NLP in ``tests/test_terminal_judge_dt.py``; ``None`` otherwise).

    Notes
    -----
    The defaults are issue #15's specification: ``c_s = 0.2``, ``c_r = 3``, ``x(0) = -1``,
    ``v(0) = 0``, ``x(T) = 1``, ``v(T) = 0``, ``T = 2``, ``N = 200``; the free-time variant
    has ``T`` in ``[0.5, 5]`` and ``J = int (1 + u^2) dt``.
    """
    args = dict(locals())
    c_s = check_positive("smooth_friction", smooth_friction)
    c_r = check_positive("rough_friction", rough_friction)
    T = check_positive("horizon", horizon)
    x0 = float(initial_position)
    if not x0 < 0:
        raise ValueError(f"initial_position must be negative (on the smooth floor), got {x0}")
    bounds = None
    if free_time:
        lo, hi = (check_positive("horizon_bounds", b) for b in horizon_bounds)
        if not lo <= T <= hi:
            raise ValueError(
                f"horizon {T} (the guess of T) must lie in horizon_bounds {horizon_bounds}"
            )
        bounds = (lo, hi)
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u")
    x, v = s[0], s[1]
    L = (1.0 + u**2) if free_time else u**2
    enter = Guard.from_expressions(
        "enter-rough", s, -x, s, kind="floor change", bodies=("block", "patch"),
        source="smooth", target="rough",
    )  # fmt: skip
    leave = Guard.from_expressions(
        "leave-rough", s, x, s, kind="floor change", bodies=("block", "patch"),
        source="rough", target="smooth",
    )  # fmt: skip
    params = {
        "smooth_friction": c_s,
        "rough_friction": c_r,
        "initial_position": x0,
        "target_position": float(target_position),
        "horizon": T,
        "steps": int(steps),
        "push": float(push),
        "free_time": bool(free_time),
        "horizon_bounds": None if bounds is None else list(bounds),
    }
    defaults = all(args[k] == val for k, val in _DEFAULTS.items()) and (
        not free_time or tuple(horizon_bounds) == (0.5, 5.0)
    )
    return HybridOCP.from_modes(
        s,
        u,
        modes=[_mode("smooth", s, u, c_s, L), _mode("rough", s, u, c_r, L)],
        transitions=[enter, leave],
        initial_mode="smooth",
        phi=ca.SX(0.0),
        terminal_eq=ca.vertcat(x - float(target_position), v),
        x0=[x0, 0.0],
        horizon=T,
        steps=steps,
        horizon_bounds=bounds,
        u_guess=np.full((int(steps), 1), float(push)),
        name="friction_patch_free_time" if free_time else "friction_patch",
        state_labels=["x", "v"],
        control_labels=["u"],
        meta={
            "family": "friction_patch",
            "params": params,
            "claimed_sequence": list(_CLAIMED) if defaults else None,
        },
    )
