"""An independent optimum of a disc scene for a *fixed* event sequence (no hybridoc code).

It reads the scene's TOML file itself (:mod:`tomllib`, the rules of ``docs/scenes.rst``) and
uses numpy, scipy and casadi only; it imports nothing from :mod:`hybridoc`.

Why the NLP below is exact
--------------------------
Between events every disc is a double integrator (``p' = v``, ``m v' = u`` for an actuated
disc, ``v' = 0`` otherwise) and the running cost ``eps |u|^2`` depends on the control only.
The costate therefore satisfies ``lambda_p' = 0`` and ``lambda_v' = -lambda_p`` on every phase,
so the minimum principle's control ``u = -lambda_v / (2 eps m)`` is *affine in time on every
phase*. Parameterising each actuated disc's force on phase ``k`` as ``u = a_k + b_k tau``
(``tau`` the time since the phase began) and the phase durations ``d_k`` (summing to ``T``)
as unknowns therefore contains the sequence-fixed optimum, and every quantity is closed
form: positions are cubic in ``tau``, ``int |u|^2 = |a|^2 d + a.b d^2 + |b|^2 d^3 / 3``. No
time grid, no integrator: the NLP's optimum is the continuous-time optimum of the sequence
(not of the grid of piecewise-constant controls).

The NLP (CasADi SX + IPOPT at tol 1e-13) imposes, at the end of phase ``k < K``, the named
guard's gap ``= 0`` and its approach speed ``<= 0``, then applies the frictionless impulse
with restitution ``e`` and the masses (``docs/scenes.rst``); it minimises the scene's cost
``sum |p_i(T) - target_i|^2 + eps int |u|^2``. A few sampled gaps per phase are kept
``>= 0`` only to steer IPOPT away from controls that pass through a body; the result is then
*checked a posteriori* in numpy (:func:`check`): on every phase, every guard's gap is minimised
(dense sampling, then a bounded scalar minimisation around each sampled minimum) and must
stay positive inside the phase, the named guard must reach zero only at the phase's end
(transversally: approach speed below ``-1e-6``) and no other guard may touch at an event.
A result that fails the check is not a control with that sequence and is discarded.

:func:`solve_sequence` runs IPOPT from a starting guess (event times and, optionally,
controls on a grid) and from ``starts - 1`` perturbed or random guesses, and returns the best
checked result. :func:`grid_controls` averages the affine controls over a uniform grid, to
replay the optimum in the independent simulator ``tests/oracle.py``.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np
import scipy.optimize as so

__all__ = [
    "FrictionResult",
    "NLPResult",
    "check_friction",
    "friction_optimum",
    "friction_state",
    "check",
    "grid_controls",
    "guard_names",
    "load_scene",
    "oracle_dict",
    "solve_sequence",
]


# ------------------------------------------------------------------------------- scene data
@dataclass
class Scene:
    horizon: float
    steps: int
    eps: float
    e: float
    names: list[str]
    radius: np.ndarray
    mass: np.ndarray
    pos0: np.ndarray  # (n, 2)
    vel0: np.ndarray  # (n, 2)
    actuated: list[int]  # disc indices in scene order
    targets: list[tuple[int, np.ndarray]]
    wall_names: list[str]
    wall_point: np.ndarray  # (m, 2)
    wall_normal: np.ndarray  # (m, 2), unit
    initial_control: np.ndarray  # (steps, 2 * n_actuated)
    guards: list[tuple[str, int, int, str]] = field(default_factory=list)  # kind, i, j, name


def load_scene(path: str | Path) -> Scene:
    """The scene of a TOML file, with the defaults of ``docs/scenes.rst``."""
    path = Path(path)
    with path.open("rb") as fh:
        raw = tomllib.load(fh)
    steps = int(raw.get("steps", 480))
    discs = raw["discs"]
    names = [str(d["name"]) for d in discs]
    actuated = [i for i, d in enumerate(discs) if d.get("actuated", False)]
    targets = [(i, np.array(d["target"], float)) for i, d in enumerate(discs) if "target" in d]
    walls = raw.get("walls", [])
    wall_names = [str(w.get("name", f"wall{k}")) for k, w in enumerate(walls)]
    normals = np.array([w["normal"] for w in walls], float).reshape(-1, 2)
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True) if len(walls) else normals
    cols = []
    for i in actuated:
        ic = np.array(discs[i].get("initial_control", [0.0, 0.0]), float)
        cols.append(np.tile(ic, (steps, 1)) if ic.ndim == 1 else ic)
    sc = Scene(
        horizon=float(raw["horizon"]),
        steps=steps,
        eps=float(raw.get("control_weight", 0.01)),
        e=float(raw.get("restitution", 1.0)),
        names=names,
        radius=np.array([float(d["radius"]) for d in discs]),
        mass=np.array([float(d.get("mass", 1.0)) for d in discs]),
        pos0=np.array([d["position"] for d in discs], float),
        vel0=np.array([d.get("velocity", [0.0, 0.0]) for d in discs], float),
        actuated=actuated,
        targets=targets,
        wall_names=wall_names,
        wall_point=np.array([w["point"] for w in walls], float).reshape(-1, 2),
        wall_normal=normals,
        initial_control=np.hstack(cols) if cols else np.zeros((steps, 0)),
    )
    n = len(names)
    sc.guards = [
        ("pair", i, j, f"{names[i]}|{names[j]}") for i in range(n) for j in range(i + 1, n)
    ]
    sc.guards += [
        ("wall", i, w, f"{names[i]}|{wall_names[w]}") for i in range(n) for w in range(len(walls))
    ]
    return sc


def guard_names(sc: Scene) -> list[str]:
    return [g[3] for g in sc.guards]


def oracle_dict(sc: Scene, steps: int) -> dict[str, Any]:
    """The plain-data scene that ``tests/oracle.py`` takes, on a grid of ``steps`` intervals."""
    act = set(sc.actuated)
    tgt = dict(sc.targets)
    return {
        "horizon": sc.horizon,
        "steps": steps,
        "control_weight": sc.eps,
        "restitution": sc.e,
        "discs": [
            {
                "name": sc.names[i],
                "position": sc.pos0[i].tolist(),
                "velocity": sc.vel0[i].tolist(),
                "radius": float(sc.radius[i]),
                "mass": float(sc.mass[i]),
                "actuated": i in act,
                "target": None if i not in tgt else tgt[i].tolist(),
            }
            for i in range(len(sc.names))
        ],
        "walls": [
            {
                "name": sc.wall_names[k],
                "point": sc.wall_point[k].tolist(),
                "normal": sc.wall_normal[k].tolist(),
            }
            for k in range(len(sc.wall_names))
        ],  # fmt: skip
    }


# ------------------------------------------------------------------------ the physics (generic)
# Written once over an array namespace so that CasADi (symbolic) and numpy (the check) share
# the formulas of this file, and nothing else.
def _norm(x: Any, sym: bool) -> Any:
    return ca.sqrt(x[0] ** 2 + x[1] ** 2) if sym else math.hypot(float(x[0]), float(x[1]))


def _gap(sc: Scene, g: tuple[str, int, int, str], P: list, sym: bool) -> Any:
    kind, i, j, _ = g
    if kind == "pair":
        return _norm(P[i] - P[j], sym) - (sc.radius[i] + sc.radius[j])
    n = sc.wall_normal[j]
    d = P[i] - (ca.DM(sc.wall_point[j]) if sym else sc.wall_point[j])
    return d[0] * n[0] + d[1] * n[1] - sc.radius[i]


def _approach_and_reset(sc: Scene, g: tuple[str, int, int, str], P: list, V: list, sym: bool):
    """(approach speed w, new velocity list) of the impulse at guard ``g``."""
    kind, i, j, _ = g
    V = list(V)
    if kind == "pair":
        r = P[i] - P[j]
        n = r / _norm(r, sym)
        w = (V[i][0] - V[j][0]) * n[0] + (V[i][1] - V[j][1]) * n[1]
        J = -(1.0 + sc.e) * w / (1.0 / sc.mass[i] + 1.0 / sc.mass[j])
        V[i] = V[i] + (J / sc.mass[i]) * n
        V[j] = V[j] - (J / sc.mass[j]) * n
        return w, V
    n = sc.wall_normal[j]
    w = V[i][0] * n[0] + V[i][1] * n[1]
    V[i] = V[i] - ((1.0 + sc.e) * w) * (n if not sym else ca.DM(n))
    return w, V


def _flow(sc: Scene, P: list, V: list, A: list, B: list, tau: Any) -> tuple[list, list]:
    """Positions and velocities after ``tau`` under the forces ``a + b tau`` (A, B per disc)."""
    P2, V2 = [], []
    for i in range(len(P)):
        if A[i] is None:
            P2.append(P[i] + V[i] * tau)
            V2.append(V[i])
        else:
            m = sc.mass[i]
            P2.append(P[i] + V[i] * tau + (A[i] * (tau**2 / 2) + B[i] * (tau**3 / 6)) / m)
            V2.append(V[i] + (A[i] * tau + B[i] * (tau**2 / 2)) / m)
    return P2, V2


def _per_disc(sc: Scene, a: Any, b: Any) -> tuple[list, list]:
    A: list = [None] * len(sc.names)
    B: list = [None] * len(sc.names)
    for k, i in enumerate(sc.actuated):
        A[i] = a[2 * k : 2 * k + 2]
        B[i] = b[2 * k : 2 * k + 2]
    return A, B


# ------------------------------------------------------------------------------ the NLP
@dataclass
class NLPResult:
    """A checked sequence-fixed extremal (``valid``) or the reason it is not one."""

    sequence: list[str]
    cost: float
    terminal: float
    running: float
    durations: np.ndarray  # (K + 1,)
    a: np.ndarray  # (K + 1, nu): force at the start of each phase
    b: np.ndarray  # (K + 1, nu): its slope
    valid: bool
    reason: str = ""
    min_gap: float = math.inf  # smallest gap inside phases, over all guards
    approach_speeds: list[float] = field(default_factory=list)
    ipopt_status: str = ""
    starts_valid: int = 0

    @property
    def event_times(self) -> np.ndarray:
        return np.cumsum(self.durations)[:-1]

    def control(self, t: float) -> np.ndarray:
        edges = np.concatenate([[0.0], np.cumsum(self.durations)])
        k = min(int(np.searchsorted(edges, t, side="right")) - 1, len(self.durations) - 1)
        return self.a[k] + self.b[k] * (t - edges[k])


_SAMPLES = 6  # sampled interior gaps per phase and guard kept >= 0 (steering only)


class _Problem:
    def __init__(self, sc: Scene, sequence: list[str]) -> None:
        names = guard_names(sc)
        unknown = [s for s in sequence if s not in names]
        if unknown:
            raise ValueError(f"unknown guards {unknown}; the scene's guards are {names}")
        self.sc, self.seq = sc, list(sequence)
        self.ev = [sc.guards[names.index(s)] for s in sequence]
        K, nu = len(sequence), 2 * len(sc.actuated)
        self.K, self.nu = K, nu
        d = ca.SX.sym("d", K + 1)
        a = ca.SX.sym("a", K + 1, nu)
        b = ca.SX.sym("b", K + 1, nu)
        x = ca.vertcat(d, ca.vec(a), ca.vec(b))
        P = [ca.DM(p) for p in sc.pos0]
        V = [ca.DM(v) for v in sc.vel0]
        g, lbg, ubg = [ca.sum1(d) - sc.horizon], [0.0], [0.0]
        running = 0
        for k in range(K + 1):
            ak, bk, dk = a[k, :].T, b[k, :].T, d[k]
            A, B = _per_disc(sc, ak, bk)
            running += ca.sumsqr(ak) * dk + ca.dot(ak, bk) * dk**2 + ca.sumsqr(bk) * dk**3 / 3
            for s in range(1, _SAMPLES + 1):
                Ps, _ = _flow(sc, P, V, A, B, dk * s / (_SAMPLES + 1))
                for gd in sc.guards:
                    g.append(_gap(sc, gd, Ps, True))
                    lbg.append(0.0)
                    ubg.append(ca.inf)
            P, V = _flow(sc, P, V, A, B, dk)
            if k < K:
                g.append(_gap(sc, self.ev[k], P, True))
                lbg.append(0.0)
                ubg.append(0.0)
                w, V = _approach_and_reset(sc, self.ev[k], P, V, True)
                g.append(w)
                lbg.append(-ca.inf)
                ubg.append(0.0)
        terminal = 0
        for i, target in sc.targets:
            terminal += ca.sumsqr(P[i] - ca.DM(target))
        f = terminal + sc.eps * running
        self.f_parts = ca.Function("parts", [x], [terminal, running])
        self.solver = ca.nlpsol(
            "seqnlp",
            "ipopt",
            {"x": x, "f": f, "g": ca.vertcat(*g)},
            {
                "ipopt.print_level": 0,
                "print_time": False,
                "ipopt.tol": 1e-13,
                "ipopt.acceptable_tol": 1e-10,
                "ipopt.max_iter": 600,
                "ipopt.sb": "yes",
            },
        )
        self.lbg, self.ubg = lbg, ubg
        self.lbx = np.concatenate([np.zeros(K + 1), -np.inf * np.ones(2 * (K + 1) * nu)])

    def pack(self, d: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.concatenate([d, a.reshape(-1, order="F"), b.reshape(-1, order="F")])

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        K1, nu = self.K + 1, self.nu
        d = x[:K1]
        a = x[K1 : K1 + K1 * nu].reshape((K1, nu), order="F")
        b = x[K1 + K1 * nu :].reshape((K1, nu), order="F")
        return d, a, b

    def solve(self, x0: np.ndarray) -> NLPResult:
        out = self.solver(x0=x0, lbx=self.lbx, lbg=self.lbg, ubg=self.ubg)
        stats = self.solver.stats()
        x = np.array(out["x"]).ravel()
        d, a, b = self.unpack(x)
        terminal, running = (float(v) for v in self.f_parts(x))
        res = NLPResult(
            sequence=self.seq,
            cost=terminal + self.sc.eps * running,
            terminal=terminal,
            running=self.sc.eps * running,
            durations=d,
            a=a,
            b=b,
            valid=False,
            ipopt_status=str(stats["return_status"]),
        )
        if not stats["success"]:
            res.reason = f"IPOPT: {stats['return_status']}"
            return res
        return check(self.sc, res)


# ------------------------------------------------------------------------------ the check
def _state_at(sc: Scene, res: NLPResult, k: int) -> tuple[list, list]:
    """Positions and velocities at the start of phase ``k`` (after the reset of event k - 1)."""
    P = [p.copy() for p in sc.pos0]
    V = [v.copy() for v in sc.vel0]
    names = guard_names(sc)
    for j in range(k):
        A, B = _per_disc(sc, res.a[j], res.b[j])
        P, V = _flow(sc, P, V, A, B, res.durations[j])
        _, V = _approach_and_reset(sc, sc.guards[names.index(res.sequence[j])], P, V, False)
    return P, V


def check(sc: Scene, res: NLPResult, *, samples: int = 2000, tol: float = 1e-9) -> NLPResult:
    """Replay ``res`` exactly in numpy; ``res.valid`` when its events are exactly its sequence."""
    names = guard_names(sc)
    P = [p.copy() for p in sc.pos0]
    V = [v.copy() for v in sc.vel0]
    min_gap, speeds = math.inf, []
    K = len(res.sequence)
    for k in range(K + 1):
        dk = float(res.durations[k])
        A, B = _per_disc(sc, res.a[k], res.b[k])
        if dk > 0:
            taus = np.linspace(0.0, dk, samples + 1)[1:-1]
            for gd in sc.guards:

                def gap(
                    t: float, gd: tuple = gd, P: list = P, V: list = V, A: list = A, B: list = B
                ) -> float:
                    return float(_gap(sc, gd, _flow(sc, P, V, A, B, t)[0], False))

                vals = np.array([gap(t) for t in taus])
                j = int(np.argmin(vals))
                lo, hi = taus[max(j - 1, 0)], taus[min(j + 1, len(taus) - 1)]
                best = min(vals[j], so.minimize_scalar(gap, bounds=(lo, hi), method="bounded",
                                                       options={"xatol": 1e-14}).fun)  # fmt: skip
                min_gap = min(min_gap, best)
                if best <= tol:
                    res.reason = f"phase {k}: {gd[3]} touches inside the phase (gap {best:.3g})"
                    res.min_gap = min_gap
                    return res
        P, V = _flow(sc, P, V, A, B, dk)
        if k == K:
            break
        gd = sc.guards[names.index(res.sequence[k])]
        for other in sc.guards:
            if other is not gd and abs(float(_gap(sc, other, P, False))) <= 1e-7:
                res.reason = f"event {k}: {other[3]} touches at the same time as {gd[3]}"
                return res
        if abs(float(_gap(sc, gd, P, False))) > 1e-9:
            res.reason = f"event {k}: {gd[3]} gap {float(_gap(sc, gd, P, False)):.3g} at the event"
            return res
        w, V = _approach_and_reset(sc, gd, P, V, False)
        speeds.append(float(w))
        if w > -1e-6:
            res.reason = f"event {k}: {gd[3]} not transversal (approach speed {w:.3g})"
            return res
    res.min_gap, res.approach_speeds, res.valid, res.reason = min_gap, speeds, True, ""
    return res


# ---------------------------------------------------------------------------- starting guesses
def _fit(sc: Scene, durations: np.ndarray, controls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per phase, the least-squares affine fit of grid controls (rows = grid intervals)."""
    N = controls.shape[0]
    mids = (np.arange(N) + 0.5) * sc.horizon / N
    edges = np.concatenate([[0.0], np.cumsum(durations)])
    K1, nu = len(durations), controls.shape[1]
    a, b = np.zeros((K1, nu)), np.zeros((K1, nu))
    for k in range(K1):
        inside = (mids >= edges[k]) & (mids < edges[k + 1])
        if inside.sum() >= 2:
            M = np.column_stack([np.ones(inside.sum()), mids[inside] - edges[k]])
            coef = np.linalg.lstsq(M, controls[inside], rcond=None)[0]
            a[k], b[k] = coef[0], coef[1]
        else:
            j = min(int(np.searchsorted(mids, 0.5 * (edges[k] + edges[k + 1]))), N - 1)
            a[k] = controls[j]
    return a, b


