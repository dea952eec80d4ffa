"""Policy training on any HybridOCP: through the judge's event-exact closed loop and its
exact adjoint, from Python and from ``hybridoc train-policy``, judged by ``validate-policy``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import hybridoc
from hybridoc.cli import main
from hybridoc.errors import SceneError
from hybridoc.workflows.policy_format import load_mlp_policy
from hybridoc.workflows.training import (
    judged_loss,
    mlp_policy,
    train_policy,
    training_draws,
)

STEPS = 30  # a coarse grid keeps each closed loop (judge + adjoint) near 15 ms

PROBLEM = """
import hybridoc

def ball():
    p = hybridoc.as_ocp("bouncing-ball")
    spread = lambda rng, M: p.x0 + rng.uniform(-0.1, 0.1, (M, p.nx))
    return p.replace(name="ball-train", steps=30, distribution=spread)

def no_dist():
    return hybridoc.as_ocp("bouncing-ball").replace(name="ball-plain", steps=30)
"""


def _spread(rng: np.random.Generator, m: int) -> np.ndarray:
    return np.array([1.0, 0.0]) + rng.uniform(-0.1, 0.1, (m, 2))


@pytest.fixture(scope="module")
def ball() -> hybridoc.HybridOCP:
    return hybridoc.as_ocp("bouncing-ball").replace(steps=STEPS, distribution=_spread)


def _judged(problem: hybridoc.HybridOCP, policy: torch.nn.Module, x0: np.ndarray) -> list[float]:
    """The judge's cost of each initial state's closed loop, the policy called as a module."""
    return [hybridoc.evaluate(problem.replace(x0=x), policy=policy).cost for x in x0]


def test_the_initialisation_follows_the_problems_scale(ball: hybridoc.HybridOCP) -> None:
    """s_mean: the draws' mean; s_scale: the height's and speed's reach under the free drop
    (half of 1 m and of the speed range -g t1 .. e g t1); u_scale: the thrust that moves the
    speed by its scale over T. An untrained policy acts as the initial guess u = 0."""
    pol = mlp_policy(ball, hidden=8, layers=2)
    draws = hybridoc.workflows.datasets.draw_initial_states(ball, 64, 0)
    np.testing.assert_allclose(pol.s_mean.numpy(), draws.mean(0), rtol=0, atol=1e-15)
    g, e = 9.81, 0.8
    t1 = np.sqrt(2 * draws[:, 0].mean() / g)  # first impact of the free drop from s_mean
    # the speed's range: from -g t1 just before the bounce to e g t1 just after it
    assert pol.s_scale[1].item() == pytest.approx(0.5 * (1 + e) * g * t1, rel=0.05)
    assert 0.4 < pol.s_scale[0].item() < 0.6
    assert pol.u_scale.item() == pytest.approx(pol.s_scale[1].item() / ball.horizon, rel=1e-12)
    assert pol.u_offset.item() == 0.0
    with torch.no_grad():
        u = pol(torch.tensor(0.3), torch.as_tensor(ball.x0)).item()
    assert abs(u) < 0.5 * pol.u_scale.item()  # the small last layer
    # bounds set the output scale where both are finite
    bounded = ball.replace(u_min=np.array([-2.0]), u_max=np.array([3.0]))
    assert mlp_policy(bounded, hidden=4, layers=1).u_scale.item() == 2.5


def test_the_training_gradient_against_central_differences(ball: hybridoc.HybridOCP) -> None:
    """The gradient train_policy descends on a generic problem, with a bounce in every
    closed loop, against central differences of the judge's cost of the module."""
    pol = mlp_policy(ball, hidden=6, layers=1, seed=3)
    with torch.no_grad():  # a policy that reacts to the state: feedback in the adjoint
        pol.net[-1].weight.mul_(20.0)
    x0 = training_draws(ball, 2)[0]
    loss = judged_loss(ball, pol, x0)
    loss.backward()
    base = [hybridoc.evaluate(ball.replace(x0=x), policy=pol) for x in x0]
    assert all(ev.sequence == ["floor"] for ev in base)
    assert float(loss.detach()) == pytest.approx(np.mean([ev.cost for ev in base]), rel=1e-12)
    params = list(pol.parameters())
    rng = np.random.default_rng(7)
    d = [torch.as_tensor(rng.standard_normal(p.shape)) for p in params]
    exact = sum(float((p.grad * di).sum()) for p, di in zip(params, d, strict=True))

    def judge(eps: float) -> float:
        with torch.no_grad():
            for p, di in zip(params, d, strict=True):
                p.add_(eps * di)
        costs = _judged(ball, pol, x0)
        with torch.no_grad():
            for p, di in zip(params, d, strict=True):
                p.sub_(eps * di)
        return float(np.mean(costs))

    eps = 1e-5
    fd = (judge(eps) - judge(-eps)) / (2 * eps)
    print(f"directional derivative: adjoint {exact:.12g}, central differences {fd:.12g}")
    assert abs(exact) > 1e-3
    assert fd == pytest.approx(exact, rel=1e-6)


