"""Feedback policies: closed-loop rollout, training, and the exact closed-loop gradient."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import hybridoc
from hybridoc.errors import ControlsError, SceneError
from hybridoc.solvers.simulator import Simulator
from hybridoc.workflows.training import (
    closed_loop_cost,
    closed_loop_gradient,
    mlp_policy,
    train_policy,
)

STEPS = 48


@pytest.fixture(scope="module")
def scene() -> hybridoc.problems.Scene:
    # the paper's single collision on a coarse grid: ball1 still strikes ball2
    return hybridoc.load_scene("single-collision").with_steps(STEPS)


def _x0_batch(scene, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x0 = np.tile(scene.initial_state(), (n, 1))
    x0[:, 2:4] += rng.uniform(-0.3, 0.3, (n, 2))  # ball2's start
    return x0


class TimeTable(torch.nn.Module):
    """A policy that ignores the state: the open-loop controls of its grid interval."""

    def __init__(self, table: np.ndarray, dt: float) -> None:
        super().__init__()
        self.table = torch.as_tensor(table, dtype=torch.float64)
        self.dt = dt

    def forward(self, t: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        k = torch.round(torch.as_tensor(t) / self.dt).long().reshape(-1)
        u = self.table[k].expand(state.reshape(-1, state.shape[-1]).shape[0], -1)
        return u[0] if state.ndim == 1 else u


@pytest.mark.parametrize("toi", ["both", "none"])
def test_state_blind_policy_equals_open_loop(scene, toi):
    rng = np.random.default_rng(1)
    table = scene.initial_controls() + 0.3 * rng.standard_normal((STEPS, 2))
    sim = Simulator(scene, toi=toi)
    x0 = torch.as_tensor(_x0_batch(scene, 3))
    pol = TimeTable(table, scene.dt)
    states, u = sim.rollout_policy(pol, x0)
    ref = sim.rollout(np.tile(table, (3, 1, 1)), x0)
    assert torch.allclose(u, torch.as_tensor(table).expand(3, -1, -1), rtol=0, atol=0)
    assert float((states - ref).abs().max()) < 1e-12
    loss = sim.policy_loss(pol, x0)
    assert abs(float(loss) - float(sim.loss(np.tile(table, (3, 1, 1)), x0).mean())) < 1e-12
    # the judge's zoh evaluation of the same policy is the open-loop evaluation
    ev_cl = hybridoc.evaluate(scene, policy=pol)
    ev_ol = hybridoc.evaluate(scene, table)
    assert ev_cl.cost == pytest.approx(ev_ol.cost, rel=1e-12, abs=0)
    assert ev_cl.sequence == ev_ol.sequence == ["ball1|ball2"]


def test_simulator_closed_loop_gradcheck(scene):
    small = scene.with_steps(12)
    sim = Simulator(small, toi="both")
    pol = mlp_policy(small, hidden=3, layers=1, seed=0)
    names = [n for n, _ in pol.named_parameters()]
    params = tuple(p.detach().clone().requires_grad_(True) for p in pol.parameters())
    x0 = torch.as_tensor(_x0_batch(small, 2, seed=3))
    # the rollout must contain the collision, else the check is vacuous
    states, _ = sim.rollout_policy(pol, x0)
    assert float(states.detach()[:, -1, 6:8].norm(dim=1).min()) > 0.1  # ball2 was struck

    def f(*ps: torch.Tensor) -> torch.Tensor:
        p_dict = dict(zip(names, ps, strict=True))
        return sim.policy_loss(lambda t, s: torch.func.functional_call(pol, p_dict, (t, s)), x0)

    assert torch.autograd.gradcheck(f, params, eps=1e-6, atol=1e-7, rtol=1e-6, fast_mode=True)


def test_exact_closed_loop_gradient_matches_judge_fd(scene):
    pol = mlp_policy(scene, hidden=6, layers=1, seed=2)
    x0 = scene.initial_state()
    x0[2:4] += [0.1, -0.05]
    cost = closed_loop_cost(scene, pol, x0)
    cost.backward()
    base = hybridoc.evaluate(scene.with_initial_state(x0), policy=pol)
    assert base.sequence == ["ball1|ball2"]
    assert float(cost.detach()) == base.cost
    params = list(pol.parameters())
    rng = np.random.default_rng(4)
    for _ in range(2):
        d = [torch.as_tensor(rng.standard_normal(p.shape)) for p in params]
        exact = sum(float((p.grad * di).sum()) for p, di in zip(params, d, strict=True))

        def judge(eps: float, d=d) -> float:
            with torch.no_grad():
                for p, di in zip(params, d, strict=True):
                    p.add_(eps * di)
            ev = hybridoc.evaluate(scene.with_initial_state(x0), policy=pol)
            with torch.no_grad():
                for p, di in zip(params, d, strict=True):
                    p.sub_(eps * di)
            assert ev.sequence == base.sequence
            return ev.cost

        eps = 1e-5
        fd = (judge(eps) - judge(-eps)) / (2 * eps)
        assert fd == pytest.approx(exact, rel=1e-6)

    # and with respect to the initial state (closed loop: the policy reacts to it)
    xt = torch.as_tensor(x0).requires_grad_(True)
    closed_loop_cost(scene, pol, xt, params=[]).backward()
    d = rng.standard_normal(8)
    eps = 1e-6
    up = hybridoc.evaluate(scene.with_initial_state(x0 + eps * d), policy=pol).cost
    down = hybridoc.evaluate(scene.with_initial_state(x0 - eps * d), policy=pol).cost
    assert (up - down) / (2 * eps) == pytest.approx(float(xt.grad @ torch.as_tensor(d)), rel=1e-6)


def test_closed_loop_feedback_of_zero_is_the_open_loop_gradient(scene):
    pol = TimeTable(scene.initial_controls(), scene.dt)
    cl = closed_loop_gradient(scene, pol)
    ol = hybridoc.gradient(scene, scene.initial_controls())
    assert not cl.feedback.any()
    np.testing.assert_allclose(cl.d_controls, ol.d_controls, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(cl.d_initial_state, ol.d_initial_state, rtol=1e-12, atol=1e-14)


def test_batched_closed_loop_cost_is_the_mean(scene):
    pol = mlp_policy(scene, hidden=4, layers=1, seed=1)
    x0 = _x0_batch(scene, 2, seed=5)
    c = closed_loop_cost(scene, pol, x0)
    each = [hybridoc.evaluate(scene.with_initial_state(x), policy=pol).cost for x in x0]
    assert float(c.detach()) == pytest.approx(np.mean(each), rel=1e-14)
    c.backward()
    g_mean = [p.grad.clone() for p in pol.parameters()]
    for p in pol.parameters():
        p.grad = None
    for x in x0:
        (closed_loop_cost(scene, pol, x) / 2).backward()
    for a, p in zip(g_mean, pol.parameters(), strict=True):
        torch.testing.assert_close(a, p.grad, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("toi", ["both", "none"])
def test_training_reduces_the_loss(scene, toi):
    small = scene.with_steps(24)
    pol = mlp_policy(small, hidden=8, layers=1, seed=0)
    res = train_policy(small, pol, _x0_batch(small, 4), toi=toi, iters=6, lr=5e-3)
    assert len(res.losses) == 6
    assert res.final_loss < 0.98 * res.losses[0]
    # deterministic with the seed
    pol2 = mlp_policy(small, hidden=8, layers=1, seed=0)
    res2 = train_policy(small, pol2, _x0_batch(small, 4), toi=toi, iters=6, lr=5e-3)
    assert res2.losses == res.losses


class Recorder:
    """A Progress that records what a run reports."""

    def __init__(self) -> None:
        self.stages: list[str] = []
        self.counts: list[tuple[int, int, str]] = []
        self.closed = False

    def stage(self, text: str) -> None:
        self.stages.append(text)

    def detail(self, text: str) -> None:
        pass

    def count(self, done: int, total: int, text: str = "") -> None:
        self.counts.append((done, total, text))

    def close(self) -> None:
        self.closed = True


def test_training_reports_its_iterations_through_progress(scene):
    small = scene.with_steps(24)
    rec = Recorder()
    res = train_policy(
        small, mlp_policy(small, hidden=4, layers=1), _x0_batch(small, 2), iters=3, progress=rec
    )
    assert rec.stages == ["adam on 2 initial states"]
    assert [c[:2] for c in rec.counts] == [(1, 3), (2, 3), (3, 3)]
    assert rec.counts[-1][2] == f"loss {res.losses[-1]:.6g}"
    assert not rec.closed  # a caller's own Progress stays open for its next stage


def test_lbfgs_training_reduces_the_loss(scene):
    small = scene.with_steps(24)
    pol = mlp_policy(small, hidden=4, layers=1, seed=0)
    res = train_policy(small, pol, _x0_batch(small, 2), iters=1, lr=1.0, optimizer="lbfgs")
    assert res.final_loss < res.losses[0]


def test_mlp_policy_starts_near_the_guess(scene):
    pol = mlp_policy(scene, seed=7)
    u = pol(torch.tensor(0.0, dtype=torch.float64), torch.as_tensor(scene.initial_state()))
    assert u.shape == (2,)
    assert float((u.detach() - torch.tensor([0.0, 3.0])).abs().max()) < 0.5
    again = mlp_policy(scene, seed=7)
    for a, b in zip(pol.parameters(), again.parameters(), strict=True):
        assert torch.equal(a, b)


def test_bad_inputs_raise_one_clear_error(scene):
    small = scene.with_steps(6)
    pol = mlp_policy(small, hidden=2, layers=1)
    sim = Simulator(small)
    for bad in (np.zeros(7), np.zeros((2, 3)), np.zeros((1, 2, 8)), [[np.nan] * 8]):
        with pytest.raises(ControlsError, match="x0"):
            sim.rollout_policy(pol, bad)
        with pytest.raises(ControlsError, match="x0"):
            closed_loop_cost(small, pol, bad)
    with pytest.raises(ControlsError, match="x0"):
        train_policy(small, pol, np.zeros(8), iters=1)
    x0 = _x0_batch(small, 2)

    def wrong_shape(t, s):
        return torch.zeros(s.shape[0], 3, dtype=torch.float64)

    def nan(t, s):
        return torch.full((s.shape[0], 2), float("nan"), dtype=torch.float64)

    def raises(t, s):
        raise RuntimeError("boom")

    for bad_pol, msg in ((wrong_shape, "shape"), (nan, "non-finite"), (raises, "boom")):
        with pytest.raises(ControlsError, match=msg):
            sim.policy_loss(bad_pol, x0)
        with pytest.raises(ControlsError):
            closed_loop_cost(small, bad_pol, x0)
    with pytest.raises(SceneError, match="optimizer"):
        train_policy(small, pol, x0, iters=1, optimizer="sgd")
    with pytest.raises(ControlsError, match="parameters"):
        train_policy(small, torch.nn.Identity(), x0, iters=1)


class Linear(torch.nn.Module):
    """``u = K s + b``, batched or not."""

    def __init__(self, nx: int, nu: int, b: np.ndarray) -> None:
        super().__init__()
        gen = torch.Generator().manual_seed(0)
        self.K = torch.nn.Parameter(0.1 * torch.randn(nu, nx, dtype=torch.float64, generator=gen))
        self.b = torch.nn.Parameter(torch.as_tensor(b, dtype=torch.float64))

    def forward(self, t: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        return state @ self.K.T + self.b


def test_exact_closed_loop_gradient_on_a_generic_problem():
    ocp = hybridoc.as_ocp("bouncing-ball")  # a HybridOCP, not a disc scene
    pol = Linear(ocp.nx, ocp.nu, ocp.u_guess.mean(0))
    closed_loop_cost(ocp, pol).backward()
    base = hybridoc.evaluate(ocp, policy=pol).sequence
    assert base == ["floor"]
    params = list(pol.parameters())
    d = [torch.as_tensor(np.random.default_rng(0).standard_normal(p.shape)) for p in params]
    exact = sum(float((p.grad * di).sum()) for p, di in zip(params, d, strict=True))
    costs = []
    for eps in (1e-5, -1e-5):
        with torch.no_grad():
            for p, di in zip(params, d, strict=True):
                p.add_(eps * di)
        ev = hybridoc.evaluate(ocp, policy=pol)
        with torch.no_grad():
            for p, di in zip(params, d, strict=True):
                p.sub_(eps * di)
        assert ev.sequence == base
        costs.append(ev.cost)
    assert (costs[0] - costs[1]) / 2e-5 == pytest.approx(exact, rel=1e-6)
