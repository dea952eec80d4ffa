"""Diverse starting controls and a batched L-BFGS: gradient descent from many starts at once.

:func:`starting_controls` builds ``K`` initial controls that reach different event
sequences: the problem's guess, smooth perturbations of it, random smooth controls, and
(problems with a geometry: disc scenes) constant forces that aim each actuated body at each
other body and at each plane (:mod:`hybridoc.solvers.starting`, re-exported here).
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
from typing import Any

import numpy as np

from hybridoc.ocp import HybridOCP, Structure
from hybridoc.problems import scene_of
from hybridoc.scales import optimizer_units
from hybridoc.solvers.starting import (
    diverse_controls,
    diverse_starts,
    smooth_noise,
    starting_controls,
)

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
    cs, jc, tc = optimizer_units(ocp)
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