def solve_sequence(
    sc: Scene | str | Path,
    sequence: list[str],
    times: list[float] | None = None,
    controls: np.ndarray | None = None,
    *,
    starts: int = 8,
    seed: int = 0,
) -> NLPResult:
    """The best checked extremal of ``sequence`` from the guess and ``starts - 1`` others.

    ``times``: a guess of the event times (evenly spread if ``None``); ``controls``: a guess on
    a uniform grid, one row per interval (the scene's initial guess if ``None``). Returns an
    invalid :class:`NLPResult` (``valid`` False, ``cost`` inf) if no start gave a checked one.
    """
    if not isinstance(sc, Scene):
        sc = load_scene(sc)
    prob = _Problem(sc, sequence)
    K, T = len(sequence), sc.horizon
    rng = np.random.default_rng(seed)
    U = sc.initial_control if controls is None else np.asarray(controls, float)
    guesses = []
    if times is None:
        t0 = np.linspace(0.0, T, K + 2)[1:-1]
    else:
        t0 = np.asarray(times, float)
    d0 = np.diff(np.concatenate([[0.0], t0, [T]]))
    guesses.append((d0, *_fit(sc, d0, U)))
    scale = max(1.0, float(np.abs(U).max()) if U.size else 1.0)
    while len(guesses) < starts:
        r = len(guesses)
        if r % 2 == 1:  # perturbed guess
            t = np.sort(np.clip(t0 + rng.normal(0, 0.05 * T, K), 0.01 * T, 0.99 * T))
            d = np.diff(np.concatenate([[0.0], t, [T]]))
            a, b = _fit(sc, d, U)
            a = a + rng.normal(0, 0.3 * scale, a.shape)
        else:  # random guess
            t = np.sort(rng.uniform(0.05 * T, 0.95 * T, K))
            d = np.diff(np.concatenate([[0.0], t, [T]]))
            a = rng.normal(0, 2 * scale, (K + 1, prob.nu))
            b = np.zeros_like(a)
        guesses.append((d, a, b))
    best: NLPResult | None = None
    n_valid = 0
    for d, a, b in guesses:
        res = prob.solve(prob.pack(d, a, b))
        if res.valid:
            n_valid += 1
            if best is None or not best.valid or res.cost < best.cost:
                best = res
        elif best is None:
            best = res
    assert best is not None
    best.starts_valid = n_valid
    if not best.valid:
        best.cost = math.inf
    return best


