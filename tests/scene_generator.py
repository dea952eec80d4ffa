"""Random disc scenes with independently computed optima (issue #29), no hybridoc code.

Two halves, both numpy/scipy and the standard library only (nothing here imports
:mod:`hybridoc`, :mod:`problems` or CasADi; ``tests/test_scene_generator.py`` checks it):

The generator
    :func:`generate` draws a seeded, deterministic scene of one of the :data:`FAMILIES`:
    chains (A strikes B strikes C ...), bank shots (off a side wall, possibly slanted),
    dodges (reach a target past a guard disc), breaks (a rack of up to four discs),
    intercepts (strike a moving disc), inelastic pairs and scenes whose optimum has no
    contact. One actuated disc ``a`` carries a force ``u``; the cost is
    ``eps int |u|^2 + sum |p_i(T) - target_i|^2`` (``docs/scenes.rst``); restitution 0.3 to 1,
    horizons 0.5 to 5 s, up to 5 discs. :meth:`GenScene.to_toml` writes hybridoc's scene
    format.

The independent optimum
    Between events every disc is a double integrator and the running cost depends on ``u``
    only, so the costate of the actuated disc's velocity is affine in time between the
    events that involve that disc (an event between two other bodies leaves its costate
    continuous), and so is the minimum principle's control ``u = -lambda_v / (2 eps m)``.
    :func:`simulate` therefore takes an *event-triggered piecewise-affine* control: phase
    ``k`` starts at the actuated disc's ``k``-th event and applies ``a_k + b_k tau`` (``tau``
    the time since the phase began). For a fixed event sequence this family contains the
    exact continuous-time optimum, and the cost is a smooth function of ``(a_k, b_k)`` (the
    events move with the control). The simulator is event-driven and exact: positions are
    cubic in time, a wall's gap is a cubic and a pair's squared distance a sextic, whose first
    crossing is a polynomial root polished by Newton's method.

    The cost is a sum of squares (targets, and the control's integral by two-point
    Gauss-Legendre, exact for the square of an affine function), so each start is a
    Levenberg-Marquardt solve (:func:`scipy.optimize.least_squares`). :func:`optimum` runs it
    from many starts (no force, the scene's plan, strikes aimed at every disc and wall at
    several times and angles, random forces) and returns the best, its event sequence and how
    many starts reached it.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.optimize as so

__all__ = [
    "FAMILIES",
    "GenDisc",
    "GenScene",
    "Optimum",
    "SimResult",
    "Wall",
    "generate",
    "generate_many",
    "optimum",
    "scene_from_dict",
    "simulate",
]

FAMILIES = ("chain", "bank", "dodge", "break", "intercept", "inelastic", "no-contact")
"""The families :func:`generate` draws from, in the order of ``index % len(FAMILIES)``."""

MAX_EVENTS = 24
"""More events than this in one simulation (a disc pushed into another with ``e < 1``
chatters) make the control invalid for the optimiser (its cost is returned as infinite)."""

ACCEPT_EVENTS = 6
""":func:`accepted` redraws a scene where a control with more events than this was found
cheaper than the optimum's (:attr:`Optimum.long_best`): there a longer push (chattering
contacts, beyond :data:`MAX_EVENTS`) may well be cheaper still, so the optimum would not be
known."""


@dataclass
class GenDisc:
    """A disc: name, initial position and velocity, radius, mass, actuated, target."""

    name: str
    p: tuple[float, float]
    r: float
    v: tuple[float, float] = (0.0, 0.0)
    m: float = 1.0
    actuated: bool = False
    target: tuple[float, float] | None = None


@dataclass
class Wall:
    """An infinite straight wall through ``point`` with unit ``normal`` into free space."""

    name: str
    point: tuple[float, float]
    normal: tuple[float, float]


@dataclass
class GenScene:
    """A generated scene; ``guess`` is the actuated disc's initial-guess force on the first
    half of the horizon (:meth:`guess_controls`)."""

    name: str
    family: str
    horizon: float
    eps: float
    e: float
    discs: list[GenDisc]
    walls: list[Wall] = field(default_factory=list)
    steps: int = 240
    guess: tuple[float, float] = (0.0, 0.0)
    plan: list[str] = field(default_factory=list)

    @property
    def actuated(self) -> int:
        """Index of the actuated disc."""
        return next(i for i, d in enumerate(self.discs) if d.actuated)

    def guard_names(self) -> list[str]:
        """Guard names as hybridoc spells them: ``a|b`` for pairs (i < j), ``disc|wall``."""
        names = []
        n = len(self.discs)
        for i in range(n):
            for j in range(i + 1, n):
                names.append(f"{self.discs[i].name}|{self.discs[j].name}")
        for d in self.discs:
            for w in self.walls:
                names.append(f"{d.name}|{w.name}")
        return names

    def guess_controls(self) -> np.ndarray:
        """The initial guess on the grid, ``(steps, 2)``: the force ``guess`` on the cells
        that start before ``T / 2``, none after (a constant push would chatter against a
        struck disc when ``e < 1``)."""
        starts = np.arange(self.steps) * self.horizon / self.steps
        return np.where((starts < self.horizon / 2)[:, None], np.array(self.guess), 0.0)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-able description (read back by :func:`scene_from_dict`)."""
        return {
            "name": self.name,
            "family": self.family,
            "horizon": self.horizon,
            "eps": self.eps,
            "e": self.e,
            "steps": self.steps,
            "guess": list(self.guess),
            "plan": list(self.plan),
            "discs": [
                {
                    "name": d.name,
                    "p": list(d.p),
                    "r": d.r,
                    "v": list(d.v),
                    "m": d.m,
                    "actuated": d.actuated,
                    "target": None if d.target is None else list(d.target),
                }
                for d in self.discs
            ],
            "walls": [
                {"name": w.name, "point": list(w.point), "normal": list(w.normal)}
                for w in self.walls
            ],
        }

    def to_toml(self) -> str:
        """The scene in hybridoc's TOML format (``docs/scenes.rst``)."""

        def vec(x: Any) -> str:
            return f"[{float(x[0])!r}, {float(x[1])!r}]"

        lines = [
            f'name = "{self.name}"',
            f'description = "generated {self.family} scene (tests/scene_generator.py)"',
            f"horizon = {self.horizon!r}",
            f"steps = {self.steps}",
            f"control_weight = {self.eps!r}",
            f"restitution = {self.e!r}",
        ]
        for d in self.discs:
            lines += ["", "[[discs]]", f'name = "{d.name}"', f"position = {vec(d.p)}"]
            lines += [f"velocity = {vec(d.v)}", f"radius = {d.r!r}", f"mass = {d.m!r}"]
            if d.actuated:
                rows = ", ".join(vec(u) for u in self.guess_controls())
                lines += ["actuated = true", f"initial_control = [{rows}]"]
            if d.target is not None:
                lines.append(f"target = {vec(d.target)}")
        for w in self.walls:
            lines += ["", "[[walls]]", f'name = "{w.name}"', f"point = {vec(w.point)}"]
            lines.append(f"normal = {vec(w.normal)}")
        return "\n".join(lines) + "\n"


