"""Two water tanks joined by a pipe at a height: the pipe's flow switches with the levels."""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from hybridoc.ocp import Guard, HybridOCP, Mode
from hybridoc.problems.library.registry import library_problem

from ._common import check_positive

__all__ = ["two_tanks"]

_DEFAULTS = {
    "pipe_height": 0.5,
    "pipe_conductance": 2.0,
    "outflow": 0.5,
    "initial_levels": (0.2, 0.3),
    "target_level": 0.8,
    "weight": 10.0,
    "eps": 0.1,
    "horizon": 3.0,
    "steps": 150,
    "pump": 0.5,
}
#: the optimal event sequence of the defaults, checked in tests/library_optima.py
_CLAIMED = ["spill", "connect"]


def _affine_flow(name: str, s: ca.SX, u: ca.SX, f: ca.SX, L: ca.SX) -> ca.Function:
    """The exact flow map of a mode ``s' = A s + b u + d`` (2 states) under a constant ``u``.

    With ``A``'s eigenvalues ``l_1 != l_2`` (real) and the spectral projectors
    ``P_i = (A - l_j I) / (l_i - l_j)``: ``exp(A h) = sum_i exp(l_i h) P_i`` and
    ``int_0^h exp(A t) dt = sum_i (exp(l_i h) - 1) / l_i P_i`` (``h P_i`` for ``l_i = 0``),
    so ``s(h) = exp(A h) s + int_0^h exp(A t) dt (b u + d)``; the running cost ``L(u)``
    integrates to ``L h``.
    """
    jac = ca.jacobian(f, s)
    if ca.depends_on(jac, ca.vertcat(s, u)) or ca.depends_on(L, s):
        raise ValueError(f"mode {name!r}: the flow must be affine, the cost free of the state")
    A = np.array(ca.evalf(jac), dtype=float).reshape(2, 2)
    rest = ca.substitute(f, s, ca.DM.zeros(2))  # b u + d
    tr, det = A[0, 0] + A[1, 1], A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    disc = tr * tr / 4 - det
    if not disc > 0:
        raise ValueError(
            f"mode {name!r}: the flow's closed form needs distinct rates (eigenvalues "
            f"{tr / 2:g} twice); choose pipe_conductance != outflow"
        )
    lam = (tr / 2 + math.sqrt(disc), tr / 2 - math.sqrt(disc))
    h = ca.SX.sym("h")
    E, G = ca.SX.zeros(2, 2), ca.SX.zeros(2, 2)
    for li, lj in (lam, lam[::-1]):
        P = ca.DM((A - lj * np.eye(2)) / (li - lj))
        E += ca.exp(li * h) * P
        # expm1: exact to rounding over the short steps of event location, and for an l
        # that rounding left tiny instead of 0 (apart and backflowing have l = 0: tank 1
        # has no outlet)
        G += (h if li == 0.0 else ca.expm1(li * h) / li) * P
    end = ca.mtimes(E, s) + ca.mtimes(G, rest)
    return ca.Function(f"flow_{name}", [s, u, h], [end, L * h])


