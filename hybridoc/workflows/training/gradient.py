"""Feedback policies, the exact closed-loop gradient (:mod:`hybridoc.workflows.training`):
the judge's event-exact closed-loop cost as a differentiable torch scalar
(:func:`closed_loop_cost`, :func:`closed_loop_gradient`, :func:`judged_loss`); the
derivation is in the package's notes."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from hybridoc.errors import ControlsError
from hybridoc.evaluator import adjoint, evaluate
from hybridoc.ocp import HybridOCP, as_float_array
from hybridoc.problem import ProblemLike, as_ocp
from hybridoc.solvers.threads import torch_threads
from hybridoc.workflows.training.policy import MLPPolicy


def judged_loss(
    problem: ProblemLike,
    policy: torch.nn.Module,
    x0: Any,
    *,
    params: Sequence[torch.Tensor] | None = None,
) -> torch.Tensor:
    """What :func:`train_policy` minimises on a problem that is not a disc scene.

    The mean over ``x0`` of the judge's closed-loop cost (zero-order hold) as a
    differentiable torch scalar, as :func:`closed_loop_cost`, except that the judge rolls
    out a numpy copy of an :class:`MLPPolicy` (the function its saved policy file computes,
    the same to rounding, ten times faster to call per grid step than the module); the
    backward pass differentiates the module along that closed loop by the exact discrete
    adjoint, event times included (module notes).

    Parameters
    ----------
    problem
        Anything :func:`hybridoc.evaluate` accepts.
    policy
        A batched torch policy (:func:`closed_loop_cost`), e.g. :func:`mlp_policy`.
    x0
        ``(nx,)`` or ``(B, nx)`` initial states.
    params
        The tensors to differentiate with respect to; default the policy's parameters that
        require grad.

    Returns
    -------
    torch.Tensor
        A float64 scalar; ``.backward()`` fills the parameters' ``.grad``.

    Raises
    ------
    ControlsError, EvaluationError
        As :func:`closed_loop_cost`.
    """
    torch_threads()
    ocp = as_ocp(problem)
    x = x0_tensor(x0, ocp.nx)
    if params is None:
        params = [p for p in policy.parameters() if p.requires_grad]
    runner = _Runner(ocp, policy, {}, judge_policy=numpy_twin(policy))
    return _ClosedLoopCost.apply(runner, x, *params)


def numpy_twin(policy: torch.nn.Module) -> Callable[..., Any]:
    """What the judge rolls out for ``policy``: for an :class:`MLPPolicy`, the same function
    in numpy (as the saved policy file computes it; a torch call per grid step costs ten
    times more than the judge's step), otherwise the policy itself."""
    if not isinstance(policy, MLPPolicy):
        return policy
    layers = [m for m in policy.net if isinstance(m, torch.nn.Linear)]
    if len(layers) + sum(isinstance(m, torch.nn.Tanh) for m in policy.net) != len(policy.net):
        return policy

    def arr(x: torch.Tensor) -> np.ndarray:
        return x.detach().cpu().numpy().astype(float).copy()

    Ws = [arr(m.weight) for m in layers]
    bs = [arr(m.bias) for m in layers]
    mean, scale = arr(policy.s_mean), arr(policy.s_scale)
    off, gain = arr(policy.u_offset), arr(policy.u_scale)
    lo = None if policy.u_min is None else arr(policy.u_min)
    hi = None if policy.u_max is None else arr(policy.u_max)
    horizon = policy.horizon

    def numpy_policy(t: float, state: np.ndarray) -> np.ndarray:
        z = np.concatenate([[2.0 * float(t) / horizon - 1.0], (state - mean) / scale])
        for k, (W, b) in enumerate(zip(Ws, bs, strict=True)):
            z = W @ z + b
            if k < len(Ws) - 1:
                z = np.tanh(z)
        u = off + gain * z
        # the same clip as MLPPolicy.forward and the policy file's (exact: max, min)
        return u if lo is None else np.minimum(np.maximum(u, lo), hi)

    return numpy_policy


def x0_tensor(x0: Any, nx: int, *, batch_only: bool = False) -> torch.Tensor:
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
    return _closed_loop(as_ocp(problem), policy, policy, x0, kwargs)


def _closed_loop(
    ocp: HybridOCP,
    policy: Callable[..., Any],
    judge_policy: Callable[..., Any],
    x0: Any,
    kwargs: dict[str, Any],
) -> ClosedLoopGradient:
    """:func:`closed_loop_gradient` with ``judge_policy`` rolled out (the same function as
    ``policy``, which is differentiated)."""
    if x0 is not None:
        ocp = ocp.replace(x0=x0_tensor(x0, ocp.nx)[0].detach().numpy().copy())
    ev = evaluate(ocp, policy=judge_policy, hold="zoh", **kwargs)
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
    """The closed loops of :class:`_ClosedLoopCost`: ``judge_policy`` (default ``policy``)
    is rolled out by the judge, ``policy`` differentiated."""

    def __init__(
        self,
        ocp: HybridOCP,
        policy: Callable[..., Any],
        kwargs: dict[str, Any],
        judge_policy: Callable[..., Any] | None = None,
    ) -> None:
        self.ocp, self.policy, self.kwargs = ocp, policy, kwargs
        self.judge_policy = policy if judge_policy is None else judge_policy

    def one(self, x0: torch.Tensor) -> ClosedLoopGradient:
        return _closed_loop(self.ocp, self.policy, self.judge_policy, x0, self.kwargs)


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
        x = x0_tensor(x0, ocp.nx)
    if params is None:
        params = (
            [p for p in policy.parameters() if p.requires_grad]
            if isinstance(policy, torch.nn.Module)
            else []
        )
    return _ClosedLoopCost.apply(_Runner(ocp, policy, kwargs), x, *params)
