"""Policy training's own optimiser steps against ``torch.optim``, which they replace.

``torch.optim``'s first optimiser imports ``torch._dynamo`` (seconds per process), so
training runs :class:`~hybridoc.workflows.training.TensorAdam`,
:func:`~hybridoc.workflows.training.cosine_annealing_lrs` and the numpy port of
``torch.optim.LBFGS`` (:func:`~hybridoc.solvers.optimizers.lbfgs_torch_step`). Adam and
the schedule give torch's iterates bit for bit; L-BFGS agrees to rounding, which the
iterations amplify as the problem's conditioning does (measured: torch against itself
from a start one ulp away on single-collision, 24 steps, differs by 1.7e-12, 5e-10 and
1.7e-7 relative after one, two and three calls of ``step``).

The references construct ``torch.optim`` optimisers, so the first test here in a process
pays the ``torch._dynamo`` import (the ``torch_optim`` fixture, in its set-up).
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

import hybridoc
from hybridoc.errors import EvaluationError, SceneError
from hybridoc.solvers.optimizers import LBFGS, lbfgs_torch_step
from hybridoc.solvers.simulator import Simulator
from hybridoc.workflows import training
from hybridoc.workflows.training import (
    TensorAdam,
    cosine_annealing_lrs,
    mlp_policy,
    train_policy,
)


@pytest.fixture(scope="module")
def torch_optim() -> None:
    """Construct one torch optimiser first: its one-time torch._dynamo import is set-up."""
    torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=0.1)


def _mlp(dtype: torch.dtype = torch.float64, seed: int = 0) -> tuple[torch.nn.Module, ...]:
    """A small tanh MLP, an extra offset, and regression data (a smooth, non-convex loss)."""
    gen = torch.Generator().manual_seed(seed)
    net = torch.nn.Sequential(
        torch.nn.Linear(3, 8, dtype=dtype), torch.nn.Tanh(), torch.nn.Linear(8, 2, dtype=dtype)
    )
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(0.5 * torch.randn(p.shape, generator=gen, dtype=dtype))
    offset = torch.nn.Parameter(torch.randn(2, generator=gen, dtype=dtype))
    X = torch.randn(40, 3, generator=gen, dtype=dtype)
    Y = torch.sin(2 * X[:, :2]) + X[:, 2:] ** 2
    return net, offset, X, Y


def _flat(params: list[torch.Tensor]) -> np.ndarray:
    return np.concatenate([p.detach().numpy().ravel() for p in params])


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("schedule", ["constant", "cosine"])
def test_adam_is_torch_optim_adam_bit_for_bit(torch_optim, dtype, schedule):
    """50 steps of TensorAdam (and the cosine rates, set after each step as train_policy
    does) against torch.optim.Adam and CosineAnnealingLR: the same parameters bit for bit
    after every step. The offset enters the loss on even steps only, so on odd steps it has
    no gradient: both skip it and its step count lags."""
    steps, lr = 50, 0.05
    runs = []
    for ours in (False, True):
        net, offset, X, Y = _mlp(dtype)
        params = [*net.parameters(), offset]
        if ours:
            opt = TensorAdam(params, lr)
            lrs = cosine_annealing_lrs(lr, lr / 100, steps, steps)
        else:
            opt = torch.optim.Adam(params, lr=lr)
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps, eta_min=lr / 100)
        trace = []
        for k in range(steps):
            opt.zero_grad()
            out = net(X) + offset if k % 2 == 0 else net(X)
            ((out - Y) ** 2).mean().backward()
            opt.step()
            if schedule == "cosine":
                if ours:
                    opt.lr = lrs[k + 1]
                else:
                    sched.step()
            trace.append([p.detach().clone() for p in params])
        runs.append(trace)
    start = [p.detach() for p in [*_mlp(dtype)[0].parameters(), _mlp(dtype)[1]]]
    assert not torch.equal(runs[0][-1][0], start[0])  # it trained
    for k, (ref, ours) in enumerate(zip(*runs, strict=True)):
        for a, b in zip(ref, ours, strict=True):
            assert a.dtype == b.dtype == dtype
            assert torch.equal(a, b), f"step {k + 1}: max diff {float((a - b).abs().max())}"


@pytest.mark.parametrize("t_max", [1, 7, 30])
def test_cosine_rates_are_cosine_annealing_lr_bit_for_bit(torch_optim, t_max):
    """30 scheduler steps (past t_max = 1 and 7: torch's rates climb back there): the same
    rates bit for bit as CosineAnnealingLR, and the closed form to rounding."""
    base, eta_min, steps = 0.03, 3e-4, 30
    p = torch.zeros(2, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.SGD([p], lr=base)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, t_max, eta_min=eta_min)
    ref = [sched.get_last_lr()[0]]
    for _ in range(steps):
        opt.step()
        sched.step()
        ref.append(sched.get_last_lr()[0])
    ours = cosine_annealing_lrs(base, eta_min, t_max, steps)
    assert ours == ref
    k = np.arange(steps + 1)
    closed = eta_min + (base - eta_min) * (1 + np.cos(np.pi * k / t_max)) / 2
    np.testing.assert_allclose(ours, closed, rtol=1e-12, atol=1e-15)
    assert ours[min(t_max, steps)] == pytest.approx(eta_min, rel=1e-12)
    with pytest.raises(SceneError, match="t_max"):
        cosine_annealing_lrs(base, eta_min, 0, steps)


def test_lbfgs_torch_step_is_torch_optim_lbfgs_to_rounding(torch_optim):
    """Two calls (40 iterations) of lbfgs_torch_step on the flattened parameters of the MLP
    regression against torch.optim.LBFGS(max_iter=20, line_search_fn="strong_wolfe"): the
    same losses at the start of each call and the same parameters to 1e-11 relative
    (measured 6.5e-15 after one call, 5e-12 after three, 1.2e-8 after six: rounding grown by
    the iterations), with the same number of iterations."""
    net, offset, X, Y = _mlp()
    params = list(net.parameters())
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=20, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = ((net(X) - Y) ** 2).mean()
        loss.backward()
        return loss

    ref_losses = [float(opt.step(closure).detach()) for _ in range(2)]
    ref = _flat(params)
    ref_iters = opt.state[params[0]]["n_iter"]

    net, offset, X, Y = _mlp()
    params = list(net.parameters())
    flat = training._FlatParameters(params)

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        flat.set(x)
        for p in params:
            p.grad = None
        loss = ((net(X) - Y) ** 2).mean()
        loss.backward()
        return float(loss.detach()), flat.grad()

    ours = LBFGS(1.0, history_size=100, tolerance_grad=1e-7, tolerance_change=1e-9)
    x = flat.get()
    f, g = fun(x)
    losses = []
    for _ in range(2):
        losses.append(f)
        x, f, g = lbfgs_torch_step(ours, fun, x, f, g, max_iter=20)
    assert ours.n_iter == ref_iters == 40
    np.testing.assert_allclose(losses, ref_losses, rtol=1e-13)
    assert f < 0.5 * losses[0]  # it trained
    rel = np.abs(x - ref).max() / np.abs(ref).max()
    print(f"lbfgs_torch_step vs torch.optim.LBFGS after 40 iterations: {rel:.2e} relative")
    assert rel < 1e-11


def test_lbfgs_training_is_torch_optim_lbfgs_to_rounding(torch_optim):
    """train_policy(optimizer="lbfgs") on single-collision (8 steps, two initial states)
    against the loop it replaced, torch.optim.LBFGS on the simulator's loss: one iteration
    (8 of torch's, its 25 evaluations spent), the same loss and final loss to 1e-13
    relative and the same parameters to 1e-13 relative (measured 4e-16 after one
    iteration, 8e-16 after three on 12 steps)."""
    scene = hybridoc.load_scene("single-collision").with_steps(8)
    x0 = np.tile(scene.initial_state(), (2, 1))
    x0[1, 2:4] += 0.2
    pol = mlp_policy(scene, hidden=4, layers=1, seed=0)
    res = train_policy(scene, pol, x0, iters=1, lr=1.0, optimizer="lbfgs")

    ref_pol = mlp_policy(scene, hidden=4, layers=1, seed=0)
    sim, x0_t = Simulator(scene), torch.as_tensor(x0)
    params = list(ref_pol.parameters())
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=20, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = sim.policy_loss(ref_pol, x0_t)
        loss.backward()
        return loss

    ref_losses = [float(opt.step(closure).detach())]
    assert opt.state[params[0]]["n_iter"] >= 5  # the curvature history is in play
    with torch.no_grad():
        ref_final = float(sim.policy_loss(ref_pol, x0_t))
    np.testing.assert_allclose(res.losses, ref_losses, rtol=1e-13)
    assert res.final_loss == pytest.approx(ref_final, rel=1e-13)
    assert res.final_loss < 0.9 * res.losses[0]  # it trained
    ours, ref = _flat(list(pol.parameters())), _flat(params)
    assert np.abs(ours - ref).max() <= 1e-13 * np.abs(ref).max()


class _FailAt:
    """A loss that raises the judge's EvaluationError at its ``n``-th call and records
    every value and state it returns."""

    def __init__(self, loss, n: int) -> None:
        self.loss, self.n, self.calls = loss, n, 0
        self.seen: list[tuple[float, dict[str, torch.Tensor]]] = []

    def __call__(self, problem, policy, x0, **kwargs):
        self.calls += 1
        if self.calls == self.n:
            raise EvaluationError("sustained contact (a test's failure)")
        value = self.loss(problem, policy, x0, **kwargs)
        state = {k: v.detach().clone() for k, v in policy.state_dict().items()}
        self.seen.append((float(value.detach()), state))
        return value


def _ball() -> hybridoc.HybridOCP:
    def spread(rng: np.random.Generator, m: int) -> np.ndarray:
        return np.array([1.0, 0.0]) + rng.uniform(-0.1, 0.1, (m, 2))

    return hybridoc.as_ocp("bouncing-ball").replace(steps=20, distribution=spread)


def test_adam_stops_at_a_judge_failure_with_the_best_parameters(monkeypatch):
    """The judge fails at the fifth loss: Adam stops at iteration 5 with the lowest loss of
    the four judged and the parameters it was judged at."""
    ball = _ball()
    fail = _FailAt(training.judged_loss, 5)
    monkeypatch.setattr(training, "judged_loss", fail)
    pol = mlp_policy(ball, hidden=4, layers=1, seed=1)
    res = train_policy(ball, pol, 2, iters=8, lr=0.05)
    assert res.message.startswith("stopped at iteration 5 of 8: the judge could not")
    values = [v for v, _ in fail.seen[:4]]
    assert res.losses == values
    best = int(np.argmin(values))
    assert res.final_loss == values[best]
    for k, v in pol.state_dict().items():
        assert torch.equal(v, fail.seen[best][1][k])


def test_lbfgs_stops_at_a_judge_failure_with_the_parameters_before_it(monkeypatch):
    """The loss fails at the first evaluation after a one-iteration run's last (in the
    second iteration's line search): L-BFGS stops there with the parameters and loss of
    that one-iteration run, bit for bit."""
    scene = hybridoc.load_scene("single-collision").with_steps(8)
    x0 = np.tile(scene.initial_state(), (2, 1))
    x0[1, 2:4] += 0.2
    loss = Simulator.policy_loss
    calls = {"n": 0, "fail": 0}

    def counted(self, policy, x0_batch):
        calls["n"] += 1
        if calls["n"] == calls["fail"]:
            raise EvaluationError("sustained contact (a test's failure)")
        return loss(self, policy, x0_batch)

    monkeypatch.setattr(Simulator, "policy_loss", counted)
    plain = mlp_policy(scene, hidden=4, layers=1, seed=0)
    one = train_policy(scene, plain, x0, iters=1, lr=1.0, optimizer="lbfgs")
    calls.update(fail=calls["n"] + 1, n=0)
    pol = mlp_policy(scene, hidden=4, layers=1, seed=0)
    res = train_policy(scene, pol, x0, iters=2, lr=1.0, optimizer="lbfgs")
    assert calls["n"] >= calls["fail"]
    assert res.message.startswith("stopped at iteration 2 of 2: the judge could not")
    assert res.losses == one.losses and not one.message
    assert res.final_loss == one.final_loss < res.losses[0]
    for a, b in zip(pol.parameters(), plain.parameters(), strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("lr", [-1e-3, float("nan"), float("inf")])
def test_a_bad_learning_rate_is_refused(lr):
    scene = hybridoc.load_scene("single-collision").with_steps(6)
    pol = mlp_policy(scene, hidden=2, layers=1)
    for optimizer in ("adam", "lbfgs"):
        with pytest.raises(SceneError, match="lr must be a finite number >= 0"):
            train_policy(scene, pol, np.zeros((1, 8)), iters=1, lr=lr, optimizer=optimizer)


def test_training_does_not_import_torch_dynamo():
    """In a fresh process, importing the training module and training a policy (Adam with
    the cosine schedule, then L-BFGS) leaves torch._dynamo unimported."""
    code = """
import sys
import numpy as np
import hybridoc
from hybridoc.workflows.training import mlp_policy, train_policy
assert "torch._dynamo" not in sys.modules, "import"
scene = hybridoc.load_scene("single-collision").with_steps(6)
x0 = np.tile(scene.initial_state(), (2, 1))
for optimizer in ("adam", "lbfgs"):
    pol = mlp_policy(scene, hidden=2, layers=1)
    res = train_policy(scene, pol, x0, iters=2, optimizer=optimizer, schedule="cosine")
    assert len(res.losses) == 2
assert "torch._dynamo" not in sys.modules, "training"
print("ok")
"""
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]
