"""Independent optima of the problem library (``problems/library``), without hybridoc's solvers.

Every problem is restated here by hand from its parameters (``ocp.meta["params"]``; the tests
check the restatement against the library's CasADi functions) and solved for a *fixed* event
sequence by methods that share no code with ``hybridoc.reference`` or ``hybridoc.solvers``:

Double integrators (``bouncing_ball``, ``ball_on_slope``, ``juggling_paddle``)
    The flow is linear, ``x' = A x + B u + c`` with a nilpotent ``A``; the resets are linear,
    ``x+ = R x``; the guards are linear, ``n . x = 0``; the running cost is ``eps |u|^2`` and
    the terminal cost a quadratic. For a fixed sequence the costate is polynomial on each
    phase, so the optimal control is linear in time on each phase,
    ``u = a_k + b_k (t - gamma_{k-1})``. For fixed event times ``gamma`` the state is affine in
    the coefficients ``p = (a_k, b_k)``, the cost quadratic and the guard conditions
    ``psi(x(gamma_k-)) = 0`` linear: one KKT solve gives the exact value ``V(gamma)``.
    ``V`` is minimised over the ordered event times by a grid, SLSQP, and Newton's method on
    its complex-step gradient (to ``|dV/dgamma| < 1e-13``).

    The same computation with a sequence imposed is a *relaxation* (the floor may be crossed
    between events, an "impact" may even leave the guard upwards), so its minimum is a lower
    bound of the cost of any control with that sequence: the alternatives are compared
    through these lower bounds.

    The HMP is *checked*, not imposed: the costate is integrated backward from
    ``lambda(T) = grad phi``; at each event the multiplier ``pi`` is fitted (least squares)
    so that ``lambda(gamma-) = R^T lambda(gamma+) + pi n`` reproduces the control before the
    event; what is left (the control mismatch on every phase and the Hamiltonian jump at every
    event) must vanish.

Pendulum (``pendulum_wall``)
    A multiple-shooting NLP with its own RK4 (casadi ``Opti`` + IPOPT, piecewise-constant
    control, event times as variables through phase-duration scaling), one per sequence; the
    claimed sequence's NLP point is then polished by indirect shooting of the HMP (costate ODE,
    jump with multiplier, Hamiltonian continuity, transversality; SciPy's DOP853 at 1e-12 and
    ``scipy.optimize.root``), which gives the exact continuous optimum; the NLP's cost must
    agree to the discretisation error.

:func:`independent_optimum` returns, for each configuration name in :data:`CONFIGS`, the
cost, sequence, event times, a callable ``u(t)`` and the breakpoints to pass with it to
:func:`hybridoc.evaluate_callable`, the lower bounds of the alternative sequences and the HMP
residuals.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
import itertools
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
import scipy.optimize as so
from scipy.integrate import solve_ivp

__all__ = [
    "CONFIGS",
    "LinearModel",
    "build",
    "expected_table",
    "hmp_check",
    "independent_optimum",
    "library",
    "linear_model",
    "pendulum_rhs",
]


def library() -> Any:
    """The ``hybridoc.problems.library`` package, imported by file path if not installed."""
    name = "hybridoc.problems.library"
    if name in sys.modules:
        return sys.modules[name]
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as exc:
        if exc.name != name:
            raise
    import hybridoc.problems

    path = Path(__file__).resolve().parents[1] / "problems" / "library"
    spec = importlib.util.spec_from_file_location(
        name, path / "__init__.py", submodule_search_locations=[str(path)]
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    hybridoc.problems.library = module  # type: ignore[attr-defined]
    return module


#: configuration name -> (problem function, keyword arguments)
CONFIGS: dict[str, tuple[str, dict[str, Any]]] = {
    **{
        f"bouncing_ball(bounces={k}, e={e:g})": (
            "bouncing_ball",
            {"bounces": k, "restitution": e},
        )
        for k in (0, 1, 2)
        for e in (1.0, 0.8)
    },
    "ball_on_slope(bounces=1, e=0.9)": ("ball_on_slope", {"bounces": 1}),
    "ball_on_slope(bounces=2, e=0.9)": ("ball_on_slope", {"bounces": 2}),
    "juggling_paddle(e=0.8)": ("juggling_paddle", {"restitution": 0.8}),
    "juggling_paddle(e=1)": ("juggling_paddle", {"restitution": 1.0}),
    "juggling_paddle(e=0.8, mu=0.5)": ("juggling_paddle", {"mass_ratio": 0.5}),
    "pendulum_wall(e=0.8)": ("pendulum_wall", {"restitution": 0.8}),
    "pendulum_wall(e=1)": ("pendulum_wall", {"restitution": 1.0}),
}

#: the independent claim: number of events of the optimum of each configuration
CLAIMED_EVENTS = {
    **{f"bouncing_ball(bounces={k}, e={e:g})": k for k in (0, 1, 2) for e in (1.0, 0.8)},
    "ball_on_slope(bounces=1, e=0.9)": 1,
    "ball_on_slope(bounces=2, e=0.9)": 2,
    "juggling_paddle(e=0.8)": 1,
    "juggling_paddle(e=1)": 1,
    "juggling_paddle(e=0.8, mu=0.5)": 2,
    "pendulum_wall(e=0.8)": 1,
    "pendulum_wall(e=1)": 1,
}


def build(name: str) -> Any:
    """The library's ``HybridOCP`` of a configuration."""
    fn, kwargs = CONFIGS[name]
    return getattr(library(), fn)(**kwargs)


# --------------------------------------------------------------------------------------------
# double integrators: exact sequence-fixed optima


