"""Problems on which gradient descent meets kinks (issue #29), built as a user would.

The loss of piecewise-constant controls is not smooth where an event time crosses a grid
time (the control that governs the event changes there), and a descent can stall with an
event pinned to a grid time. Each problem here comes with what the tests need to judge gd
independently of it.

- :func:`snell`: the lifeguard problem (Snell refraction). From ``(-5, 5)`` on land at
  speed 10 to ``(5, -5)`` in the water at speed 3, the shore ``y = 0``; as a free-final-time
  problem ``s' = v_q u``, ``L = 1 + |u|^2``, ``s(T) = (5, -5)``, whose optimum is
  ``2 T_min`` (at a constant speed ``|u| = c`` a distance ``d`` costs ``(1 + c^2) d / (v c)``,
  least at ``c = 1``: twice the travel time). :func:`snell_grid_optimum` computes the optimum
  on gd's own grid with numpy/scipy only.
- :func:`thermostat`: a room heated by a heater that switches on and off at temperature
  thresholds, with a controlled supplement power.
- :func:`ball_2d`: a ball in a vertical plane, pushed by a thrust, bouncing on the floor.
"""

from __future__ import annotations

import math
from typing import Any

import casadi as ca
import numpy as np

from hybridoc import Guard, HybridOCP

__all__ = ["SNELL_T_MIN", "ball_2d", "snell", "snell_grid_optimum", "snell_t_min", "thermostat"]

LAND, WATER = 10.0, 3.0
START, FINISH = (-5.0, 5.0), (5.0, -5.0)


def snell_t_min() -> float:
    """The least travel time of the lifeguard problem, by Snell's law (a 1-D root)."""
    from scipy.optimize import brentq

    (x0, y0), (x1, y1) = START, FINISH

    def snell_residual(xc: float) -> float:  # sin(a1) / v1 - sin(a2) / v2 at crossing xc
        s1 = (xc - x0) / math.hypot(xc - x0, y0)
        s2 = (x1 - xc) / math.hypot(x1 - xc, y1)
        return s1 / LAND - s2 / WATER

    xc = brentq(snell_residual, x0, x1, xtol=1e-15)
    return math.hypot(xc - x0, y0) / LAND + math.hypot(x1 - xc, y1) / WATER


SNELL_T_MIN = 2.7254594329141
"""The least time, as the issue gives it (:func:`snell_t_min` recomputes it)."""


def snell(steps: int = 20, horizon: float = 6.0, weight: float | None = None) -> HybridOCP:
    """The lifeguard problem (module notes); ``horizon`` is the guess of ``T``, the guess
    of the controls a straight line at ``|s'| = d / T``.

    ``weight=None``: the free final time with ``s(T) = (5, -5)`` required. A number: ``T``
    fixed at ``horizon``, the target a terminal cost ``weight |s(T) - (5, -5)|^2``.
    """
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u", 2)
    cost = 1 + ca.sumsqr(u)
    shore = Guard.from_expressions("shore", s, s[1], s, source="land", target="water")
    d = np.subtract(FINISH, START)
    guess = np.tile(d / horizon / LAND, (steps, 1))
    if weight is None:
        target = {"phi": ca.SX(0), "terminal_eq": s - ca.DM(FINISH), "horizon_bounds": (0.5, 20.0)}
    else:
        target = {"phi": weight * ca.sumsqr(s - ca.DM(FINISH))}
    return HybridOCP.from_modes(
        s, u,
        modes={"land": (LAND * u, cost), "water": (WATER * u, cost)},
        transitions=[shore], initial_mode="land", x0=START, horizon=horizon, steps=steps,
        u_guess=guess, name=f"snell(steps={steps})", **target,
    )  # fmt: skip