def grid_controls(sc: Scene, res: NLPResult, steps: int) -> np.ndarray:
    """The exact averages of ``res``'s affine controls over ``steps`` uniform intervals."""
    edges = np.concatenate([[0.0], np.cumsum(res.durations)])
    edges[-1] = sc.horizon
    grid = np.linspace(0.0, sc.horizon, steps + 1)
    out = np.zeros((steps, res.a.shape[1]))
    for n in range(steps):
        lo, hi = grid[n], grid[n + 1]
        for k in range(len(res.durations)):
            s, e = max(lo, edges[k]), min(hi, edges[k + 1])
            if e > s:  # int_s^e a + b (t - t_k) dt
                s0, e0 = s - edges[k], e - edges[k]
                out[n] += res.a[k] * (e0 - s0) + res.b[k] * (e0**2 - s0**2) / 2
        out[n] /= hi - lo
    return out


# --------------------------------------------------------------------------------------------
# friction patch (issue #15): a block x' = v, v' = u - c v whose friction c changes at x = 0
#
# The sequence-fixed optimum, from issue #15's specification alone. With the running cost
# u^2 (or 1 + u^2) the minimum principle gives u = -lambda_v / 2, lambda_x' = 0 and
# lambda_v' = c lambda_v - lambda_x on each phase, so the optimal force on a phase of friction
# c is exactly ``a + b exp(c tau)`` (``tau`` the time since the phase began). Under that force
# the phase's flow is closed form (below), and the NLP over (a_k, b_k, d_k) per phase, with
# the switching condition x = 0 (crossed in the right direction) at each phase end and the
# terminal equalities x(T) = x_target, v(T) = 0, contains the sequence-fixed continuous
# optimum: a multiple-shooting NLP whose shooting intervals are the phases, with exact flows
# (no grid, no integrator). The result is checked a posteriori (:func:`check_friction`): every
# phase stays on its side of x = 0 between its ends.


