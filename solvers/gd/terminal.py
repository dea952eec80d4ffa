"""Terminal constraints and a free final time in gd: the augmented Lagrangian around
SciPy's L-BFGS-B on the generic time-of-impact simulation (:func:`solve_terminal`; the
package's notes)."""

from __future__ import annotations

import math
import time
import weakref
from typing import Any

import numpy as np

from hybridoc import tolerances
from hybridoc.errors import OptionError
from hybridoc.evaluator import evaluate
from hybridoc.ocp import HybridOCP, Structure
from hybridoc.progress import Progress
from hybridoc.solution import Solution, Status
from hybridoc.solvers.gd.descent import infeasibility, initial_controls, run_settings
from hybridoc.solvers.gd.limits import NonFinite, current_watch
from hybridoc.solvers.gd.loss import is_direct_both
from hybridoc.solvers.gd.options import DEFAULT_SMOOTHING, GDOptions

RHO_GROWTH = 10.0
"""Terminal constraints: the factor of the penalty when an outer iteration has not cut the
violation to :data:`RHO_PROGRESS` of the previous one."""


RHO_PROGRESS = 0.25
"""Terminal constraints: see :data:`RHO_GROWTH`."""


RHO_MAX = 1e9
"""Terminal constraints: the largest penalty (beyond it the inner problem is too stiff for
L-BFGS to gain anything)."""


TERMINAL_MARGIN = 0.1
"""The outer loop stops at this fraction of ``terminal_tol`` (on the simulation's final
state), so that the judge's own final state, equal up to rounding and the event-time Newton
iterations, is within the tolerance."""


_TERMINAL_LOSSES: weakref.WeakKeyDictionary[Structure, dict[tuple[Any, ...], Any]] = (
    weakref.WeakKeyDictionary()
)


def _terminal_loss(ocp: HybridOCP, path_weight: float) -> Any:
    """The :class:`~hybridoc.solvers.compiled.TerminalLoss` of a problem, kept per structure
    (the final time is an input of it, not part of the key)."""
    from hybridoc.solvers.compiled import TerminalLoss, per_structure

    key = (ocp.steps, path_weight, tuple(ocp.x0.tolist()))
    return per_structure(
        _TERMINAL_LOSSES, ocp, key, lambda: TerminalLoss(ocp, path_weight=path_weight)
    )


def _terminal_refusal(ocp: HybridOCP, opts: GDOptions) -> str | None:
    """Why gd cannot run ``opts`` on a problem with terminal constraints or a free final
    time (``None``: it can)."""
    what = "terminal constraints" if ocp.has_terminal_constraints else "a free final time"
    if ocp.has_terminal_constraints and ocp.free_horizon:
        what = "terminal constraints and a free final time"
    if opts.optimizer != "lbfgs":
        return (
            f"{what} are solved by an augmented Lagrangian around L-BFGS-B; optimizer "
            f"{opts.optimizer!r} is not supported there (use lbfgs)"
        )
    if opts.starts > 1 or opts.hops:
        return (
            f"the multi-start and the hops explore the unconstrained, fixed-time loss; with "
            f"{what} use starts=1 and hops=0 (and --controls for another start)"
        )
    if opts.path == "torch" or not is_direct_both(opts.contact) or opts.integrator != "exact":
        return (
            f"{what} use the compiled generic time-of-impact simulation (contact 'direct', "
            "TOI 'both', integrator 'exact', path 'auto' or 'compiled')"
        )
    if opts.max_step is not None:
        return f"max_step applies to gd's own L-BFGS; {what} use SciPy's L-BFGS-B"
    return None


