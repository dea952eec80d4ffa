"""Diverse starting controls and a batched L-BFGS: gradient descent from many starts at once.

:func:`starting_controls` builds ``K`` initial controls that reach different event
sequences: the problem's guess, smooth perturbations of it, random smooth controls, and (disc
scenes) constant forces that aim each actuated disc at each other disc and at each wall.
:func:`batched_lbfgs` minimises a batch of controls together: every iteration is one call of
the compiled loss mapped over the batch
(:meth:`~hybridoc.solvers.compiled.CompiledLoss.value_and_grad_batch`), not a Python loop
over starts; each start keeps its own curvature
pairs and its own backtracking step.
"""

from __future__ import annotations

import time
import weakref
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.ocp import HybridOCP, Structure
from hybridoc.problems import scene_of

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.capabilities import Geometry

__all__ = [
    "EXPLORE_SMOOTHING",
    "SWITCH_MIN_SAVING",
    "batched_lbfgs",
    "cached_exploration_loss",
    "distinct_basins",
    "diverse_controls",
    "diverse_starts",
    "exploration_loss",
    "explore",
    "mode_slots",
    "mode_switch",
    "resample",
    "smooth_noise",
    "starting_controls",
]

EXPLORE_SMOOTHING = 1e-3
"""Weight of the smoothness penalty in the first stage of :func:`explore`."""


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
    return scale if scale > 0 else float(_units(ocp)[0].max())


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


def resample(u: np.ndarray, steps: int) -> np.ndarray:
    """Piecewise-constant controls ``(..., N, nu)`` on ``steps`` equal cells (midpoint rule)."""
    N = u.shape[-2]
    idx = np.minimum(((np.arange(steps) + 0.5) / steps * N).astype(int), N - 1)
    return u[..., idx, :]


def _direction(g: np.ndarray, S: list[np.ndarray], Yh: list[np.ndarray]) -> np.ndarray:
    """The L-BFGS search direction of every start (:func:`batched_lbfgs`): the two-loop
    recursion over the curvature pairs ``S``, ``Yh``, batched over starts; normalised
    steepest descent where that is not a descent direction."""
    q = g.copy()
    alphas = []
    for s, y in zip(reversed(S), reversed(Yh), strict=True):
        ys = np.einsum("bi,bi->b", y, s)
        rho = np.where(ys > 0, 1.0 / np.where(ys > 0, ys, 1.0), 0.0)
        a = rho * np.einsum("bi,bi->b", s, q)
        q -= a[:, None] * y
        alphas.append((a, rho))
    gamma = 1.0 / np.maximum(np.linalg.norm(g, axis=1), 1e-300)
    if S:
        s, y = S[-1], Yh[-1]
        ys, yy = np.einsum("bi,bi->b", s, y), np.einsum("bi,bi->b", y, y)
        gamma = np.where(ys > 0, ys / np.where(yy > 0, yy, 1.0), gamma)
    r = gamma[:, None] * q
    for (a, rho), s, y in zip(reversed(alphas), S, Yh, strict=True):
        b = rho * np.einsum("bi,bi->b", y, r)
        r += (a - b)[:, None] * s
    d = -r
    slope = np.einsum("bi,bi->b", d, g)
    bad = ~(slope < 0) | ~np.isfinite(slope)
    d[bad] = -g[bad] / np.maximum(np.linalg.norm(g[bad], axis=1), 1e-300)[:, None]
    return d