def scene_from_dict(d: dict[str, Any]) -> GenScene:
    """The inverse of :meth:`GenScene.to_dict`."""
    discs = [
        GenDisc(
            x["name"],
            tuple(x["p"]),
            x["r"],
            tuple(x["v"]),
            x["m"],
            x["actuated"],
            None if x["target"] is None else tuple(x["target"]),
        )
        for x in d["discs"]
    ]
    walls = [Wall(w["name"], tuple(w["point"]), tuple(w["normal"])) for w in d["walls"]]
    return GenScene(
        d["name"],
        d["family"],
        d["horizon"],
        d["eps"],
        d["e"],
        discs,
        walls,
        d["steps"],
        tuple(d["guess"]),
        list(d["plan"]),
    )


# --------------------------------------------------------------------------- generator

_NAMES = ("a", "b", "c", "d", "f")


def _rot(v: np.ndarray, ang: float) -> np.ndarray:
    c, s = math.cos(ang), math.sin(ang)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def _unit(ang: float) -> np.ndarray:
    return np.array([math.cos(ang), math.sin(ang)])


def _tup(x: np.ndarray) -> tuple[float, float]:
    return (round(float(x[0]), 6), round(float(x[1]), 6))


def _valid(sc: GenScene, margin: float = 0.05) -> bool:
    """No two discs within ``margin`` of touching, no disc within ``margin`` of a wall or on
    its far side."""
    for i, di in enumerate(sc.discs):
        for dj in sc.discs[i + 1 :]:
            if math.dist(di.p, dj.p) < di.r + dj.r + margin:
                return False
        for w in sc.walls:
            n = np.array(w.normal) / np.linalg.norm(w.normal)
            if (np.array(di.p) - np.array(w.point)) @ n < di.r + margin:
                return False
    return True