class _Augmented:
    """The inner problem of the augmented Lagrangian: ``x = (u, z)`` with
    ``T = T0 + z sqrt(dt0)`` when the final time is free (the scale makes the curvature in
    ``z`` of the ``1 / dt0``-scaled objective comparable with that in a control value),
    objective ``(J + A + smoothing) / dt0``."""

    def __init__(self, ocp: HybridOCP, loss: Any, opts: GDOptions, progress: Progress) -> None:
        self.ocp, self.loss, self.opts, self.progress = ocp, loss, opts, progress
        self.shape = (ocp.steps, ocp.nu)
        self.T0 = float(ocp.horizon)
        self.dt0 = self.T0 / ocp.steps
        self.sz = math.sqrt(self.dt0)
        self.free = ocp.free_horizon
        self.nu = np.zeros(loss.n_eq)
        self.mu = np.zeros(loss.n_in)
        self.rho = float(opts.terminal_rho)
        self.penalty = 0.0
        self.n_evals = 0
        self.iterations = 0
        self.history: list[float] = []
        self.marks: list[list[Any]] = []  # [start in history, name] of each stage
        self.watch = current_watch()

    def pack(self, u: np.ndarray, T: float) -> np.ndarray:
        z = [(T - self.T0) / self.sz] if self.free else []
        return np.concatenate([np.ravel(u), z])

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, float]:
        n = self.shape[0] * self.shape[1]
        T = self.T0 + self.sz * float(x[n]) if self.free else self.T0
        return x[:n].reshape(self.shape), T

    def bounds(self) -> list[tuple[float, float]]:
        ocp = self.ocp
        out = list(zip(np.tile(ocp.u_min, ocp.steps), np.tile(ocp.u_max, ocp.steps), strict=True))
        if self.free:
            lo, hi = ocp.horizon_bounds  # type: ignore[misc]
            out.append(((lo - self.T0) / self.sz, (hi - self.T0) / self.sz))
        return [(None if math.isinf(a) else a, None if math.isinf(b) else b) for a, b in out]

    def fun(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        self.n_evals += 1
        if self.watch is not None:
            self.watch.check()
        if not np.isfinite(x).all():
            raise NonFinite("the controls or the final time became NaN or infinite")
        u, T = self.unpack(x)
        J, A, _, gU, gT = self.loss.evaluate(u, T, self.nu, self.mu, self.rho)
        if self.watch is not None:  # the latest: a lower J may violate the constraints
            self.watch.offer(float(J), u, T, latest=True)
        value = J + A
        if self.penalty:
            diff = u[1:] - u[:-1]
            value += self.penalty * float((diff * diff).sum()) / self.dt0
            w = 2.0 * self.penalty / self.dt0
            gU = gU.copy()
            gU[1:] += w * diff
            gU[:-1] -= w * diff
        grad = np.concatenate([np.ravel(gU), [gT * self.sz] if self.free else []])
        if not (math.isfinite(value) and np.isfinite(grad).all()):
            raise NonFinite(f"the loss or its gradient became non-finite ({value})")
        return value / self.dt0, grad / self.dt0

    def minimise(self, x0: np.ndarray) -> tuple[np.ndarray, str, bool]:
        """One inner L-BFGS-B solve from ``x0``: the result, SciPy's message, and whether
        it met its convergence test (not the iteration limit or a callback's stop)."""
        from scipy.optimize import minimize

        opts = self.opts
        k0 = self.iterations

        def cb(x: np.ndarray) -> None:
            self.iterations += 1
            if self.watch is not None:
                self.watch.iterations += 1
            u, _ = self.unpack(x)
            value = self.fun(x)[0] * self.dt0
            self.history.append(value)
            self.progress.count(self.iterations - k0, None, f"iterations, loss {value:.6g}")
            if opts.callback is not None and opts.callback(self.iterations, value, u.copy()):
                raise StopIteration

        res = minimize(
            self.fun, x0, jac=True, method="L-BFGS-B", bounds=self.bounds(), callback=cb,
            options={"maxiter": opts.iters, "maxfun": 20 * max(opts.iters, 1),
                     "ftol": 1e-15, "gtol": 1e-12},
        )  # fmt: skip
        if res.status == 99:
            return res.x, "stopped by the callback", False
        if res.status == 1 or opts.iters == 0:
            return res.x, f"finished the requested iterations (L-BFGS-B: {res.message})", False
        return res.x, f"converged: L-BFGS-B: {res.message}", True


def solve_terminal(ocp: HybridOCP, opts: GDOptions, initial: Any, progress: Progress) -> Solution:
    """gd on a problem with terminal constraints or a free final time (module notes):
    the augmented Lagrangian's outer loop around L-BFGS-B, judged at the final time found."""
    reason = _terminal_refusal(ocp, opts)
    if reason is not None:
        raise OptionError(f"gd cannot solve {ocp.name!r} so: {reason}")
    t_start = time.perf_counter()
    loss = _terminal_loss(ocp, opts.path_weight)
    prob = _Augmented(ocp, loss, opts, progress)
    u0 = initial_controls(ocp, initial)
    if ocp.has_bounds:
        u0 = np.clip(u0, ocp.u_min, ocp.u_max)
    x = prob.pack(u0, prob.T0)
    smoothing = DEFAULT_SMOOTHING if opts.smoothing is None else opts.smoothing
    tol = opts.terminal_tol
    outer: list[dict[str, Any]] = []
    message, converged, nan_stop = "", False, False
    try:
        # the smoothing stages (module notes on kinks) run on the first outer iteration only
        for i, mu_s in enumerate(smoothing):
            prob.marks.append([len(prob.history), f"mu {mu_s:g}"])
            progress.stage(
                f"smoothing stage {i + 1} of {len(smoothing)}, mu {mu_s:g} "
                f"(terminal penalty {prob.rho:g})"
            )
            prob.penalty = mu_s
            x, _, _ = prob.minimise(x)
        prob.penalty = 0.0
        previous = math.inf
        for k in range(opts.terminal_iters):
            if k == 0:  # one mark: a line per outer iteration would crowd the figure
                prob.marks.append([len(prob.history), "augmented Lagrangian"])
            progress.stage(
                f"augmented Lagrangian: outer iteration {k + 1} of at most "
                f"{opts.terminal_iters}, rho {prob.rho:g}"
            )
            x, message, converged = prob.minimise(x)
            u, T = prob.unpack(x)
            J, _, s_end, _, _ = loss.evaluate(u, T)
            he, hi = loss.constraints(s_end)
            # primal feasibility, and complementarity of the inequalities' multipliers
            viol = max(
                float(np.max(np.abs(he), initial=0.0)),
                float(np.max(np.abs(np.minimum(hi, prob.mu / prob.rho)), initial=0.0)),
            )
            outer.append({"rho": prob.rho, "violation": viol, "loss": J, "horizon": T})
            progress.detail(f"violation {viol:.3g}")
            if message == "stopped by the callback" or viol <= TERMINAL_MARGIN * tol:
                break
            prob.nu = prob.nu + prob.rho * he
            prob.mu = np.maximum(0.0, prob.mu - prob.rho * hi)
            if viol > RHO_PROGRESS * previous:
                prob.rho = min(prob.rho * RHO_GROWTH, RHO_MAX)
            previous = viol
    except NonFinite as exc:
        message, converged, nan_stop = f"stopped early: {exc}", False, True
    u, T = prob.unpack(x)
    J = float(loss.evaluate(u, T)[0])
    return _terminal_solution(ocp, opts, prob, u, T, J, outer, message, converged, nan_stop,
                              t_start)  # fmt: skip


def _terminal_solution(
    ocp: HybridOCP,
    opts: GDOptions,
    prob: _Augmented,
    u: np.ndarray,
    T: float,
    J: float,
    outer: list[dict[str, Any]],
    message: str,
    converged: bool,
    nan_stop: bool,
    t_start: float,
) -> Solution:
    """The judged Solution of :func:`solve_terminal`: the judge runs at the final time
    found, and its terminal violation decides between success and infeasible."""
    judged = ocp.replace(horizon=T) if ocp.free_horizon else ocp
    ev = evaluate(judged, u)
    violation = getattr(ev, "terminal_violation", None)
    if violation is None:  # a judge that does not report it yet: measure its final state
        violation = ocp.terminal_violation(ev.final_state)
    violation = float(violation)
    info: dict[str, Any] = {
        "loss": J,
        "iterations": prob.iterations,
        "loss_evaluations": prob.n_evals,
        "nan_stop": nan_stop,
        "diverged": False,
        "converged": converged,
        "message": message,
        "outer": outer,
        "terminal_violation": violation,
        "terminal_multipliers": {"eq": prob.nu.tolist(), "ineq": prob.mu.tolist()},
        "history_stages": prob.marks if prob.history else [],
    }
    if ocp.free_horizon:
        info["horizon"] = float(T)
    settings = {
        **run_settings(ocp, opts, "compiled"),
        "simulation": "generic",
        "optimizer": "lbfgs-b",
        "augmented_lagrangian": True,
        "terminal_tol": opts.terminal_tol,
        "terminal_rho": opts.terminal_rho,
        "terminal_iters": opts.terminal_iters,
        "smoothing": list(DEFAULT_SMOOTHING if opts.smoothing is None else opts.smoothing),
    }
    elapsed = time.perf_counter() - t_start
    sol = Solution.from_evaluation(
        ev,
        method="gd",
        scene=ocp.name,
        settings=settings,
        timings={"solve_time_s": elapsed, "optimization_time_s": elapsed},
        info=info,
        arrays={"loss_history": np.array(prob.history or [J], dtype=float)},
    )
    status, text = Status.SUCCESS, ""
    if not converged:
        status = Status.NOT_CONVERGED
        text = message or "the inner L-BFGS-B did not converge"
    if violation > opts.terminal_tol:
        status = Status.INFEASIBLE
        text = (
            f"the judge finds the terminal constraints violated by {violation:.3g}, above "
            f"terminal_tol {opts.terminal_tol:.3g}, after {len(outer)} outer iteration(s) "
            f"(penalty {prob.rho:g}); {text or 'raise terminal_iters'}"
        )
    elif status is Status.SUCCESS and max(ev.bound_violation, ev.path_violation) > (
        tolerances.FEASIBILITY
    ):
        status, text = Status.INFEASIBLE, infeasibility(ev)
    return sol.set_status(status, text)
