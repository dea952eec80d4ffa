"""The starting controls of the batched multi-start (:mod:`hybridoc.solvers.multistart`).

:func:`starting_controls` builds ``K`` initial controls that reach different event
sequences: the problem's guess, smooth perturbations of it, random smooth controls, and
(problems with a :attr:`~hybridoc.capabilities.Capabilities.geometry`: disc scenes)
constant forces that aim each actuated body at each other body and at each plane.
:func:`diverse_controls` and :func:`diverse_starts` add late strikes, bounce-first starts
and pairs of strikers, each start with its kind. :mod:`hybridoc.solvers.multistart`
re-exports them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.ocp import HybridOCP
from hybridoc.scales import optimizer_units

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.capabilities import Geometry

__all__ = [
    "AIM_FRACTIONS",
    "diverse_controls",
    "diverse_starts",
    "smooth_noise",
    "starting_controls",
]


def _stacked(ocp: HybridOCP, pool: list[np.ndarray], count: int) -> np.ndarray:
    """The first ``count`` starts of ``pool`` as one ``(count, N, nu)`` array, clipped to the
    control bounds."""
    U = np.stack(pool[:count])
    if ocp.has_bounds:
        U = np.clip(U, ocp.u_min, ocp.u_max)
    return U


def smooth_noise(rng: np.random.Generator, N: int, nu: int, modes: int = 4) -> np.ndarray:
    """A random smooth control shape on N cells (a few cosine modes), unit scale."""
    t = (np.arange(N) + 0.5) / N
    out = np.zeros((N, nu))
    for k in range(modes):
        out += rng.standard_normal(nu)[None, :] * np.cos(np.pi * k * t)[:, None] / (1 + k)
    return out


def _control_scale(ocp: HybridOCP) -> float:
    """The size of the random starts: the guess's largest value, or half the largest finite
    bound, or (a zero guess without bounds) the problem's control scale."""
    u0 = np.asarray(ocp.u_guess, dtype=float)
    scale = float(np.abs(u0).max(initial=0.0))
    if ocp.has_bounds:
        finite = np.concatenate([np.abs(ocp.u_min), np.abs(ocp.u_max)])
        finite = finite[np.isfinite(finite)]
        if finite.size:
            scale = max(scale, 0.5 * float(finite.max()))
    return scale if scale > 0 else float(optimizer_units(ocp)[0].max())


def _aimed(ocp: HybridOCP) -> list[np.ndarray]:
    """Disc scenes: controls that steer each actuated disc at each other body or wall.

    The bodies' positions are read off the initial guess's trajectory (the judge's), at
    several times: a constant force from the start reaches the body where it will be at that
    time (then the disc coasts); and, from each event of the guess on, the guess's control
    up to the event followed by a constant force that chases the body to where it will be
    later. Basins that need a second hit (multiple-collision's three-event optimum) start
    from these."""
    from hybridoc.errors import HybridocError
    from hybridoc.evaluator import evaluate

    geo = ocp.capabilities.geometry
    if geo is None:
        return []
    try:
        ev = evaluate(ocp)
    except HybridocError:
        return []
    T, N = ocp.horizon, ocp.steps
    n = geo.n_bodies
    u0 = np.array(ocp.u_guess, dtype=float)
    grid = ocp.time_grid()
    fracs = np.array([0.3, 0.5, 0.7, 0.85])
    starts = [0.0] + sorted({float(e.time) for e in ev.events if e.time < 0.8 * T})
    out = []
    for t_s in starts:
        s_start = ev.sample([t_s])[0]
        n_s = min(int(np.searchsorted(grid, t_s, side="right")) - 1, N - 1) if t_s > 0 else 0
        for k, i in enumerate(geo.actuated_indices):
            d = geo.bodies[i]
            p = geo.position(s_start, i)
            v = geo.velocity(s_start, i)
            for t_a in t_s + fracs * (T - t_s):
                aims = [geo.position(ev.sample([t_a])[0], j) for j in range(n) if j != i]
                for wall in geo.planes:
                    nrm = np.asarray(wall.normal)
                    aims.append(p - ((p - np.asarray(wall.point)) @ nrm) * nrm)
                for q in aims:
                    dt = t_a - t_s
                    F = d.mass * 2 * (np.asarray(q) - p - v * dt) / dt**2
                    u = u0.copy() if t_s > 0 else np.zeros_like(u0)
                    n_a = min(int(np.searchsorted(grid, t_a, side="right")), N)
                    u[n_s:, 2 * k : 2 * k + 2] = 0.0
                    u[n_s:n_a, 2 * k : 2 * k + 2] = F
                    out.append(u)
    return out