@dataclass
class FrictionResult:
    """The sequence-fixed optimum of the friction patch."""

    cost: float
    horizon: float
    durations: np.ndarray  # per phase
    a: np.ndarray
    b: np.ndarray
    frictions: list[float]
    final_state: np.ndarray
    status: str


def _friction_phase(c: float, x0: Any, v0: Any, a: Any, b: Any, tau: Any, sym: bool) -> tuple:
    """``(x, v, integral u^2)`` after ``tau`` under ``u = a + b exp(c tau)``."""
    exp = ca.exp if sym else np.exp
    em, ep = exp(-c * tau), exp(c * tau)
    v = v0 * em + (a / c) * (1 - em) + b * (ep - em) / (2 * c)
    x = x0 + v0 * (1 - em) / c + (a / c) * (tau - (1 - em) / c) + b * (ep + em - 2) / (2 * c**2)
    usq = a**2 * tau + 2 * a * b * (ep - 1) / c + b**2 * (ep**2 - 1) / (2 * c)
    return x, v, usq


def friction_optimum(
    frictions: list[float],
    *,
    x0: float = -1.0,
    x_target: float = 1.0,
    horizon: float | None = 2.0,
    horizon_bounds: tuple[float, float] | None = None,
    time_cost: float = 0.0,
    starts: int = 6,
) -> FrictionResult:
    """The optimum for the phases of the given frictions, in order (the first is the
    initial floor's; consecutive phases switch at ``x = 0``).

    ``horizon`` fixes ``T``; ``horizon_bounds`` frees it (``horizon=None``). The running cost is
    ``time_cost + u^2``. IPOPT (tol 1e-14) from ``starts`` guesses; the best result that
    :func:`check_friction` accepts is returned.
    """
    P = len(frictions)
    w = ca.SX.sym("w", 3 * P)
    a, b, d = w[0:P], w[P : 2 * P], w[2 * P : 3 * P]
    x, v, J = x0, 0.0, 0.0
    g, lbg, ubg = [], [], []
    for k, c in enumerate(frictions):
        x, v, usq = _friction_phase(c, x, v, a[k], b[k], d[k], True)
        J = J + usq + time_cost * d[k]
        if k < P - 1:
            g += [x, v]  # at the switch: on the boundary, crossing towards the next floor
            sign = 1.0 if frictions[k] == frictions[0] else -1.0
            lbg += [0.0, 0.0 if sign > 0 else -np.inf]
            ubg += [0.0, np.inf if sign > 0 else 0.0]
    g += [x - x_target, v, ca.sum1(d)]
    lo, hi = (horizon, horizon) if horizon_bounds is None else horizon_bounds
    lbg += [0.0, 0.0, lo]
    ubg += [0.0, 0.0, hi]
    solver = ca.nlpsol(
        "friction",
        "ipopt",
        {"x": w, "f": J, "g": ca.vertcat(*g)},
        {"ipopt.tol": 1e-14, "ipopt.print_level": 0, "print_time": False, "ipopt.max_iter": 3000},
    )
    lbx = np.r_[np.full(2 * P, -np.inf), np.full(P, 1e-3)]
    ubx = np.r_[np.full(2 * P, np.inf), np.full(P, hi)]
    rng = np.random.default_rng(7)
    best: FrictionResult | None = None
    T0 = 0.5 * (lo + hi) if horizon_bounds is not None else lo
    for i in range(starts):
        d0 = np.full(P, T0 / P) if i == 0 else rng.dirichlet(np.ones(P)) * T0
        w0 = np.r_[np.full(P, 1.0) if i == 0 else rng.normal(size=P), np.zeros(P), d0]
        res = solver(x0=w0, lbx=lbx, ubx=ubx, lbg=lbg, ubg=ubg)
        if not solver.stats()["success"]:
            continue
        sol = np.asarray(res["x"]).ravel()
        r = FrictionResult(
            cost=float(res["f"]),
            horizon=float(sol[2 * P :].sum()),
            durations=sol[2 * P :],
            a=sol[:P],
            b=sol[P : 2 * P],
            frictions=list(frictions),
            final_state=np.zeros(2),
            status=solver.stats()["return_status"],
        )
        if check_friction(r, x0=x0) and (best is None or r.cost < best.cost):
            best = r
    if best is None:
        raise RuntimeError(f"no checked optimum for the frictions {frictions}")
    return best


