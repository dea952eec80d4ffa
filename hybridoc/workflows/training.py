"""Feedback policies: training through the differentiable simulator, and their exact gradient.

A feedback policy ``u = pi(t, s)`` is judged by :func:`hybridoc.evaluate` with
``policy=pi`` (zero-order hold: sampled at the grid times from the exact state and held over
the interval). This module trains such policies and differentiates that judgement.

:func:`mlp_policy`
    A small multilayer perceptron ``(t, s) -> u`` with an input normalisation from the scene
    and an output offset equal to the scene's initial control, so an untrained policy acts
    like the initial guess.
:func:`train_policy`
    Trains a policy on a batch of initial states by gradient descent (Adam or L-BFGS)
    through the closed-loop rollout of the differentiable disc simulator
    (:meth:`hybridoc.solvers.simulator.Simulator.rollout_policy`), with the paper's
    time-of-impact corrections (``toi="both"``) or without them (``toi="none"``).
:func:`closed_loop_cost`
    The judge's event-exact closed-loop cost as a differentiable torch scalar: its backward
    pass is the exact gradient with respect to the policy's parameters (and the initial
    states), by the discrete adjoint of the closed loop (below).

The exact closed-loop gradient
    With zero-order hold the closed loop is the discrete-time system
    ``s_{n+1} = F_n(s_n, u_n)``, ``u_n = pi(t_n, s_n; theta)``, where ``F_n`` is the exact
    flow over grid interval ``n`` with every event's jump. The open-loop adjoint of the judge
    (:func:`hybridoc.evaluator.adjoint`: transposed segment Jacobians, and the hybrid minimum
    principle's jump relation at every event, i.e. the saltation matrix) gives
    ``dF_n/ds^T mu`` and ``dF_n/du^T mu``. The closed-loop costate adds the policy's
    reaction at every grid time,

    .. math::

        g_n = \\frac{\\partial F_n}{\\partial u}^\\top \\mu_{n+1}
              + \\frac{\\partial c_n}{\\partial u}, \\qquad
        \\mu_n = \\frac{\\partial F_n}{\\partial s}^\\top \\mu_{n+1}
                 + \\frac{\\partial c_n}{\\partial s}
                 + \\frac{\\partial \\pi}{\\partial s}^\\top g_n,

    from ``mu_N = grad phi(s_N)``, and ``dJ/dtheta = sum_n (d pi/d theta)^T g_n``,
    ``dJ/ds_0 = mu_0``. The Jacobians ``d pi/ds`` come from torch in one batched call, and
    the parameter gradient from one vector-Jacobian product through the policy. The gradient
    is that of the judge's cost wherever the event sequence does not change under the
    perturbation (not at grazing contacts).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from hybridoc.errors import ControlsError, SceneError
from hybridoc.evaluator import adjoint, evaluate
from hybridoc.ocp import HybridOCP, as_float_array
from hybridoc.problem import ProblemLike, as_ocp, disc_scene
from hybridoc.progress import Progress, ProgressLike, progress_scope
from hybridoc.solvers.simulator import Simulator
from hybridoc.solvers.threads import torch_threads

__all__ = [
    "ClosedLoopGradient",
    "MLPPolicy",
    "TrainResult",
    "closed_loop_cost",
    "closed_loop_gradient",
    "mlp_policy",
    "train_policy",
]

OPTIMIZERS = ("adam", "lbfgs")


# ---------------------------------------------------------------------------- the policy
class MLPPolicy(torch.nn.Module):
    """A multilayer perceptron feedback policy ``u = pi(t, s)`` with fixed normalisations.

    ``pi(t, s) = u_offset + u_scale * net([2 t / T - 1, (s - s_mean) / s_scale])`` with
    ``net`` a ``tanh`` MLP. Called with ``t`` of shape ``()`` or ``(B,)`` and ``s`` of shape
    ``(nx,)`` or ``(B, nx)``; returns ``(nu,)`` or ``(B, nu)``, so the same module runs in the
    judge (one state at a time) and in the simulator (a batch). Rows of a batch are
    independent.

    Parameters
    ----------
    nx, nu
        State and control dimensions.
    hidden
        Width of each hidden layer.
    layers
        Number of hidden layers.
    horizon
        ``T``, for the time input.
    s_mean, s_scale
        ``(nx,)`` state offset and scale of the input normalisation.
    u_offset, u_scale
        ``(nu,)`` output offset and scale.
    generator
        Random generator of the initial weights.
    """

    def __init__(
        self,
        nx: int,
        nu: int,
        *,
        hidden: int,
        layers: int,
        horizon: float,
        s_mean: np.ndarray,
        s_scale: np.ndarray,
        u_offset: np.ndarray,
        u_scale: np.ndarray,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.nx, self.nu, self.horizon = int(nx), int(nu), float(horizon)
        f64 = torch.float64
        self.register_buffer("s_mean", torch.as_tensor(np.asarray(s_mean, float), dtype=f64))
        self.register_buffer("s_scale", torch.as_tensor(np.asarray(s_scale, float), dtype=f64))
        self.register_buffer("u_offset", torch.as_tensor(np.asarray(u_offset, float), dtype=f64))
        self.register_buffer("u_scale", torch.as_tensor(np.asarray(u_scale, float), dtype=f64))
        mods: list[torch.nn.Module] = []
        width = nx + 1
        for _ in range(layers):
            mods += [torch.nn.Linear(width, hidden, dtype=f64), torch.nn.Tanh()]
            width = hidden
        last = torch.nn.Linear(width, nu, dtype=f64)
        mods.append(last)
        self.net = torch.nn.Sequential(*mods)
        with torch.no_grad():
            for m in self.net:
                if isinstance(m, torch.nn.Linear):
                    bound = 1.0 / math.sqrt(m.in_features)
                    m.weight.copy_(
                        (torch.rand(m.weight.shape, generator=generator, dtype=f64) * 2 - 1) * bound
                    )
                    m.bias.zero_()
            # a small last layer: the untrained policy is close to the offset
            last.weight.mul_(0.1)

    def forward(self, t: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        """The controls ``(nu,)`` for one state ``(nx,)``, or ``(B, nu)`` for ``(B, nx)``."""
        single = state.ndim == 1
        s = state.reshape(-1, self.nx).to(torch.float64)
        tt = torch.as_tensor(t, dtype=torch.float64).reshape(-1)
        tt = tt.expand(s.shape[0]) if tt.numel() == 1 else tt
        z = torch.cat(
            [(2.0 * tt / self.horizon - 1.0)[:, None], (s - self.s_mean) / self.s_scale], 1
        )
        u = self.u_offset + self.u_scale * self.net(z)
        return u[0] if single else u


def mlp_policy(
    scene: ProblemLike, *, hidden: int = 32, layers: int = 2, seed: int = 0
) -> MLPPolicy:
    """A small MLP feedback policy for a disc scene that starts near its initial guess.

    The inputs are normalised with the scene's scales: the time to ``[-1, 1]``, positions
    relative to the initial state by the scene's length scale (the spread of the initial
    positions and targets, at least 1), velocities by the velocity the initial control
    reaches over the horizon (at least 1). The output is the scene's initial control (its
    mean over the grid) plus ``u_scale`` times the network, whose last layer starts small.

    Parameters
    ----------
    scene
        A disc scene (a :class:`~hybridoc.problems.Scene`, built-in name or TOML path).
    hidden
        Width of each hidden layer.
    layers
        Number of hidden layers.
    seed
        Seed of the initial weights (the result is deterministic).

    Returns
    -------
    MLPPolicy
        A float64 ``torch.nn.Module``.
    """
    sc = disc_scene(scene)
    if hidden < 1 or layers < 0:
        raise SceneError(f"hidden must be >= 1 and layers >= 0, got {hidden}, {layers}")
    x0 = sc.initial_state()
    n = sc.n_discs
    pts = [d.position for d in sc.discs] + [d.target for d in sc.discs if d.target is not None]
    pts_a = np.array(pts, dtype=float)
    length = max(1.0, float(np.max(pts_a.max(0) - pts_a.min(0))))
    u0 = sc.initial_controls()
    u_mag = float(np.max(np.abs(u0))) if u0.size else 0.0
    m_min = min(d.mass for d in sc.discs)
    speed = max(1.0, u_mag * sc.horizon / m_min)
    s_scale = np.r_[np.full(2 * n, length), np.full(2 * n, speed)]
    gen = torch.Generator().manual_seed(int(seed))
    return MLPPolicy(
        4 * n,
        sc.n_controls,
        hidden=int(hidden),
        layers=int(layers),
        horizon=sc.horizon,
        s_mean=x0,
        s_scale=s_scale,
        u_offset=u0.mean(0),
        u_scale=np.full(sc.n_controls, max(1.0, u_mag)),
        generator=gen,
    )


# ---------------------------------------------------------------------------- training
@dataclass
class TrainResult:
    """What :func:`train_policy` returns.

    Attributes
    ----------
    policy
        The trained policy (the same object that was passed in, trained in place).
    losses
        The simulator's mean closed-loop loss at each iteration (before its update).
    final_loss
        The loss after the last update.
    seconds
        Wall time of the training.
    toi, contact, integrator
        The simulator's settings.
    """

    policy: torch.nn.Module
    losses: list[float] = field(default_factory=list)
    final_loss: float = float("nan")
    seconds: float = 0.0
    toi: str = "both"
    contact: str = "direct"
    integrator: str = "symplectic-euler"


def train_policy(
    scene: ProblemLike,
    policy: torch.nn.Module,
    x0_batch: Any,
    *,
    toi: str = "both",
    iters: int = 100,
    lr: float = 1e-2,
    optimizer: str = "adam",
    contact: str = "direct",
    integrator: str = "symplectic-euler",
    seed: int = 0,
    schedule: str = "constant",
    keep_best: bool = True,
    callback: Callable[[int, float], None] | None = None,
    progress: ProgressLike = None,
) -> TrainResult:
    """Train a feedback policy through the closed-loop differentiable simulator.

    Minimises the mean over ``x0_batch`` of the simulator's discrete objective (terminal
    cost plus running cost, :meth:`~hybridoc.solvers.simulator.Simulator.policy_loss`) of
    the closed-loop rollout with zero-order hold, with full-batch Adam or L-BFGS.

    Parameters
    ----------
    scene
        A disc scene (its grid, costs and contact parameters; its initial state is not used).
    policy
        A batched ``torch.nn.Module`` ``(t (B,), s (B, nx)) -> u (B, nu)`` in float64, e.g.
        :func:`mlp_policy`. Trained in place.
    x0_batch
        ``(B, nx)`` initial states.
    toi
        Time-of-impact correction of the simulator: ``"both"`` (the paper's method),
        ``"none"``, ``"position"`` or ``"velocity"``.
    iters
        Optimiser iterations (L-BFGS: outer steps of at most 20 evaluations each).
    lr
        Learning rate.
    optimizer
        ``"adam"`` or ``"lbfgs"``.
    contact, integrator
        Contact model and integrator of the :class:`~hybridoc.solvers.simulator.Simulator`.
    seed
        Seeds torch's global generator before training (for policies with randomness).
    schedule
        Adam's learning rate: ``"constant"`` or ``"cosine"`` (from ``lr`` down to
        ``lr / 100`` over the iterations).
    keep_best
        Adam: end with the parameters of the lowest loss seen (the loss is not monotone
        with a constant step), not those of the last update.
    callback
        Called as ``callback(iteration, loss)`` after each iteration.
    progress
        ``None``/``False`` (silent, the default), ``True`` (a progress bar on stderr) or a
        :class:`~hybridoc.progress.Progress`: the training stage and its iterations, with
        the loss.

    Returns
    -------
    TrainResult

    Raises
    ------
    ControlsError
        Bad ``x0_batch`` or a policy that returns a wrong shape or non-finite value.
    SceneError
        An unknown optimiser or simulator setting.
    """
    params = _trainable(policy, optimizer, schedule, iters)
    sim = Simulator(scene, contact=contact, toi=toi, integrator=integrator)
    x0 = _x0_tensor(x0_batch, sim.nx, batch_only=True)
    torch.manual_seed(int(seed))
    result = TrainResult(policy, toi=toi, contact=sim.contact, integrator=integrator)
    t_start = time.perf_counter()
    with progress_scope(progress, "training") as p:
        p.stage(f"{optimizer} on {x0.shape[0]} initial states")
        step = _Steps(result, int(iters), callback, p)
        if optimizer == "adam":
            _train_adam(sim, policy, x0, params, lr, schedule, keep_best, step)
        else:
            _train_lbfgs(sim, policy, x0, params, lr, step)
    with torch.no_grad():
        result.final_loss = float(sim.policy_loss(policy, x0))
    result.seconds = time.perf_counter() - t_start
    return result


def _trainable(
    policy: torch.nn.Module, optimizer: str, schedule: str, iters: int
) -> list[torch.Tensor]:
    """The policy's parameters to train, after the checks of :func:`train_policy`'s
    arguments."""
    if optimizer not in OPTIMIZERS:
        raise SceneError(f"unknown optimizer {optimizer!r}; choose one of {', '.join(OPTIMIZERS)}")
    if schedule not in ("constant", "cosine"):
        raise SceneError(f"unknown schedule {schedule!r}; choose 'constant' or 'cosine'")
    if int(iters) < 0:
        raise SceneError(f"iters must be >= 0, got {iters}")
    if not isinstance(policy, torch.nn.Module):
        raise ControlsError(f"policy must be a torch.nn.Module, got {type(policy).__name__}")
    params = [p for p in policy.parameters() if p.requires_grad]
    if not params:
        raise ControlsError("the policy has no parameters that require grad: nothing to train")
    return params


@dataclass
class _Steps:
    """Where each iteration's loss goes: the result, the callback and the progress."""

    result: TrainResult
    iters: int
    callback: Callable[[int, float], None] | None
    progress: Progress

    def __call__(self, it: int, value: float) -> None:
        self.result.losses.append(value)
        if self.callback is not None:
            self.callback(it, value)
        self.progress.count(it + 1, self.iters, f"loss {value:.6g}")


