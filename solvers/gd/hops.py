"""gd's hops: rounds of batched restarts around the best control (:func:`hop`), to leave a
shallow local minimum or a kink where the descent stalled."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from hybridoc.evaluator import evaluate
from hybridoc.ocp import HybridOCP
from hybridoc.progress import Progress
from hybridoc.scales import optimizer_units as units
from hybridoc.solution import Solution, Status
from hybridoc.solvers.gd.descent import Run, infeasibility
from hybridoc.solvers.gd.kinks import kinks_apply, past_kinks
from hybridoc.solvers.gd.limits import current_watch
from hybridoc.solvers.gd.options import GDOptions

HOP_BATCH = 32
"""Hops (:func:`solve_gd`): perturbations of the best control per round."""


HOP_ITERS = 150
"""Hops: iterations of the batched L-BFGS of each round."""


HOP_PATIENCE = 2
"""Hops: rounds without improvement before stopping."""


HOP_SCALES = (1e-3, 1.0)
"""Hops: smallest and largest perturbation size, relative to ``max |u|`` (geometric spread)."""


def hop(
    ocp: HybridOCP,
    base: Solution,
    loss_obj: Any,
    opts: GDOptions,
    t0: float,
    progress: Progress,
) -> Solution:
    """:func:`solve_gd` with ``hops`` (see there): batched restarts around the best control."""
    from hybridoc.solvers.multistart import batched_lbfgs, smooth_noise

    if base.info.get("nan_stop") or base.info.get("diverged"):
        return base
    # scaled controls u / cs and loss (J / jc) / dt~ (units): the same hops in any units
    cs, jc, tc = units(ocp)
    per = jc * (ocp.horizon / ocp.steps / tc)
    lower = upper = None
    if ocp.has_bounds:
        lower, upper = ocp.u_min / cs, ocp.u_max / cs

    watch = current_watch()

    def vg(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if watch is not None:
            watch.check()
        U = X * cs
        J, gU, _ = loss_obj.value_and_grad_batch(U)
        if watch is not None and len(J):
            b = int(np.argmin(np.where(np.isfinite(J), J, np.inf)))
            watch.offer(float(J[b]), U[b])
        return J / per, gU * cs / per  # the batched L-BFGS's scaling, as in the multi-start

    x = np.array(base.controls, dtype=float) / cs
    f = float(loss_obj.value_and_grad(x * cs)[0]) / jc
    rng = np.random.default_rng(opts.seed)
    rounds: list[dict[str, Any]] = []
    stale = 0
    for r in range(opts.hops):
        progress.stage(f"hops: round {r + 1} of at most {opts.hops}")
        progress.detail(f"loss {f:.6g}")
        size = max(float(np.abs(x).max()), 1e-3)
        scales = size * np.geomspace(*HOP_SCALES, HOP_BATCH)
        P = np.stack([x + sc * smooth_noise(rng, *x.shape, modes=8) for sc in scales])
        if lower is not None:
            P = np.clip(P, lower, upper)
        X, F, _ = batched_lbfgs(vg, P, iters=HOP_ITERS, lower=lower, upper=upper)
        F = np.where(np.isfinite(F), F * (per / jc), np.inf)
        k = int(np.argmin(F))
        improved = bool(F[k] < f - 1e-13 * max(abs(f), 1.0))
        rounds.append({"loss": float(F[k]), "improved": improved, "size": float(scales[k] / size)})
        if improved:
            x, f, stale = X[k], float(F[k]), 0
        else:
            stale += 1
            if stale >= HOP_PATIENCE:
                break
    x, f = x * cs, f * jc  # back in the problem's units
    for r in rounds:
        r["loss"] *= jc
    kink = None
    improved = any(r["improved"] for r in rounds)
    if improved and kinks_apply(ocp, opts):
        # the batched L-BFGS stalls at kinks as the single descent does
        run = Run(ocp, loss_obj, opts, 0.0, progress)
        x, f, _, kink = past_kinks(ocp, run, x, f, evaluate(ocp, x), progress)
    return _hopped_solution(ocp, base, x, f, rounds, stale, opts.hops, t0, kink)


def _hopped_solution(
    ocp: HybridOCP,
    base: Solution,
    x: np.ndarray,
    f: float,
    rounds: list[dict[str, Any]],
    stale: int,
    hops: int,
    t0: float,
    kink: dict[str, Any] | None = None,
) -> Solution:
    """The Solution of the hops: the best control ``x`` (loss ``f``), judged; ``kink`` the
    record of :func:`past_kinks` on it."""
    ev = evaluate(ocp, x)
    # converged: the descent met its own test, or the hops moved it and then found nothing
    # lower in HOP_PATIENCE rounds (a descent stopped at its iteration limit that no hop
    # improves has shown nothing)
    improved = any(r["improved"] for r in rounds)
    converged = bool(base.info.get("converged")) or (improved and stale >= HOP_PATIENCE)
    info = dict(
        base.info, loss=f, hops=rounds, loss_before_hops=base.info.get("loss"),
        converged=converged,
    )  # fmt: skip
    if kink is not None:
        info["kinks"] = kink
    sol = Solution.from_evaluation(
        ev,
        method="gd",
        scene=ocp.name,
        settings=dict(base.settings, hops=hops),
        timings=dict(base.timings, hop_time_s=time.perf_counter() - t0 - base.timings.get(
            "solve_time_s", 0.0), solve_time_s=time.perf_counter() - t0),
        info=info,
        arrays=dict(base.arrays),
    )  # fmt: skip
    status, message = Status.SUCCESS, ""
    if kink is not None and kink["stalled"]:
        sol.info["converged"] = False
        status, message = Status.NOT_CONVERGED, f"after the hops, {kink['message']}"
    elif not converged:
        status, message = Status.NOT_CONVERGED, (
            f"{base.message}; and the hops did not settle either" if base.message else
            "the hops did not settle"
        )  # fmt: skip
    elif not ev.feasible:
        status, message = Status.INFEASIBLE, infeasibility(ev)
    return sol.set_status(status, message)
