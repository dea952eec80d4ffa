"""The descent loop of gd: one optimisation on numpy buffers (:class:`Run`: plain gradient
descent, Adam, L-BFGS or SciPy's L-BFGS-B), one judged descent (:func:`descend`) with its
convergence test and status, and the continuation of smoothing stages
(:func:`continuation`)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridoc.evaluator import evaluate
from hybridoc.ocp import HybridOCP
from hybridoc.progress import Progress
from hybridoc.scales import optimizer_units as units
from hybridoc.solution import Solution, Status
from hybridoc.solvers.gd.kinks import KINK_GTOL, kinks_apply, past_kinks
from hybridoc.solvers.gd.limits import NonFinite, current_watch
from hybridoc.solvers.gd.loss import make_loss, torch_value_and_grad
from hybridoc.solvers.gd.options import (
    DEFAULT_SMOOTHING,
    STALL_RTOL,
    GDOptions,
    disc_simulation,
    stall_window,
)

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.evaluation import Evaluation


def initial_controls(ocp: HybridOCP, initial: Any) -> np.ndarray:
    """The starting controls: the problem's guess, an ``(N, nu)`` array or a Solution's."""
    if initial is None:
        return np.array(ocp.u_guess, dtype=float)
    controls = getattr(initial, "controls", initial)
    return ocp.check_controls(controls, what="initial controls")


def run_settings(ocp: HybridOCP, opts: GDOptions, used_path: str) -> dict[str, Any]:
    """The JSON-ready settings of a Solution: the contact model's and the run's."""
    return {
        **opts.contact.settings(),
        "integrator": opts.integrator,
        "optimizer": opts.optimizer,
        "iters": opts.iters,
        "lr": opts.lr,
        "path": used_path,
        "simulation": "disc" if disc_simulation(ocp) else "generic",
    }


def continuation(ocp: HybridOCP, opts: GDOptions, initial: Any, progress: Progress) -> Solution:
    """One start: the smoothing stages (``opts.smoothing``), then the problem itself."""
    t_start = time.perf_counter()
    loss_obj, used_path = make_loss(ocp, opts.contact, opts.integrator, opts.path, opts.path_weight)
    u0 = initial_controls(ocp, initial)
    if ocp.has_bounds:
        u0 = np.clip(u0, ocp.u_min, ocp.u_max)
    smoothing = opts.smoothing
    if smoothing is None:
        smoothing = DEFAULT_SMOOTHING if opts.optimizer == "lbfgs" else ()
    settings = run_settings(ocp, opts, used_path)
    if not smoothing:
        progress.stage(f"descent ({opts.optimizer})")
        return descend(ocp, opts, loss_obj, u0, settings, progress, t_start=t_start)
    histories, its, stages = [], 0, []
    n = len(smoothing) + 1
    for i, mu in enumerate(smoothing):
        progress.stage(f"stage {i + 1} of {n}, smoothing mu {mu:g}")
        stage = descend(ocp, opts, loss_obj, u0, dict(settings), progress, penalty=mu)
        u0 = stage.controls
        histories.append(stage.arrays["loss_history"])
        its += stage.info["iterations"]
        stages.append({"mu": mu, "loss": stage.info["loss"], "cost": stage.cost,
                       **_stage_counts(stage)})  # fmt: skip
        # a stage need not converge (the next one starts from it), but NaN or a rising
        # loss ends the continuation
        if stage.info["nan_stop"] or stage.info["diverged"]:
            break
    progress.stage(f"stage {n} of {n}, descent ({opts.optimizer}) after smoothing")
    sol = descend(ocp, opts, loss_obj, u0, settings, progress)
    sol.settings["smoothing"] = list(smoothing)
    last = _stage_counts(sol)
    # every count over all stages (issue #34: the evaluations and time were the last one's)
    sol.info["final_stage"] = last
    sol.info["iterations"] += its
    sol.info["loss_evaluations"] = last["loss_evaluations"] + sum(
        st["loss_evaluations"] for st in stages)  # fmt: skip
    sol.timings["optimization_time_s"] = last["optimization_time_s"] + sum(
        st["optimization_time_s"] for st in stages)  # fmt: skip
    sol.info["ms_per_iteration"] = 1e3 * sol.timings["optimization_time_s"] / max(
        sol.info["iterations"], 1)  # fmt: skip
    sol.info["stages"] = stages
    sol.arrays["loss_history"] = np.concatenate(histories + [sol.arrays["loss_history"]])
    # where each stage starts in loss_history: the curve jumps there as the loss changes
    starts = np.cumsum([0] + [len(h) for h in histories]).tolist()
    names = [f"mu {st['mu']:g}" for st in stages] + ["no smoothing"]
    sol.info["history_stages"] = [[int(k), name] for k, name in zip(starts, names, strict=True)]
    sol.timings["solve_time_s"] = time.perf_counter() - t_start
    return sol


def _stage_counts(sol: Solution) -> dict[str, Any]:
    """The iterations, loss evaluations and optimisation time of one descent."""
    return {
        "iterations": int(sol.info["iterations"]),
        "loss_evaluations": int(sol.info["loss_evaluations"]),
        "optimization_time_s": float(sol.timings["optimization_time_s"]),
    }


def descend(
    ocp: HybridOCP,
    opts: GDOptions,
    loss_obj: Any,
    u0: np.ndarray,
    settings: dict[str, Any],
    progress: Progress,
    *,
    penalty: float = 0.0,
    t_start: float | None = None,
) -> Solution:
    """One descent from ``u0`` (with the smoothing ``penalty``), judged: its Solution."""
    t_start = time.perf_counter() if t_start is None else t_start
    run = Run(ocp, loss_obj, opts, penalty, progress)
    final_u, final_loss, k, message, nan_stop, history = run.optimise(u0)
    ev = evaluate(ocp, final_u)
    diverged = bool(history) and history[-1] > history[0] * (1 + 1e-9) + 1e-300
    converged, why = convergence_test(message, history, k, opts.iters)
    kink: dict[str, Any] | None = None
    if converged and not (nan_stop or diverged) and penalty == 0.0 and kinks_apply(ocp, opts):
        final_u, final_loss, ev, kink = past_kinks(ocp, run, final_u, final_loss, ev, progress)
        if kink is not None:
            k += kink["iterations"]
            history.append(final_loss)
            if kink["stalled"]:
                converged, why = False, kink["message"]
    if converged and kink is None and penalty == 0.0 and np.array_equal(final_u, u0):
        converged, why = _unmoved(run, final_u)
    t_opt = time.perf_counter() - run.t_loop
    status, status_message = _status(ev, message, history, nan_stop, diverged, converged, why)
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
    if kink is not None:
        info["kinks"] = kink
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


def _unmoved(run: Run, u: np.ndarray) -> tuple[bool, str]:
    """A descent that claims convergence without having moved from its start ``u``: whether
    ``u`` is stationary after all (the certificate of :data:`KINK_GTOL` on the scaled
    objective), and if not, the status message. Without this check a step that is too
    short for the controls' size (another unit, a tiny ``lr``) leaves the start unchanged
    and "L-BFGS made no further progress" reads as success."""
    run.scale = 1.0 / (run.jc * run.dts)
    x = run.scaled(u)
    f, g = run.fun(x)
    stat = float(np.linalg.norm(g)) * (1.0 + float(np.abs(x).max())) / (1.0 + abs(f))
    if stat <= KINK_GTOL:
        return True, ""
    return False, (
        f"the descent took no step from its start, where the gradient does not vanish "
        f"(stationarity {stat:.2e} > {KINK_GTOL:g} in the problem's scaled units): "
        "no convergence shown; try another --lr"
    )


def infeasibility(ev: Evaluation) -> str:
    """Why the judge finds a result infeasible (its status message)."""
    return ev.infeasibility() or "the judge finds the controls infeasible"


def _status(
    ev: Evaluation,
    message: str,
    history: Sequence[float],
    nan_stop: bool,
    diverged: bool,
    converged: bool,
    why: str,
) -> tuple[Status, str]:
    """The status of one descent and its message: a non-finite stop, a rising loss, no
    convergence (``why``), controls the judge finds infeasible, or success."""
    if nan_stop:
        return Status.NOT_CONVERGED, message
    if diverged:
        return Status.NOT_CONVERGED, (
            f"the loss rose from {history[0]:.6g} to {history[-1]:.6g}: the optimisation "
            "diverged; try a smaller learning rate"
        )
    if not converged:
        if not ev.feasible:  # the stronger finding: what it returns is not admissible at all
            return Status.INFEASIBLE, f"{infeasibility(ev)}; and {why}" if why else infeasibility(
                ev
            )
        return Status.NOT_CONVERGED, why
    if not ev.feasible:
        return Status.INFEASIBLE, infeasibility(ev)
    return Status.SUCCESS, ""


def convergence_test(
    message: str, history: Sequence[float], k: int, iters: int
) -> tuple[bool, str]:
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


_Result = tuple[np.ndarray, float, int, str, bool, list[float]]
"""What :meth:`Run.optimise` returns: controls, loss, iterations, message, NaN stop and the
loss history."""


class Run:
    """One optimisation of :func:`solve_gd` (no continuation), on numpy buffers.

    The objective (the loss with the smoothing and path penalties) and its gradient come
    from the compiled loss's ``value_and_grad`` as numpy arrays (the torch simulator's
    through its autograd: :func:`torch_value_and_grad`); the optimisers are those of
    :mod:`hybridoc.solvers.optimizers` (``torch.optim``'s, ported), or SciPy's L-BFGS-B
    with bounds.
    """

    def __init__(
        self,
        ocp: HybridOCP,
        loss_obj: Any,
        opts: GDOptions,
        penalty: float,
        progress: Progress,
    ) -> None:
        self.ocp = ocp
        self.loss_obj = loss_obj
        self.optimizer = opts.optimizer
        self.lr = opts.lr
        self.iters = opts.iters
        self.max_step = math.inf if opts.max_step is None else opts.max_step
        self.penalty = penalty
        self.callback = opts.callback
        self.progress = progress
        self.n_evals = 0
        self.restarts = 0
        self.t_loop = time.perf_counter()
        self.shape = (ocp.steps, ocp.nu)
        # the optimisers see scaled controls u / cs and the loss per unit of cost and scaled
        # step, (J / jc) / (dt / tc): the same numbers in any units (module notes)
        self.cs, self.jc, self.tc = units(ocp)
        self.dts = ocp.dt / self.tc
        self.scale = 1.0
        self.best: dict[str, Any] = {"loss": math.inf, "u": None}
        self.last: tuple[np.ndarray, float] | None = None
        self.watch = current_watch()
        if hasattr(loss_obj, "value_and_grad"):
            self.loss_grad: Callable[[np.ndarray], tuple[float, np.ndarray]] = lambda u: (
                loss_obj.value_and_grad(u)[:2]
            )
        else:
            self.loss_grad = torch_value_and_grad(loss_obj)

    def value_and_grad(self, u: np.ndarray) -> tuple[float, np.ndarray]:
        """The objective (with the smoothing and path penalties) of controls ``u`` and its
        gradient; keeps the best and the last evaluation."""
        self.n_evals += 1
        if self.watch is not None:
            self.watch.check()
        if not np.isfinite(u).all():
            raise NonFinite("the controls became NaN or infinite")
        value, grad = self.loss_grad(u)
        value = float(value)
        if self.watch is not None:
            self.watch.offer(value, u)
        if self.penalty:
            # mu sum |du~|^2 / dt~ in units of cost: the same weight in any units
            diff = (u[1:] - u[:-1]) / self.cs
            value = value + self.penalty * self.jc * float((diff * diff).sum()) / self.dts
            grad = np.array(grad, dtype=float)
            w = 2.0 * self.penalty * self.jc / self.dts
            grad[1:] += w * diff / self.cs
            grad[:-1] -= w * diff / self.cs
        if not math.isfinite(value):
            raise NonFinite(f"the loss became {value}")
        if value < self.best["loss"]:
            self.best["loss"], self.best["u"] = value, u.copy()
        self.last = (u.copy(), value)
        if not np.isfinite(grad).all():
            raise NonFinite("the gradient became NaN or infinite")
        return value, grad

    def fun(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """The scaled objective (times :attr:`scale`) of flat scaled controls ``u / cs``, for
        the optimisers."""
        value, grad = self.value_and_grad(self.physical(x))
        return value * self.scale, np.ravel(grad * self.cs) * self.scale

    def physical(self, x: np.ndarray) -> np.ndarray:
        """Controls ``(N, nu)`` of flat scaled controls."""
        return x.reshape(self.shape) * self.cs

    def scaled(self, u: np.ndarray) -> np.ndarray:
        """Flat scaled controls of controls ``(N, nu)``."""
        return np.ravel(u / self.cs)

    def loss_here(self, u: np.ndarray) -> float:
        """The loss at ``u`` (the last evaluation when it was there: no second rollout)."""
        if self.last is not None and np.array_equal(self.last[0], u):
            return self.last[1]
        return self.value_and_grad(u)[0]

    def report(self, k: int, loss: float, controls: Callable[[], np.ndarray]) -> bool:
        """Iteration ``k`` is done: count it, call the callback; whether the callback stops."""
        # the iteration limit is no total (a stage stops at convergence): no bar to it
        self.progress.count(k, None, f"iterations, loss {loss:.6g}")
        if self.watch is not None:
            self.watch.iterations += 1
        return self.callback is not None and bool(self.callback(k, loss, controls()))

    def optimise(self, u0: np.ndarray) -> _Result:
        """Run the optimiser; returns controls, loss, iterations, message, NaN stop, history."""
        self.t_loop = time.perf_counter()
        if self.optimizer == "lbfgs" and self.ocp.has_bounds:
            return self.lbfgsb(u0)
        u0 = np.array(u0, dtype=float)
        self.best = {"loss": math.inf, "u": u0.copy()}
        history: list[float] = []
        state = {"u": u0}
        k = 0
        try:
            if self.optimizer == "lbfgs":
                message, k = self.lbfgs(u0, history, state)
            else:
                message, k = self.first_order(u0, history, state)
            u = state["u"]
            if self.optimizer != "lbfgs" or not history:
                history.append(self.loss_here(u))
            return u.copy(), history[-1], k, message, False, history
        except NonFinite as exc:
            best, k = self.best, state.get("k", k)
            message = (
                f"stopped early at iteration {k}: {exc}; returning the best iterate "
                f"(discrete loss {best['loss']:.6g}); try a smaller learning rate"
            )
            return best["u"], best["loss"], k, message, True, history or [best["loss"]]

    def first_order(
        self, u: np.ndarray, history: list[float], state: dict[str, Any]
    ) -> tuple[str, int]:
        """Plain gradient descent or Adam, projected on the control bounds."""
        from hybridoc.solvers.optimizers import SGD, Adam

        opt = SGD(self.lr) if self.optimizer == "gd" else Adam(self.lr)
        ocp = self.ocp
        for k in range(self.iters):
            state["k"] = k
            value, grad = self.value_and_grad(u)
            history.append(value)
            # a step in scaled controls along the gradient of the scaled loss
            u = opt.step(u / self.cs, grad * self.cs / self.jc) * self.cs
            if ocp.has_bounds:
                u = np.clip(u, ocp.u_min, ocp.u_max)
            state["u"] = u
            if self.report(k + 1, history[-1], lambda u=u: u.copy()):
                return "stopped by the callback", k + 1
        state["k"] = self.iters
        return "finished the requested iterations", self.iters

    def lbfgs(self, u0: np.ndarray, history: list[float], state: dict[str, Any]) -> tuple[str, int]:
        """L-BFGS with the max-step cut-back and restarts at kinks
        (:func:`~hybridoc.solvers.optimizers.lbfgs_iterations`)."""
        from hybridoc.solvers.optimizers import GD_LINE_SEARCH_EVALS, lbfgs_iterations

        # L-BFGS has absolute thresholds (curvature pairs with y.s <= 1e-10 are dropped) while
        # the gradient with respect to one control value scales with dt: it sees loss / dt
        self.scale = 1.0 / (self.jc * self.dts)
        state["k"] = 0
        if self.iters == 0:
            return "finished the requested iterations", 0
        x0 = self.scaled(u0)
        start = self.fun(x0)
        history.append(self.loss_here(u0))
        steps = lbfgs_iterations(
            self.fun, x0, lr=self.lr, max_step=self.max_step / float(self.cs.max()),
            max_ls=GD_LINE_SEARCH_EVALS, start=start,
        )  # fmt: skip
        for k, it in zip(range(self.iters), steps, strict=False):
            state["k"] = k
            u = self.physical(it.x)
            state["u"] = u
            if it.event in ("restart", "converged", "cut-rejected"):
                history.append(history[-1])
            else:
                history.append(self.loss_here(u))
            if it.event in ("cut", "cut-rejected", "restart"):
                self.restarts += 1
            if it.event == "converged":
                return "converged: L-BFGS made no further progress", k + 1
            if self.report(k + 1, history[-1], lambda u=u: u.copy()):
                return "stopped by the callback", k + 1
        state["k"] = self.iters
        return "finished the requested iterations", self.iters

    def lbfgsb(self, u0: np.ndarray) -> _Result:
        """SciPy's L-BFGS-B on the same objective (problems with control bounds)."""
        from scipy.optimize import minimize

        ocp = self.ocp
        shape = u0.shape
        history: list[float] = []
        k = 0
        # scaled: controls u / cs, loss (J / jc) / dt~ (identity scales: J / dt as before)
        per = self.jc * self.dts

        def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
            u = self.physical(x)
            if self.last is not None and np.array_equal(self.last[0], u):
                value = self.last[1]  # the callback's point: SciPy has just evaluated it
                return value / per, self.last_grad
            value, grad = self.value_and_grad(u)
            self.last_grad = np.ravel(grad * self.cs) / per
            return value / per, self.last_grad

        def cb(x: np.ndarray) -> None:
            nonlocal k
            k += 1
            history.append(fun(x)[0] * per)
            if self.report(k, history[-1], lambda: self.physical(x)):
                raise StopIteration

        lo, hi = ocp.u_min / self.cs, ocp.u_max / self.cs
        bounds = list(zip(np.tile(lo, shape[0]), np.tile(hi, shape[0]), strict=True))
        self.last_grad = np.zeros(u0.size)
        history.append(fun(self.scaled(u0))[0] * per)
        try:
            res = minimize(
                fun, self.scaled(u0), jac=True, method="L-BFGS-B", bounds=bounds,
                callback=cb, options={"maxiter": self.iters, "ftol": 1e-15, "gtol": 1e-12},
            )  # fmt: skip
        except NonFinite as exc:
            return u0, history[-1], k, f"stopped early: {exc}", True, history
        x = res.x
        if res.status == 99:  # the callback raised StopIteration
            msg = "stopped by the callback"
        elif res.status == 1:  # SciPy's iteration limit
            msg = f"finished the requested iterations (L-BFGS-B: {res.message})"
        else:  # SciPy's convergence tests, or a line search that cannot progress
            msg = f"converged: L-BFGS-B: {res.message}"
        final = fun(x)[0] * per
        history.append(final)
        return self.physical(x), final, k, msg, False, history