def _family_scene(
    family: str, rng: np.random.Generator
) -> tuple[list[GenDisc], list[Wall], list[str]]:
    """One draw of a family's discs, walls and plan (intended events), actuated disc first."""
    U = rng.uniform
    rad = lambda: round(float(U(0.12, 0.25)), 3)  # noqa: E731
    mass = lambda: round(float(U(0.5, 2.0)), 3)  # noqa: E731
    ang0 = U(-math.pi, math.pi)
    pa = np.zeros(2)
    walls: list[Wall] = []
    if family == "chain":
        n = int(rng.integers(3, 6))
        discs = [GenDisc("a", _tup(pa), rad(), actuated=True, m=mass())]
        p, ang = pa, ang0
        for k in range(1, n):
            ang = ang + U(-0.5, 0.5) * (k > 1)
            r = rad()
            p = p + _unit(ang) * (discs[-1].r + r + U(0.15, 0.5))
            discs.append(GenDisc(_NAMES[k], _tup(p), r, m=mass()))
        tgt = p + _unit(ang + U(-0.6, 0.6)) * U(0.3, 0.9)
        discs[-1].target = _tup(tgt)
        plan = [f"{_NAMES[k]}|{_NAMES[k + 1]}" for k in range(n - 1)]
    elif family == "bank":
        # wall frame: tangent t, normal n (into free space); the wall is the line n = 0
        t_ax, n_ax = _unit(ang0), _unit(ang0 + math.pi / 2)
        side = rng.choice([-1.0, 1.0])
        pb = n_ax * U(0.35, 0.7)
        pa = pb + t_ax * side * U(0.3, 0.9) + n_ax * U(0.7, 1.3)
        tgt = pb + t_ax * side * U(0.1, 0.8) + n_ax * U(0.2, 1.0)
        discs = [
            GenDisc("a", _tup(pa), rad(), actuated=True, m=mass()),
            GenDisc("b", _tup(pb), rad(), m=mass(), target=_tup(tgt)),
        ]
        walls = [Wall("w0", _tup(np.zeros(2)), _tup(n_ax))]
        if rng.random() < 0.4:  # a second, side wall
            walls.append(Wall("w1", _tup(-t_ax * side * U(0.6, 1.2)), _tup(t_ax * side)))
        plan = ["a|b", "b|w0"]
    elif family == "dodge":
        L = U(1.0, 2.2)
        d = _unit(ang0)
        tgt = pa + d * L
        discs = [GenDisc("a", _tup(pa), rad(), actuated=True, m=mass(), target=_tup(tgt))]
        for k in range(1, int(rng.integers(2, 4))):
            off = U(-0.35, 0.35)
            pg = pa + d * L * U(0.3, 0.7) + _rot(d, math.pi / 2) * off
            discs.append(GenDisc(_NAMES[k], _tup(pg), rad(), m=round(float(U(0.5, 4.0)), 3)))
        plan = []
    elif family == "break":
        n_rack = int(rng.integers(2, 5))
        d = _unit(ang0)
        r = rad()
        apex = pa + d * U(0.6, 1.0)
        discs = [GenDisc("a", _tup(pa), rad(), actuated=True, m=mass())]
        gap = 2 * r + U(0.06, 0.12)
        spots = [apex, apex + gap * _rot(d, 0.52), apex + gap * _rot(d, -0.52)]
        spots.append(apex + gap * (_rot(d, 0.52) + _rot(d, -0.52)))
        for k in range(n_rack):
            discs.append(GenDisc(_NAMES[k + 1], _tup(spots[k]), r, m=mass()))
        who = int(rng.integers(1, n_rack + 1))
        p = np.array(discs[who].p)
        discs[who].target = _tup(p + _unit(ang0 + U(-1.0, 1.0)) * U(0.3, 0.9))
        plan = ["a|b"]
    elif family == "intercept":
        d = _unit(ang0)
        pb = pa + d * U(0.8, 1.4) - _rot(d, math.pi / 2) * U(0.4, 0.9)
        vb = _rot(d, math.pi / 2) * U(0.3, 1.0)
        tgt = pb + d * U(0.3, 0.9) + _rot(d, math.pi / 2) * U(-0.3, 0.6)
        discs = [
            GenDisc("a", _tup(pa), rad(), actuated=True, m=mass()),
            GenDisc("b", _tup(pb), rad(), v=_tup(vb), m=mass(), target=_tup(tgt)),
        ]
        plan = ["a|b"]
    elif family == "inelastic":
        d = _unit(ang0)
        pb = pa + d * U(0.6, 1.2)
        tgt = pb + _unit(ang0 + U(-0.8, 0.8)) * U(0.3, 1.0)
        discs = [
            GenDisc("a", _tup(pa), rad(), actuated=True, m=mass()),
            GenDisc("b", _tup(pb), rad(), m=mass(), target=_tup(tgt)),
        ]
        plan = ["a|b"]
    elif family == "no-contact":
        d = _unit(ang0)
        tgt = pa + d * U(0.6, 1.5)
        discs = [GenDisc("a", _tup(pa), rad(), actuated=True, m=mass(), target=_tup(tgt))]
        for k in range(1, int(rng.integers(2, 4))):
            pg = pa + d * U(0.2, 1.2) + _rot(d, math.pi / 2) * rng.choice([-1, 1]) * U(0.5, 0.9)
            vg = _unit(U(-math.pi, math.pi)) * U(0.0, 0.3)
            discs.append(GenDisc(_NAMES[k], _tup(pg), rad(), v=_tup(vg), m=mass()))
        plan = []
    else:
        raise ValueError(f"unknown family {family!r}")
    return discs, walls, plan


def generate(index: int, seed: int = 0, family: str | None = None, draw: int = 0) -> GenScene:
    """Scene number ``index`` of the seeded sequence ``seed`` (deterministic).

    The family is ``FAMILIES[index % len(FAMILIES)]`` unless given; the horizon is drawn in
    [0.5, 5] s, the restitution in [0.3, 1] (``inelastic``: [0.3, 0.6]), the control weight
    log-uniformly in [0.003, 0.03]. The initial guess (:meth:`GenScene.guess_controls`) is a
    force on the first half of the horizon that brings the actuated disc's centre to the
    first planned disc's (or to its target) at about 0.6 T. ``draw`` > 0 draws
    another scene of the same family (its name ends in ``-r<draw>``; :func:`accepted`).
    """
    family = family or FAMILIES[index % len(FAMILIES)]
    rng = np.random.default_rng([seed, index, FAMILIES.index(family), draw])
    for _ in range(1000):
        discs, walls, plan = _family_scene(family, rng)
        T = round(float(rng.uniform(0.5, 5.0)), 3)
        lo, hi = (0.3, 0.6) if family == "inelastic" else (0.3, 1.0)
        e = round(float(rng.uniform(lo, hi)), 3) if rng.random() < 0.8 else 1.0
        if family == "inelastic":
            e = round(float(rng.uniform(lo, hi)), 3)
        eps = round(float(math.exp(rng.uniform(math.log(0.003), math.log(0.03)))), 5)
        a = discs[0]
        # scale velocities so that a drifting disc moves about the same whatever T
        for dd in discs:
            dd.v = _tup(np.array(dd.v) / T)
        if plan:
            first = plan[0].split("|")[1]
            goal = np.array(next(x.p for x in discs if x.name == first))
        else:
            goal = np.array(a.target)
        th = 0.6 * T
        guess = 2 * a.m * (goal - np.array(a.p)) / th**2
        sc = GenScene(
            name=f"gen-{seed}-{index:03d}-{family}",
            family=family,
            horizon=T,
            eps=eps,
            e=e,
            discs=discs,
            walls=walls,
            steps=200,
            guess=_tup(guess),
            plan=plan,
        )
        if _valid(sc):
            return sc
    raise RuntimeError(f"no valid {family} scene drawn")  # pragma: no cover