# over 80 lines: one problem stated whole; most lines are its keyword parameters, listed
# in the signature, checked, and recorded in meta["params"]
@library_problem("two-tanks")
def two_tanks(
    *,
    pipe_height: float = 0.5,
    pipe_conductance: float = 2.0,
    outflow: float = 0.5,
    initial_levels: tuple[float, float] = (0.2, 0.3),
    target_level: float = 0.8,
    weight: float = 10.0,
    eps: float = 0.1,
    horizon: float = 3.0,
    steps: int = 150,
    pump: float = 0.5,
) -> HybridOCP:
    r"""Two tanks joined by a pipe at a height, the second filled through the first (4 modes).

    State ``(h1, h2, mode)`` (the water levels), control ``u`` (the pump's net inflow into
    tank 1; negative: it drains). Tank 2 drains through its bottom, ``c h2``. The pipe
    between the tanks sits at height ``p`` and carries ``a (max(h1, p) - max(h2, p))`` from
    tank 1 to tank 2, so which levels are above it is the mode::

        apart       (h1 < p, h2 < p):  h1' = u,                 h2' = -c h2
        spilling    (h1 > p > h2):     h1' = u - a (h1 - p),    h2' = a (h1 - p) - c h2
        connected   (h1 > p, h2 > p):  h1' = u - a (h1 - h2),   h2' = a (h1 - h2) - c h2
        backflowing (h1 < p < h2):     h1' = u + a (h2 - p),    h2' = -a (h2 - p) - c h2

        spill          apart -> spilling        when p - h1 reaches 0 from above
        spill-stops    spilling -> apart        when h1 - p reaches 0 from above
        connect        spilling -> connected    when p - h2 reaches 0 from above
        disconnect     connected -> spilling    when h2 - p reaches 0 from above
        backflow       connected -> backflowing when h1 - p reaches 0 from above
        reconnect      backflowing -> connected when p - h1 reaches 0 from above
        backflow-stops backflowing -> apart     when h2 - p reaches 0 from above
        (identity resets)
        minimise   w (h2(T) - r)^2 + eps int_0^T u^2 dt

    Tank 2 cannot rise while apart (nothing flows in), so ``apart`` has one way out. Both
    tanks start below the pipe, ``(h1, h2)(0) = initial_levels``; the target ``r`` lies
    above it, so tank 1 must fill up to the pipe and spill into tank 2 until tank 2 reaches
    the pipe too. Every mode is affine with real distinct rates, so each has an exact flow
    map (sums of exponentials; the judge needs no integrator); ``spill``'s guard is linear
    in time along ``apart``'s flow (``degree=1``), the others are not polynomials. The
    initial guess pumps ``u = pump`` throughout (``0.5``: spill at ``t = 0.6``, connect
    near ``t = 2.14``).

    HMP structure: ``u = -lambda_1 / (2 eps)``, ``lambda' = -A_q^T lambda`` in mode ``q``;
    while apart ``lambda_1`` is constant (the pump runs at a constant rate until tank 1
    spills); ``lambda(T) = (0, 2 w (h2(T) - r))``, so the pump stops at ``T``. The pipe's
    flow is continuous in the levels, so the flows of two modes agree on the guard between
    them: at a transversal event the costate does not jump (the guard's multiplier is 0) and
    the Hamiltonian is continuous; what changes is the flow's Jacobian, and with it the
    costate's rates (``u`` has a kink in its derivative there).

    Parameters
    ----------
    pipe_height
        ``p > 0``.
    pipe_conductance
        ``a > 0``; must differ from ``outflow`` (the spilling flow's closed form needs
        distinct rates).
    outflow
        ``c > 0``, tank 2's outlet.
    initial_levels
        ``(h1, h2)(0)``, both in ``[0, p)``.
    target_level
        ``r``, tank 2's level wanted at ``T``.
    weight
        ``w >= 0``.
    eps
        Control weight.
    horizon, steps
        ``T`` and ``N``.
    pump
        The constant inflow of the initial guess.

    Returns
    -------
    HybridOCP
        With modes ``("apart", "spilling", "connected", "backflowing")``; ``meta`` holds
        ``"family"``, ``"params"`` and ``"claimed_sequence"`` (``["spill", "connect"]`` for
        the defaults, checked independently in ``tests/library_optima.py``; ``None``
        otherwise).

    Notes
    -----
    The defaults: ``p = 0.5``, ``a = 2``, ``c = 0.5``, ``(h1, h2)(0) = (0.2, 0.3)``,
    ``r = 0.8``, ``w = 10``, ``eps = 0.1``, ``T = 3``, ``N = 150``. The optimum pumps at a
    constant rate until tank 1 spills (``t = 0.5978389``), tank 2 reaches the pipe at
    ``t = 1.8119983``, cost ``0.1364700867`` (``tests/library_optima.py``).
    """
    args = dict(locals())
    p = check_positive("pipe_height", pipe_height)
    a = check_positive("pipe_conductance", pipe_conductance)
    c = check_positive("outflow", outflow)
    eps = check_positive("eps", eps)
    T = check_positive("horizon", horizon)
    h10, h20 = (float(v) for v in initial_levels)
    if not (0.0 <= h10 < p and 0.0 <= h20 < p):
        raise ValueError(
            f"initial_levels must both lie in [0, pipe_height) = [0, {p:g}) (the tanks start "
            f"apart), got {(h10, h20)}"
        )
    if float(weight) < 0:
        raise ValueError(f"weight must be non-negative, got {weight}")
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u")
    h1, h2 = s[0], s[1]
    L = eps * u**2

    def mode(name: str, pipe: ca.SX) -> Mode:
        f = ca.vertcat(u - pipe, pipe - c * h2)
        return Mode(
            name,
            f=ca.Function(f"f_{name}", [s, u], [f]),
            L=ca.Function(f"L_{name}", [s, u], [L]),
            flow_map=_affine_flow(name, s, u, f, L),
        )

    modes = [
        mode("apart", ca.SX(0.0)),
        mode("spilling", a * (h1 - p)),
        mode("connected", a * (h1 - h2)),
        mode("backflowing", -a * (h2 - p)),
    ]

    def level(name: str, psi: ca.SX, source: str, target: str, **kw: int) -> Guard:
        return Guard.from_expressions(
            name, s, psi, s, kind="level", bodies=("tank1", "tank2", "pipe"),
            source=source, target=target, **kw,
        )  # fmt: skip

    transitions = [
        level("spill", p - h1, "apart", "spilling", degree=1),
        level("spill-stops", h1 - p, "spilling", "apart"),
        level("connect", p - h2, "spilling", "connected"),
        level("disconnect", h2 - p, "connected", "spilling"),
        level("backflow", h1 - p, "connected", "backflowing"),
        level("reconnect", p - h1, "backflowing", "connected"),
        level("backflow-stops", h2 - p, "backflowing", "apart"),
    ]
    params = {
        "pipe_height": p,
        "pipe_conductance": a,
        "outflow": c,
        "initial_levels": [h10, h20],
        "target_level": float(target_level),
        "weight": float(weight),
        "eps": eps,
        "horizon": T,
        "steps": int(steps),
        "pump": float(pump),
    }
    defaults = all(
        (tuple(args[k]) == v) if k == "initial_levels" else args[k] == v
        for k, v in _DEFAULTS.items()
    )
    return HybridOCP.from_modes(
        s,
        u,
        modes=modes,
        transitions=transitions,
        initial_mode="apart",
        phi=float(weight) * (h2 - float(target_level)) ** 2,
        x0=[h10, h20],
        horizon=T,
        steps=steps,
        u_guess=np.full((int(steps), 1), float(pump)),
        name="two_tanks",
        state_labels=["h1", "h2"],
        control_labels=["u"],
        meta={
            "family": "two_tanks",
            "params": params,
            "claimed_sequence": list(_CLAIMED) if defaults else None,
        },
    )