def friction_state(r: FrictionResult, t: np.ndarray, *, x0: float = -1.0) -> np.ndarray:
    """``(x, v, u)`` of the optimum at the times ``t`` (columns)."""
    t = np.atleast_1d(np.asarray(t, dtype=float))
    out = np.zeros((t.size, 3))
    starts = np.r_[0.0, np.cumsum(r.durations)]
    x, v = x0, 0.0
    for k, c in enumerate(r.frictions):
        last = k == len(r.frictions) - 1
        sel = (t >= starts[k]) & ((t < starts[k + 1]) | last)
        tau = t[sel] - starts[k]
        xs, vs, _ = _friction_phase(c, x, v, r.a[k], r.b[k], tau, False)
        out[sel] = np.c_[xs, vs, r.a[k] + r.b[k] * np.exp(c * tau)]
        x, v, _ = _friction_phase(c, x, v, r.a[k], r.b[k], r.durations[k], False)
    r.final_state = np.array([x, v])
    return out


def check_friction(r: FrictionResult, *, x0: float = -1.0, samples: int = 4000) -> bool:
    """Whether each phase stays strictly on its floor's side of ``x = 0`` inside it."""
    side = -1.0  # the first floor is x < 0
    x, v = x0, 0.0
    for k, c in enumerate(r.frictions):
        tau = np.linspace(0.0, r.durations[k], samples)[1:-1]
        xs, _, _ = _friction_phase(c, x, v, r.a[k], r.b[k], tau, False)
        if np.any(side * xs <= 0):
            return False
        x, v, _ = _friction_phase(c, x, v, r.a[k], r.b[k], r.durations[k], False)
        side = -side
    return True