def generate_many(n: int, seed: int = 0) -> list[GenScene]:
    """Scenes ``0 .. n-1`` of :func:`generate` (every family in turn)."""
    return [generate(i, seed) for i in range(n)]


def accepted(index: int, seed: int = 0, **options: Any) -> tuple[GenScene, Optimum, list[str]]:
    """Scene ``index`` with its optimum: the first draw (``draw = 0, 1, ...``) whose optimum
    found has at most :data:`ACCEPT_EVENTS` events and no control seen with more events is
    cheaper (a push that chatters would be); also the names of the draws rejected.
    ``options`` go to :func:`optimum`."""
    rejected = []
    for draw in range(20):
        sc = generate(index, seed, draw=draw)
        opt = optimum(sc, **options)
        pushes = opt.long_best is not None and opt.long_best < opt.cost
        if len(opt.sequence) <= ACCEPT_EVENTS and not pushes:
            return sc, opt, rejected
        rejected.append(sc.name)
    raise RuntimeError(f"scene {index}: 20 draws, each with a chattering optimum")


# --------------------------------------------------------------------------- simulation


@dataclass
class SimResult:
    """One simulation: the cost, its residuals, the events ``(time, guard name)``, the phase
    start times of the actuated disc's control, the final positions and velocities."""

    cost: float
    residuals: np.ndarray
    events: list[tuple[float, str]]
    phase_starts: list[float]
    positions: np.ndarray
    velocities: np.ndarray
    valid: bool = True

    @property
    def sequence(self) -> list[str]:
        """The guard names of the events in order."""
        return [g for _, g in self.events]


class _Sim:
    """The scene's geometry in arrays, and its guards."""

    def __init__(self, sc: GenScene) -> None:
        self.sc = sc
        self.n = len(sc.discs)
        self.ia = sc.actuated
        self.P0 = np.array([d.p for d in sc.discs], float)
        self.V0 = np.array([d.v for d in sc.discs], float)
        self.r = np.array([d.r for d in sc.discs], float)
        self.m = np.array([d.m for d in sc.discs], float)
        self.guards: list[tuple[str, int, int, str]] = []  # (kind, i, j or wall, name)
        for i in range(self.n):
            for j in range(i + 1, self.n):
                self.guards.append(("pair", i, j, f"{sc.discs[i].name}|{sc.discs[j].name}"))
        for i in range(self.n):
            for k, w in enumerate(sc.walls):
                self.guards.append(("wall", i, k, f"{sc.discs[i].name}|{w.name}"))
        self.wp = np.array([w.point for w in sc.walls], float).reshape(-1, 2)
        wn = np.array([w.normal for w in sc.walls], float).reshape(-1, 2)
        self.wn = wn / np.linalg.norm(wn, axis=1, keepdims=True) if len(wn) else wn
        self.targets = [(i, np.array(d.target)) for i, d in enumerate(sc.discs) if d.target]


def _horner(c: list[float], t: float) -> float:
    v = 0.0
    for x in c:
        v = v * t + x
    return v


def _first_crossing(coeffs: list[float], tmax: float, scale: float) -> float:
    """The first time in ``(0, tmax]`` at which the polynomial (highest power first, value at
    0 >= about 0) crosses zero downwards; ``inf`` if none. Roots from the companion matrix,
    polished by Newton's method on the polynomial; a root at 0 (a contact that just fired and
    now separates) is skipped by its rising slope, one at 0 that approaches fires at once."""
    c = list(coeffs)
    while c and c[0] == 0.0:
        c.pop(0)
    deg = len(c) - 1
    if deg < 1:
        return math.inf
    dc = [x * (deg - k) for k, x in enumerate(c[:-1])]
    if deg == 1:
        roots = [-c[1] / c[0]]
    elif deg == 2:
        a, b, cc = c
        disc = b * b - 4 * a * cc
        if disc < 0:
            return math.inf
        q = -0.5 * (b + math.copysign(math.sqrt(disc), b))
        roots = [q / a, cc / q if q != 0 else 0.0]
    else:
        rts = np.roots(c)
        roots = rts[np.abs(rts.imag) <= 1e-6 * (1 + np.abs(rts.real))].real.tolist()
    if abs(c[-1]) <= 1e-11 and c[-2] < 0:
        return 0.0  # at contact and approaching: a push fires again at once (chatter)
    best = math.inf
    for t in sorted(roots):
        if t < -1e-9 or t > tmax + 1e-9:
            continue
        for _ in range(3):  # polish
            d = _horner(dc, t)
            if d == 0:
                break
            t = t - _horner(c, t) / d
        if t <= 1e-12 * scale or t > tmax or t >= best:
            continue
        if _horner(dc, t) < 0:  # approaching (a separating root is the contact at 0)
            best = t
    return best


