"""Taking a converged descent past the kinks of the loss: the events near grid times
(:func:`pinned_events`) and the nonsmooth BFGS with its stationarity certificate
(:func:`past_kinks`)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc import tolerances
from hybridoc.evaluator import evaluate
from hybridoc.ocp import HybridOCP
from hybridoc.progress import Progress
from hybridoc.solvers.gd.options import GDOptions

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.evaluation import Evaluation
    from hybridoc.solvers.gd.descent import Run


KINK_BAND = 0.1
"""An event within this fraction of a step of a grid time (not 0 or ``T``) sits at or
near a kink of the loss (:func:`past_kinks`)."""


KINK_ITERS = 1000
"""The most iterations of the nonsmooth BFGS that takes a descent past a kink."""


KINK_GTOL = tolerances.value("kink")
"""A point at a kink is stationary when the smallest convex combination of the gradients
around it (:attr:`~hybridoc.solvers.optimizers.NonsmoothResult.stationarity`, of the loss
per step ``J / dt``) times ``1 + max |u|`` is at most this times ``1 + |J / dt|``: no
direction lowers the loss by more than about this, relative, per unit change of the
controls."""


KINK_MAX_SIZE = 2000
"""The nonsmooth BFGS keeps a dense ``n x n`` inverse Hessian (``n = N nu``): above this
size gd reports a kink without going past it."""


def kinks_apply(ocp: HybridOCP, opts: GDOptions) -> bool:
    """Whether gd looks for kinks after a converged descent: the exact integrator (the
    judge's event times are the simulation's), unbounded controls, no callback (the
    nonsmooth iterations do not report to it)."""
    return opts.integrator == "exact" and not ocp.has_bounds and opts.callback is None


def pinned_events(ocp: HybridOCP, ev: Evaluation, band: float = KINK_BAND) -> list[dict[str, Any]]:
    """The events of an evaluation within ``band`` of a step of an inner grid time
    ``t_k = k T / N``, ``0 < k < N``, where the piecewise-constant control jumps and the loss
    has a kink: ``{"event", "name", "time", "grid_index", "grid_time", "offset"}`` each
    (``event`` counts from 1, ``offset`` is ``(time - t_k) / dt``)."""
    dt = ocp.dt
    out = []
    for i, e in enumerate(ev.events):
        k = round(e.time / dt)
        offset = e.time / dt - k
        if 0 < k < ocp.steps and abs(offset) <= band:
            out.append({
                "event": i + 1, "name": e.name or str(e.guard), "time": e.time,
                "grid_index": int(k), "grid_time": k * dt, "offset": float(offset),
            })  # fmt: skip
    return out


def past_kinks(
    ocp: HybridOCP,
    run: Run,
    u: np.ndarray,
    loss: float,
    ev: Evaluation,
    progress: Progress,
) -> tuple[np.ndarray, float, Evaluation, dict[str, Any] | None]:
    """Take a converged descent past the kinks of its loss.

    L-BFGS stalls where an event time crosses a grid time (the loss is continuous there but
    its gradient jumps), short of the kink or on it. When an event is within
    :data:`KINK_BAND` of a step of a grid time, the nonsmooth BFGS
    (:func:`~hybridoc.solvers.optimizers.nonsmooth_bfgs`) continues from the result: it
    converges onto the kink where the optimum of the grid sits on one, and moves on where
    it does not. Its certificate, the smallest convex combination of the gradients at its
    last iterates, decides: stationary (:data:`KINK_GTOL`), or stalled at a kink.

    Returns the controls, their loss and evaluation, and ``None`` (no event near a grid
    time) or the record ``info["kinks"]``: the events near grid times before and after,
    the iterations, evaluations, the certificate, ``stalled`` and the status message.
    """
    from hybridoc.solvers.optimizers import nonsmooth_bfgs

    near = pinned_events(ocp, ev)
    if not near:
        return u, loss, ev, None
    record: dict[str, Any] = {"before": near, "loss_before": float(loss), "iterations": 0}
    scale = 1.0 / (run.jc * run.dts)  # the objective L-BFGS sees, (J / jc) / dt~
    run.scale = scale
    x = run.scaled(u)  # scaled controls: the certificate is the same in any units
    f_here, g_here = run.fun(x)
    here = float(np.linalg.norm(g_here)) * (1.0 + float(np.abs(x).max())) / (1.0 + abs(f_here))
    if here <= KINK_GTOL:  # stationary where it stands: the loss is smooth there
        record.update(after=near, loss=float(loss), stationarity=here, stalled=False, message="")
        return u, loss, ev, record
    if u.size > KINK_MAX_SIZE:
        relative = here
        record["message_bfgs"] = f"not run: {u.size} controls, above {KINK_MAX_SIZE}"
    else:
        progress.stage(f"past the kinks: event {near[0]['event']} near grid time "
                       f"t_{near[0]['grid_index']}")  # fmt: skip
        res = nonsmooth_bfgs(run.fun, x, max_iter=KINK_ITERS, gtol=KINK_GTOL,
                             start=(f_here, g_here))  # fmt: skip
        record.update(iterations=res.iterations, evaluations=res.evaluations,
                      message_bfgs=res.message, bundle=res.bundle)  # fmt: skip
        relative = res.stationarity
        if res.f < f_here:
            u, loss = run.physical(res.x), res.f / scale
            ev = evaluate(ocp, u)
    after = pinned_events(ocp, ev)
    stalled = not relative <= KINK_GTOL
    record.update(after=after, loss=float(loss), stationarity=float(relative), stalled=stalled)
    record["message"] = ""
    if stalled:
        pin = (after or near)[0]
        record["message"] = (
            f"stalled at a kink: event {pin['event']} ({pin['name']!r}, t = {pin['time']:.10g}) "
            f"pinned at grid time t_{pin['grid_index']} = {pin['grid_time']:.10g} (off by "
            f"{pin['offset']:+.2e} of a step), where the loss is not smooth; the gradients "
            f"around it do not cancel (stationarity {relative:.2e} > {KINK_GTOL:g})"
        )
    return u, loss, ev, record