def _snell_cell_cost(
    steps: int, j: int, T: float, theta: float, weight: float | None = None, controls: bool = False
) -> Any:
    """The least cost on the grid of ``steps`` cells of ``T / steps`` with the shore crossed
    in cell ``j`` at the fraction ``theta`` of it (``inf`` where that cannot happen).

    The land cells before ``j`` share one control ``a`` and the water cells after it one
    control ``b`` (the cost is strictly convex and they only move the state by their sum);
    cell ``j`` has ``c``, at speed 10 for ``theta dt`` and 3 for the rest. For fixed ``T``
    and ``theta`` the state is linear in ``z = (a, b, c)``: the shore at ``theta`` is one
    linear equation, the final state ``B z + s0``, and the cost
    ``T + dt (j|a|^2 + m|b|^2 + |c|^2)`` (plus ``weight |B z + s0 - target|^2`` at a fixed
    ``T``; with ``weight=None`` the final state is required) a quadratic: one linear
    (KKT) system. ``controls=True``: ``(cost, (N, 2) controls)``.
    """
    dt = T / steps
    m = steps - 1 - j
    (x0, y0), (x1, y1) = START, FINISH
    # columns a_x, a_y, b_x, b_y, c_x, c_y; rows: the shore at theta, then final x and y
    A = np.array([
        [0, LAND * dt * j, 0, 0, 0, LAND * dt * theta],
        [LAND * dt * j, 0, WATER * dt * m, 0, (LAND * theta + WATER * (1 - theta)) * dt, 0],
        [0, 0, 0, WATER * dt * m, 0, WATER * dt * (1 - theta)],
    ])  # fmt: skip
    r = np.array([-y0, x1 - x0, y1])
    w = dt * np.array([j, j, m, m, 1.0, 1.0])
    keep = w > 0
    A, w = A[:, keep], w[keep]
    n = int(keep.sum())
    if weight is None:  # min z'Wz s.t. A z = r
        K = np.block([[2 * np.diag(w), A.T], [A, np.zeros((3, 3))]])
        rhs = np.concatenate([np.zeros(n), r])
    else:  # min z'Wz + weight |A[1:] z - r[1:]|^2 s.t. A[0] z = r[0]
        B = A[1:]
        K = np.block([[2 * np.diag(w) + 2 * weight * B.T @ B, A[:1].T],
                      [A[:1], np.zeros((1, 1))]])  # fmt: skip
        rhs = np.concatenate([2 * weight * B.T @ r[1:], r[:1]])
    try:
        sol = np.linalg.solve(K, rhs)
    except np.linalg.LinAlgError:
        return math.inf
    z = np.zeros(6)
    z[keep] = sol[:n]
    rows = A @ sol[:n] - r
    if abs(rows[0]) > 1e-9 or (weight is None and np.abs(rows).max() > 1e-9):
        return math.inf
    a_y, c_y = z[1], z[5]
    y_start = y0 + LAND * dt * j * a_y  # y at the start of cell j: still on land
    if y_start < -1e-12 or (theta > 0 and c_y >= 0):
        return math.inf
    value = T + float(w @ (sol[:n] ** 2))
    if weight is not None:
        value += weight * float(rows[1:] @ rows[1:])
    if controls:
        u = np.empty((steps, 2))
        u[:j], u[j], u[j + 1 :] = z[0:2], z[4:6], z[2:4]
        return value, u
    return value