def starting_controls(ocp: HybridOCP, count: int, *, seed: int | None = 0) -> np.ndarray:
    """``count`` diverse starting controls ``(count, N, nu)`` (module notes): the problem's
    guess first, then aimed controls (disc scenes; three in four), perturbations of the guess
    and random smooth controls. Deterministic for a given ``seed``."""
    rng = np.random.default_rng(seed)
    u0 = np.array(ocp.u_guess, dtype=float)
    N, nu = u0.shape
    scale = _control_scale(ocp)
    aimed = _aimed(ocp)
    order = rng.permutation(len(aimed)) if aimed else np.zeros(0, dtype=int)
    pool: list[np.ndarray] = [u0]
    a = k = 0
    while len(pool) < count:
        kind = k % 8
        if kind < 6 and a < len(aimed):
            pool.append(aimed[int(order[a])] + 0.05 * scale * smooth_noise(rng, N, nu))
            a += 1
        elif kind == 6 or (kind < 6 and k % 2 == 0):
            pool.append(u0 + 0.3 * scale * smooth_noise(rng, N, nu))
        else:
            pool.append(scale * smooth_noise(rng, N, nu))
        k += 1
    return _stacked(ocp, pool, count)


AIM_FRACTIONS = (0.3, 0.5, 0.7, 0.85)
"""When an aimed start (:func:`diverse_controls`) reaches its aim: fractions of the time
left after its force starts."""


def _contact_aim(geo: Geometry, i: int, j: int, q: np.ndarray, length: float = 1.0) -> np.ndarray:
    """Where body ``i``'s centre should be to strike body ``j`` (at ``q``) towards ``j``'s
    target: behind ``j`` on the line from its target (``j``'s centre when it has none, or
    when ``j`` is at its target to ``1e-12`` of the problem's ``length`` scale)."""
    target = geo.bodies[j].target
    if target is None:
        return q
    d = q - np.asarray(target, dtype=float)
    norm = float(np.linalg.norm(d))
    if norm < 1e-12 * length:  # at its target already: no direction to strike it
        return q
    return q + (geo.bodies[i].radius + geo.bodies[j].radius) * d / norm