class _Batch:
    """The evaluations of :func:`batched_lbfgs`: at every start (:meth:`all`), or at some
    (:meth:`at`, by ``some`` where that is cheaper), flat ``(B, n)``."""

    def __init__(
        self,
        value_and_grad: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
        shape: tuple[int, ...],
        some: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None,
    ) -> None:
        self.value_and_grad, self.shape, self.some = value_and_grad, shape, some
        self.B = shape[0]
        # the latest seconds of a batched call and of ``some`` per start: where ``some`` runs
        # in CasADi's virtual machine while the batch is compiled C (the first run of a
        # problem), one start costs as much as the whole batch, and the batch is called
        # instead (the choice moves no iterate: both give the same numbers)
        self.took = {"batch": 0.0, "one": 0.0}

    def all(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Values and gradients at every row of ``Y``."""
        v, g = self.value_and_grad(Y.reshape(self.shape))
        return np.asarray(v, dtype=float), np.asarray(g, dtype=float).reshape(self.B, -1)

    def at(self, Y: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Values and gradients at the ``rows`` of ``Y`` (elsewhere NaN and zero)."""
        some, took, B, shape = self.some, self.took, self.B, self.shape
        n = int(rows.sum())
        if (
            some is None
            or not 0 < n <= B // 2
            or n * took["one"] > took["batch"]
            or not np.isfinite(Y[rows]).all()
        ):
            t0 = time.perf_counter()
            out = self.all(Y)
            took["batch"] = time.perf_counter() - t0
            return out
        t0 = time.perf_counter()
        v, g = some(Y[rows].reshape(n, *shape[1:]))
        took["one"] = (time.perf_counter() - t0) / n
        v_all, g_all = np.full(B, np.nan), np.zeros_like(Y)
        v_all[rows] = np.asarray(v, dtype=float)
        g_all[rows] = np.asarray(g, dtype=float).reshape(n, -1)
        return v_all, g_all


def batched_lbfgs(
    value_and_grad: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    U0: np.ndarray,
    *,
    iters: int = 100,
    history: int = 20,
    lower: np.ndarray | None = None,
    upper: np.ndarray | None = None,
    deadline: float | None = None,
    some: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """L-BFGS with backtracking on a batch of starts, one batched call per trial point.

    Parameters
    ----------
    value_and_grad
        ``(B, n...) -> (values (B,), gradients (B, n...))``.
    U0
        Starting points ``(B, ...)``.
    iters
        Iterations.
    history
        Curvature pairs kept per start.
    lower, upper
        Optional bounds (projected after every step).
    deadline
        A :func:`time.perf_counter` time after which no further iteration starts (the
        points reached so far are returned).
    some
        The same function as ``value_and_grad`` for a few of the starts, ``(b, n...) ->
        (values (b,), gradients (b, n...))``, row for row bit for bit. Where given, a trial
        point at which at most half the starts still search (the others accepted their step,
        converged or stopped) is evaluated at those starts only, unless ``some`` took
        longer for that many starts than the latest batched call for all (measured as it
        runs): on pendulum-wall and the two tanks about half the batched calls of the
        descent were backtracking steps of one or two starts, whose batch evaluated every
        start and used one or two values. The iterates are the same either way.

    Returns
    -------
    X, values, evaluations
        The final points, their values and the number of calls (batched or of ``some``).
    """
    shape = U0.shape
    B = shape[0]
    X = U0.reshape(B, -1).astype(float).copy()
    batch = _Batch(value_and_grad, shape, some)
    vg, vg_at = batch.all, batch.at

    def project(Y: np.ndarray) -> np.ndarray:
        if lower is None and upper is None:
            return Y
        lo = -np.inf if lower is None else np.broadcast_to(lower, shape[1:]).ravel()
        hi = np.inf if upper is None else np.broadcast_to(upper, shape[1:]).ravel()
        return np.clip(Y, lo, hi)

    f, g = vg(X)
    calls = 1
    S: list[np.ndarray] = []
    Yh: list[np.ndarray] = []
    active = np.isfinite(f)
    failures = np.zeros(B, dtype=int)
    for _ in range(iters):
        if deadline is not None and time.perf_counter() > deadline:
            break
        d = _direction(g, S, Yh)
        slope = np.einsum("bi,bi->b", d, g)
        step = np.ones(B)
        accepted = np.zeros(B, dtype=bool)
        Xn, fn, gn = X.copy(), f.copy(), g.copy()
        for _ls in range(10):  # one batch, one pace: a failing start retries next iteration
            trial = project(X + step[:, None] * d)
            ft, gt = vg_at(trial, active & ~accepted)
            calls += 1
            ok = np.isfinite(ft) & (ft <= f + 1e-4 * step * slope) & ~accepted & active
            Xn[ok], fn[ok], gn[ok] = trial[ok], ft[ok], gt[ok]
            accepted |= ok
            pending = active & ~accepted
            if not pending.any():
                break
            step[pending] *= 0.5
        s_new = Xn - X
        y_new = gn - g
        keep = np.einsum("bi,bi->b", s_new, y_new) > 1e-12 * np.maximum(
            np.einsum("bi,bi->b", s_new, s_new), 1e-300
        )
        s_new[~keep] = 0.0  # no curvature pair for these starts this time (rho = 0)
        y_new[~keep] = 0.0
        S.append(s_new)
        Yh.append(y_new)
        if len(S) > history:
            S.pop(0)
            Yh.pop(0)
        converged = accepted & (np.abs(f - fn) <= 1e-15 * np.maximum(np.abs(f), 1.0))
        X, f, g = Xn, fn, gn
        # a failed line search (a kink of the loss spoils the quasi-Newton model): forget
        # that start's curvature pairs and try again from steepest descent; stop it after
        # three failures in a row
        failed = active & ~accepted
        failures = np.where(failed, failures + 1, 0)
        for s_old, y_old in zip(S, Yh, strict=True):
            s_old[failed] = 0.0
            y_old[failed] = 0.0
        active &= ~converged & (failures < 3)
        if not active.any():
            break
    return X.reshape(shape), f, calls


def exploration_loss(coarse: HybridOCP) -> Any:
    """The loss :func:`explore` descends by default: the compiled exact simulation of
    contact ``direct`` with TOI ``both`` (disc scenes), or the generic time-of-impact
    simulation, with the default path-constraint weight (a new
    :class:`~hybridoc.solvers.compiled.CompiledLoss`; gradient descent passes its cached one,
    the same function). A problem with modes is simulated through :func:`mode_slots`: the
    same step in fewer operations."""
    from hybridoc.solvers.compiled import CompiledLoss
    from hybridoc.solvers.contacts import contact_model

    integrator = "exact" if scene_of(coarse) is not None else None
    return CompiledLoss(
        mode_switch(mode_slots(coarse)), contact_model("direct", toi="both"), integrator=integrator
    )


SWITCH_MIN_SAVING = 64
"""Operations of the flow map that :func:`mode_switch`'s branches must save on average for
the switch to be used: below, the MX step's calls cost more than they save. Measured per
step (value and gradient, 80 steps, 16 starts, load 5-6): two-tanks (4 modes, 148 operations,
branches 19-57: 109 saved) virtual machine 171 -> 146 us, compiled C 82 -> 11 us; the hopper
(2 modes, 54 operations, branches 22 and 34: 26 saved) 27 -> 56 us and 2.8 -> 3.3 us."""

_LOSSES: weakref.WeakKeyDictionary[Structure, dict[tuple[Any, ...], Any]] = (
    weakref.WeakKeyDictionary()
)


def cached_exploration_loss(coarse: HybridOCP) -> Any:
    """:func:`exploration_loss`, built once per problem structure, grid, horizon and initial
    state and kept (weakly, per :class:`~hybridoc.ocp.Structure`): the reference's
    multi-start source asks for it on every solve (datasets solve one draw after another)."""
    from hybridoc.solvers.compiled import per_structure

    key = (coarse.steps, coarse.horizon, tuple(coarse.x0.tolist()))
    return per_structure(_LOSSES, coarse, key, lambda: exploration_loss(coarse))


def mode_slots(ocp: HybridOCP) -> HybridOCP:
    """The same problem with one guard per *slot* instead of one per transition, or ``ocp``.

    In a problem with modes (:meth:`~hybridoc.HybridOCP.from_modes`) a transition's guard is
    a constant (no crossing) outside its source mode, yet the time-of-impact step
    (:func:`~hybridoc.solvers.toi_sim.toi_step`) locates every guard's event, by Newton's
    method through the flow map, in every step. Slot ``k`` is the ``k``-th transition out of
    the current mode (selected by the mode index, the last state coordinate; the masked
    constant where the mode has fewer), so a step locates as many events as the busiest mode
    has transitions: two for the two tanks instead of seven (17461 -> 8145 operations per
    step). The step is the same function: the same guard fires at the same located time (the
    transitions of a mode keep their order, so ties break alike) with the same reset, and
    ``if_else`` passes its branch's value unchanged, so the loss is bit for bit that of
    ``ocp``; so is its gradient on the two tanks, while on the hopper the adjoint adds a few
    terms in another order (an ulp here and there; tests/test_candidates.py). ``ocp``
    itself where it has no
    modes, where slots would not save a guard, or where a guard is not constant outside its
    source mode."""
    import casadi as ca

    from hybridoc.ocp import Guard

    modes, guards = ocp.modes, ocp.guards
    if modes is None or not guards or any(g.source not in modes for g in guards):
        return ocp
    out = {m: [g for g in guards if g.source == m] for m in modes}
    K = max(len(v) for v in out.values())
    if K >= len(guards):
        return ocp
    x, u = ca.SX.sym("x", ocp.nx), ca.SX.sym("u", ocp.nu)
    q = x[ocp.nx - 1]
    masked: set[float] = set()
    for g in guards:
        for fn in (g.psi, g.detector or g.psi):
            expr = fn(x)
            for k, m in enumerate(modes):
                if m == g.source:
                    continue
                other = ca.substitute(expr, q, ca.SX(float(k)))
                if not other.is_constant():
                    return ocp  # a guard that is not masked outside its mode
                masked.add(float(ca.evalf(other)))
    if len(masked) != 1:
        return ocp
    rest = masked.pop()
    slots = []
    for k in range(K):
        psi, det, after = ca.SX(rest), ca.SX(rest), x
        for m, gs in out.items():
            if len(gs) <= k:
                continue
            g = gs[k]
            here = ca.fabs(q - modes.index(m)) < 0.5
            psi = ca.if_else(here, g.psi(x), psi)
            det = ca.if_else(here, (g.detector or g.psi)(x), det)
            after = ca.if_else(here, g.reset_at(x, u), after)
        slots.append(
            Guard(
                f"slot{k}",
                ca.Function(f"psi_slot{k}", [x], [psi]),
                ca.Function(f"g_slot{k}", [x, u], [after]),
                detector=ca.Function(f"det_slot{k}", [x], [det]),
            )
        )
    return ocp.replace(guards=slots)


def mode_switch(ocp: HybridOCP, min_saving: int = SWITCH_MIN_SAVING) -> HybridOCP:
    """The same problem with its closed-form flow map as a switch over the modes, or ``ocp``.

    The flow map of :meth:`~hybridoc.HybridOCP.from_modes` computes every mode's flow and
    selects the current one (SX ``if_else`` evaluates both of its branches), and the
    time-of-impact step (:func:`~hybridoc.solvers.toi_sim.toi_step`) evaluates it about 30
    times per step (the Newton iterations on each event time). Here each mode's flow is the
    flow map with the mode index fixed (the selection folds away), and the flow map is an
    MX function that calls only the current mode's branch (``casadi.Function.conditional``,
    index ``floor(q + 1/2)`` clipped to the modes: the same mode as the selection's
    ``q < k + 1/2``); the step is then built in MX around its calls. Each branch does the
    same floating-point operations as the selected branch of the SX map, so the flow's
    values are bit for bit the same. ``ocp`` itself where it has no modes or no closed-form
    SX flow map, where the mode index is not the flow's last output, or where a branch saves
    on average fewer than ``min_saving`` operations of the whole map
    (:data:`SWITCH_MIN_SAVING`).
    """
    import casadi as ca

    fm, modes = ocp.flow_map, ocp.modes
    if modes is None or not ocp.has_closed_form_flow or fm is None or not fm.is_a("SXFunction"):
        return ocp
    nx = ocp.nx
    x, u, h = ca.SX.sym("x", nx), ca.SX.sym("u", ocp.nu), ca.SX.sym("h")
    q = x[nx - 1]
    end, cost = fm(x, u, h)
    if not ca.is_equal(end[nx - 1], q):
        return ocp
    branches = []
    for k in range(len(modes)):
        fixed = ca.SX(float(k))
        # the mode index passes through as it is (its derivative stays 1, as in fm)
        body = ca.substitute(ca.vertcat(end[: nx - 1], cost), q, fixed)
        branches.append(
            ca.Function(f"flow_mode{k}", [x, u, h], [ca.vertcat(body[: nx - 1], q), body[nx - 1]])
        )
    whole = ca.Function("whole", [x, u, h], [end, cost]).n_instructions()
    mean = sum(b.n_instructions() for b in branches) / len(branches)
    if whole - mean < min_saving:
        return ocp
    switch = ca.Function.conditional("flow_by_mode", branches[:-1], branches[-1])
    xm, um, hm = ca.MX.sym("x", nx), ca.MX.sym("u", ocp.nu), ca.MX.sym("h")
    index = ca.fmin(ca.fmax(ca.floor(xm[nx - 1] + 0.5), 0.0), float(len(modes) - 1))
    s_end, c_end = switch(index, xm, um, hm)
    flow = ca.Function("flow_map", [xm, um, hm], [s_end, c_end], ["s", "u", "h"], ["s_end", "cost"])
    return ocp.replace(flow_map=flow)


def explore(
    ocp: HybridOCP,
    count: int,
    *,
    seed: int | None = 0,
    steps: int | None = None,
    iters: int = 60,
    judge: int | None = None,
    report: list[dict[str, Any]] | None = None,
    loss_for: Callable[[HybridOCP], Any] | None = None,
    starts: np.ndarray | None = None,
    deadline: float | None = None,
    repeats: int | None = None,
) -> list[dict[str, Any]]:
    """Batched descent from ``count`` diverse starts on a coarse grid, the best judged.

    Parameters
    ----------
    ocp
        The problem.
    count
        The number of starts (:func:`starting_controls`).
    seed
        Seed of the random starts.
    steps
        The coarse grid (default: the problem's).
    iters
        Iterations of the batched L-BFGS (a smoothed stage, then ``iters // 2`` plain).
    judge
        How many of the best distinct results (by discrete loss) are judged at the
        problem's resolution; default all.
    report
        A list that receives one row per start, in start order: its coarse ``loss`` and,
        where it was judged, ``cost`` and ``sequence``, else ``same_as`` (the start that
        reached the same optimum) or the reason it was not.
    loss_for
        ``loss_for(coarse_ocp)``: the loss object to descend, with ``value_and_grad_batch``;
        default :func:`exploration_loss`.
    starts
        The starting controls ``(B, N, nu)`` on the problem's grid (``count`` is then
        ignored); default :func:`starting_controls`.
    deadline
        A :func:`time.perf_counter` time after which the descent stops where it is and no
        further result is judged (the best one always is): a partial result.
    repeats
        Stop judging after this many results in a row (in the order of their coarse loss)
        brought no event sequence the judge had not seen yet; default: judge ``judge``
        results. One evaluation of a problem whose flow is integrated (CVODES) costs about
        90 ms, and the distinct losses of such problems are mostly the same sequence at
        almost the same cost (pendulum-wall, the hopper, the bouncing balls: four judged,
        one sequence).

    Returns
    -------
    list of dict
        ``[{"controls", "cost", "sequence", "evaluation"}]`` sorted by cost (failed
        evaluations dropped).
    """
    N = ocp.steps
    coarse = ocp if steps is None or steps >= N else ocp.replace(steps=int(steps))
    loss = (loss_for or exploration_loss)(coarse)
    if starts is None:
        starts = starting_controls(ocp, count, seed=seed)
    # the batched L-BFGS runs in scaled controls u / cs on the loss (J / jc) / dt~ (the
    # units of gd, hybridoc.scales.optimizer_units): the same descent in any units
    cs, jc, tc = _units(ocp)
    per = jc * (coarse.dt / tc)
    U0 = resample(np.asarray(starts, dtype=float), coarse.steps) / cs

    def make_vg(
        mu: float, one: bool = False
    ) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
        # mu: the control-smoothness penalty that weakens the kinks of the loss (an event
        # crossing a grid time), as in solve_gd's continuation; one: start by start through
        # the loss's own compiled function (a few starts: batched_lbfgs's ``some``)
        def vg(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            U = X * cs
            if one:
                rows = [loss.value_and_grad(u) for u in U]
                J, gU = np.array([r[0] for r in rows]), np.stack([r[1] for r in rows])
            else:
                J, gU, _ = loss.value_and_grad_batch(U)
            gU = gU * cs
            if mu:
                d = X[:, 1:] - X[:, :-1]
                J = J + mu * jc * (d**2).sum(axis=(1, 2)) / (coarse.dt / tc)
                gU = gU.copy()
                gU[:, 1:] += 2 * mu * jc * d / (coarse.dt / tc)
                gU[:, :-1] -= 2 * mu * jc * d / (coarse.dt / tc)
            return J / per, gU / per

        return vg

    lower = upper = None
    if ocp.has_bounds:
        lower, upper = ocp.u_min / cs, ocp.u_max / cs
    single = hasattr(loss, "value_and_grad")
    X, f, _ = batched_lbfgs(
        make_vg(EXPLORE_SMOOTHING), U0, iters=iters, lower=lower, upper=upper, deadline=deadline,
        some=make_vg(EXPLORE_SMOOTHING, one=True) if single else None,
    )  # fmt: skip
    X, f, _ = batched_lbfgs(
        make_vg(0.0), X, iters=max(iters // 2, 1), lower=lower, upper=upper, deadline=deadline,
        some=make_vg(0.0, one=True) if single else None,
    )  # fmt: skip
    X = X * cs  # back in the problem's units (f is the scaled loss per scaled step, J / per)
    picked = _distinct(f, judge)
    out, rows = _judged(ocp, X, f, picked, per, deadline, repeats)
    if report is not None:
        report.extend(rows)
    out.sort(key=lambda r: r["cost"])
    return out


def _units(ocp: HybridOCP) -> tuple[np.ndarray, float, float]:
    """:func:`hybridoc.scales.optimizer_units` (the control, cost and time scales)."""
    from hybridoc.scales import optimizer_units

    return optimizer_units(ocp)


def _same(f: np.ndarray, b: int, c: int) -> bool:
    """Starts ``b`` and ``c`` reached the same local optimum (equal losses to 1e-9)."""
    return bool(abs(f[b] - f[c]) <= 1e-9 * max(abs(f[c]), 1.0))


def _distinct(f: np.ndarray, judge: int | None) -> list[int]:
    """The starts with distinct final losses, lowest first, at most ``judge`` of them."""
    order = [int(b) for b in np.argsort(np.where(np.isfinite(f), f, np.inf))]
    picked: list[int] = []
    for b in order:
        if any(_same(f, b, c) for c in picked):
            continue  # the same local optimum again
        picked.append(b)
        if judge is not None and len(picked) >= judge:
            break
    return picked


def _judged(
    ocp: HybridOCP,
    X: np.ndarray,
    f: np.ndarray,
    picked: list[int],
    dt: float,
    deadline: float | None = None,
    repeats: int | None = None,
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The picked results resampled to the problem's grid and judged, and one report row
    per start (:func:`explore`); with ``repeats``, no more once that many in a row brought
    no new event sequence."""
    from hybridoc.errors import HybridocError
    from hybridoc.evaluator import evaluate

    out = []
    rows: list[dict[str, Any]] = [
        # f is scaled by 1 / dt (jc dt~) for the optimiser: the rows carry the discrete loss
        {"start": b, "loss": float(f[b]) * dt if np.isfinite(f[b]) else None}
        for b in range(len(f))
    ]
    sequences: set[tuple[str, ...]] = set()
    stale = 0  # judged results in a row that brought no new sequence
    for i, b in enumerate(picked):
        if i and deadline is not None and time.perf_counter() > deadline:
            rows[b]["not_judged"] = "the time budget was spent"
            continue
        if repeats is not None and stale >= repeats:
            rows[b]["not_judged"] = f"{stale} results in a row repeated a judged event sequence"
            continue
        u = resample(X[b], ocp.steps)
        try:
            ev = evaluate(ocp, u)
        except HybridocError as exc:
            rows[b]["error"] = str(exc)
            continue
        key = tuple(ev.sequence)
        stale = stale + 1 if key in sequences else 0
        sequences.add(key)
        rows[b].update(cost=ev.cost, sequence=ev.sequence)
        out.append({"controls": u, "cost": ev.cost, "sequence": ev.sequence, "evaluation": ev})
    for b, row in enumerate(rows):
        if "cost" in row or "error" in row or "not_judged" in row:
            continue
        if row["loss"] is None:
            row["error"] = "the descent diverged"
        else:
            same = [c for c in picked if _same(f, b, c)]
            row["same_as" if same else "not_judged"] = same[0] if same else True
    return out, rows


def distinct_basins(found: list[dict[str, Any]], rtol: float = 0.02) -> Iterator[dict[str, Any]]:
    """The results of :func:`explore` worth refining, best first: the first of each distinct
    event sequence, while its coarse cost is within ``rtol`` of the best (the batched phase
    ranks the basins well enough)."""
    seen: set[tuple[str, ...]] = set()
    for r in found:
        key = tuple(r["sequence"])
        if key in seen:
            continue
        if seen and r["cost"] > (1 + rtol) * found[0]["cost"]:
            return
        seen.add(key)
        yield r