def simulate(sc: GenScene, params: np.ndarray, *, sim: _Sim | None = None) -> SimResult:
    """Simulate the scene under the event-triggered piecewise-affine force ``params``.

    Parameters
    ----------
    sc
        The scene.
    params
        ``(K, 4)`` rows ``(ax, ay, bx, by)``: phase ``k`` (from the actuated disc's ``k``-th
        event, or 0, to its next) applies the force ``a_k + b_k tau``, ``tau`` the time since
        the phase began; from the ``K``-th phase on the last row continues.
    sim
        A prepared :class:`_Sim` (saves rebuilding it per call).

    Returns
    -------
    SimResult
        ``valid`` is false when more than :data:`MAX_EVENTS` events happened (cost ``inf``).
    """
    s = sim or _Sim(sc)
    params = np.asarray(params, float).reshape(-1, 4)
    K = len(params)
    T, e, ia = sc.horizon, sc.e, s.ia
    P, V = s.P0.copy(), s.V0.copy()
    m, r = s.m, s.r
    t, ph = 0.0, 0
    starts = [0.0]
    events: list[tuple[float, str]] = []
    scale = max(1.0, T)
    while True:
        a = params[ph, :2] + params[ph, 2:] * (t - starts[ph])
        b = params[ph, 2:]
        acc2, acc3 = a / m[ia], b / m[ia]  # p_a(tau) = p + v tau + acc2 tau^2/2 + acc3 tau^3/6
        tmax = T - t
        first, gi = tmax, -1
        for g, (kind, i, j, _) in enumerate(s.guards):
            if kind == "pair":
                dp, dv = P[i] - P[j], V[i] - V[j]
                c2 = np.zeros(2)
                c3 = np.zeros(2)
                if i == ia:
                    c2, c3 = acc2 / 2, acc3 / 6
                elif j == ia:
                    c2, c3 = -acc2 / 2, -acc3 / 6
                R = r[i] + r[j]
                reach = math.hypot(*dv) * first + math.hypot(*c2) * first**2
                if math.hypot(*dp) - R > reach + math.hypot(*c3) * first**3 + 1e-9:
                    continue  # cannot close within the segment
                if i != ia and j != ia:
                    coef = [dv @ dv, 2 * dp @ dv, dp @ dp - R * R]
                else:
                    # |dp + dv t + c2 t^2 + c3 t^3|^2 - R^2, highest power first
                    coef = np.zeros(7)
                    for comp in range(2):
                        poly = np.array([c3[comp], c2[comp], dv[comp], dp[comp]])
                        coef += np.convolve(poly, poly)
                    coef[-1] -= R * R
                    coef = coef.tolist()
            else:
                n_, pt = s.wn[j], s.wp[j]
                d0 = (P[i] - pt) @ n_ - r[i]
                w0 = V[i] @ n_
                if i == ia:
                    a3, a2 = acc3 @ n_ / 6, acc2 @ n_ / 2
                    if d0 > (abs(w0) + abs(a2) * first + abs(a3) * first**2) * first + 1e-9:
                        continue
                    coef = [a3, a2, w0, d0]
                else:
                    if d0 > abs(w0) * first + 1e-9:
                        continue
                    coef = [w0, d0]
            tc = _first_crossing(coef, first, scale)
            if tc < first:
                first, gi = tc, g
        # advance to `first`
        tau = first
        Vn = V.copy()
        P = P + V * tau
        P[ia] += acc2 * tau**2 / 2 + acc3 * tau**3 / 6
        Vn[ia] += acc2 * tau + acc3 * tau**2 / 2
        V = Vn
        t = t + tau
        if gi < 0 or t >= T:
            break
        kind, i, j, name = s.guards[gi]
        if kind == "pair":
            d = P[i] - P[j]
            nrm = d / np.linalg.norm(d)
            w = (V[i] - V[j]) @ nrm
            J = -(1 + e) * w / (1 / m[i] + 1 / m[j])
            V[i] += J / m[i] * nrm
            V[j] -= J / m[j] * nrm
        else:
            nrm = s.wn[j]
            V[i] -= (1 + e) * (V[i] @ nrm) * nrm
        events.append((t, name))
        if len(events) > MAX_EVENTS:
            return SimResult(math.inf, np.full(_nres(s, K), 1e3), events, starts, P, V, False)
        if (ia in (i, j)) if kind == "pair" else (i == ia):
            if ph + 1 < K:
                ph += 1
                starts.append(t)
            # beyond K phases the last row's affine force continues
    res = _residuals(s, params, starts, P)
    return SimResult(float(res @ res), res, events, starts, P, V, _apart(s, P))


def _apart(s: _Sim, P: np.ndarray) -> bool:
    """No disc inside another or behind a wall (by more than 1e-9): a safeguard, since every
    crossing is an event."""
    for kind, i, j, _ in s.guards:
        if kind == "pair":
            gap = math.hypot(*(P[i] - P[j])) - s.r[i] - s.r[j]
        else:
            gap = (P[i] - s.wp[j]) @ s.wn[j] - s.r[i]
        if gap < -1e-9:
            return False
    return True


def _nres(s: _Sim, K: int) -> int:
    return 2 * len(s.targets) + 4 * K


