"""Feedback policies, the optimiser steps (:mod:`hybridoc.workflows.training`): Adam and
L-BFGS on a policy's parameters without ``torch.optim`` (:class:`TensorAdam`,
:func:`cosine_annealing_lrs`), and :class:`Steps`, where each iteration's loss goes."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from hybridoc.errors import EvaluationError, SceneError
from hybridoc.solvers.optimizers import LBFGS, lbfgs_torch_step

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.progress import Progress
    from hybridoc.workflows.training import TrainResult


@dataclass
class Steps:
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

    def stop(self, it: int, exc: EvaluationError) -> None:
        """Record why the training ends at iteration ``it``."""
        self.result.message = (
            f"stopped at iteration {it + 1} of {self.iters}: the judge could not simulate a "
            f"closed loop ({exc}); the policy has the best parameters judged"
        )
        self.progress.detail(self.result.message)


def _snapshot(policy: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in policy.state_dict().items()}


def train_adam(
    loss_fn: Callable[[], torch.Tensor],
    policy: torch.nn.Module,
    params: list[torch.Tensor],
    lr: float,
    schedule: str,
    keep_best: bool,
    step: Steps,
) -> None:
    """Full-batch Adam (:func:`train_policy`), ending with the best parameters seen when
    ``keep_best`` (or when the judge fails on an update: then training stops)."""
    opt = TensorAdam(params, lr)
    lrs = (
        cosine_annealing_lrs(lr, lr / 100, max(step.iters, 1), step.iters)
        if schedule == "cosine"
        else None
    )
    best, best_state = math.inf, None
    for it in range(step.iters):
        opt.zero_grad()
        try:
            loss = loss_fn()
        except EvaluationError as exc:
            step.stop(it, exc)
            break
        loss.backward()
        value = float(loss.detach())
        if (keep_best or step.result.engine == "judge") and value < best:
            best = value
            best_state = _snapshot(policy)
        opt.step()
        if lrs is not None:
            opt.lr = lrs[it + 1]
        step(it, value)
    if best_state is None:
        return
    last = math.inf
    if not step.result.message:
        try:
            with torch.no_grad():
                last = float(loss_fn())
        except EvaluationError:
            pass  # the last update cannot be judged: the best parameters seen
    if keep_best and best < last or not math.isfinite(last):
        policy.load_state_dict(best_state)
        step.result.final_loss = best
    else:
        step.result.final_loss = last


def train_lbfgs(
    loss_fn: Callable[[], torch.Tensor],
    policy: torch.nn.Module,
    params: list[torch.Tensor],
    lr: float,
    step: Steps,
) -> None:
    """Full-batch L-BFGS with a strong Wolfe line search (:func:`train_policy`); a step the
    judge cannot simulate ends the training with the parameters before it.

    Each iteration is one call of ``torch.optim.LBFGS(max_iter=20,
    line_search_fn="strong_wolfe")`` with torch's defaults, by its numpy port
    (:func:`~hybridoc.solvers.optimizers.lbfgs_torch_step`) on the flattened parameters.
    torch's call first evaluates the loss where the previous call ended, which that call's
    line search has just done: the loss is deterministic, so its value and gradient are
    reused (one closed loop of the batch less per iteration, and at the end)."""
    opt = LBFGS(lr, history_size=100, tolerance_grad=1e-7, tolerance_change=1e-9)
    flat = FlatParameters(params)

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        flat.set(x)
        for p in params:
            p.grad = None
        loss = loss_fn()
        loss.backward()
        return float(loss.detach()), flat.grad()

    x = flat.get()
    start: tuple[float, np.ndarray] | None = None  # the loss and gradient at x
    for it in range(step.iters):
        before = _snapshot(policy)
        try:
            if start is None:
                start = fun(x)
            f, g = start
            x_new, f_new, g_new = lbfgs_torch_step(opt, fun, x, f, g, max_iter=20)
        except EvaluationError as exc:
            policy.load_state_dict(before)
            step.stop(it, exc)
            break
        x, start = x_new, (f_new, g_new)
        flat.set(x)
        step(it, f)
    if start is not None:
        step.result.final_loss = start[0]


class FlatParameters:
    """Tensors as one flat numpy vector (their common dtype) and back: L-BFGS's iterate."""

    def __init__(self, params: list[torch.Tensor]) -> None:
        self.params = params

    def get(self) -> np.ndarray:
        return np.concatenate([p.detach().cpu().numpy().ravel() for p in self.params])

    def grad(self) -> np.ndarray:
        # no gradient (a parameter the loss does not use): zeros, as torch.optim.LBFGS
        return np.concatenate([
            torch.zeros(p.numel(), dtype=p.dtype).numpy() if p.grad is None
            else p.grad.detach().cpu().numpy().ravel()
            for p in self.params
        ])  # fmt: skip

    def set(self, x: np.ndarray) -> None:
        offset = 0
        with torch.no_grad():
            for p in self.params:
                n = p.numel()
                p.copy_(torch.as_tensor(x[offset : offset + n]).view_as(p))
                offset += n