class _Aimer:
    """Constant-force aims of a problem's actuated bodies (its
    :attr:`~hybridoc.capabilities.Capabilities.geometry`), read off the guess's trajectory
    (:func:`diverse_controls`)."""

    def __init__(self, ocp: HybridOCP, geo: Geometry, ev: Any) -> None:
        self.ocp, self.ev, self.geo = ocp, ev, geo
        self.n = geo.n_bodies
        self.grid = ocp.time_grid()
        self.T, self.N = ocp.horizon, ocp.steps
        self.e = float(geo.restitution)
        scales = getattr(ocp, "scales", None)
        self.length = 1.0 if scales is None else float(scales.length)

    def state(self, t: float, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Body ``i``'s position and velocity at ``t`` on the guess's trajectory."""
        s = self.ev.sample([t])[0]
        return self.geo.position(s, i).copy(), self.geo.velocity(s, i).copy()

    def cell(self, t: float) -> int:
        return min(int(np.searchsorted(self.grid, t, side="right")) - 1, self.N - 1) if t > 0 else 0

    def push(
        self,
        u: np.ndarray,
        k: int,
        m: float,
        p: np.ndarray,
        v: np.ndarray,
        q: np.ndarray,
        t_s: float,
        t_a: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Write into ``u`` (column pair ``k``) the constant force that takes a disc of mass
        ``m`` from ``p``, ``v`` at ``t_s`` to ``q`` at ``t_a``; zero after. Returns the
        velocity it arrives with and ``q``."""
        dt = max(t_a - t_s, 1e-9 * self.T)
        F = m * 2 * (q - p - v * dt) / dt**2
        n_s, n_a = self.cell(t_s), min(int(np.searchsorted(self.grid, t_a, side="right")), self.N)
        u[n_s:, 2 * k : 2 * k + 2] = 0.0
        u[n_s : max(n_a, n_s + 1), 2 * k : 2 * k + 2] = F
        return 2 * (q - p) / dt - v, q

    def wall_contact(self, i: int, wall: Any, p: np.ndarray) -> np.ndarray:
        """Disc ``i``'s centre touching ``wall`` at the foot of ``p``."""
        nrm = np.asarray(wall.normal, dtype=float)
        nrm = nrm / max(float(np.linalg.norm(nrm)), 1e-300)
        d = float((p - np.asarray(wall.point, dtype=float)) @ nrm)
        return p - (d - self.geo.bodies[i].radius) * nrm

    def body_aim(self, i: int, j: int, t: float) -> np.ndarray:
        return _contact_aim(self.geo, i, j, self.state(t, j)[0], self.length)


def diverse_controls(
    ocp: HybridOCP, evaluation: Any = None
) -> list[tuple[tuple[str, ...], np.ndarray]]:
    """Structured starting controls of a problem with a geometry
    (:attr:`~hybridoc.capabilities.Capabilities.geometry`: a disc scene), each with its
    kind (empty for other problems): for every actuated disc, a constant force aimed at each
    other disc (behind it, seen from its target, when it has one) and at each wall, from
    the start and from each event of the guess on (a late strike of a body already in
    motion); bounce-first starts (at a wall first, then off it at each disc); and with
    several actuated discs, combinations (one strikes a disc, then another strikes it).
    The bodies' positions are read off the guess's trajectory (``evaluation``, default the
    judge's)."""
    from hybridoc.errors import HybridocError
    from hybridoc.evaluator import evaluate

    geo = ocp.capabilities.geometry
    if geo is None:
        return []
    try:
        ev = evaluation if evaluation is not None else evaluate(ocp)
        if not ev.segments:
            return []
    except HybridocError:
        return []
    a = _Aimer(ocp, geo, ev)
    T, n = a.T, a.n
    u0 = np.array(ocp.u_guess, dtype=float)
    zero = np.zeros_like(u0)
    act = list(geo.actuated_indices)
    out: list[tuple[tuple[str, ...], np.ndarray]] = []
    late = sorted({float(e.time) for e in ev.events if 0 < e.time < 0.8 * T})
    for k, i in enumerate(act):
        m = geo.bodies[i].mass
        name = geo.bodies[i].name
        others = [j for j in range(n) if j != i]
        # aimed from the start (the guess's own control for the other discs: zero)
        for t_s in [0.0, *late]:
            p, v = a.state(t_s, i)
            for t_a in t_s + np.asarray(AIM_FRACTIONS) * (T - t_s):
                aims = [(f"aim {name}>{geo.bodies[j].name}", a.body_aim(i, j, t_a)) for j in others]
                if t_s == 0.0:
                    aims += [(f"aim {name}>{w.name}", a.wall_contact(i, w, p)) for w in geo.planes]
                for kind, q in aims:
                    u = (u0 if t_s > 0 else zero).copy()
                    a.push(u, k, m, p, v, q, t_s, float(t_a))
                    out.append(((kind, "late" if t_s > 0 else "early"), u))
        # bounce-first: a wall, then off it at each disc
        p0, v0 = a.state(0.0, i)
        for w in geo.planes:
            nrm = np.asarray(w.normal, dtype=float)
            nrm = nrm / max(float(np.linalg.norm(nrm)), 1e-300)
            c = a.wall_contact(i, w, p0)
            for f_w in (0.2, 0.35, 0.5):
                t_w = f_w * T
                u = zero.copy()
                v1, _ = a.push(u, k, m, p0, v0, c, 0.0, t_w)
                vn = float(v1 @ nrm)
                if vn >= 0:
                    continue  # it would not reach the wall moving towards it
                v1 = v1 - (1 + a.e) * vn * nrm
                for j in others:
                    for f_a in (0.5, 0.8):
                        t_a = t_w + f_a * (T - t_w)
                        ub = u.copy()
                        a.push(ub, k, m, c, v1, a.body_aim(i, j, t_a), t_w, t_a)
                        out.append(((f"bounce {name}>{w.name}>{geo.bodies[j].name}",), ub))
    # several actuated discs: one strikes a disc, then another strikes it
    for k1, i1 in enumerate(act):
        for k2, i2 in enumerate(act):
            if i1 == i2:
                continue
            for j in (j for j in range(n) if j not in (i1, i2)):
                for f1, f2 in ((0.4, 0.6), (0.5, 0.7), (0.6, 0.8), (0.5, 0.55)):
                    u = zero.copy()
                    for k, i, f in ((k1, i1, f1), (k2, i2, f2)):
                        p, v = a.state(0.0, i)
                        a.push(u, k, geo.bodies[i].mass, p, v, a.body_aim(i, j, f * T), 0.0, f * T)
                    names = (geo.bodies[i1].name, geo.bodies[i2].name, geo.bodies[j].name)
                    out.append((("pair {}+{}>{}".format(*names),), u))
    return out


def diverse_starts(
    ocp: HybridOCP,
    count: int,
    *,
    seed: int | None = 0,
    evaluation: Any = None,
    structured: float = 0.75,
) -> np.ndarray:
    """``count`` starting controls ``(count, N, nu)``: the guess first, then the
    :func:`diverse_controls` (a ``structured`` share of the starts), taken in turn from each
    kind (each actuated disc, each aim, bounce-first, pairs) so that every kind is
    represented before any is repeated, then perturbations of the guess and random smooth
    controls. Generic problems: :func:`starting_controls`. Deterministic for a ``seed``."""
    found = diverse_controls(ocp, evaluation)
    if not found:
        return starting_controls(ocp, count, seed=seed)
    rng = np.random.default_rng(seed)
    u0 = np.array(ocp.u_guess, dtype=float)
    N, nu = u0.shape
    scale = _control_scale(ocp)
    groups: dict[tuple[str, ...], list[np.ndarray]] = {}
    for kind, u in found:
        groups.setdefault(kind, []).append(u)
    queues = [[g[int(x)] for x in rng.permutation(len(g))] for g in groups.values()]
    order = [queues[int(x)] for x in rng.permutation(len(queues))]
    picked: list[np.ndarray] = []
    want = max(int(round(structured * (count - 1))), 0)
    while len(picked) < want and any(order):
        for q in order:
            if q and len(picked) < want:
                picked.append(q.pop(0))
    pool = [u0] + [u + 0.02 * scale * smooth_noise(rng, N, nu) for u in picked]
    k = 0
    while len(pool) < count:
        if k % 2 == 0:
            pool.append(u0 + 0.3 * scale * smooth_noise(rng, N, nu))
        else:
            pool.append(scale * smooth_noise(rng, N, nu))
        k += 1
    return _stacked(ocp, pool, count)