def snell_grid_optimum(
    steps: int, horizon: float | None = None, weight: float | None = None
) -> tuple[float, float, int, float, np.ndarray]:
    """The optimum of :func:`snell` on its own grid of ``steps`` piecewise-constant
    controls, by numpy/scipy only: ``(cost, T, cell of the crossing, fraction of that
    cell, controls)``. ``weight=None``: the free final time; else ``T = horizon`` fixed.

    For each cell ``j`` of the crossing, :func:`_snell_cell_cost` (a quadratic programme in
    closed form) is minimised over ``theta`` in ``[0, 1]`` (and ``T``): a dense scan, then
    a bounded scalar search (nested over ``T`` when it is free) around its best points.
    """
    from scipy.optimize import minimize_scalar

    def over_theta(j: int, T: float) -> tuple[float, float]:
        thetas = np.linspace(0.0, 1.0, 41)
        vals = [_snell_cell_cost(steps, j, T, th, weight) for th in thetas]
        k = int(np.argmin(vals))
        if not math.isfinite(vals[k]):
            return math.inf, math.nan
        lo, hi = thetas[max(k - 1, 0)], thetas[min(k + 1, 40)]
        res = minimize_scalar(
            lambda th: _snell_cell_cost(steps, j, T, th, weight),
            bounds=(lo, hi), method="bounded", options={"xatol": 1e-13},
        )  # fmt: skip
        return (res.fun, res.x) if res.fun < vals[k] else (vals[k], thetas[k])

    best: tuple[float, float, int, float] = (math.inf, math.nan, -1, math.nan)
    for j in range(steps):
        if weight is not None:
            value, th = over_theta(j, float(horizon))  # type: ignore[arg-type]
            T = float(horizon)  # type: ignore[arg-type]
        else:
            Ts = np.linspace(2.0, 4.0, 21)
            vals = [over_theta(j, T)[0] for T in Ts]
            k = int(np.argmin(vals))
            if not math.isfinite(vals[k]):
                continue
            res = minimize_scalar(
                lambda T, j=j: over_theta(j, T)[0],
                bounds=(Ts[max(k - 1, 0)], Ts[min(k + 1, 20)]), method="bounded",
                options={"xatol": 1e-12},
            )  # fmt: skip
            T = float(res.x)
            value, th = over_theta(j, T)
        if value < best[0]:
            best = (float(value), T, j, float(th))
    cost, T, j, th = best
    return cost, T, j, th, _snell_cell_cost(steps, j, T, th, weight, controls=True)[1]


def thermostat(steps: int = 40, horizon: float = 4.0) -> HybridOCP:
    """A room warmed by a heater with hysteresis, and a controlled extra power ``u``.

    Temperature ``x`` (deviation from the outside), modes ``"on"`` (``x' = -x + 3 + u``)
    and ``"off"`` (``x' = -x + u``); the heater switches off when ``x`` rises past 2 and on
    when it falls below 1. Cost ``int u^2 dt + 10 (x(T) - 1.5)^2``, from ``x = 1.2`` with
    the heater on. Every flow is affine, so the problem is smooth between events, and the
    switches move with ``u``.
    """
    s, u = ca.SX.sym("x"), ca.SX.sym("u")
    off = Guard.from_expressions("off", s, 2.0 - s, s, source="on", target="off", degree=1)
    on = Guard.from_expressions("on", s, s - 1.0, s, source="off", target="on", degree=1)
    return HybridOCP.from_modes(
        s, u,
        modes={"on": (-s + 3.0 + u, u**2), "off": (-s + u, u**2)},
        transitions=[off, on], initial_mode="on", phi=10.0 * (s - 1.5) ** 2,
        x0=[1.2], horizon=horizon, steps=steps, name=f"thermostat(steps={steps})",
    )  # fmt: skip


def ball_2d(steps: int = 40, restitution: float = 0.8) -> HybridOCP:
    """A ball in a vertical plane, pushed by a 2-D thrust ``u``, bouncing on the floor.

    State ``(x, y, vx, vy)``, ``x'' = u_1``, ``y'' = u_2 - 9.81``; at ``y = 0``
    ``vy+ = -e vy-``. Cost ``0.01 int |u|^2 dt + 10 |(x, y)(T) - (2, 0.8)|^2`` over
    ``T = 1.2`` from rest at ``(0, 1)``; the free drop bounces once, at about 0.45.
    """
    s, u = ca.SX.sym("s", 4), ca.SX.sym("u", 2)
    x, y, vx, vy = s[0], s[1], s[2], s[3]
    floor = Guard.from_expressions(
        "floor", s, y, ca.vertcat(x, y, vx, -restitution * vy), kind="bounce", degree=2
    )
    return HybridOCP.from_expressions(
        s, u,
        f=ca.vertcat(vx, vy, u[0], u[1] - 9.81), L=0.01 * ca.sumsqr(u),
        phi=10.0 * ((x - 2.0) ** 2 + (y - 0.8) ** 2), guards=[floor], x0=[0.0, 1.0, 0.0, 0.0],
        horizon=1.2, steps=steps, name=f"ball_2d(steps={steps})",
    )  # fmt: skip
