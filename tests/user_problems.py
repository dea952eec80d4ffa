"""Published problems written as a user would write them from the docs (issue #29).

Each builder uses the public API only (:class:`hybridoc.HybridOCP`, :class:`hybridoc.Guard`,
:meth:`~hybridoc.HybridOCP.from_modes`, :meth:`~hybridoc.HybridOCP.from_expressions`), with
no tuning for any method. Each has an independent optimum computed here with numpy/scipy only
(no hybridoc solver, no CasADi), for the tests of every method.

``switched_linear_clock``
    The switched linear system of Stellato et al. (SwitchTimeOpt.jl): ``x' = A1 x`` before the
    switch, ``A2 x`` after it, ``x(0) = (1, 1)``, ``T = 1``, ``J = int |x|^2 dt``; published
    optimum ``tau* = 0.26486646``, ``J* = 5.2545429449272``. The switching time is encoded by
    the obvious clock: a state ``c`` driven by the control before the switch (``c' = u``, with
    a small cost ``CLOCK_WEIGHT u^2``), frozen after it (``c' = 0``), and the switch is the
    guard ``c = 1``. The encoding's own optimum (:func:`switched_linear_clock_optimum`) adds
    the clock's cost: the cheapest ``u`` that brings ``c`` to 1 at ``tau`` is ``1 / tau``
    before the switch and 0 after it, costing ``CLOCK_WEIGHT / tau``. At that optimum the
    control drops to zero exactly at the event, where the clock stops: a re-simulation that
    reaches ``c = 1 - 1e-12`` at ``tau`` stays there and misses the event.

``lotka_volterra_relaxed``
    mintOC's relaxed Lotka-Volterra fishing problem (Sager's benchmark): ``x0' = x0 - x0 x1 -
    0.4 x0 w``, ``x1' = -x1 + x0 x1 - 0.2 x1 w``, ``x(0) = (0.5, 0.7)``, ``t in [0, 12]``,
    ``J = int (x0 - 1)^2 + (x1 - 1)^2 dt``, ``w in [0, 1]`` (bang-bang and singular arcs);
    published optimum :data:`LOTKA_VOLTERRA_OPTIMUM` (mintOC, relaxed problem), confirmed by
    :func:`lotka_volterra_direct` (a fine piecewise-constant direct method with scipy).
"""

from __future__ import annotations

import functools

import casadi as ca
import numpy as np
import scipy.integrate
import scipy.linalg
import scipy.optimize

from hybridoc import Guard, HybridOCP

__all__ = [
    "A1",
    "A2",
    "CLOCK_WEIGHT",
    "LOTKA_VOLTERRA_OPTIMUM",
    "STELLATO_COST",
    "STELLATO_TAU",
    "lotka_volterra_cost",
    "lotka_volterra_cost_of",
    "lotka_volterra_direct",
    "lotka_volterra_relaxed",
    "switched_linear_clock",
    "switched_linear_clock_optimum",
    "switched_linear_cost",
]

A1 = np.array([[-1.0, 0.0], [1.0, 2.0]])
A2 = np.array([[1.0, 1.0], [1.0, -2.0]])
X0 = np.array([1.0, 1.0])
STELLATO_TAU = 0.26486646
"""The published optimal switching time (SwitchTimeOpt.jl's example)."""
STELLATO_COST = 5.2545429449272
"""The published optimal cost ``int_0^1 |x|^2 dt``."""
CLOCK_WEIGHT = 1e-3
"""The clock's control weight: ``L = |x|^2 + CLOCK_WEIGHT u^2`` in both modes."""
CLOCK_GUESS = 2.0
"""The initial guess drives the clock at this rate throughout: the switch at ``t = 0.5``."""

LOTKA_VOLTERRA_OPTIMUM = 1.34408
"""mintOC's optimum of the relaxed Lotka-Volterra fishing problem (5 digits published)."""


def switched_linear_clock(steps: int = 100) -> HybridOCP:
    """The switched linear system of Stellato et al. with a clock state (module docstring).

    State ``(x1, x2, c, mode)``, control ``u`` (the clock's rate). Modes ``"A1"`` (``x' = A1
    x``, ``c' = u``) and ``"A2"`` (``x' = A2 x``, ``c' = 0``), one transition ``"switch"``
    when ``1 - c`` reaches zero; ``L = |x|^2 + CLOCK_WEIGHT u^2`` in both. The initial guess
    is ``u = CLOCK_GUESS`` throughout (the switch at ``t = 0.5``).
    """
    s, u = ca.SX.sym("s", 3), ca.SX.sym("u")
    x, c = s[:2], s[2]
    cost = ca.sumsqr(x) + CLOCK_WEIGHT * u**2
    return HybridOCP.from_modes(
        s,
        u,
        modes={
            "A1": (ca.vertcat(ca.mtimes(ca.DM(A1), x), u), cost),
            "A2": (ca.vertcat(ca.mtimes(ca.DM(A2), x), 0), cost),
        },
        transitions=[
            Guard.from_expressions("switch", s, 1 - c, s, source="A1", target="A2"),
        ],
        initial_mode="A1",
        phi=0,
        x0=[X0[0], X0[1], 0.0],
        horizon=1.0,
        steps=steps,
        u_guess=np.full((steps, 1), CLOCK_GUESS),
        state_labels=["x1", "x2", "c"],
        name="switched-linear-clock",
    )