def test_training_lowers_the_judged_cost_on_held_out_draws(ball: hybridoc.HybridOCP) -> None:
    """Adam on four draws through the judge: the mean judged cost of six other draws under
    the trained policy is below that of the same policy untrained."""
    x0, seed = training_draws(ball, 4)
    assert seed == 1
    held = training_draws(ball, 6, seed=100)[0]
    pol = mlp_policy(ball, hidden=8, layers=2, seed=seed)
    before = np.mean(_judged(ball, pol, held))
    first = np.mean(_judged(ball, pol, x0))
    res = train_policy(ball, pol, x0, iters=8, lr=3e-2)
    assert res.engine == "judge" and res.toi == "both" and not res.message
    # the losses are the judged mean cost on the training draws
    assert res.losses[0] == pytest.approx(first, rel=1e-12)
    assert res.final_loss == pytest.approx(np.mean(_judged(ball, pol, x0)), rel=1e-12)
    assert res.final_loss < res.losses[0]
    after = np.mean(_judged(ball, pol, held))
    print(f"held-out mean judged cost {before:.6g} -> {after:.6g}")
    assert after < before


def test_generic_training_refuses_the_simulators_settings(ball: hybridoc.HybridOCP) -> None:
    pol = mlp_policy(ball, hidden=2, layers=1)
    with pytest.raises(SceneError, match="toi='none' needs a disc scene"):
        train_policy(ball, pol, ball.x0[None, :], toi="none", iters=1)
    with pytest.raises(SceneError, match="has no distribution of initial states"):
        train_policy(ball.replace(distribution=None), pol, 3, iters=1)


@pytest.fixture(scope="module")
def prob_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("train-generic")
    (d / "prob.py").write_text(PROBLEM)
    return d / "prob.py"


def test_cli_train_policy_then_validate_policy_on_a_python_problem(
    prob_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = f"{prob_file}:ball"
    out = tmp_path / "out"
    code = main(["train-policy", spec, "--samples", "3", "--iters", "3", "--hidden", "4",
                 "--layers", "1", "--lr", "0.03", "--out", str(out), "--json",
                 "--no-progress"])  # fmt: skip
    trained = json.loads(capsys.readouterr().out)
    assert code == 0
    assert trained["engine"] == "judge" and trained["seed"] == 1
    assert len(trained["losses"]) == 3 and trained["final_loss"] < trained["initial_loss"]
    path = out / "ball-train_train-policy.json"
    assert trained["policy"] == str(path)
    policy = load_mlp_policy(path)  # no torch, no code run
    assert policy.layers == [3, 4, 1]  # (t, h, v) -> 4 -> thrust
    # the reported loss is the judge's mean cost of the saved policy on the training draws
    problem = hybridoc.as_ocp(spec)
    x0 = training_draws(problem, 3)[0]
    judged = [hybridoc.evaluate(problem.replace(x0=x), policy=policy).cost for x in x0]
    assert trained["final_loss"] == pytest.approx(np.mean(judged), rel=1e-12)

    code = main(["validate-policy", spec, "--policy", str(path), "--samples", "1",
                 "--workers", "1", "--json", "--no-progress", "--rollouts", "judge"])  # fmt: skip
    report = json.loads(capsys.readouterr().out)
    assert code == 0 and report["summary"]["compared"] == 1
    draw = hybridoc.workflows.datasets.draw_initial_states(problem, 1, 0)[0]
    ev = hybridoc.evaluate(problem.replace(x0=draw), policy=policy)
    (worst,) = report["worst"]
    assert worst["policy_cost"] == pytest.approx(ev.cost, rel=1e-12)
    assert worst["gap"] > 0  # the exact optimum of the draw is better


def test_cli_train_policy_needs_a_distribution(
    prob_file: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for problem in ("bouncing-ball", f"{prob_file}:no_dist"):
        code = main(["train-policy", problem, "--samples", "2", "--out", str(tmp_path)])
        err = capsys.readouterr().err
        assert code == 2 and "has none" in err and "distribution=" in err, err
        assert err.count("\n") == 1  # one line
    code = main(["train-policy", f"{prob_file}:ball", "--samples", "2", "--toi", "none",
                 "--out", str(tmp_path)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "--toi none needs a disc scene" in err
    assert not list(tmp_path.iterdir())  # refused before anything is written
