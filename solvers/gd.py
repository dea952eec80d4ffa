"""Optimal control by gradient descent through a differentiable simulation.

:func:`solve_gd` minimises the discrete objective ``phi(s_N) + sum_n c_n`` over the
``N x nu`` piecewise-constant controls and measures the result with the event-exact judge:
the returned :class:`~hybridoc.solution.Solution` carries the *true* continuous cost of the
controls.

Which simulation
    Disc scenes use the disc simulator with a contact model of
    :mod:`hybridoc.solvers.contacts` (the paper's Eq. 8 objective): the compiled CasADi path
    (:class:`~hybridoc.solvers.compiled.CompiledLoss`) where the model's CasADi step serves
    the scene (every model, within limits such as the number of contacts of ``lcp`` and
    ``convex``), else the torch :class:`~hybridoc.solvers.simulator.Simulator`. Every other
    problem uses the generic time-of-impact simulation (:mod:`hybridoc.solvers.toi_sim`),
    compiled the same way.

Integrator
    ``"exact"`` (the default): the exact flow of the piecewise-constant control with
    Newton-refined times of impact, whose loss is the continuous cost. ``"symplectic-euler"``:
    the paper's scheme (``hybridoc ablation`` uses it to reproduce Table 1).

Control bounds and path constraints
    Bounds are honoured by projection (``gd``, ``adam``) or by SciPy's L-BFGS-B (``lbfgs``);
    path constraints by a quadratic penalty in the objective, and the judge reports any
    remaining violation (status ``infeasible``).
"""

from __future__ import annotations

import math
import numbers
import sys
import time
import weakref
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from hybridoc.errors import SceneError
from hybridoc.ocp import HybridOCP, Structure
from hybridoc.problem import ProblemLike, as_ocp
from hybridoc.problems.disc_ocp import DiscOCP
from hybridoc.solution import Solution, Status
from hybridoc.solvers.threads import torch_threads

__all__ = [
    "DEFAULT_SMOOTHING",
    "HOP_BATCH",
    "HOP_ITERS",
    "HOP_PATIENCE",
    "HOP_SCALES",
    "INTEGRATORS",
    "OPTIMIZERS",
    "PAPER_SETTINGS",
    "default_settings",
    "make_loss",
    "solve_gd",
]

INTEGRATORS = ("exact", "symplectic-euler")

OPTIMIZERS = ("gd", "adam", "lbfgs")

PAPER_SETTINGS: dict[str, tuple[float, int]] = {
    "single-collision": (200.0, 500),
    "multiple-collision": (50.0, 1500),
}
"""The paper's plain gradient descent: ``scene name -> (learning rate, iterations)``."""

DEFAULT_SMOOTHING = (1e-4, 1e-5, 1e-6)
"""Default continuation weights of ``lbfgs`` (see ``smoothing`` in :func:`solve_gd`)."""

STALL_RTOL = 1e-9
"""Convergence test at the iteration limit (:func:`solve_gd`): the loss changed by at most
this, relative, over the last :func:`stall_window` iterations."""


