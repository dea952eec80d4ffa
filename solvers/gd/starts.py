"""gd's multi-start (``starts > 1``): the batched exploration of
:mod:`hybridoc.solvers.multistart` on a coarse grid, then the best distinct basins refined
by the continuation (:func:`run_multistart`)."""

from __future__ import annotations

import dataclasses
import time
from typing import Any

from hybridoc.errors import OptionError
from hybridoc.ocp import HybridOCP
from hybridoc.progress import Progress
from hybridoc.solution import Solution
from hybridoc.solvers.gd.descent import continuation
from hybridoc.solvers.gd.limits import current_watch
from hybridoc.solvers.gd.loss import exploration_loss
from hybridoc.solvers.gd.options import (
    MULTISTART_ITERS,
    MULTISTART_REFINE,
    MULTISTART_SMOOTHING,
    MULTISTART_STEPS,
    GDOptions,
    disc_simulation,
)


def run_multistart(ocp: HybridOCP, opts: GDOptions, progress: Progress) -> Solution:
    """:func:`solve_gd` with ``starts > 1`` (see its ``starts``)."""
    from hybridoc.solvers.multistart import distinct_basins, explore

    t0 = time.perf_counter()
    if disc_simulation(ocp) and opts.contact.name != "direct":
        raise OptionError(
            "the batched multi-start explores with the compiled exact simulation of contact "
            "'direct'; other contact models start from its result with --controls"
        )
    coarse = min(ocp.steps, MULTISTART_STEPS)
    rows: list[dict[str, Any]] = []
    progress.stage(f"multi-start: {opts.starts} starts on {coarse} steps")
    watch = current_watch()
    found = explore(
        ocp, opts.starts, seed=opts.seed, steps=coarse, iters=MULTISTART_ITERS, report=rows,
        loss_for=exploration_loss, deadline=None if watch is None else watch.deadline,
    )  # fmt: skip
    if watch is not None:
        for r in found:  # judged on the problem's grid: the exact loss is the judged cost
            watch.offer(float(r["cost"]), r["controls"])
        watch.check()
    t_explore = time.perf_counter() - t0
    single = dataclasses.replace(opts, starts=1)
    # the batched phase has found the basin: one light smoothing stage for the kinks
    smoothing = opts.smoothing
    if smoothing is None:
        smoothing = MULTISTART_SMOOTHING if opts.optimizer == "lbfgs" else ()
    refined: list[Solution] = []
    for r in distinct_basins(found):
        key = tuple(r["sequence"])
        progress.stage(f"multi-start: refining the basin {' '.join(key) or '(no events)'}")
        refine = dataclasses.replace(single, smoothing=smoothing)
        refined.append(continuation(ocp, refine, r["controls"], progress))
        if len(refined) >= MULTISTART_REFINE:
            break
    if not refined:
        return continuation(ocp, single, None, progress)
    best = min(refined, key=lambda s: s.cost)
    best.settings["starts"] = opts.starts
    best.settings["seed"] = opts.seed
    best.info["starts"] = rows  # every start: coarse loss, judged cost and events
    best.info["explore_steps"] = coarse
    best.info["refined"] = [{"cost": s.cost, "sequence": s.sequence} for s in refined]
    best.timings["explore_time_s"] = t_explore
    best.timings["solve_time_s"] = time.perf_counter() - t0
    return best