@dataclass
class LinearModel:
    """``x' = A x + B u + c``, ``L = eps |u|^2``, ``phi = (x - xt)^T W (x - xt)``, guards
    ``psi = n . x`` with resets ``x+ = R x``, all restated by hand."""

    A: np.ndarray
    B: np.ndarray
    c: np.ndarray
    eps: float
    W: np.ndarray
    xt: np.ndarray
    x0: np.ndarray
    T: float
    guards: dict[str, np.ndarray]
    resets: dict[str, np.ndarray]
    powers: list[np.ndarray] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        nx = self.A.shape[0]
        self.powers = [np.linalg.matrix_power(self.A, k) for k in range(nx)]
        assert np.all(np.linalg.matrix_power(self.A, nx) == 0), "A must be nilpotent"

    @property
    def nx(self) -> int:
        return self.A.shape[0]

    @property
    def nu(self) -> int:
        return self.B.shape[1]

    def f(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.A @ x + self.B @ u + self.c

    def phase(self, tau: Any) -> tuple[Any, Any, Any, Any]:
        """``x(tau) = E x(0) + Fa a + Fb b + fc`` under ``u = a + b t`` (exact series)."""
        E = Fa = Fb = fc = 0
        for k, Ak in enumerate(self.powers):
            E = E + Ak * tau**k / math.factorial(k)
            Fa = Fa + (Ak @ self.B) * tau ** (k + 1) / math.factorial(k + 1)
            Fb = Fb + (Ak @ self.B) * tau ** (k + 2) / math.factorial(k + 2)
            fc = fc + (Ak @ self.c) * tau ** (k + 1) / math.factorial(k + 1)
        return E, Fa, Fb, fc

    def costate_back(self, lam_end: np.ndarray, tau: float) -> np.ndarray:
        """``lambda`` a time ``tau`` before ``lam_end`` (``lambda' = -A^T lambda``)."""
        out = np.zeros_like(lam_end)
        for k, Ak in enumerate(self.powers):
            out = out + Ak.T @ lam_end * tau**k / math.factorial(k)
        return out


def linear_model(ocp: Any) -> LinearModel:
    """The hand-written model of a double-integrator configuration from its parameters."""
    fam, P = ocp.meta["family"], ocp.meta["params"]
    e = P["restitution"]
    if fam == "bouncing_ball":
        return LinearModel(
            A=np.array([[0.0, 1.0], [0.0, 0.0]]),
            B=np.array([[0.0], [1.0]]),
            c=np.array([0.0, -P["gravity"]]),
            eps=P["eps"],
            W=np.diag([P["weight_height"], P["weight_velocity"]]),
            xt=np.array([P["target_height"], P["target_velocity"]]),
            x0=np.array([P["initial_height"], 0.0]),
            T=P["horizon"],
            guards={"floor": np.array([1.0, 0.0])},
            resets={"floor": np.diag([1.0, -e])},
        )
    if fam == "ball_on_slope":
        a = math.radians(P["slope_deg"])
        n = np.array([-math.sin(a), math.cos(a)])
        A = np.zeros((4, 4))
        A[0, 2] = A[1, 3] = 1.0
        R = np.eye(4)
        R[2:, 2:] -= (1 + e) * np.outer(n, n)
        return LinearModel(
            A=A,
            B=np.vstack([np.zeros((2, 2)), np.eye(2)]),
            c=np.array([0.0, 0.0, 0.0, -P["gravity"]]),
            eps=P["eps"],
            W=np.diag([P["weight_position"]] * 2 + [P["weight_velocity"]] * 2),
            xt=np.array(list(P["target"]) + list(P["target_velocity"])),
            x0=np.array(list(P["initial_position"]) + [0.0, 0.0]),
            T=P["horizon"],
            guards={"slope": np.concatenate([n, [0.0, 0.0]])},
            resets={"slope": R},
        )
    if fam == "juggling_paddle":
        # state (y_p, v_p, y_b, v_b); w = v_b - v_p; k = (1 + e) / (1 + mu)
        mu = P["mass_ratio"]
        k = (1 + e) / (1 + mu)
        A = np.zeros((4, 4))
        A[0, 1] = A[2, 3] = 1.0
        R = np.eye(4)
        R[1, 1], R[1, 3] = 1 - mu * k, mu * k  # v_p+ = v_p + mu k w
        R[3, 1], R[3, 3] = k, 1 - k  # v_b+ = v_b - k w
        wp = P["weight_paddle"]
        return LinearModel(
            A=A,
            B=np.array([[0.0], [1.0], [0.0], [0.0]]),
            c=np.array([0.0, 0.0, 0.0, -P["gravity"]]),
            eps=P["eps"],
            W=np.diag([wp, wp, P["weight_height"], P["weight_velocity"]]),
            xt=np.array([0.0, 0.0, P["target_height"], P["target_velocity"]]),
            x0=np.array([0.0, 0.0, P["ball_height"], 0.0]),
            T=P["horizon"],
            guards={"paddle|ball": np.array([-1.0, 0.0, 1.0, 0.0])},
            resets={"paddle|ball": R},
        )
    raise ValueError(f"no linear model for {fam!r}")


def _boundaries(mod: LinearModel, gammas: Any) -> Any:
    return np.concatenate([[0.0], gammas, [mod.T]])


def sequence_qp(
    mod: LinearModel, seq: list[str], gammas: Any
) -> tuple[Any, np.ndarray, np.ndarray]:
    """Exact minimum over ``p`` for fixed event times: ``(V, p, guard multipliers)``.

    Complex-analytic in ``gammas`` (transposes, no conjugates) for complex-step derivatives.
    """
    gammas = np.asarray(gammas)
    K, nu = len(seq), mod.nu
    npar = 2 * nu * (K + 1)
    dtype = complex if np.iscomplexobj(gammas) else float
    M = np.zeros((mod.nx, npar), dtype=dtype)
    m = mod.x0.astype(dtype)
    Q = np.zeros((npar, npar), dtype=dtype)
    C, d = [], []
    b = _boundaries(mod, gammas)
    eye = np.eye(nu)
    for k in range(K + 1):
        tau = b[k + 1] - b[k]
        E, Fa, Fb, fc = mod.phase(tau)
        ia = slice(2 * nu * k, 2 * nu * k + nu)
        ib = slice(2 * nu * k + nu, 2 * nu * (k + 1))
        M = E @ M
        M[:, ia] += Fa
        M[:, ib] += Fb
        m = E @ m + fc
        # eps int_0^tau |a + b t|^2 dt
        Q[ia, ia] += mod.eps * tau * eye
        Q[ia, ib] += mod.eps * tau**2 / 2 * eye
        Q[ib, ia] += mod.eps * tau**2 / 2 * eye
        Q[ib, ib] += mod.eps * tau**3 / 3 * eye
        if k < K:
            n = mod.guards[seq[k]]
            C.append(n @ M)
            d.append(-(n @ m))
            R = mod.resets[seq[k]]
            M, m = R @ M, R @ m
    P = Q + M.T @ mod.W @ M
    q = M.T @ mod.W @ (m - mod.xt)
    c0 = (m - mod.xt) @ mod.W @ (m - mod.xt)
    if K:
        Cm = np.array(C)
        kkt = np.block([[2 * P, Cm.T], [Cm, np.zeros((K, K))]])
        sol = np.linalg.solve(kkt, np.concatenate([-2 * q, np.array(d)]))
        p, nu_mult = sol[:npar], sol[npar:]
    else:
        p, nu_mult = np.linalg.solve(P, -q), np.zeros(0)
    return p @ P @ p + 2 * q @ p + c0, p, nu_mult


_BIG = 1e9


def _value(mod: LinearModel, seq: list[str], g: Any) -> Any:
    try:
        return sequence_qp(mod, seq, g)[0]
    except np.linalg.LinAlgError:
        return _BIG


def _grad(mod: LinearModel, seq: list[str], g: np.ndarray) -> np.ndarray:
    """Complex-step gradient of ``V`` (exact to rounding)."""
    g = np.asarray(g, dtype=float)
    out = np.zeros(g.size)
    for i in range(g.size):
        gc = g.astype(complex)
        gc[i] += 1e-30j
        out[i] = np.imag(_value(mod, seq, gc)) / 1e-30
    return out


def _ordered(mod: LinearModel, g: np.ndarray, gap: float) -> bool:
    return bool(np.all(np.diff(_boundaries(mod, g)) > gap))


def _newton(mod: LinearModel, seq: list[str], g: np.ndarray, gap: float) -> np.ndarray:
    """Newton on ``dV/dgamma = 0`` (Hessian by central differences of the exact gradient)."""
    g = np.asarray(g, dtype=float)
    for _ in range(30):
        gr = _grad(mod, seq, g)
        if np.max(np.abs(gr)) < 1e-13:
            break
        h = 1e-6
        hess = np.column_stack(
            [
                (_grad(mod, seq, g + h * ei) - _grad(mod, seq, g - h * ei)) / (2 * h)
                for ei in np.eye(g.size)
            ]
        )
        try:
            step = np.linalg.solve(0.5 * (hess + hess.T), gr)
        except np.linalg.LinAlgError:
            break
        g_new = g - step
        if not _ordered(mod, g_new, gap):
            break
        g = g_new
        if np.max(np.abs(step)) < 1e-15:
            break
    return g


#: grid points per event time for the search over event times, by number of events
_GRID = {1: 100, 2: 36, 3: 14}


def minimise_over_times(
    mod: LinearModel, seq: list[str], *, keep: int = 3, gap: float = 1e-4
) -> tuple[float, np.ndarray]:
    """Global minimum of the relaxed sequence-fixed problem over ordered event times with
    phases of at least ``gap``: grid search, SLSQP from the ``keep`` best points, Newton."""
    K = len(seq)
    if K == 0:
        return float(_value(mod, seq, np.zeros(0))), np.zeros(0)
    grid = np.linspace(0.0, mod.T, _GRID[K] + 2)[1:-1]
    starts = sorted(
        (
            (float(_value(mod, seq, np.array(c))), np.array(c))
            for c in itertools.combinations(grid, K)
        ),
        key=lambda vc: vc[0],
    )[:keep]
    cons = [{"type": "ineq", "fun": lambda g, i=i: g[i + 1] - g[i] - gap} for i in range(K - 1)]
    best: tuple[float, np.ndarray] | None = None
    for _, g0 in starts:
        res = so.minimize(
            lambda g: float(_value(mod, seq, g)),
            g0,
            jac=lambda g: _grad(mod, seq, g),
            method="SLSQP",
            bounds=[(gap, mod.T - gap)] * K,
            constraints=cons,
            options={"ftol": 1e-15, "maxiter": 300},
        )
        g = res.x
        if _ordered(mod, g, 0.5 * gap):
            g2 = _newton(mod, seq, g, 0.5 * gap)
            if _value(mod, seq, g2) <= _value(mod, seq, g) + 1e-12:
                g = g2
        v = float(_value(mod, seq, g))
        if best is None or v < best[0]:
            best = (v, g)
    assert best is not None
    return best


def linear_control(
    mod: LinearModel, gammas: np.ndarray, p: np.ndarray
) -> Callable[[float], np.ndarray]:
    """``u(t) = a_k + b_k (t - gamma_{k-1})`` on phase ``k``."""
    b = _boundaries(mod, gammas)
    nu = mod.nu

    def u(t: float) -> np.ndarray:
        k = int(np.clip(np.searchsorted(b, t, side="right") - 1, 0, len(gammas)))
        a0 = p[2 * nu * k : 2 * nu * k + nu]
        a1 = p[2 * nu * k + nu : 2 * nu * (k + 1)]
        return a0 + a1 * (t - b[k])

    return u


def _trajectory(
    mod: LinearModel, seq: list[str], gammas: np.ndarray, p: np.ndarray
) -> tuple[list[np.ndarray], list[np.ndarray], np.ndarray]:
    """States at phase starts (after resets), at event times before the resets, and at T."""
    b = _boundaries(mod, gammas)
    nu = mod.nu
    x = mod.x0.copy()
    starts, minus = [], []
    for k in range(len(seq) + 1):
        starts.append(x.copy())
        E, Fa, Fb, fc = mod.phase(b[k + 1] - b[k])
        x = (
            E @ x
            + Fa @ p[2 * nu * k : 2 * nu * k + nu]
            + Fb @ p[2 * nu * k + nu : 2 * nu * (k + 1)]
            + fc
        )
        if k < len(seq):
            minus.append(x.copy())
            x = mod.resets[seq[k]] @ x
    return starts, minus, x


def hmp_check(
    mod: LinearModel, seq: list[str], gammas: np.ndarray, p: np.ndarray
) -> dict[str, Any]:
    """Residuals of the HMP at a candidate (see the module notes).

    Returns ``control`` (max over phases of ``|u - u*(lambda)|``, ``u* = -B^T lambda /
    (2 eps)``, relative to ``max |u|``), ``hamiltonian`` (max ``|H(gamma-) - H(gamma+)|``
    relative to the size of ``H``'s terms), ``multipliers`` (``pi_k``), ``costate0``
    (``lambda(0)``) and ``approach_speeds`` (``d psi / dt`` just before each event).
    """
    b = _boundaries(mod, gammas)
    K, nu = len(seq), mod.nu
    starts, minus, xT = _trajectory(mod, seq, gammas, p)

    def u_phase(k: int, tau: float) -> np.ndarray:
        return p[2 * nu * k : 2 * nu * k + nu] + p[2 * nu * k + nu : 2 * nu * (k + 1)] * tau

    def u_star(lmb: np.ndarray) -> np.ndarray:
        return -(mod.B.T @ lmb) / (2 * mod.eps)

    def ham(x: np.ndarray, uu: np.ndarray, lmb: np.ndarray) -> tuple[float, float]:
        terms = np.concatenate([[mod.eps * uu @ uu], lmb * mod.f(x, uu)])
        return float(np.sum(terms)), float(np.sum(np.abs(terms)))

    durations = np.diff(b)
    u_scale = max(
        float(np.max(np.abs(u_phase(k, s))))
        for k in range(K + 1)
        for s in np.linspace(0.0, durations[k], 5)
    )
    lam = 2 * mod.W @ (xT - mod.xt)  # transversality: lambda(T) = grad phi
    ctrl_res, ham_res, pis = 0.0, 0.0, []
    for k in range(K, -1, -1):
        tau = durations[k]
        # lambda is a polynomial of degree < nx on the phase, u of degree 1: nx + 1 points
        for s in np.linspace(0.0, tau, mod.nx + 1):
            lm = mod.costate_back(lam, s)
            ctrl_res = max(ctrl_res, float(np.max(np.abs(u_phase(k, tau - s) - u_star(lm)))))
        lam_plus = mod.costate_back(lam, tau)  # lambda at the start of phase k
        if k == 0:
            break
        # event k - 1 ends phase k - 1: lambda(gamma-) = R^T lambda(gamma+) + pi n, pi fitted
        # to the control before the event: u*(lambda-) = u(gamma-) and
        # d/dt u* = B^T A^T lambda- / (2 eps) = the slope b_{k-1}
        R, n = mod.resets[seq[k - 1]], mod.guards[seq[k - 1]]
        u_minus = u_phase(k - 1, durations[k - 1])
        slope = p[2 * nu * (k - 1) + nu : 2 * nu * k]

        def resid(lmb: np.ndarray, u_minus: Any = u_minus, slope: Any = slope) -> np.ndarray:
            return np.concatenate(
                [u_star(lmb) - u_minus, (mod.B.T @ mod.A.T @ lmb) / (2 * mod.eps) - slope]
            )

        base = R.T @ lam_plus
        r0, r1 = resid(base), resid(base + n) - resid(base)
        pi = float(-(r1 @ r0) / (r1 @ r1))
        pis.append(pi)
        lam_minus = base + pi * n
        h_minus, s_minus = ham(minus[k - 1], u_minus, lam_minus)
        h_plus, s_plus = ham(starts[k], u_phase(k, 0.0), lam_plus)
        ham_res = max(ham_res, abs(h_minus - h_plus) / max(1.0, s_minus, s_plus))
        lam = lam_minus  # the fit's residual shows in the control check of phase k - 1
    speeds = [
        float(mod.guards[seq[k]] @ mod.f(minus[k], u_phase(k, durations[k]))) for k in range(K)
    ]
    return {
        "control": ctrl_res / max(u_scale, 1e-300),
        "hamiltonian": ham_res,
        "multipliers": pis[::-1],
        "costate0": lam_plus,
        "approach_speeds": speeds,
    }


def _linear_optimum(name: str) -> dict[str, Any]:
    t0 = time.perf_counter()
    ocp = build(name)
    mod = linear_model(ocp)
    guard = next(iter(mod.guards))
    K = CLAIMED_EVENTS[name]
    seq = [guard] * K
    cost, gammas = minimise_over_times(mod, seq, keep=4)
    _, p, _ = sequence_qp(mod, seq, gammas)
    alternatives = {}
    for k_alt in range(4):
        if k_alt != K:
            alternatives[k_alt] = minimise_over_times(mod, [guard] * k_alt, keep=2)[0]
    return {
        "name": name,
        "ocp": ocp,
        "cost": cost,
        "sequence": seq,
        "event_times": [float(g) for g in gammas],
        "control_callable": linear_control(mod, gammas, p),
        "breakpoints": [float(g) for g in gammas],
        "coefficients": p.reshape(K + 1, 2, mod.nu),
        "alternatives": alternatives,
        "hmp": hmp_check(mod, seq, gammas, p),
        "method": (
            "exact sequence-fixed optimum: KKT solve for the phase-wise linear control at "
            "fixed event times, minimised over the event times (grid, SLSQP, Newton on the "
            "complex-step gradient); alternatives: relaxed lower bounds, same method"
        ),
        "seconds": time.perf_counter() - t0,
    }


# --------------------------------------------------------------------------------------------
# pendulum: sequence-fixed NLP (own RK4) and indirect polish


def pendulum_rhs(P: dict[str, Any], x: Any, u: Any, sin: Callable[[Any], Any] = np.sin) -> Any:
    """``(theta', omega')`` of the pendulum, restated from its parameters."""
    g, ell, m = P["gravity"], P["length"], P["mass"]
    return [x[1], -(g / ell) * sin(x[0]) + u / (m * ell**2)]


def pendulum_nlp(
    P: dict[str, Any],
    events: int,
    *,
    intervals: int = 60,
    substeps: int = 8,
    min_phase: float = 0.005,
    gamma0: list[float] | None = None,
) -> tuple[float, np.ndarray, list[np.ndarray]]:
    """Multiple shooting with ``events`` wall impacts at variable times.

    Each phase has ``intervals`` equal intervals of piecewise-constant torque, integrated by
    ``substeps`` RK4 steps each; ``theta <= theta_w`` at every node; each phase lasts at least
    ``min_phase``. Returns the cost, the event times and the torques of each phase.
    """
    e, tw, T = P["restitution"], P["wall_angle"], P["horizon"]
    x, u, h = ca.SX.sym("x", 2), ca.SX.sym("u"), ca.SX.sym("h")

    def f(xx: Any, uu: Any) -> Any:
        return ca.vertcat(*pendulum_rhs(P, xx, uu, ca.sin))

    xk = x
    for _ in range(substeps):
        hh = h / substeps
        k1 = f(xk, u)
        k2 = f(xk + hh / 2 * k1, u)
        k3 = f(xk + hh / 2 * k2, u)
        k4 = f(xk + hh * k3, u)
        xk = xk + hh / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    step = ca.Function("rk4", [x, u, h], [xk])
    opti = ca.Opti()
    gam = opti.variable(events) if events else None
    bounds = ca.vertcat(0, gam, T) if events else ca.vertcat(0, T)
    x0 = ca.DM([P["initial_angle"], 0.0])
    cost, xs, controls = 0, x0, []
    for k in range(events + 1):
        dur = bounds[k + 1] - bounds[k]
        U = opti.variable(intervals)
        X = opti.variable(2, intervals + 1)
        controls.append(U)
        opti.subject_to(X[:, 0] == xs)
        for j in range(intervals):
            opti.subject_to(X[:, j + 1] == step(X[:, j], U[j], dur / intervals))
            cost += P["eps"] * U[j] ** 2 * dur / intervals
            opti.set_initial(X[:, j], x0)
        opti.subject_to(X[0, 1:intervals] <= tw)
        opti.set_initial(X[:, intervals], x0)
        xe = X[:, intervals]
        if events:
            opti.subject_to(dur >= min_phase)
        if k < events:
            opti.subject_to(xe[0] == tw)
            xs = ca.vertcat(xe[0], -e * xe[1])
    cost += P["weight_angle"] * (xe[0] - P["target_angle"]) ** 2
    cost += P["weight_velocity"] * (xe[1] - P["target_velocity"]) ** 2
    opti.minimize(cost)
    if events:
        guess = gamma0 if gamma0 is not None else np.linspace(0, T, events + 2)[1:-1]
        opti.set_initial(gam, guess)
    opti.solver(
        "ipopt",
        {"print_time": False},
        {"print_level": 0, "sb": "yes", "tol": 1e-12, "max_iter": 3000},
    )
    sol = opti.solve()
    gv = np.atleast_1d(np.asarray(sol.value(gam), dtype=float)) if events else np.zeros(0)
    us = [np.atleast_1d(np.asarray(sol.value(U), dtype=float)) for U in controls]
    return float(sol.value(cost)), gv, us


def _piecewise_constant(
    T: float, gammas: np.ndarray, torques: list[np.ndarray]
) -> tuple[Callable[[float], np.ndarray], list[float]]:
    b = np.concatenate([[0.0], gammas, [T]])

    def u(t: float) -> np.ndarray:
        k = int(np.clip(np.searchsorted(b, t, side="right") - 1, 0, len(gammas)))
        n = len(torques[k])
        j = int(np.clip(math.floor((t - b[k]) / (b[k + 1] - b[k]) * n), 0, n - 1))
        return np.array([torques[k][j]])

    nodes = np.concatenate(
        [np.linspace(b[k], b[k + 1], len(torques[k]) + 1) for k in range(len(gammas) + 1)]
    )
    return u, sorted({float(t) for t in nodes if 0 < t < T})


_DOP853: dict[str, Any] = {"method": "DOP853", "rtol": 1e-12, "atol": 1e-12}


def pendulum_indirect(P: dict[str, Any], gamma: float, torques: list[np.ndarray]) -> dict[str, Any]:
    """The HMP extremal with one wall impact, by shooting from an NLP point.

    Unknowns ``(lambda(0), gamma, pi)``; residuals: the guard at ``gamma-``, Hamiltonian
    continuity, ``lambda(T) = grad phi``; the costate jumps by
    ``lambda(gamma-) = R^T lambda(gamma+) + pi grad psi`` with ``R = diag(1, -e)`` and
    ``grad psi = (-1, 0)``. ODEs by SciPy's DOP853 at ``rtol = atol = 1e-12``.
    """
    g, ell, m, e = P["gravity"], P["length"], P["mass"], P["restitution"]
    eps, tw, T = P["eps"], P["wall_angle"], P["horizon"]
    k_u = 1.0 / (2 * eps * m * ell**2)  # u = -k_u lambda_omega

    def rhs(_t: float, z: np.ndarray) -> np.ndarray:
        th, om, lt, lo = z[:4]
        uu = -k_u * lo
        acc = -(g / ell) * math.sin(th) + uu / (m * ell**2)
        return np.array([om, acc, (g / ell) * math.cos(th) * lo, -lt, eps * uu * uu])

    def ham(z: np.ndarray) -> float:
        uu = -k_u * z[3]
        return (
            eps * uu * uu + z[2] * z[1] + z[3] * (-(g / ell) * math.sin(z[0]) + uu / (m * ell**2))
        )

    def shoot(w: np.ndarray, dense: bool = False) -> tuple[np.ndarray, Any, Any, float]:
        lt0, lo0, gm, pi = w
        z0 = np.array([P["initial_angle"], 0.0, lt0, lo0, 0.0])
        s1 = solve_ivp(rhs, (0.0, gm), z0, dense_output=dense, **_DOP853)
        zm = s1.y[:, -1]
        # lambda(gamma-) = R^T lambda+ + pi (-1, 0): lambda_theta+ = lambda_theta- + pi,
        # lambda_omega+ = -lambda_omega- / e
        zp = np.array([zm[0], -e * zm[1], zm[2] + pi, -zm[3] / e, zm[4]])
        s2 = solve_ivp(rhs, (gm, T), zp, dense_output=dense, **_DOP853)
        zT = s2.y[:, -1]
        grad_phi = [
            2 * P["weight_angle"] * (zT[0] - P["target_angle"]),
            2 * P["weight_velocity"] * (zT[1] - P["target_velocity"]),
        ]
        res = np.array([tw - zm[0], ham(zm) - ham(zp), zT[2] - grad_phi[0], zT[3] - grad_phi[1]])
        terminal = (
            P["weight_angle"] * (zT[0] - P["target_angle"]) ** 2
            + P["weight_velocity"] * (zT[1] - P["target_velocity"]) ** 2
        )
        return res, s1, s2, float(zT[4] + terminal)

    # start: lambda_omega = -u / k_u and lambda_theta = u' / k_u from the NLP's torques
    u1, u2 = torques
    d1, d2 = gamma / len(u1), (T - gamma) / len(u2)
    slope0 = np.polyfit(d1 * (np.arange(5) + 0.5), u1[:5], 1)[0]
    slope_m = np.polyfit(d1 * (np.arange(5) + 0.5), u1[-5:], 1)[0]
    slope_p = np.polyfit(d2 * (np.arange(5) + 0.5), u2[:5], 1)[0]
    w0 = np.array([slope0 / k_u, -u1[0] / k_u, gamma, (slope_p - slope_m) / k_u])
    sol = so.root(lambda w: shoot(w)[0], w0, method="hybr", options={"xtol": 1e-14})
    res, s1, s2, cost = shoot(sol.x, dense=True)
    gm = float(sol.x[2])

    def u(t: float) -> np.ndarray:
        z = s1.sol(min(t, gm)) if t <= gm else s2.sol(max(t, gm))
        return np.array([-k_u * z[3]])

    return {
        "cost": cost,
        "gamma": gm,
        "multiplier": float(sol.x[3]),
        "costate0": sol.x[:2].copy(),
        "residual": float(np.max(np.abs(res))),
        "control": u,
        "approach_speed": float(-s1.y[1, -1]),  # d psi/dt = -omega
    }


def _pendulum_optimum(name: str) -> dict[str, Any]:
    t0 = time.perf_counter()
    ocp = build(name)
    P = ocp.meta["params"]
    K = CLAIMED_EVENTS[name]
    assert K == 1
    nlp_cost, gammas, torques = pendulum_nlp(P, 1)
    ind = pendulum_indirect(P, float(gammas[0]), torques)
    alternatives = {k: pendulum_nlp(P, k, gamma0=[0.7, 0.8, 0.9][:k])[0] for k in (0, 2)}
    u_nlp, bp_nlp = _piecewise_constant(P["horizon"], gammas, torques)
    return {
        "name": name,
        "ocp": ocp,
        "cost": ind["cost"],
        "sequence": ["wall"],
        "event_times": [ind["gamma"]],
        "control_callable": ind["control"],
        "breakpoints": [ind["gamma"]],
        "alternatives": alternatives,
        "hmp": {
            "residual": ind["residual"],
            "multipliers": [ind["multiplier"]],
            "costate0": ind["costate0"],
            "approach_speeds": [ind["approach_speed"]],
        },
        "nlp": {
            "cost": nlp_cost,
            "event_times": gammas.tolist(),
            "control_callable": u_nlp,
            "breakpoints": bp_nlp,
        },
        "method": (
            "multiple-shooting NLP (own RK4, 60 intervals per phase, IPOPT) per sequence; "
            "claimed sequence polished by indirect HMP shooting (DOP853 1e-12); alternatives: "
            "NLP optima (no impact: theta <= theta_w at the nodes; two impacts: phases of at "
            "least 0.005)"
        ),
        "seconds": time.perf_counter() - t0,
    }


@functools.cache
def independent_optimum(name: str) -> dict[str, Any]:
    """The independent optimum of a configuration of :data:`CONFIGS` (cached).

    Keys: ``cost``, ``sequence`` (guard names), ``event_times``, ``control_callable``
    (``u(t) -> (nu,)``), ``breakpoints`` (pass to :func:`hybridoc.evaluate_callable`),
    ``alternatives`` (number of events -> cost: a lower bound for the double integrators,
    the NLP optimum for the pendulum), ``hmp`` (residuals, multipliers ``pi``, ``lambda(0)``,
    approach speeds), ``method``, ``ocp`` and ``seconds``.
    """
    if CONFIGS[name][0] == "pendulum_wall":
        return _pendulum_optimum(name)
    return _linear_optimum(name)


def expected_table() -> dict[str, dict[str, Any]]:
    """``{name: {"cost", "sequence", "event_times", "alternatives", "method"}}`` for every
    configuration (computed, cached)."""
    out = {}
    for name in CONFIGS:
        r = independent_optimum(name)
        out[name] = {
            "cost": r["cost"],
            "sequence": list(r["sequence"]),
            "event_times": list(r["event_times"]),
            "alternatives": dict(r["alternatives"]),
            "method": r["method"],
        }
    return out


# --------------------------------------------------------------------------------------------
# problems with modes (hybridoc.HybridOCP.from_modes): exact sequence-fixed optima
#
# hopper
#     In flight the leg force does nothing, so u = 0 there. In stance the HMP gives
#     ``u = -lambda_v / (2 eps)`` with ``lambda_y' = k lambda_v``, ``lambda_v' = -lambda_y``:
#     ``u = a cos(w tau) + b sin(w tau)``, ``w = sqrt(k)``, ``tau`` the time since touchdown.
#     For fixed event times the stance states are affine in ``(a, b)`` (the matrix
#     exponential of the oscillator driven by the harmonic ``u``, resonance included), a
#     flight between two stances of length ``d`` needs the liftoff speed ``g d / 2`` and
#     lands at ``-g d / 2``, and the guards at the event times are linear: one KKT solve
#     gives the exact value ``V(times)``, minimised over the free event times (Nelder-Mead
#     to ``1e-11``). The first touchdown is the free fall's. With the times imposed, guards
#     may be crossed between events (a relaxation): the minimum is a lower bound of the cost
#     of that sequence, which is how the alternatives are compared; the claimed optimum is
#     checked to cross no guard between its events.
# coulomb_block
#     Both modes are double integrators with a constant friction term: ``u`` is linear in
#     time on each phase; for a fixed reversal time the state is affine in the coefficients
#     and the guard ``v(gamma) = 0`` linear: one KKT solve, minimised over ``gamma``.
#     Without a reversal the block never moves left, so ``x(T) >= 0`` and ``J >= w_x
#     x_target^2`` (the defaults' target lies behind the start); two reversals: the relaxed
#     lower bound.
# two_tanks
#     Every mode is affine, ``s' = A_q s + b u + d_q``, the cost ``eps u^2`` plus a quadratic
#     of ``s(T)``: the HMP's ``u = -lambda_1 / (2 eps)`` makes state and costate one linear
#     system per mode, ``z = (s, lambda, 1)``, ``z' = M_q z``, solved by a matrix exponential
#     (:func:`small_expm`, Taylor series with scaling and squaring).
#     For fixed event times the unknowns ``(lambda(0), pi_1, ..., pi_K)`` (the costate jumps
#     ``lambda(gamma+) = lambda(gamma-) - pi grad psi``) enter every condition linearly (the
#     guards at the event times, ``lambda(T) = grad phi``): one linear solve gives the
#     minimum of the convex problem with those times imposed, its cost exactly by Van Loan's
#     integral of ``lambda_1^2`` (again an exponential). Minimised over the event times
#     (grid, Nelder-Mead), then polished to Hamiltonian continuity at every event (``root``).
#     Sequences that end apart or spilling leave ``h2(T) < p``: ``J >= w (r - p)^2``; one
#     more event (``backflow``): the relaxed lower bound (:func:`tanks_alternatives`).


#: configuration name -> (problem function, keyword arguments) of the problems with modes
MODE_CONFIGS: dict[str, tuple[str, dict[str, Any]]] = {
    "hopper": ("hopper", {}),
    "coulomb_block": ("coulomb_block", {}),
    "two_tanks": ("two_tanks", {}),
}


def build_mode_problem(name: str) -> Any:
    """The library's ``HybridOCP`` of a configuration of :data:`MODE_CONFIGS`."""
    fn, kwargs = MODE_CONFIGS[name]
    module = importlib.import_module(f"{library().__name__}.{fn}")
    return getattr(module, fn)(**kwargs)


class _Quadratic:
    """A quadratic ``p^T H p + g^T p + c`` in the coefficients ``p`` (numbers only)."""

    def __init__(self, n: int) -> None:
        self.H, self.g, self.c = np.zeros((n, n)), np.zeros(n), 0.0

    def add_square(self, weight: float, aff: np.ndarray) -> None:
        """Add ``weight (a^T p + a0)^2`` for the affine ``aff = (a, a0)``."""
        a, a0 = aff[:-1], aff[-1]
        self.H += weight * np.outer(a, a)
        self.g += 2 * weight * a0 * a
        self.c += weight * a0 * a0


def _kkt(J: _Quadratic, cons: list[np.ndarray]) -> tuple[float, np.ndarray]:
    """Minimum of ``J`` subject to the affine ``cons = 0`` (rows ``(a, a0)``), and ``p``."""
    n = J.g.size
    m = len(cons)
    A = np.array([c[:-1] for c in cons]).reshape(m, n)
    b = -np.array([c[-1] for c in cons])
    K = np.block([[2 * J.H, A.T], [A, np.zeros((m, m))]])
    p = np.linalg.solve(K, np.concatenate([-J.g, b]))[:n]
    return float(p @ J.H @ p + J.g @ p + J.c), p


def _hopper_stance_map(P: dict[str, Any], d: float) -> np.ndarray:
    """``exp(M d)`` of the stance driven by ``u = a cos(w tau) + b sin(w tau)``: the map
    from ``(y, v, 1, a, b)`` at touchdown to the same vector ``d`` later."""
    from scipy.linalg import expm

    k, l0, g = P["stiffness"], P["rest_length"], P["gravity"]
    w = math.sqrt(k)
    M = np.zeros((5, 5))
    M[0, 1] = 1.0
    M[1, 0], M[1, 2], M[1, 3] = -k, k * l0 - g, 1.0
    M[3, 4], M[4, 3] = w, -w  # (p, q): p = a cos(w tau) + b sin(w tau) = u
    return expm(M * d)


def _hopper_first_touchdown(P: dict[str, Any]) -> tuple[float, float]:
    """Time and speed of the first touchdown (free fall: u has no effect in flight)."""
    g, y0, v0, l0 = P["gravity"], P["initial_height"], P["initial_velocity"], P["rest_length"]
    t1 = (v0 + math.sqrt(v0 * v0 + 2 * g * (y0 - l0))) / g
    return t1, v0 - g * t1


def hopper_value(P: dict[str, Any], K: int, free: np.ndarray) -> tuple[float, np.ndarray]:
    """``V`` of the ``K``-event sequence (touchdown, liftoff, ...) at the event times
    ``(t1, *free)`` (``t1`` the free fall's), and the stance coefficients ``(a_j, b_j)``."""
    g, l0, eps, T = P["gravity"], P["rest_length"], P["eps"], P["horizon"]
    w = math.sqrt(P["stiffness"])
    t1, v1 = _hopper_first_touchdown(P)
    times = [t1, *map(float, free)]
    if K == 0 or any(b <= a for a, b in zip([0.0, *times], [*times, T], strict=False)):
        return math.inf, np.zeros(0)
    stances = (K + 1) // 2
    n = 2 * stances

    def const(x: float) -> np.ndarray:
        out = np.zeros(n + 1)
        out[-1] = x
        return out

    J = _Quadratic(n)
    cons: list[np.ndarray] = []
    y_s, v_s = const(l0), const(v1)
    y_end = None
    for j in range(stances):
        t_td = times[2 * j]
        t_lo = times[2 * j + 1] if 2 * j + 1 < K else T
        d = t_lo - t_td
        E = _hopper_stance_map(P, d)
        # (y, v, 1, a, b) at touchdown as affine functions of p
        ea, eb = np.zeros(n + 1), np.zeros(n + 1)
        ea[2 * j], eb[2 * j + 1] = 1.0, 1.0
        z = [y_s, v_s, const(1.0), ea, eb]
        ye = sum(E[0, i] * z[i] for i in range(5))
        ve = sum(E[1, i] * z[i] for i in range(5))
        # eps int (a cos + b sin)^2 = eps (a^2 Icc + 2 a b Ics + b^2 Iss)
        s2 = math.sin(2 * w * d) / (4 * w)
        icc, iss, ics = d / 2 + s2, d / 2 - s2, math.sin(w * d) ** 2 / (2 * w)
        J.H[2 * j, 2 * j] += eps * icc
        J.H[2 * j + 1, 2 * j + 1] += eps * iss
        J.H[2 * j, 2 * j + 1] += eps * ics
        J.H[2 * j + 1, 2 * j] += eps * ics
        if 2 * j + 1 >= K:  # stance until T
            y_end = ye
            break
        cons.append(ye - const(l0))  # liftoff
        if 2 * j + 2 < K:  # a flight of length d_f, then touchdown
            d_f = times[2 * j + 2] - t_lo
            cons.append(ve - const(g * d_f / 2))
            y_s, v_s = const(l0), const(-g * d_f / 2)
        else:  # the last flight, to T
            d_T = T - t_lo
            y_end = const(l0) + d_T * ve - const(g * d_T**2 / 2)
    assert y_end is not None
    J.add_square(1.0, y_end - const(P["target_height"]))
    return _kkt(J, cons)


def _hopper_minimum(
    P: dict[str, Any], K: int, starts: list[list[float]], xatol: float = 1e-11
) -> tuple[float, np.ndarray]:
    """``min V`` over the free event times of the ``K``-event sequence: Nelder-Mead from
    each of ``starts`` (the best one kept)."""
    if K <= 1:
        return hopper_value(P, K, np.zeros(0))[0], np.zeros(0)
    best = (math.inf, np.zeros(K - 1))
    for start in starts:
        res = so.minimize(
            lambda x: hopper_value(P, K, x)[0], start, method="Nelder-Mead",
            options={"xatol": xatol, "fatol": 1e-16, "maxfev": 20000},
        )  # fmt: skip
        if res.fun < best[0]:
            best = (float(res.fun), np.asarray(res.x))
    return best


def hopper_control(
    P: dict[str, Any], K: int, times: list[float], coeffs: np.ndarray
) -> Callable[[float], np.ndarray]:
    """``u(t)``: zero in flight, ``a_j cos(w tau) + b_j sin(w tau)`` in stance ``j``."""
    w = math.sqrt(P["stiffness"])
    T = P["horizon"]
    stances = [
        (times[2 * j], times[2 * j + 1] if 2 * j + 1 < K else T) for j in range((K + 1) // 2)
    ]

    def u(t: float) -> np.ndarray:
        for j, (a, b) in enumerate(stances):
            if a <= t < b or (t == b == T):
                tau = t - a
                return np.array(
                    [coeffs[2 * j] * math.cos(w * tau) + coeffs[2 * j + 1] * math.sin(w * tau)]
                )
        return np.array([0.0])

    return u


def hopper_trajectory(
    P: dict[str, Any], K: int, times: list[float], coeffs: np.ndarray, samples: int = 400
) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """``(mode, tau, y)`` per phase, sampled from the closed forms (for the checks)."""
    g, l0, T = P["gravity"], P["rest_length"], P["horizon"]
    t1, v1 = _hopper_first_touchdown(P)
    bounds = [0.0, *times, T]
    out = []
    tau = np.linspace(0.0, t1, samples)
    out.append(("flight", tau, P["initial_height"] + P["initial_velocity"] * tau - g * tau**2 / 2))
    y, v = l0, v1
    for k in range(1, K + 1):
        d = bounds[k + 1] - bounds[k]
        tau = np.linspace(0.0, d, samples)
        if k % 2 == 1:
            j = (k - 1) // 2
            z0 = np.array([y, v, 1.0, coeffs[2 * j], coeffs[2 * j + 1]])
            Z = np.array([_hopper_stance_map(P, x) @ z0 for x in tau])
            out.append(("stance", tau, Z[:, 0]))
            y, v = Z[-1, 0], Z[-1, 1]
        else:
            out.append(("flight", tau, y + v * tau - g * tau**2 / 2))
            y, v = y + v * d - g * d * d / 2, v - g * d
    return out


def hopper_nlp(
    P: dict[str, Any], K: int, durations: list[float], intervals: int = 40
) -> float | None:
    """The sequence-fixed optimum of ``K`` events (touchdown, liftoff, ...) by an NLP with
    the guards as path constraints, started from the given stance durations; ``None`` when
    IPOPT fails.

    Stances: ``intervals`` constant forces each, stepped exactly (the oscillator about
    ``l0 + (u - g) / k``), free durations of at least 0.005, ``y <= l0`` at the nodes, and
    a liftoff at ``y = l0`` with ``v >= 0``; a flight between two stances lasts ``2 v / g``
    (it lands where it took off, with the opposite speed: above ``l0`` in between); the last
    flight ends at ``T`` with ``y(T) >= l0``. The relaxation of the KKT method (event times
    imposed, guards free in between) gives no lower bound here: a long stance that rises
    above ``l0`` and comes back costs less than any real hop.
    """
    g, k, l0, eps, T = (P[x] for x in ("gravity", "stiffness", "rest_length", "eps", "horizon"))
    w = math.sqrt(k)
    t1, v1 = _hopper_first_touchdown(P)

    def step(y: Any, v: Any, u: Any, h: Any) -> tuple[Any, Any]:
        y_eq = l0 + (u - g) / k
        c, s = ca.cos(w * h), ca.sin(w * h)
        return y_eq + (y - y_eq) * c + v / w * s, -(y - y_eq) * w * s + v * c

    opti = ca.Opti()
    stances = (K + 1) // 2
    y, v, J, elapsed = l0, v1, 0, t1
    for j in range(stances):
        U, d = opti.variable(intervals), opti.variable()
        opti.set_initial(d, durations[j])
        opti.set_initial(U, 0.0)
        opti.subject_to(d >= 0.005)
        for i in range(intervals):
            y, v = step(y, v, U[i], d / intervals)
            J += eps * U[i] ** 2 * d / intervals
            if i < intervals - 1 or 2 * j + 1 >= K:
                opti.subject_to(y <= l0)
        elapsed = elapsed + d
        if 2 * j + 1 >= K:  # stance until T
            opti.subject_to(elapsed == T)
            break
        opti.subject_to(y == l0)
        opti.subject_to(v >= 0)
        if 2 * j + 2 < K:  # a flight, then the next touchdown
            elapsed = elapsed + 2 * v / g
            v = -v
        else:
            d_T = T - elapsed
            opti.subject_to(d_T >= 0)
            y = l0 + v * d_T - g * d_T**2 / 2
            opti.subject_to(y >= l0)
    J += (y - P["target_height"]) ** 2
    opti.minimize(J)
    ipopt = {"print_level": 0, "sb": "yes", "tol": 1e-10, "max_iter": 3000}
    opti.solver("ipopt", {"print_time": False}, ipopt)
    try:
        return float(opti.solve().value(J))
    except RuntimeError:
        return None


def hopper_alternatives(name: str = "hopper") -> dict[int, float]:
    """The other sequences' optima (1, 2, 3, 5 and 6 events): :func:`hopper_nlp` from
    short, medium and long stances, the cheapest kept."""
    P = build_mode_problem(name).meta["params"]
    out = {}
    for K in (1, 2, 3, 5, 6):
        n = (K + 1) // 2
        starts = [[0.1] * n, [0.18] * n, [0.3] * n, [0.6 / n] * n]
        costs = [c for c in (hopper_nlp(P, K, d) for d in starts) if c is not None]
        out[K] = min(costs, default=math.inf)
    return out


def _hopper_optimum(name: str) -> dict[str, Any]:
    t0 = time.perf_counter()
    ocp = build_mode_problem(name)
    P = ocp.meta["params"]
    K = 4
    cost, free = _hopper_minimum(P, K, [[0.42, 0.87, 1.05]])  # the free hopper's events
    t1, _ = _hopper_first_touchdown(P)
    times = [t1, *map(float, free)]
    _, coeffs = hopper_value(P, K, free)
    seq = ["touchdown", "liftoff"] * (K // 2)
    return {
        "name": name,
        "ocp": ocp,
        "cost": cost,
        "sequence": seq,
        "modes": ["flight", "stance", "flight", "stance", "flight"],
        "event_times": times,
        "coefficients": coeffs,
        "control_callable": hopper_control(P, K, times, coeffs),
        "breakpoints": times,
        "trajectory": hopper_trajectory(P, K, times, coeffs),
        "method": (
            "exact sequence-fixed optimum: harmonic stance controls (HMP), KKT solve at fixed "
            "event times through the matrix exponential, minimised over the event times "
            "(Nelder-Mead); alternatives: hopper_alternatives"
        ),
        "seconds": time.perf_counter() - t0,
    }


def coulomb_value(P: dict[str, Any], gammas: list[float]) -> tuple[float, np.ndarray]:
    """``V`` of the block with reversals at ``gammas`` (alternating right -> left -> ...),
    and the coefficients ``(a_k, b_k)`` of ``u = a_k + b_k (t - gamma_{k-1})``."""
    mu, T, eps = P["friction"], P["horizon"], P["eps"]
    bounds = [0.0, *gammas, T]
    if any(b <= a for a, b in zip(bounds[:-1], bounds[1:], strict=True)):
        return math.inf, np.zeros(0)
    n = 2 * (len(gammas) + 1)
    x, v = np.zeros(n + 1), np.zeros(n + 1)
    v[-1] = P["initial_velocity"]
    J = _Quadratic(n)
    cons = []
    for k in range(n // 2):
        d = bounds[k + 1] - bounds[k]
        a, b = np.zeros(n + 1), np.zeros(n + 1)
        a[2 * k], b[2 * k + 1] = 1.0, 1.0
        fr = np.zeros(n + 1)
        fr[-1] = -mu if k % 2 == 0 else mu  # right, left, right, ...
        x = x + v * d + (a + fr) * d**2 / 2 + b * d**3 / 6
        v = v + (a + fr) * d + b * d**2 / 2
        # eps int_0^d (a + b t)^2 dt
        J.H[2 * k : 2 * k + 2, 2 * k : 2 * k + 2] += eps * np.array(
            [[d, d**2 / 2], [d**2 / 2, d**3 / 3]]
        )
        if k < n // 2 - 1:
            cons.append(v.copy())
    target = np.zeros(n + 1)
    target[-1] = P["target_position"]
    J.add_square(P["weight_position"], x - target)
    J.add_square(P["weight_velocity"], v)
    return _kkt(J, cons)


def _coulomb_optimum(name: str) -> dict[str, Any]:
    t0 = time.perf_counter()
    ocp = build_mode_problem(name)
    P = ocp.meta["params"]
    T = P["horizon"]
    res = so.minimize_scalar(
        lambda g: coulomb_value(P, [g])[0], bounds=(1e-6, T - 1e-6), method="bounded",
        options={"xatol": 1e-13},
    )  # fmt: skip
    gamma = float(res.x)
    cost, coeffs = coulomb_value(P, [gamma])
    two = so.minimize(
        lambda g: coulomb_value(P, list(g))[0], [gamma, 0.5 * (gamma + T)],
        method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-14},
    )  # fmt: skip

    def u(t: float) -> np.ndarray:
        k = 0 if t < gamma else 1
        return np.array([coeffs[2 * k] + coeffs[2 * k + 1] * (t - (0.0 if k == 0 else gamma))])

    return {
        "name": name,
        "ocp": ocp,
        "cost": cost,
        "sequence": ["reverse"],
        "modes": ["right", "left"],
        "event_times": [gamma],
        "coefficients": coeffs,
        "control_callable": u,
        "breakpoints": [gamma],
        # no reversal: x never decreases, so x(T) >= 0 > x_target and J >= w_x x_target^2
        "alternatives": {0: P["weight_position"] * P["target_position"] ** 2, 2: float(two.fun)},
        "method": (
            "exact sequence-fixed optimum: KKT solve for the phase-wise linear force at a "
            "fixed reversal time, minimised over it (bounded Brent); alternatives: relaxed "
            "lower bounds, same method"
        ),
        "seconds": time.perf_counter() - t0,
    }


def small_expm(M: np.ndarray) -> np.ndarray:
    """``exp(M)`` of a small matrix: scaling and squaring of the Taylor series to rounding
    (scipy's Pade code on 5 x 5 matrices is ~100x slower when BLAS threads are oversubscribed;
    here the norms stay below ~20)."""
    s = max(0, math.ceil(math.log2(max(np.max(np.sum(np.abs(M), axis=1)), 1e-300) / 0.25)))
    A = M / 2.0**s
    out, term = np.eye(M.shape[0]), np.eye(M.shape[0])
    for k in range(1, 19):  # 0.25^19 / 19! ~ 1e-29
        term = term @ A / k
        out = out + term
    for _ in range(s):
        out = out @ out
    return out


@dataclass
class TankModel:
    """The two tanks restated by hand from their parameters: per mode ``(A, b, d)`` of
    ``s' = A s + b u + d``, per guard ``(source, target, n, offset)`` with
    ``psi = n . s + offset``."""

    P: dict[str, Any]
    modes: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = field(init=False)
    guards: dict[str, tuple[str, str, np.ndarray, float]] = field(init=False)

    def __post_init__(self) -> None:
        a, c, p = self.P["pipe_conductance"], self.P["outflow"], self.P["pipe_height"]
        b = np.array([1.0, 0.0])
        self.modes = {
            "apart": (np.array([[0.0, 0.0], [0.0, -c]]), b, np.zeros(2)),
            "spilling": (np.array([[-a, 0.0], [a, -c]]), b, np.array([a * p, -a * p])),
            "connected": (np.array([[-a, a], [a, -a - c]]), b, np.zeros(2)),
            "backflowing": (np.array([[0.0, a], [0.0, -a - c]]), b, np.array([-a * p, a * p])),
        }
        e1, e2 = np.array([1.0, 0.0]), np.array([0.0, 1.0])
        self.guards = {
            "spill": ("apart", "spilling", -e1, p),
            "spill-stops": ("spilling", "apart", e1, -p),
            "connect": ("spilling", "connected", -e2, p),
            "disconnect": ("connected", "spilling", e2, -p),
            "backflow": ("connected", "backflowing", e1, -p),
            "reconnect": ("backflowing", "connected", -e1, p),
            "backflow-stops": ("backflowing", "apart", e2, -p),
        }

    def f(self, mode: str, s: np.ndarray, u: float) -> np.ndarray:
        A, b, d = self.modes[mode]
        return A @ s + b * u + d

    def modes_along(self, seq: list[str]) -> list[str]:
        out = ["apart"]
        for g in seq:
            src, dst, _, _ = self.guards[g]
            assert src == out[-1], (seq, g)
            out.append(dst)
        return out

    def hamiltonian_matrix(self, mode: str) -> np.ndarray:
        """``M`` of ``z' = M z``, ``z = (s, lambda, 1)``, under ``u = -lambda_1 / (2 eps)``."""
        A, b, d = self.modes[mode]
        M = np.zeros((5, 5))
        M[:2, :2] = A
        M[:2, 2:4] = -np.outer(b, b) / (2 * self.P["eps"])
        M[:2, 4] = d
        M[2:4, 2:4] = -A.T
        return M


def tanks_solve(
    tm: TankModel, seq: list[str], gammas: Any
) -> tuple[float, list[np.ndarray], list[np.ndarray], np.ndarray]:
    """The minimum of the sequence-fixed problem with the event times ``gammas`` imposed.

    Returns the cost, ``z`` at the start of each phase (after the jump), ``z`` at each event
    before the jump, and the multipliers ``pi``."""
    P = tm.P
    K, T, eps = len(seq), P["horizon"], P["eps"]
    bounds = [0.0, *map(float, gammas), T]
    modes = tm.modes_along(seq)
    # z = Z @ (lambda_0 (2), pi_1..pi_K, 1): affine in the unknowns; each condition is a
    # row over the same vector that must vanish
    n = 2 + K + 1
    one = np.eye(n)[-1]
    Z = np.zeros((5, n))
    Z[:2, -1] = P["initial_levels"]
    Z[2:4, :2] = np.eye(2)
    Z[4, -1] = 1.0
    conditions, starts_Z, minus_Z = [], [], []
    for k in range(K + 1):
        starts_Z.append(Z)
        Z = small_expm(tm.hamiltonian_matrix(modes[k]) * (bounds[k + 1] - bounds[k])) @ Z
        if k < K:
            minus_Z.append(Z)
            _, _, nrm, off = tm.guards[seq[k]]
            conditions.append(nrm @ Z[:2] + off * one)  # psi(s(gamma_k-)) = 0
            Z = Z.copy()
            Z[2:4, 2 + k] -= nrm  # lambda(gamma+) = lambda(gamma-) - pi_k n
    w, r = P["weight"], P["target_level"]
    # lambda(T) = grad phi = (0, 2 w (h2(T) - r))
    conditions.append(Z[2])
    conditions.append(Z[3] - 2 * w * (Z[1] - r * one))
    C = np.array(conditions)
    x = np.append(np.linalg.solve(C[:, :-1], -C[:, -1]), 1.0)
    zs = [S @ x for S in starts_Z]
    zm = [S @ x for S in minus_Z]
    cost = w * ((Z @ x)[1] - r) ** 2
    Q = np.zeros((5, 5))
    Q[2, 2] = 1.0 / (4 * eps)  # eps u^2 = lambda_1^2 / (4 eps)
    for k in range(K + 1):
        M = tm.hamiltonian_matrix(modes[k])
        big = np.block([[-M.T, Q], [np.zeros((5, 5)), M]])
        F = small_expm(big * (bounds[k + 1] - bounds[k]))
        gram = F[5:, 5:].T @ F[:5, 5:]  # Van Loan: int_0^tau exp(M^T t) Q exp(M t) dt
        cost += zs[k] @ gram @ zs[k]
    return float(cost), zs, zm, x[2 : 2 + K]


def tanks_hamiltonian_jumps(tm: TankModel, seq: list[str], gammas: Any) -> np.ndarray:
    """``H(gamma+) - H(gamma-)`` at each event of the imposed-times optimum."""
    _, zs, zm, _ = tanks_solve(tm, seq, gammas)
    modes, eps = tm.modes_along(seq), tm.P["eps"]

    def ham(mode: str, z: np.ndarray) -> float:
        u = -z[2] / (2 * eps)
        return eps * u * u + z[2:4] @ tm.f(mode, z[:2], u)

    return np.array([ham(modes[k + 1], zs[k + 1]) - ham(modes[k], zm[k]) for k in range(len(seq))])


def tanks_state(
    tm: TankModel, seq: list[str], gammas: list[float], zs: list[np.ndarray], t: float
) -> tuple[str, np.ndarray]:
    """The mode and ``z = (s, lambda, 1)`` at time ``t`` of an imposed-times optimum."""
    bounds = [0.0, *gammas, tm.P["horizon"]]
    k = int(np.clip(np.searchsorted(bounds, t, side="right") - 1, 0, len(seq)))
    mode = tm.modes_along(seq)[k]
    return mode, small_expm(tm.hamiltonian_matrix(mode) * (t - bounds[k])) @ zs[k]


def _tanks_minimum(
    tm: TankModel, seq: list[str], grid: int = 12, xatol: float = 1e-6
) -> tuple[float, np.ndarray]:
    """``min V`` over ordered event times: the best of a grid, Nelder-Mead from it."""
    T = tm.P["horizon"]
    pts = np.linspace(0.0, T, grid + 2)[1:-1]

    def value(g: np.ndarray) -> float:
        if np.any(np.diff(np.concatenate([[0.0], g, [T]])) <= 1e-6):
            return math.inf
        try:
            return tanks_solve(tm, seq, g)[0]
        except np.linalg.LinAlgError:
            return math.inf

    start = min(itertools.combinations(pts, len(seq)), key=lambda g: value(np.array(g)))
    res = so.minimize(
        value, np.array(start), method="Nelder-Mead",
        options={"xatol": xatol, "fatol": 1e-13, "maxfev": 1000},
    )  # fmt: skip
    return float(res.fun), np.asarray(res.x)


def _tanks_optimum(name: str) -> dict[str, Any]:
    t0 = time.perf_counter()
    ocp = build_mode_problem(name)
    tm = TankModel(ocp.meta["params"])
    P = tm.P
    seq = ["spill", "connect"]
    v_nm, g_nm = _tanks_minimum(tm, seq)
    sol = so.root(lambda g: tanks_hamiltonian_jumps(tm, seq, g), g_nm, options={"xtol": 1e-15})
    gammas = [float(g) for g in sol.x]
    cost, zs, zm, pis = tanks_solve(tm, seq, gammas)
    eps = P["eps"]

    def u(t: float) -> np.ndarray:
        return np.array([-tanks_state(tm, seq, gammas, zs, t)[1][2] / (2 * eps)])

    bound = P["weight"] * (P["target_level"] - P["pipe_height"]) ** 2
    return {
        "name": name,
        "ocp": ocp,
        "model": tm,
        "cost": cost,
        "sequence": seq,
        "modes": tm.modes_along(seq),
        "event_times": gammas,
        "control_callable": u,
        "breakpoints": gammas,
        "phase_starts": zs,
        # what ends apart or spilling has h2(T) < p <= r; more: tanks_alternatives
        "alternatives": {"ends below the pipe (any number of events)": bound},
        "hmp": {
            "hamiltonian_jumps": tanks_hamiltonian_jumps(tm, seq, gammas),
            "multipliers": pis,
            "costate0": zs[0][2:4],
            "nelder_mead": (v_nm, g_nm),
        },
        "method": (
            "exact sequence-fixed optimum: the linear state-costate system per mode by expm, "
            "one linear solve for the costate and jump multipliers at fixed event times, "
            "Van Loan's integral for the cost; minimised over the event times (grid, "
            "Nelder-Mead), polished to Hamiltonian continuity (root)"
        ),
        "seconds": time.perf_counter() - t0,
    }


def tanks_alternatives(name: str = "two_tanks") -> dict[str, float]:
    """The relaxed lower bound of one more event after the optimum's (``backflow``: tank 1
    drains below the pipe while tank 2 is above it), minimised over its event times."""
    tm = TankModel(build_mode_problem(name).meta["params"])
    seq = ["spill", "connect", "backflow"]
    return {", ".join(seq): _tanks_minimum(tm, seq, grid=10, xatol=1e-6)[0]}


@functools.cache
def mode_optimum(name: str) -> dict[str, Any]:
    """The independent optimum of a configuration of :data:`MODE_CONFIGS` (cached); keys as
    :func:`independent_optimum`'s, with ``"modes"`` (the modes visited)."""
    fn = MODE_CONFIGS[name][0]
    if fn == "hopper":
        return _hopper_optimum(name)
    if fn == "two_tanks":
        return _tanks_optimum(name)
    return _coulomb_optimum(name)