_GL = (0.5 - 0.5 / math.sqrt(3), 0.5 + 0.5 / math.sqrt(3))


def _residuals(s: _Sim, params: np.ndarray, starts: list[float], P: np.ndarray) -> np.ndarray:
    """Targets' misses, then per phase ``sqrt(eps d / 2) u(tau_g)`` at the two Gauss points of
    the phase (``d`` its duration): their squares sum to ``eps int |u|^2`` exactly."""
    T, eps = s.sc.horizon, s.sc.eps
    out = []
    for i, tgt in s.targets:
        out.extend(P[i] - tgt)
    K = len(params)
    ends = list(starts[1:]) + [T]
    for k in range(K):
        if k < len(starts):
            d = ends[k] - starts[k]
            w = math.sqrt(eps * d / 2)
            for g in _GL:
                out.extend(w * (params[k, :2] + params[k, 2:] * g * d))
        else:
            out.extend([0.0] * 4)
    return np.array(out)


# --------------------------------------------------------------------------- optimum


@dataclass
class Optimum:
    """The independent optimum of a scene.

    ``cost``, ``sequence`` (guard names), ``event_times``, ``params`` (the
    :func:`simulate` force rows) and ``phase_starts``; ``starts`` run, ``hits`` (starts within
    a relative ``1e-6`` of the best cost with its sequence), ``runner_up`` (the best cost of
    another event sequence, ``None`` if none), ``seconds`` of CPU, ``local_minima`` (up to 8
    distinct costs and sequences found), ``long_best`` (the cheapest control seen with more
    than :data:`ACCEPT_EVENTS` events, ``None`` if none).
    """

    cost: float
    sequence: list[str]
    event_times: list[float]
    params: list[list[float]]
    phase_starts: list[float]
    starts: int
    hits: int
    runner_up: float | None
    runner_up_sequence: list[str] | None
    seconds: float
    local_minima: list[tuple[float, list[str]]] = field(default_factory=list)
    long_best: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-able fields."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__}

    def force(self, t: float) -> np.ndarray:
        """The optimal force at time ``t`` (the phase that contains ``t``)."""
        k = int(np.searchsorted(self.phase_starts, t, side="right") - 1)
        k = max(0, min(k, len(self.params) - 1))
        row = np.asarray(self.params[k])
        return row[:2] + row[2:] * (t - self.phase_starts[k])


def _aimed(s: _Sim, q: np.ndarray, t_hit: float) -> np.ndarray:
    """The constant force that brings the actuated disc's centre to ``q`` at ``t_hit``."""
    ia = s.ia
    return 2 * s.m[ia] * (q - s.P0[ia] - s.V0[ia] * t_hit) / t_hit**2


def _starts(sc: GenScene, s: _Sim, K: int, rng: np.random.Generator) -> list[np.ndarray]:
    """Initial params: no force, the plan's guess, strikes aimed at every disc (its centre
    moving to its target, or at angles about the line of centres) and every wall, at
    several times, then random forces."""
    T, ia = sc.horizon, s.ia
    out: list[np.ndarray] = []

    def add(force: np.ndarray, brake: bool = False, t_hit: float = 0.0) -> None:
        x = np.zeros((K, 4))
        x[:, :2] = force  # the same force on after the events (the guess's continuation)
        if brake and K > 1:
            x[1:, :2] = 0.0  # or none after the strike
        out.append(x)

    add(np.zeros(2))
    add(np.array(sc.guess, float))
    for j in range(s.n):
        if j == ia:
            continue
        R = s.r[ia] + s.r[j]
        for frac in (0.35, 0.55, 0.8):
            th = frac * T
            pj = s.P0[j] + s.V0[j] * th
            base = pj - (s.P0[ia] + s.V0[ia] * th)
            base = base / max(np.linalg.norm(base), 1e-12)
            dirs = [(base, False)]
            if frac == 0.55:
                dirs += [(_rot(base, -0.5), False), (_rot(base, 0.5), False)]
            tgt = sc.discs[j].target
            if tgt is not None and np.linalg.norm(np.asarray(tgt) - pj) > 1e-9:
                dvec = np.asarray(tgt) - pj
                dirs += [(dvec / np.linalg.norm(dvec), False), (dvec / np.linalg.norm(dvec), True)]
            for dvec, brake in dirs:
                # aim a little past contact so that the strike happens before th
                add(_aimed(s, pj - 0.8 * R * dvec, th), brake=brake)
    for k in range(len(sc.walls)):
        n_, pt = s.wn[k], s.wp[k]
        for frac in (0.35, 0.7):
            th = frac * T
            pa = s.P0[ia] + s.V0[ia] * th
            foot = pa - ((pa - pt) @ n_ - s.r[ia] * 0.8) * n_
            for along in (-0.5, 0.5):
                tang = np.array([-n_[1], n_[0]])
                add(_aimed(s, foot + along * tang, th))
    scale = max(np.linalg.norm(np.array(sc.guess)), 1.0)
    for _ in range(3):
        x = np.zeros((K, 4))
        x[0, :2] = rng.normal(0, scale, 2)
        x[:, 2:] = rng.normal(0, scale / T, (K, 2)) * 0.3
        out.append(x)
    return out