def _train_adam(
    sim: Simulator,
    policy: torch.nn.Module,
    x0: torch.Tensor,
    params: list[torch.Tensor],
    lr: float,
    schedule: str,
    keep_best: bool,
    step: _Steps,
) -> None:
    """Full-batch Adam (:func:`train_policy`), ending with the best parameters seen when
    ``keep_best``."""
    opt = torch.optim.Adam(params, lr=lr)
    sched = (
        torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(step.iters, 1), eta_min=lr / 100)
        if schedule == "cosine"
        else None
    )
    best, best_state = math.inf, None
    for it in range(step.iters):
        opt.zero_grad()
        loss = sim.policy_loss(policy, x0)
        loss.backward()
        value = float(loss.detach())
        if keep_best and value < best:
            best = value
            best_state = {k: v.detach().clone() for k, v in policy.state_dict().items()}
        opt.step()
        if sched is not None:
            sched.step()
        step(it, value)
    if best_state is not None:
        with torch.no_grad():
            last = float(sim.policy_loss(policy, x0))
        if best < last:
            policy.load_state_dict(best_state)


def _train_lbfgs(
    sim: Simulator,
    policy: torch.nn.Module,
    x0: torch.Tensor,
    params: list[torch.Tensor],
    lr: float,
    step: _Steps,
) -> None:
    """Full-batch L-BFGS with a strong Wolfe line search (:func:`train_policy`)."""
    opt = torch.optim.LBFGS(params, lr=lr, max_iter=20, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = sim.policy_loss(policy, x0)
        loss.backward()
        return loss

    for it in range(step.iters):
        loss = opt.step(closure)
        step(it, float(loss.detach()))


def _x0_tensor(x0: Any, nx: int, *, batch_only: bool = False) -> torch.Tensor:
    """``x0`` as a float64 ``(B, nx)`` tensor, or one clear ControlsError."""
    if isinstance(x0, torch.Tensor):
        x = x0.to(torch.float64)
        if x.is_complex():
            raise ControlsError("x0 must be real numbers")
    else:
        x = torch.as_tensor(as_float_array(x0, "x0", error=ControlsError))
    ok = x.ndim == 2 if batch_only else x.ndim in (1, 2)
    if not ok or x.shape[-1] != nx or x.numel() == 0:
        want = f"(B, {nx})" if batch_only else f"({nx},) or (B, {nx})"
        raise ControlsError(f"x0 must have shape {want}, got {tuple(x.shape)}")
    if not bool(torch.isfinite(x).all()):
        raise ControlsError("x0 contains NaN or infinite values")
    return x.reshape(-1, nx)


# ---------------------------------------------------------------------------- exact gradient
@dataclass
class ClosedLoopGradient:
    """The judge's closed-loop evaluation of one initial state and its adjoint quantities.

    Attributes
    ----------
    cost
        The judge's cost ``J``.
    d_controls
        ``(N, nu)``: ``g_n``, the derivative of ``J`` with respect to ``u_n`` alone, the
        policy's reaction in later intervals included.
    d_initial_state
        ``(nx,)``: ``dJ/ds(0)`` of the closed loop.
    grid_states
        ``(N, nx)``: the states ``s(t_n)`` at which the policy was called.
    feedback
        ``(N, nu, nx)``: the policy's state Jacobians there.
    evaluation
        The judge's :class:`~hybridoc.evaluation.Evaluation`.
    """

    cost: float
    d_controls: np.ndarray
    d_initial_state: np.ndarray
    grid_states: np.ndarray
    feedback: np.ndarray
    evaluation: Any


def _policy_batch(
    policy: Callable[..., Any], t: torch.Tensor, s: torch.Tensor, nu: int
) -> torch.Tensor:
    try:
        out = policy(t, s)
    except Exception as exc:
        raise ControlsError(
            f"the policy raised {type(exc).__name__} on a batch of {s.shape[0]} states "
            f"(closed_loop_cost calls it batched: t (B,), state (B, nx)): {exc}"
        ) from exc
    if not isinstance(out, torch.Tensor) or tuple(out.shape) != (s.shape[0], nu):
        shape = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
        raise ControlsError(
            f"the policy returned {shape} for a batch of {s.shape[0]} states; expected "
            f"({s.shape[0]}, {nu}): closed_loop_cost needs a batched torch policy"
        )
    if not bool(torch.isfinite(out).all()):
        raise ControlsError("the policy returned a non-finite control")
    return out


def closed_loop_gradient(
    problem: ProblemLike, policy: Callable[..., Any], x0: Any = None, **kwargs: Any
) -> ClosedLoopGradient:
    """The judge's zero-order-hold closed-loop evaluation and its exact adjoint.

    Parameters
    ----------
    problem
        Anything :func:`hybridoc.evaluate` accepts.
    policy
        A batched torch policy ``(t (B,), s (B, nx)) -> (B, nu)`` that also accepts one
        state (``t`` of shape ``()``, ``s`` of shape ``(nx,)``), e.g. :func:`mlp_policy`.
    x0
        ``(nx,)`` initial state; default the problem's.
    **kwargs
        Passed to :func:`hybridoc.evaluate` (``graze_tol``, ...).

    Returns
    -------
    ClosedLoopGradient
    """
    ocp = as_ocp(problem)
    if x0 is not None:
        ocp = ocp.replace(x0=_x0_tensor(x0, ocp.nx)[0].detach().numpy().copy())
    ev = evaluate(ocp, policy=policy, hold="zoh", **kwargs)
    idx = np.array([seg.interval for seg in ev.segments], dtype=int)
    first = np.flatnonzero(np.r_[True, idx[1:] != idx[:-1]])
    S = np.array([ev.segments[i].s0 for i in first])
    assert S.shape == (ocp.steps, ocp.nx)
    J = _state_jacobians(policy, ocp, S)
    g = adjoint(ev, feedback=J)
    return ClosedLoopGradient(
        cost=ev.cost,
        d_controls=g.d_controls,
        d_initial_state=g.d_initial_state,
        grid_states=S,
        feedback=J,
        evaluation=ev,
    )


def _state_jacobians(policy: Callable[..., Any], ocp: HybridOCP, S: np.ndarray) -> np.ndarray:
    """``d pi/d s (t_n, s_n)``, ``(N, nu, nx)``, by ``nu`` backward passes of one batch."""
    t = torch.as_tensor(ocp.time_grid()[:-1], dtype=torch.float64)
    s = torch.as_tensor(S, dtype=torch.float64).requires_grad_(True)
    with torch.enable_grad():
        out = _policy_batch(policy, t, s, ocp.nu)
        if not out.requires_grad:  # the policy ignores the state
            return np.zeros((S.shape[0], ocp.nu, ocp.nx))
        rows = []
        for j in range(ocp.nu):
            (gj,) = torch.autograd.grad(
                out[:, j].sum(), s, retain_graph=j < ocp.nu - 1, allow_unused=True
            )
            rows.append(torch.zeros_like(s) if gj is None else gj)
    return torch.stack(rows, 1).detach().numpy()


class _ClosedLoopCost(torch.autograd.Function):
    @staticmethod
    def forward(ctx: Any, runner: _Runner, x0: torch.Tensor, *params: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        results = [runner.one(row) for row in x0.detach()]
        ctx.runner = runner
        ctx.results = results
        ctx.n_params = len(params)
        ctx.save_for_backward(*params)
        cost = float(np.mean([r.cost for r in results]))
        return torch.tensor(cost, dtype=torch.float64)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[Any, ...]:  # type: ignore[override]
        runner: _Runner = ctx.runner
        results: list[ClosedLoopGradient] = ctx.results
        params = ctx.saved_tensors
        B = len(results)
        w = grad.to(torch.float64) / B
        d_x0 = torch.as_tensor(np.array([r.d_initial_state for r in results])) * w
        if not params:
            return (None, d_x0)
        ocp = runner.ocp
        t = torch.as_tensor(np.tile(ocp.time_grid()[:-1], B), dtype=torch.float64)
        s = torch.as_tensor(np.concatenate([r.grid_states for r in results]), dtype=torch.float64)
        g = torch.as_tensor(np.concatenate([r.d_controls for r in results])) * w
        with torch.enable_grad():
            out = _policy_batch(runner.policy, t, s, ocp.nu)
            if not out.requires_grad:  # no parameter acts on the output
                return (None, d_x0, *(torch.zeros_like(p) for p in params))
            grads = torch.autograd.grad(out, params, grad_outputs=g, allow_unused=True)
            grads = tuple(
                torch.zeros_like(p) if gr is None else gr
                for p, gr in zip(params, grads, strict=True)
            )
        return (None, d_x0, *grads)


class _Runner:
    def __init__(self, ocp: HybridOCP, policy: Callable[..., Any], kwargs: dict[str, Any]) -> None:
        self.ocp, self.policy, self.kwargs = ocp, policy, kwargs

    def one(self, x0: torch.Tensor) -> ClosedLoopGradient:
        return closed_loop_gradient(self.ocp, self.policy, x0, **self.kwargs)


def closed_loop_cost(
    problem: ProblemLike,
    policy: torch.nn.Module | Callable[..., Any],
    x0: Any = None,
    *,
    params: Sequence[torch.Tensor] | None = None,
    **kwargs: Any,
) -> torch.Tensor:
    """The judge's closed-loop cost (zero-order hold) as a differentiable torch scalar.

    The value is the mean over the initial states of
    ``hybridoc.evaluate(problem with x0, policy=policy).cost``, the event-exact continuous
    cost. Its backward pass is the exact gradient (module notes) with respect to the
    policy's parameters, and to ``x0`` when that is a tensor that requires grad. It is the
    derivative of the judge's cost wherever the event sequence does not change under the
    perturbation.

    Parameters
    ----------
    problem
        Anything :func:`hybridoc.evaluate` accepts.
    policy
        A batched torch policy ``(t (B,), s (B, nx)) -> (B, nu)`` that also accepts a single
        state (``t`` of shape ``()``, ``s`` of shape ``(nx,)``), such as :func:`mlp_policy`;
        rows of a batch must be independent.
    x0
        ``(nx,)`` or ``(B, nx)`` initial states; default the problem's.
    params
        The tensors to differentiate with respect to; default the policy's parameters that
        require grad.
    **kwargs
        Passed to :func:`hybridoc.evaluate` (``graze_tol``, ``penetration_tol``, ...).

    Returns
    -------
    torch.Tensor
        A float64 scalar; ``.backward()`` fills the parameters' ``.grad``.

    Raises
    ------
    ControlsError
        A wrong ``x0``, or a policy that raises or returns a wrong shape or non-finite value.
    EvaluationError
        What the judge raises (sustained contact, Zeno behaviour, ...).
    """
    torch_threads()
    ocp = as_ocp(problem)
    if x0 is None:
        x = torch.as_tensor(ocp.x0, dtype=torch.float64)[None, :]
    else:
        x = _x0_tensor(x0, ocp.nx)
    if params is None:
        params = (
            [p for p in policy.parameters() if p.requires_grad]
            if isinstance(policy, torch.nn.Module)
            else []
        )
    return _ClosedLoopCost.apply(_Runner(ocp, policy, kwargs), x, *params)