def _gramian(A: np.ndarray, h: float) -> np.ndarray:
    """``int_0^h exp(A^T t) exp(A t) dt`` by Van Loan's block exponential."""
    n = A.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -A.T
    M[:n, n:] = np.eye(n)
    M[n:, n:] = A
    E = scipy.linalg.expm(M * h)
    return E[n:, n:].T @ E[:n, n:]


def switched_linear_cost(tau: float) -> float:
    """``int_0^1 |x|^2 dt`` of the switched system switching at ``tau`` (matrix
    exponentials; ``tau >= 1``: no switch)."""
    tau = float(min(max(tau, 0.0), 1.0))
    x_tau = scipy.linalg.expm(A1 * tau) @ X0
    return float(X0 @ _gramian(A1, tau) @ X0 + x_tau @ _gramian(A2, 1.0 - tau) @ x_tau)


@functools.cache
def switched_linear_clock_optimum() -> tuple[float, float]:
    """``(tau, J)``: the clock encoding's optimum, ``min_tau switched_linear_cost(tau) +
    CLOCK_WEIGHT / tau`` (bounded scalar minimisation to 1e-12 in ``tau``); compared with
    not switching at all (``switched_linear_cost(1)`` plus nothing: ``u = 0``)."""
    res = scipy.optimize.minimize_scalar(
        lambda t: switched_linear_cost(t) + CLOCK_WEIGHT / t,
        bounds=(0.05, 0.95),
        method="bounded",
        options={"xatol": 1e-12},
    )
    tau, J = float(res.x), float(res.fun)
    assert J < switched_linear_cost(1.0)
    return tau, J


def lotka_volterra_relaxed(steps: int = 120) -> HybridOCP:
    """mintOC's relaxed Lotka-Volterra fishing problem (module docstring): no guards, the
    bounded control ``w in [0, 1]``, initial guess ``w = 0``."""
    s, w = ca.SX.sym("x", 2), ca.SX.sym("w")
    x0, x1 = s[0], s[1]
    return HybridOCP.from_expressions(
        s,
        w,
        f=ca.vertcat(x0 - x0 * x1 - 0.4 * x0 * w, -x1 + x0 * x1 - 0.2 * x1 * w),
        L=(x0 - 1) ** 2 + (x1 - 1) ** 2,
        phi=0,
        guards=[],
        x0=[0.5, 0.7],
        horizon=12.0,
        steps=steps,
        u_min=[0.0],
        u_max=[1.0],
        state_labels=["prey", "predator"],
        control_labels=["fishing"],
        name="lotka-volterra-relaxed",
    )


def _lv_rhs(t: float, y: np.ndarray, w: float) -> np.ndarray:
    x0, x1 = y[0], y[1]
    return np.array(
        [
            x0 - x0 * x1 - 0.4 * x0 * w,
            -x1 + x0 * x1 - 0.2 * x1 * w,
            (x0 - 1) ** 2 + (x1 - 1) ** 2,
        ]
    )


def lotka_volterra_cost(w: np.ndarray, horizon: float = 12.0) -> float:
    """The cost of a piecewise-constant ``w`` on equal intervals (DOP853 at 1e-11)."""
    w = np.asarray(w, dtype=float)
    edges = np.linspace(0.0, horizon, w.size + 1)
    y = np.array([0.5, 0.7, 0.0])
    for k in range(w.size):
        sol = scipy.integrate.solve_ivp(
            _lv_rhs, (edges[k], edges[k + 1]), y, args=(w[k],), method="DOP853",
            rtol=1e-11, atol=1e-12,
        )  # fmt: skip
        y = sol.y[:, -1]
    return float(y[2])


@functools.cache
def lotka_volterra_direct(intervals: int = 60) -> tuple[float, np.ndarray]:
    """An independent upper bound of the optimum: the best piecewise-constant ``w`` on
    ``intervals`` equal intervals (L-BFGS-B in the box, finite-difference gradients of
    :func:`lotka_volterra_cost`). Any such control is admissible, so its cost bounds the
    optimum from above; on 60 intervals it is within ~1e-3 of mintOC's value."""
    w0 = np.zeros(intervals)
    w0[int(intervals * 2.5 / 12) : int(intervals * 4.5 / 12)] = 1.0
    res = scipy.optimize.minimize(
        lotka_volterra_cost, w0, method="L-BFGS-B", bounds=[(0.0, 1.0)] * intervals,
        options={"maxiter": 200, "ftol": 1e-13, "gtol": 1e-9}, jac="3-point",
    )  # fmt: skip
    return float(res.fun), np.asarray(res.x)


def lotka_volterra_cost_of(u, breakpoints, horizon: float = 12.0) -> float:
    """The cost of a callable control ``u(t)`` (smooth between ``breakpoints``), integrated
    by scipy's DOP853 at 1e-11 piece by piece: a judge independent of hybridoc's."""
    cuts = np.unique(np.clip(np.r_[0.0, np.asarray(breakpoints, dtype=float), horizon], 0, horizon))
    y = np.array([0.5, 0.7, 0.0])
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        sol = scipy.integrate.solve_ivp(
            lambda t, y: _lv_rhs(t, y, float(np.ravel(u(t))[0])), (a, b), y,
            method="DOP853", rtol=1e-11, atol=1e-12,
        )  # fmt: skip
        y = sol.y[:, -1]
    return float(y[2])