class TensorAdam:
    """Adam on torch tensors in place: ``torch.optim.Adam``'s step, without ``torch.optim``.

    The arithmetic of torch's single-tensor Adam (its CPU path) with its defaults: no
    weight decay, no AMSGrad, ``maximize=False``. Per tensor, at its ``k``-th step,
    ``m.lerp_(g, 1 - beta1)``, ``v.mul_(beta2).addcmul_(g, g, value=1 - beta2)``, then
    ``p.addcdiv_(m, v.sqrt() / sqrt(1 - beta2^k) + eps, value=-lr / (1 - beta1^k))``;
    a tensor without a gradient is skipped (and its ``k`` does not advance), so the
    iterates are those of ``torch.optim.Adam`` bit for bit on the CPU, in float64 and
    float32. Building a ``torch.optim`` optimiser imports ``torch._dynamo`` the first time
    (seconds per process); this does not.

    Parameters
    ----------
    params
        The tensors to train (leaves that require grad).
    lr
        The learning rate; the attribute ``lr`` may be changed between steps (a schedule).
    betas
        The decay rates of the gradient's first and second moment averages.
    eps
        Added to the denominator.

    Raises
    ------
    SceneError
        ``lr`` negative or not finite, or ``betas`` outside ``[0, 1)``.
    """

    def __init__(
        self,
        params: Sequence[torch.Tensor],
        lr: float,
        betas: tuple[float, float] = (0.9, 0.999),
        eps: float = 1e-8,
    ) -> None:
        if not lr >= 0 or not math.isfinite(lr):
            raise SceneError(f"lr must be a finite number >= 0, got {lr}")
        if not all(0.0 <= b < 1.0 for b in betas):
            raise SceneError(f"betas must be in [0, 1), got {betas}")
        self.params = list(params)
        self.lr = lr
        self.betas = betas
        self.eps = eps
        self.steps = [0] * len(self.params)
        self.moments: list[tuple[torch.Tensor, torch.Tensor] | None] = [None] * len(self.params)

    def zero_grad(self) -> None:
        """Forget the gradients (``None``, as ``torch.optim``'s ``zero_grad``)."""
        for p in self.params:
            p.grad = None

    def step(self) -> None:
        """One Adam step of every tensor that has a gradient."""
        beta1, beta2 = self.betas
        with torch.no_grad():
            for i, p in enumerate(self.params):
                grad = p.grad
                if grad is None:
                    continue
                if self.moments[i] is None:
                    zeros = torch.zeros_like(p, memory_format=torch.preserve_format)
                    self.moments[i] = (zeros, zeros.clone())
                exp_avg, exp_avg_sq = self.moments[i]  # type: ignore[misc]
                self.steps[i] += 1
                # torch counts steps in a float tensor and raises the betas to its value
                k = float(self.steps[i])
                exp_avg.lerp_(grad, 1 - beta1)
                exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
                step_size = self.lr / (1 - beta1**k)
                bias_correction2_sqrt = (1 - beta2**k) ** 0.5
                denom = (exp_avg_sq.sqrt() / bias_correction2_sqrt).add_(self.eps)
                p.addcdiv_(exp_avg, denom, value=-step_size)


def cosine_annealing_lrs(base_lr: float, eta_min: float, t_max: int, steps: int) -> list[float]:
    """The learning rates of ``torch.optim.lr_scheduler.CosineAnnealingLR``, step by step.

    Its recursive form (what its ``step()`` computes from the previous rate), so that the
    rates are torch's bit for bit; they follow
    ``eta_min + (base_lr - eta_min) (1 + cos(pi k / t_max)) / 2`` up to rounding.

    Parameters
    ----------
    base_lr
        The rate before the first step.
    eta_min
        The lowest rate.
    t_max
        The steps from ``base_lr`` down to ``eta_min`` (``>= 1``).
    steps
        How many scheduler steps.

    Returns
    -------
    list of float
        ``steps + 1`` rates: ``[0]`` is ``base_lr``, ``[k]`` the rate after ``k`` steps.

    Raises
    ------
    SceneError
        ``t_max < 1``.
    """
    if t_max < 1:
        raise SceneError(f"t_max must be >= 1, got {t_max}")
    lrs = [base_lr]
    lr = base_lr
    for k in range(1, steps + 1):
        if (k - 1 - t_max) % (2 * t_max) == 0:
            # torch's restart branch: past the minimum the rate climbs back
            lr = lr + (base_lr - eta_min) * (1 - math.cos(math.pi / t_max)) / 2
        else:
            # torch's order of operations: (ratio * (lr - eta_min)) + eta_min
            ratio = (1 + math.cos(math.pi * k / t_max)) / (1 + math.cos(math.pi * (k - 1) / t_max))
            lr = ratio * (lr - eta_min) + eta_min
        lrs.append(lr)
    return lrs