def stall_window(iters: int) -> int:
    """The iterations over which the loss must have stalled at the limit: a tenth of them,
    at least 10 (a run of fewer iterations cannot show that it has converged)."""
    return max(10, iters // 10)


def _positive(x: Any) -> bool:
    """``x`` is a real number, finite and > 0 (not a string, not a bool)."""
    return isinstance(x, numbers.Real) and not isinstance(x, bool) and math.isfinite(x) and x > 0


class _NonFinite(Exception):
    """The loss or its gradient became NaN or infinite."""


def default_settings(problem: Any, optimizer: str) -> tuple[float, int]:
    """Default ``(learning rate, iterations)`` of an optimiser on a scene.

    Plain ``gd`` uses the paper's settings on the paper's problems and otherwise a learning
    rate of ``0.1 / dt`` (the gradient with respect to one control value scales with ``dt``)
    for 1000 iterations; ``adam`` uses 0.05 for 1000 iterations; ``lbfgs`` a step of 0.1 (the
    first trial step of its strong-Wolfe line search) for at most 300 iterations: with 1.0 it
    leaps from the multiple-collision guess to ``u = 0``, where nothing collides.
    """
    if optimizer == "gd":
        return PAPER_SETTINGS.get(problem.name, (0.1 / problem.dt, 1000))
    if optimizer == "adam":
        return 0.05, 1000
    if optimizer == "lbfgs":
        return 0.1, 300
    raise SceneError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")


class _Progress:
    """A one-line progress bar on stderr."""

    def __init__(self, total: int, label: str) -> None:
        self.total, self.label, self.last = total, label, 0.0

    def update(self, k: int, loss: float, force: bool = False) -> None:
        now = time.perf_counter()
        if not force and now - self.last < 0.1:
            return
        self.last = now
        width = 30
        filled = int(width * k / max(self.total, 1))
        bar = "#" * filled + "." * (width - filled)
        sys.stderr.write(f"\r{self.label} [{bar}] {k}/{self.total} loss {loss:.6g}")
        sys.stderr.flush()

    def close(self) -> None:
        sys.stderr.write("\n")
        sys.stderr.flush()


_LOSSES: weakref.WeakKeyDictionary[Structure, dict[tuple[Any, ...], Any]] = (
    weakref.WeakKeyDictionary()
)


def make_loss(
    ocp: HybridOCP,
    contact: str,
    toi: str,
    integrator: str,
    path: str = "auto",
    path_weight: float = 1e5,
) -> tuple[Any, str]:
    """The differentiable objective of a problem: ``(loss object, "compiled" | "torch")``.

    The loss object has ``loss(controls, x0=None)`` (torch, differentiable). Compiled losses
    are kept per problem structure and settings: building one takes milliseconds, but
    continuation stages and repeated solves reuse it.
    """
    from hybridoc.solvers.contacts import contact_model

    if path not in ("auto", "compiled", "torch"):
        raise SceneError(f"unknown path {path!r}; choose auto, compiled or torch")
    is_disc = isinstance(ocp, DiscOCP)
    if integrator not in INTEGRATORS:
        raise SceneError(
            f"unknown integrator {integrator!r}; choose one of {', '.join(INTEGRATORS)}"
        )
    if is_disc:
        model = contact_model(contact, toi=toi)
        # every registered model has a CasADi step, within limits (e.g. the scene's number of
        # contacts for the coupled impulse models): auto falls back to torch outside them
        reason = model.casadi_unsupported(ocp.scene, integrator)
        if path == "compiled" and reason is not None:
            raise SceneError(f"no compiled path: {reason}")
        use_compiled = path == "compiled" or (path == "auto" and reason is None)
    else:
        if contact != "direct" or toi != "both":
            raise SceneError(
                f"contact models and TOI settings apply to disc scenes; {ocp.name!r} is "
                "simulated by the generic time-of-impact method (contact='direct', toi='both')"
            )
        if integrator != "exact":
            raise SceneError(
                f"integrator {integrator!r} applies to disc scenes; the generic time-of-impact "
                "simulation integrates the flow exactly"
            )
        if path == "torch":
            raise SceneError("the torch simulator simulates disc scenes only; use path='compiled'")
        use_compiled = True
    if not use_compiled:
        from hybridoc.solvers.simulator import Simulator

        return Simulator(ocp, contact=contact, toi=toi, integrator=integrator), "torch"
    from hybridoc.solvers.compiled import CompiledLoss

    key = (ocp.steps, ocp.horizon, contact, toi, integrator, path_weight, tuple(ocp.x0.tolist()))
    cache = _LOSSES.setdefault(ocp.structure, {})
    loss = cache.get(key)
    if loss is None:
        if len(cache) > 8:
            cache.clear()
        loss = CompiledLoss(
            ocp, contact, toi, integrator if is_disc else None, path_weight=path_weight
        )
        cache[key] = loss
    return loss, "compiled"


def default_integrator(ocp: HybridOCP, contact: str, toi: str) -> str:
    """``"exact"`` where it exists (impulse models with both TOI corrections, generic
    problems), else the paper's ``"symplectic-euler"``."""
    if not isinstance(ocp, DiscOCP):
        return "exact"
    from hybridoc.solvers.contacts import contact_model

    model = contact_model(contact, toi=toi)
    return (
        "exact"
        if model.impulse_based and getattr(model, "toi", None) == "both"
        else ("symplectic-euler")
    )


def _initial(ocp: HybridOCP, initial: Any) -> np.ndarray:
    """The starting controls: the problem's guess, an ``(N, nu)`` array or a Solution's."""
    if initial is None:
        return np.array(ocp.u_guess, dtype=float)
    controls = getattr(initial, "controls", initial)
    return ocp.check_controls(controls, what="initial controls")


def solve_gd(
    problem: ProblemLike,
    *,
    contact: str = "direct",
    toi: str = "both",
    integrator: str | None = None,
    optimizer: str = "lbfgs",
    iters: int | None = None,
    lr: float | None = None,
    initial: Any = None,
    callback: Callable[[int, float, np.ndarray], Any] | None = None,
    progress: bool = False,
    path: str = "auto",
    max_step: float | None = None,
    smoothing: Sequence[float] | None = None,
    path_weight: float = 1e5,
    starts: int = 1,
    seed: int | None = 0,
    hops: int = 0,
    _penalty: float = 0.0,
) -> Solution:
    """Minimise the discrete objective by gradient descent through the simulation.

    Parameters
    ----------
    problem
        Any problem (:func:`hybridoc.problem.as_ocp`): a built-in name, a Scene, a
        HybridOCP, a ``.toml`` path or ``file.py:function``.
    contact, toi
        Disc scenes: the contact model (:data:`hybridoc.solvers.contacts.CONTACT_MODELS`)
        and its time-of-impact correction.
    integrator
        ``"exact"`` or ``"symplectic-euler"`` (disc scenes only; the paper's). Default: exact
        for impulse models with both TOI corrections and for generic problems, symplectic
        Euler otherwise (the other settings have no exact form).
    optimizer
        ``"gd"`` (plain gradient descent, as in the paper), ``"adam"`` or ``"lbfgs"``
        (``torch.optim.LBFGS`` with a strong-Wolfe line search; SciPy's L-BFGS-B when the
        problem has control bounds; default).
    iters, lr
        Iterations and learning rate; defaults from :func:`default_settings`.
    initial
        Starting controls: ``None`` (the problem's guess), an ``(N, nu)`` array or a
        Solution.
    callback
        Called as ``callback(iteration, loss, controls)`` after every iteration; a true
        return value stops the optimisation.
    progress
        Show a progress bar on stderr (quiet by default).
    path
        ``"auto"`` (the compiled CasADi path where the model's CasADi step serves the scene,
        else torch),
        ``"compiled"`` or ``"torch"`` (disc scenes).
    max_step
        ``lbfgs`` only: the largest change of any control value in one iteration (longer
        steps are shortened and the curvature history is reset); default: no limit.
    smoothing
        Continuation weights ``mu_1 > mu_2 > ...``: before the real problem, solve it with the
        penalty ``mu sum_n |u_{n+1} - u_n|^2 / dt`` (about ``mu int |du/dt|^2 dt``) added, for
        each ``mu`` in turn, each stage starting from the previous result (``iters`` iterations
        per stage). The loss of piecewise-constant controls has a kink wherever an event
        crosses a grid time at which the control jumps, and gradient methods stall there; the
        penalty weakens those kinks so that the events first move to the right times.
        Default: :data:`DEFAULT_SMOOTHING` for ``lbfgs``, none for ``gd`` and ``adam``.
    path_weight
        Weight of the quadratic penalty on path-constraint violations (problems with
        ``path`` constraints).
    starts
        Multi-start: ``starts`` initial controls (the guess, perturbations of it, random smooth
        controls, controls aimed at each body and wall; :mod:`hybridoc.solvers.multistart`)
        descend together, one batched rollout per iteration, on a coarse grid; the best
        distinct results are refined by the single-start method at full resolution and the
        best of them returned. ``info["starts"]`` lists every start's result (its loss on
        the coarse grid; the judge's cost and events of each distinct optimum).
    seed
        Seed of the random starts (and of the hops' perturbations).
    hops
        Batched restarts after the descent, for losses with kinks (the symplectic Euler
        loss kinks wherever a contact moves to another step, and gradient descent stalls at
        a kink that is not a minimum, or in a shallow local minimum beside a lower one): in
        each round, :data:`HOP_BATCH` perturbations of the best control, at sizes spread
        geometrically from 1e-3 to 1 of its largest value, descend together by the batched
        L-BFGS of :mod:`hybridoc.solvers.multistart`; the lowest replaces the best when it is
        lower. Stops after ``hops`` rounds or :data:`HOP_PATIENCE` rounds without
        improvement. ``info["hops"]`` lists the rounds. Compiled path only.

    Returns
    -------
    hybridoc.solution.Solution
        Method ``"gd"``; the controls of the last iterate (of the best iterate if the loss
        became non-finite); ``cost`` is the judge's continuous cost of those controls.
        ``info`` holds the final discrete ``loss``, ``iterations``, ``message`` and
        ``converged``; ``status`` is ``success`` (the optimiser met its convergence test:
        L-BFGS could make no further progress, or the loss stalled, to :data:`STALL_RTOL`
        over :func:`stall_window` iterations, at the iteration limit), ``not-converged``
        (the iteration limit without meeting it, ``iters=0``, a stop by the callback, a
        non-finite or rising loss) or ``infeasible``.
    """
    import hybridoc
    from hybridoc.solution import Solution

    ocp = as_ocp(problem)
    torch_threads()  # the optimisers run in torch: one thread unless HYBRIDOC_THREADS says
    if optimizer not in OPTIMIZERS:
        raise SceneError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")
    lr0, it0 = default_settings(ocp, optimizer)
    lr = lr0 if lr is None else lr
    iters = it0 if iters is None else iters
    # checked strictly: int(1.5) or float("1e-3") would hide a mistake in the caller
    if isinstance(iters, bool) or not isinstance(iters, numbers.Integral) or iters < 0:
        raise SceneError(f"iters must be an integer >= 0, got {iters!r}")
    if not _positive(lr):
        raise SceneError(f"lr must be a positive finite number, got {lr!r}")
    if max_step is not None and not _positive(max_step):
        raise SceneError(f"max_step must be a positive finite number or None, got {max_step!r}")
    iters, lr = int(iters), float(lr)
    if integrator is None:
        integrator = default_integrator(ocp, contact, toi)
    if isinstance(starts, bool) or not isinstance(starts, numbers.Integral) or starts < 1:
        raise SceneError(f"starts must be an integer >= 1, got {starts!r}")
    if isinstance(hops, bool) or not isinstance(hops, numbers.Integral) or hops < 0:
        raise SceneError(f"hops must be an integer >= 0, got {hops!r}")
    if hops:
        t_hop = time.perf_counter()
        loss_obj, used_path = make_loss(ocp, contact, toi, integrator, path, path_weight)
        if not hasattr(loss_obj, "value_and_grad_batch"):
            raise SceneError(
                f"hops run batched rollouts on the compiled path; the {used_path} path of "
                f"contact {contact!r} has none"
            )
        base = solve_gd(
            ocp, contact=contact, toi=toi, integrator=integrator, optimizer=optimizer,
            iters=iters, lr=lr, initial=initial, callback=callback, progress=progress,
            path=path, max_step=max_step, smoothing=smoothing, path_weight=path_weight,
            starts=starts, seed=seed,
        )  # fmt: skip
        return _hop(ocp, base, loss_obj, int(hops), seed, t_hop)
    if starts > 1:
        return _multistart(
            ocp, int(starts), seed, dict(
                contact=contact, toi=toi, integrator=integrator, optimizer=optimizer,
                iters=iters, lr=lr, callback=callback, progress=progress, path=path,
                max_step=max_step, smoothing=smoothing, path_weight=path_weight,
            ),
        )  # fmt: skip
    t_start = time.perf_counter()
    loss_obj, used_path = make_loss(ocp, contact, toi, integrator, path, path_weight)
    u0 = _initial(ocp, initial)
    if ocp.has_bounds:
        u0 = np.clip(u0, ocp.u_min, ocp.u_max)
    if smoothing is None:
        smoothing = DEFAULT_SMOOTHING if optimizer == "lbfgs" and not _penalty else ()
    weights = tuple(smoothing) if isinstance(smoothing, Iterable | np.ndarray) else None
    if (
        isinstance(smoothing, str)
        or weights is None
        or not all(isinstance(m, numbers.Real) and math.isfinite(m) and m >= 0 for m in weights)
    ):
        raise SceneError(f"smoothing weights must be finite numbers >= 0, got {smoothing!r}")
    smoothing = tuple(float(m) for m in weights)
    settings = {
        "contact": contact,
        "toi": toi,
        "integrator": integrator,
        "optimizer": optimizer,
        "iters": iters,
        "lr": lr,
        "path": used_path,
        "simulation": "disc" if isinstance(ocp, DiscOCP) else "generic",
    }
    if smoothing:
        kwargs = dict(
            contact=contact, toi=toi, integrator=integrator, optimizer=optimizer, iters=iters,
            lr=lr, callback=callback, progress=progress, path=path, max_step=max_step,
            smoothing=(), path_weight=path_weight,
        )  # fmt: skip
        histories, its, stages = [], 0, []
        for mu in smoothing:
            stage = solve_gd(ocp, initial=u0, _penalty=mu, **kwargs)
            u0 = stage.controls
            histories.append(stage.arrays["loss_history"])
            its += stage.info["iterations"]
            stages.append({"mu": mu, "loss": stage.info["loss"], "cost": stage.cost})
            # a stage need not converge (the next one starts from it), but NaN or a rising
            # loss ends the continuation
            if stage.info["nan_stop"] or stage.info["diverged"]:
                break
        sol = solve_gd(ocp, initial=u0, **kwargs)
        sol.settings["smoothing"] = list(smoothing)
        sol.info["iterations"] += its
        sol.info["stages"] = stages
        sol.arrays["loss_history"] = np.concatenate(histories + [sol.arrays["loss_history"]])
        sol.timings["solve_time_s"] = time.perf_counter() - t_start
        return sol
    run = _Run(ocp, loss_obj, optimizer, lr, iters, max_step, _penalty, callback)
    bar = _Progress(
        iters, f"gd/{optimizer}" + (f" (smoothing, mu {_penalty:g})" if _penalty else "")
    )
    final_u, final_loss, k, message, nan_stop, history = run.optimise(u0, bar if progress else None)
    t_opt = time.perf_counter() - run.t_loop
    ev = hybridoc.evaluate(ocp, final_u)
    status, status_message = Status.SUCCESS, ""
    diverged = bool(history) and history[-1] > history[0] * (1 + 1e-9) + 1e-300
    converged, why = _converged(message, history, k, iters)
    if nan_stop:
        status, status_message = Status.NOT_CONVERGED, message
    elif diverged:
        status = Status.NOT_CONVERGED
        status_message = (
            f"the loss rose from {history[0]:.6g} to {history[-1]:.6g}: the optimisation "
            "diverged; try a smaller learning rate"
        )
    elif not converged:
        status, status_message = Status.NOT_CONVERGED, why
    elif not ev.feasible:
        status = Status.INFEASIBLE
        status_message = (
            f"the controls violate the bounds by {ev.bound_violation:.3g} and the path "
            f"constraints by {ev.path_violation:.3g}"
        )
    info = {
        "loss": float(final_loss),
        "iterations": int(k),
        "loss_evaluations": int(run.n_evals),
        "nan_stop": nan_stop,
        "diverged": diverged,
        "converged": converged and not (nan_stop or diverged),
        "message": message,
        "ms_per_iteration": 1e3 * t_opt / max(k, 1),
        "restarts": run.restarts,
    }
    sol = Solution.from_evaluation(
        ev,
        method="gd",
        scene=ocp.name,
        settings=settings,
        timings={"solve_time_s": time.perf_counter() - t_start, "optimization_time_s": t_opt},
        info=info,
        arrays={"loss_history": np.array(history, dtype=float)},
    )
    return sol.set_status(status, status_message)


def _converged(message: str, history: Sequence[float], k: int, iters: int) -> tuple[bool, str]:
    """Whether one optimisation met its convergence test, and if not, the status message.

    The test: the optimiser stopped because it could make no further progress (L-BFGS: a
    fresh start moves nowhere; L-BFGS-B: SciPy's own test), or, at the iteration limit, the
    loss spread by at most :data:`STALL_RTOL` (relative, ``max - min`` over the last
    :func:`stall_window` iterations; a loss tending to 0 is measured against 1e-12 of the
    initial one). Plain ``gd`` and ``adam`` have only the second.
    """
    if message.startswith("converged"):
        return True, ""
    if message == "stopped by the callback":
        return False, f"stopped by the callback after {k} iteration(s), before converging"
    if iters == 0:
        return False, "iters = 0: no descent was run; the controls are the initial guess"
    w = stall_window(iters)
    if len(history) > w:
        window = np.asarray(history[-w - 1 :], dtype=float)
        # the spread over the window, not two end points (a 2-cycle would pass), relative
        # to the loss, with a floor for a loss that falls towards 0
        scale = max(abs(float(window.min())), 1e-12 * abs(float(history[0])), 1e-300)
        change = float(window.max() - window.min()) / scale
        if change <= STALL_RTOL:
            return True, ""
        tail = f"the loss still changed by {change:.2e} (relative) over the last {w} iterations"
        if float(window[1:].min()) >= float(np.min(history[:-w])):
            # no better than before the window: it oscillates, more iterations will not help
            return False, (
                f"stopped at the iteration limit ({iters}) before converging: {tail} without "
                "improving on its best loss (it oscillates: a smaller --lr, or the default "
                "optimizer lbfgs, may settle)"
            )
    else:
        tail = (
            f"{k} iteration(s) are too few to tell (the test: a relative change of the loss of "
            f"at most {STALL_RTOL:g} over the last {w} iterations)"
        )
    return False, (
        f"stopped at the iteration limit ({iters}) before converging: {tail}; raise the "
        "iterations (--iters)"
    )


HOP_BATCH = 32
"""Hops (:func:`solve_gd`): perturbations of the best control per round."""
HOP_ITERS = 150
"""Hops: iterations of the batched L-BFGS of each round."""
HOP_PATIENCE = 2
"""Hops: rounds without improvement before stopping."""
HOP_SCALES = (1e-3, 1.0)
"""Hops: smallest and largest perturbation size, relative to ``max |u|`` (geometric spread)."""


def _hop(
    ocp: HybridOCP, base: Solution, loss_obj: Any, hops: int, seed: int | None, t0: float
) -> Solution:
    """:func:`solve_gd` with ``hops`` (see there): batched restarts around the best control."""
    from hybridoc.evaluator import evaluate
    from hybridoc.solvers.multistart import batched_lbfgs, smooth_noise

    if base.info.get("nan_stop") or base.info.get("diverged"):
        return base
    dt = ocp.horizon / ocp.steps
    lower = upper = None
    if ocp.has_bounds:
        lower, upper = ocp.u_min, ocp.u_max

    def vg(U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        J, gU, _ = loss_obj.value_and_grad_batch(U)
        return J / dt, gU / dt  # the batched L-BFGS's scaling, as in the multi-start

    x = np.array(base.controls, dtype=float)
    f = float(loss_obj.value_and_grad(x)[0])
    rng = np.random.default_rng(seed)
    rounds: list[dict[str, Any]] = []
    stale = 0
    for _ in range(hops):
        size = max(float(np.abs(x).max()), 1e-3)
        scales = size * np.geomspace(*HOP_SCALES, HOP_BATCH)
        P = np.stack([x + sc * smooth_noise(rng, *x.shape, modes=8) for sc in scales])
        if lower is not None:
            P = np.clip(P, lower, upper)
        X, F, _ = batched_lbfgs(vg, P, iters=HOP_ITERS, lower=lower, upper=upper)
        F = np.where(np.isfinite(F), F * dt, np.inf)
        k = int(np.argmin(F))
        improved = bool(F[k] < f - 1e-13 * max(abs(f), 1.0))
        rounds.append({"loss": float(F[k]), "improved": improved, "size": float(scales[k] / size)})
        if improved:
            x, f, stale = X[k], float(F[k]), 0
        else:
            stale += 1
            if stale >= HOP_PATIENCE:
                break
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
    if not converged:
        status, message = Status.NOT_CONVERGED, (
            f"{base.message}; and the hops did not settle either" if base.message else
            "the hops did not settle"
        )  # fmt: skip
    elif not ev.feasible:
        status = Status.INFEASIBLE
        message = (
            f"the controls violate the bounds by {ev.bound_violation:.3g} and the path "
            f"constraints by {ev.path_violation:.3g}"
        )
    return sol.set_status(status, message)


#: multi-start: the coarse grid of the batched phase, its iterations, and how many distinct
#: results are refined at full resolution
MULTISTART_STEPS = 60
MULTISTART_ITERS = 60
MULTISTART_REFINE = 2
MULTISTART_SMOOTHING = (3e-6,)


def _multistart(ocp: HybridOCP, starts: int, seed: int | None, options: dict[str, Any]) -> Solution:
    """:func:`solve_gd` with ``starts > 1`` (see its ``starts``)."""
    from hybridoc.solvers.multistart import explore

    t0 = time.perf_counter()
    if isinstance(ocp, DiscOCP) and options["contact"] != "direct":
        raise SceneError(
            "the batched multi-start explores with the compiled exact simulation of contact "
            "'direct'; other contact models start from its result with --initial"
        )
    coarse = min(ocp.steps, MULTISTART_STEPS)
    rows: list[dict[str, Any]] = []
    found = explore(ocp, starts, seed=seed, steps=coarse, iters=MULTISTART_ITERS, report=rows)
    t_explore = time.perf_counter() - t0
    refined: list[Solution] = []
    seen: set[tuple[str, ...]] = set()
    for r in found:
        key = tuple(r["sequence"])
        if key in seen:
            continue
        if refined and r["cost"] > 1.02 * found[0]["cost"]:
            break  # the batched phase ranks the basins well enough
        seen.add(key)
        # the batched phase has found the basin: one light smoothing stage for the kinks
        smoothing = options["smoothing"]
        if smoothing is None:
            smoothing = MULTISTART_SMOOTHING if options["optimizer"] == "lbfgs" else ()
        refined.append(solve_gd(ocp, initial=r["controls"], **dict(options, smoothing=smoothing)))
        if len(refined) >= MULTISTART_REFINE:
            break
    if not refined:
        return solve_gd(ocp, **options)
    best = min(refined, key=lambda s: s.cost)
    best.settings["starts"] = starts
    best.settings["seed"] = seed
    best.info["starts"] = rows  # every start: coarse loss, judged cost and events
    best.info["explore_steps"] = coarse
    best.info["refined"] = [{"cost": s.cost, "sequence": s.sequence} for s in refined]
    best.timings["explore_time_s"] = t_explore
    best.timings["solve_time_s"] = time.perf_counter() - t0
    return best


class _Run:
    """One optimisation of :func:`solve_gd` (no continuation)."""

    def __init__(
        self,
        ocp: HybridOCP,
        loss_obj: Any,
        optimizer: str,
        lr: float,
        iters: int,
        max_step: float | None,
        penalty: float,
        callback: Callable[[int, float, np.ndarray], Any] | None,
    ) -> None:
        self.ocp = ocp
        self.loss_obj = loss_obj
        self.optimizer = optimizer
        self.lr = lr
        self.iters = iters
        self.max_step = math.inf if max_step is None else max_step
        self.penalty = penalty
        self.callback = callback
        self.n_evals = 0
        self.restarts = 0
        self.t_loop = time.perf_counter()

    def value(self, u: Any) -> Any:
        """The objective (with the smoothing and path penalties) of torch controls ``u``."""
        import torch

        self.n_evals += 1
        if not bool(torch.isfinite(u).all()):
            raise _NonFinite("the controls became NaN or infinite")
        value = self.loss_obj.loss(u)
        if self.penalty:
            value = value + self.penalty * ((u[1:] - u[:-1]) ** 2).sum() / self.ocp.dt
        val = float(value.detach())
        if not math.isfinite(val):
            raise _NonFinite(f"the loss became {val}")
        return value

    def optimise(
        self, u0: np.ndarray, bar: _Progress | None
    ) -> tuple[np.ndarray, float, int, str, bool, list[float]]:
        """Run the optimiser; returns controls, loss, iterations, message, NaN stop, history."""
        import torch

        self.t_loop = time.perf_counter()
        if self.optimizer == "lbfgs" and self.ocp.has_bounds:
            return self._lbfgsb(u0, bar)
        ocp = self.ocp
        u = torch.tensor(u0, dtype=torch.float64, requires_grad=True)
        best = {"loss": math.inf, "u": u0.copy()}

        last: dict[str, Any] = {"u": None, "value": None}

        def evaluate_loss() -> Any:
            value = self.value(u)
            val = float(value.detach())
            if val < best["loss"]:
                best["loss"], best["u"] = val, u.detach().numpy().copy()
            last["u"], last["value"] = u.detach().clone(), val
            return value

        def loss_here() -> float:
            """The loss at the current controls (the line search's last evaluation when it
            was there: no second rollout)."""
            if last["u"] is not None and torch.equal(last["u"], u.detach()):
                return float(last["value"])
            return float(evaluate_loss().detach())

        # L-BFGS has absolute thresholds (curvature pairs with y.s <= 1e-10 are dropped) while
        # the gradient with respect to one control value scales with dt: it sees loss / dt
        scale = 1.0 / ocp.dt if self.optimizer == "lbfgs" else 1.0

        def closure() -> Any:
            opt.zero_grad()
            value = evaluate_loss() * scale
            value.backward()
            if not bool(torch.isfinite(u.grad).all()):
                raise _NonFinite("the gradient became NaN or infinite")
            return value

        def make_optimizer() -> Any:
            if self.optimizer == "gd":
                return torch.optim.SGD([u], lr=self.lr)
            if self.optimizer == "adam":
                return torch.optim.Adam([u], lr=self.lr)
            return torch.optim.LBFGS(
                [u],
                lr=self.lr,
                max_iter=1,
                history_size=50,
                line_search_fn="strong_wolfe",
                tolerance_grad=1e-12,
                tolerance_change=1e-15,
            )

        def project() -> None:
            if ocp.has_bounds:
                with torch.no_grad():
                    u.copy_(torch.clamp(u, torch.as_tensor(ocp.u_min), torch.as_tensor(ocp.u_max)))

        opt = make_optimizer()
        history: list[float] = []
        message = "finished the requested iterations"
        k = 0
        fresh = True
        try:
            for k in range(self.iters):
                if self.optimizer == "lbfgs":
                    if not history:
                        history.append(loss_here())
                    before = u.detach().clone()
                    opt.step(closure)
                    jump = float((u.detach() - before).abs().max())
                    if jump > self.max_step:
                        # a quasi-Newton step can leap into another event sequence: cut it
                        # back (inf-norm) and reset the curvature history
                        with torch.no_grad():
                            u.copy_(before + (u - before) * (self.max_step / jump))
                        opt, fresh = make_optimizer(), True
                        self.restarts += 1
                        value = float(evaluate_loss().detach())
                        if value > history[-1]:
                            with torch.no_grad():
                                u.copy_(before)
                            value = history[-1]
                        history.append(value)
                    elif torch.equal(before, u.detach()):
                        # kinks of the loss (a contact moving to another step) can spoil the
                        # quasi-Newton model: restart from here with an empty history; stop
                        # when a fresh start makes no progress either
                        history.append(history[-1])
                        if fresh:
                            message = "converged: L-BFGS made no further progress"
                            k += 1
                            break
                        opt, fresh = make_optimizer(), True
                        self.restarts += 1
                    else:
                        history.append(loss_here())
                        fresh = False
                else:
                    history.append(float(closure().detach()))
                    opt.step()
                    project()
                if bar:
                    bar.update(k + 1, history[-1])
                if self.callback is not None and self.callback(
                    k + 1, history[-1], u.detach().numpy().copy()
                ):
                    message = "stopped by the callback"
                    k += 1
                    break
            else:
                k = self.iters
            if self.optimizer != "lbfgs" or not history:
                history.append(float(evaluate_loss().detach()))
            return u.detach().numpy().copy(), history[-1], k, message, False, history
        except _NonFinite as exc:
            message = (
                f"stopped early at iteration {k}: {exc}; returning the best iterate "
                f"(discrete loss {best['loss']:.6g}); try a smaller learning rate"
            )
            return best["u"], best["loss"], k, message, True, history or [best["loss"]]
        finally:
            if bar:
                bar.update(k, history[-1] if history else math.nan, force=True)
                bar.close()

    def _lbfgsb(
        self, u0: np.ndarray, bar: _Progress | None
    ) -> tuple[np.ndarray, float, int, str, bool, list[float]]:
        """SciPy's L-BFGS-B on the same objective (problems with control bounds)."""
        import torch
        from scipy.optimize import minimize

        ocp = self.ocp
        shape = u0.shape
        history: list[float] = []
        k = 0

        def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
            u = torch.tensor(x.reshape(shape), dtype=torch.float64, requires_grad=True)
            value = self.value(u)
            value.backward()
            return float(value.detach()) / ocp.dt, u.grad.numpy().ravel() / ocp.dt

        def cb(x: np.ndarray) -> None:
            nonlocal k
            k += 1
            history.append(fun(x)[0] * ocp.dt)
            if bar:
                bar.update(k, history[-1])
            if self.callback is not None and self.callback(k, history[-1], x.reshape(shape)):
                raise StopIteration

        bounds = list(zip(np.tile(ocp.u_min, shape[0]), np.tile(ocp.u_max, shape[0]), strict=True))
        history.append(fun(u0.ravel())[0] * ocp.dt)
        try:
            res = minimize(
                fun, u0.ravel(), jac=True, method="L-BFGS-B", bounds=bounds,
                callback=cb, options={"maxiter": self.iters, "ftol": 1e-15, "gtol": 1e-12},
            )  # fmt: skip
            x = res.x
            if res.status == 99:  # the callback raised StopIteration
                msg = "stopped by the callback"
            elif res.status == 1:  # SciPy's iteration limit
                msg = f"finished the requested iterations (L-BFGS-B: {res.message})"
            else:  # SciPy's convergence tests, or a line search that cannot progress
                msg = f"converged: L-BFGS-B: {res.message}"
        except _NonFinite as exc:
            return u0, history[-1], k, f"stopped early: {exc}", True, history
        finally:
            if bar:
                bar.close()
        final = fun(x)[0] * ocp.dt
        history.append(final)
        return x.reshape(shape), final, k, msg, False, history
