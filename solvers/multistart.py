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

from collections.abc import Callable
from typing import Any

import numpy as np

from hybridoc.ocp import HybridOCP
from hybridoc.problems.disc_ocp import DiscOCP

__all__ = [
    "EXPLORE_SMOOTHING",
    "batched_lbfgs",
    "exploration_loss",
    "explore",
    "resample",
    "smooth_noise",
    "starting_controls",
]

EXPLORE_SMOOTHING = 1e-3
"""Weight of the smoothness penalty in the first stage of :func:`explore`."""


def smooth_noise(rng: np.random.Generator, N: int, nu: int, modes: int = 4) -> np.ndarray:
    """A random smooth control shape on N cells (a few cosine modes), unit scale."""
    t = (np.arange(N) + 0.5) / N
    out = np.zeros((N, nu))
    for k in range(modes):
        out += rng.standard_normal(nu)[None, :] * np.cos(np.pi * k * t)[:, None] / (1 + k)
    return out


def _control_scale(ocp: HybridOCP) -> float:
    u0 = np.asarray(ocp.u_guess, dtype=float)
    scale = float(np.abs(u0).max(initial=0.0))
    if ocp.has_bounds:
        finite = np.concatenate([np.abs(ocp.u_min), np.abs(ocp.u_max)])
        finite = finite[np.isfinite(finite)]
        if finite.size:
            scale = max(scale, 0.5 * float(finite.max()))
    return scale if scale > 0 else 1.0


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

    if not isinstance(ocp, DiscOCP):
        return []
    scene = ocp.scene
    try:
        ev = evaluate(ocp)
    except HybridocError:
        return []
    T, N = ocp.horizon, ocp.steps
    n = scene.n_discs
    u0 = np.array(ocp.u_guess, dtype=float)
    grid = ocp.time_grid()
    fracs = np.array([0.3, 0.5, 0.7, 0.85])
    starts = [0.0] + sorted({float(e.time) for e in ev.events if e.time < 0.8 * T})
    out = []
    for t_s in starts:
        s_start = ev.sample([t_s])[0]
        n_s = min(int(np.searchsorted(grid, t_s, side="right")) - 1, N - 1) if t_s > 0 else 0
        for k, i in enumerate(scene.actuated_indices):
            d = scene.discs[i]
            p = s_start[2 * i : 2 * i + 2]
            v = s_start[2 * n + 2 * i : 2 * n + 2 * i + 2]
            for t_a in t_s + fracs * (T - t_s):
                aims = [ev.sample([t_a])[0][2 * j : 2 * j + 2] for j in range(n) if j != i]
                for wall in scene.walls:
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
    U = np.stack(pool[:count])
    if ocp.has_bounds:
        U = np.clip(U, ocp.u_min, ocp.u_max)
    return U


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


def batched_lbfgs(
    value_and_grad: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]],
    U0: np.ndarray,
    *,
    iters: int = 100,
    history: int = 20,
    lower: np.ndarray | None = None,
    upper: np.ndarray | None = None,
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

    Returns
    -------
    X, values, evaluations
        The final points, their values and the number of batched calls.
    """
    shape = U0.shape
    B = shape[0]
    X = U0.reshape(B, -1).astype(float).copy()

    def vg(Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        v, g = value_and_grad(Y.reshape(shape))
        return np.asarray(v, dtype=float), np.asarray(g, dtype=float).reshape(B, -1)

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
        d = _direction(g, S, Yh)
        slope = np.einsum("bi,bi->b", d, g)
        step = np.ones(B)
        accepted = np.zeros(B, dtype=bool)
        Xn, fn, gn = X.copy(), f.copy(), g.copy()
        for _ls in range(10):  # one batch, one pace: a failing start retries next iteration
            trial = project(X + step[:, None] * d)
            ft, gt = vg(trial)
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
    the same function)."""
    from hybridoc.solvers.compiled import CompiledLoss
    from hybridoc.solvers.contacts import contact_model

    integrator = "exact" if isinstance(coarse, DiscOCP) else None
    return CompiledLoss(coarse, contact_model("direct", toi="both"), integrator=integrator)


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

    Returns
    -------
    list of dict
        ``[{"controls", "cost", "sequence", "evaluation"}]`` sorted by cost (failed
        evaluations dropped).
    """
    N = ocp.steps
    coarse = ocp if steps is None or steps >= N else ocp.replace(steps=int(steps))
    loss = (loss_for or exploration_loss)(coarse)
    U0 = resample(starting_controls(ocp, count, seed=seed), coarse.steps)

    def make_vg(mu: float) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
        # mu: the control-smoothness penalty that weakens the kinks of the loss (an event
        # crossing a grid time), as in solve_gd's continuation
        def vg(U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            J, gU, _ = loss.value_and_grad_batch(U)
            if mu:
                d = U[:, 1:] - U[:, :-1]
                J = J + mu * (d**2).sum(axis=(1, 2)) / coarse.dt
                gU = gU.copy()
                gU[:, 1:] += 2 * mu * d / coarse.dt
                gU[:, :-1] -= 2 * mu * d / coarse.dt
            return J / coarse.dt, gU / coarse.dt

        return vg

    lower = upper = None
    if ocp.has_bounds:
        lower, upper = ocp.u_min, ocp.u_max
    X, f, _ = batched_lbfgs(make_vg(EXPLORE_SMOOTHING), U0, iters=iters, lower=lower, upper=upper)
    X, f, _ = batched_lbfgs(make_vg(0.0), X, iters=max(iters // 2, 1), lower=lower, upper=upper)
    picked = _distinct(f, judge)
    out, rows = _judged(ocp, X, f, picked, coarse.dt)
    if report is not None:
        report.extend(rows)
    out.sort(key=lambda r: r["cost"])
    return out


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
    ocp: HybridOCP, X: np.ndarray, f: np.ndarray, picked: list[int], dt: float
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The picked results resampled to the problem's grid and judged, and one report row
    per start (:func:`explore`)."""
    from hybridoc.errors import HybridocError
    from hybridoc.evaluator import evaluate

    out = []
    rows: list[dict[str, Any]] = [
        # f is scaled by 1 / dt for the optimiser: the rows carry the discrete loss itself
        {"start": b, "loss": float(f[b]) * dt if np.isfinite(f[b]) else None}
        for b in range(len(f))
    ]
    for b in picked:
        u = resample(X[b], ocp.steps)
        try:
            ev = evaluate(ocp, u)
        except HybridocError as exc:
            rows[b]["error"] = str(exc)
            continue
        rows[b].update(cost=ev.cost, sequence=ev.sequence)
        out.append({"controls": u, "cost": ev.cost, "sequence": ev.sequence, "evaluation": ev})
    for b, row in enumerate(rows):
        if "cost" in row or "error" in row:
            continue
        if row["loss"] is None:
            row["error"] = "the descent diverged"
        else:
            same = [c for c in picked if _same(f, b, c)]
            row["same_as" if same else "not_judged"] = same[0] if same else True
    return out, rows