def _forced(
    s: _Sim, params: np.ndarray, times: np.ndarray, seq: list[int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Propagate with the event sequence imposed: at ``times[k]`` the reset of guard
    ``seq[k]`` is applied whatever the gaps. Returns the residuals, each event's gap and its
    normal speed (both must vanish or be negative for a real event)."""
    sc = s.sc
    T, e, ia, m, r = sc.horizon, sc.e, s.ia, s.m, s.r
    K = len(params)
    P, V = s.P0.copy(), s.V0.copy()
    t, ph = 0.0, 0
    starts = [0.0]
    gaps, speeds = [], []
    for k in range(len(seq) + 1):
        t_next = times[k] if k < len(seq) else T
        tau = t_next - t
        a = params[ph, :2] + params[ph, 2:] * (t - starts[ph])
        acc2, acc3 = a / m[ia], params[ph, 2:] / m[ia]
        P = P + V * tau
        P[ia] += acc2 * tau**2 / 2 + acc3 * tau**3 / 6
        V = V.copy()
        V[ia] += acc2 * tau + acc3 * tau**2 / 2
        t = t_next
        if k == len(seq):
            break
        kind, i, j, _ = s.guards[seq[k]]
        if kind == "pair":
            d = P[i] - P[j]
            dist = math.hypot(*d)
            nrm = d / dist
            w = (V[i] - V[j]) @ nrm
            gaps.append(dist - r[i] - r[j])
            speeds.append(w)
            J = -(1 + e) * w / (1 / m[i] + 1 / m[j])
            V[i] += J / m[i] * nrm
            V[j] -= J / m[j] * nrm
            hit_a = ia in (i, j)
        else:
            nrm = s.wn[j]
            w = V[i] @ nrm
            gaps.append((P[i] - s.wp[j]) @ nrm - r[i])
            speeds.append(w)
            V[i] -= (1 + e) * w * nrm
            hit_a = i == ia
        if hit_a and ph + 1 < K:
            ph += 1
            starts.append(t)
    return _residuals(s, params, starts, P), np.array(gaps), np.array(speeds)


def _a_events(s: _Sim, seq: list[int]) -> int:
    ia = s.ia
    return sum(
        1
        for g in seq
        if (s.guards[g][0] == "pair" and ia in s.guards[g][1:3])
        or (s.guards[g][0] == "wall" and s.guards[g][1] == ia)
    )


def _solve_sequence(
    s: _Sim, seq: list[int], params: np.ndarray, times: list[float]
) -> tuple[np.ndarray, SimResult] | None:
    """The optimum of one event sequence: SLSQP over the force rows and the event times with
    each event's gap = 0 and normal speed <= 0 imposed, from ``params``/``times``; then
    re-simulated by :func:`simulate`, and kept only if the free simulation has that sequence
    and that cost (no other contact on the way, no missed event)."""
    T = s.sc.horizon
    M = len(seq)
    K = _a_events(s, seq) + 1
    p0 = np.zeros((K, 4))
    p0[: min(K, len(params))] = params[:K]
    if len(params) < K:
        p0[len(params) :] = params[-1]
    x0 = np.concatenate([p0.ravel(), np.asarray(times, float)])
    nP = 4 * K

    def split(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return x[:nP].reshape(K, 4), x[nP:]

    memo: dict[bytes, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def forced(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # SLSQP asks the objective and both constraints at the same points
        key = x.tobytes()
        if key not in memo:
            if len(memo) > 64:
                memo.clear()
            memo[key] = _forced(s, *split(x), seq)
        return memo[key]

    def obj(x: np.ndarray) -> float:
        res = forced(x)[0]
        return float(res @ res)

    def eq(x: np.ndarray) -> np.ndarray:
        return forced(x)[1]

    def ineq(x: np.ndarray) -> np.ndarray:
        tm = x[nP:]
        order = np.concatenate([[tm[0]], np.diff(tm), [T - tm[-1]]])
        return np.concatenate([-forced(x)[2], order])

    cons = [{"type": "ineq", "fun": ineq}]
    if M:
        cons.append({"type": "eq", "fun": eq})
    else:
        cons = []
    try:
        sol = so.minimize(
            obj, x0, method="SLSQP", constraints=cons, options={"maxiter": 150, "ftol": 1e-16}
        )
    except (ValueError, FloatingPointError, ZeroDivisionError):  # pragma: no cover
        return None
    pk, _ = split(sol.x)
    res = simulate(s.sc, pk, sim=s)
    names = [s.guards[g][3] for g in seq]
    if not res.valid or res.sequence != names or abs(res.cost - sol.fun) > 1e-8 * max(1, sol.fun):
        return None
    return pk, res


def optimum(
    sc: GenScene,
    *,
    phases: int = 4,
    seed: int = 0,
    max_starts: int | None = None,
    extra_starts: list[np.ndarray] | None = None,
    sequences: int = 8,
    explore_nfev: int = 60,
    descents: int = 4,
) -> Optimum:
    """The scene's optimum from many starts (see the module's notes).

    Each start is a Levenberg-Marquardt solve in the event-triggered parametrisation; every
    event sequence met on the way (with the cheapest control that met it) is a candidate, and
    the ``sequences`` cheapest candidates are then solved with their sequence imposed
    (:func:`_solve_sequence`, which re-simulates its answer). The best re-simulated control
    is polished by Levenberg-Marquardt with central differences.

    Parameters
    ----------
    sc
        The scene.
    phases
        Rows of the event-triggered force of the starts (so up to ``phases - 1`` events of
        the actuated disc with a phase of their own).
    seed
        Seed of the random starts.
    max_starts
        Run at most this many starts (in the order of :func:`_starts`).
    extra_starts
        Further ``(phases, 4)`` starts, run first.
    sequences
        How many candidate sequences get a sequence-fixed solve.
    explore_nfev
        Simulations of each start's short descent.
    descents
        How many of the short descents' results (at most two per sequence) descend on.
    """
    t0 = time.process_time()
    s = _Sim(sc)
    rng = np.random.default_rng(seed)
    starts = list(extra_starts or []) + _starts(sc, s, phases, rng)
    if max_starts is not None:
        starts = starts[:max_starts]
    index = {g[3]: k for k, g in enumerate(s.guards)}
    # sequence -> (cost, params, event times) of the cheapest control seen with it, and of
    # the first (often a start: a tamer point than an iterate's passing visit)
    seen: dict[tuple[str, ...], tuple[float, np.ndarray, list[float]]] = {}
    first_seen: dict[tuple[str, ...], tuple[float, np.ndarray, list[float]]] = {}

    long_best = [math.inf]  # the cheapest control seen with more than ACCEPT_EVENTS events

    def record(x: np.ndarray, res: SimResult) -> None:
        key = tuple(res.sequence)
        if res.valid and len(key) > ACCEPT_EVENTS:
            long_best[0] = min(long_best[0], res.cost)
        if not res.valid or len(key) > 8:
            return
        entry = (res.cost, x.copy(), [t for t, _ in res.events])
        first_seen.setdefault(key, entry)
        if key not in seen or res.cost < seen[key][0]:
            seen[key] = entry

    def fun_for(shape: tuple[int, int]):
        def fun(x: np.ndarray) -> np.ndarray:
            res = simulate(sc, x.reshape(shape), sim=s)
            record(x.reshape(shape), res)
            return res.residuals

        return fun

    found: list[tuple[float, np.ndarray, SimResult]] = []
    shape = (phases, 4)
    fun = fun_for(shape)

    def descend(x0: np.ndarray, nfev: int) -> tuple[float, np.ndarray, SimResult] | None:
        sol = so.least_squares(
            fun, x0.ravel(), method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=nfev
        )
        res = simulate(sc, sol.x.reshape(shape), sim=s)
        if res.valid and math.isfinite(res.cost):
            return res.cost, sol.x.reshape(shape).copy(), res
        return None

    # a short descent from every start (each sequence met is recorded), then the cheapest
    # few, of distinct sequences, descend to the end
    short = []
    for x0 in starts:
        x0 = np.asarray(x0, float).reshape(shape)
        first = simulate(sc, x0, sim=s)
        if not first.valid:
            continue
        record(x0, first)
        out = descend(x0, explore_nfev)
        if out is not None:
            short.append(out)
    short.sort(key=lambda f: f[0])
    picked: list[tuple[str, ...]] = []
    for _c, x, res in short:
        key = tuple(res.sequence)
        if picked.count(key) >= 2 or len(picked) >= descents:
            continue
        picked.append(key)
        out = descend(x, 600)
        if out is not None:
            found.append(out)
    # sequence-fixed solves of the cheapest candidates
    ranked = sorted(seen.items(), key=lambda kv: kv[1][0])[:sequences]
    for key, (_, x, times) in ranked:
        seq = [index[g] for g in key]
        out = _solve_sequence(s, seq, x, times)
        if out is None and first_seen[key][1] is not x:
            out = _solve_sequence(s, seq, first_seen[key][1], first_seen[key][2])
        if out is not None:
            found.append((out[1].cost, out[0], out[1]))
    if not found:
        raise RuntimeError(f"{sc.name}: no start gave a valid control")
    found.sort(key=lambda f: f[0])
    best_cost, best_x, best = found[0]
    # polish the best with central differences (forward ones stop at ~1e-8 of the gradient)
    bshape = best_x.shape
    sol = so.least_squares(
        lambda z: simulate(sc, z.reshape(bshape), sim=s).residuals,
        best_x.ravel(),
        method="trf",
        jac="3-point",
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
        max_nfev=2000,
    )
    pol = simulate(sc, sol.x.reshape(bshape), sim=s)
    if pol.valid and pol.cost < best_cost:
        best_cost, best_x, best = pol.cost, sol.x.reshape(bshape).copy(), pol
    hits = sum(
        1
        for c, _, r in found
        if c <= best_cost * (1 + 1e-6) + 1e-15 and r.sequence == best.sequence
    )
    others = sorted((c, r.sequence) for c, _, r in found if r.sequence != best.sequence)
    minima: list[tuple[float, list[str]]] = []
    for c, _, r in found:
        if not any(abs(c - c2) <= 1e-9 * max(c, 1e-12) and q == r.sequence for c2, q in minima):
            minima.append((c, r.sequence))
    return Optimum(
        cost=best_cost,
        sequence=best.sequence,
        event_times=[float(t) for t, _ in best.events],
        params=best_x.tolist(),
        phase_starts=[float(t) for t in best.phase_starts],
        starts=len(found),
        hits=hits,
        runner_up=others[0][0] if others else None,
        runner_up_sequence=others[0][1] if others else None,
        seconds=time.process_time() - t0,
        local_minima=minima[:8],
        long_best=None if math.isinf(long_best[0]) else long_best[0],
    )
