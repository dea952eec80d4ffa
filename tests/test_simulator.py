"""The differentiable simulator, its CasADi step and its compiled path."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import hybridoc
from hybridoc.errors import ControlsError, SceneError
from hybridoc.problems import Disc, Scene, Wall
from hybridoc.solvers.casadi_step import make_step
from hybridoc.solvers.compiled import CompiledLoss
from hybridoc.solvers.contacts import TOI_MODES
from hybridoc.solvers.simulator import Simulator

F64 = torch.float64


def head_on(steps: int = 7) -> Scene:
    """Striker at x = -1 moving right at 1, target at rest at 0: contact at t = 0.6."""
    return Scene(
        horizon=1.0,
        steps=steps,
        discs=(
            Disc("a", (-1.0, 0.0), 0.2, velocity=(1.0, 0.0), actuated=True),
            Disc("b", (0.0, 0.0), 0.2, target=(1.0, 0.0)),
        ),
    )


def wall_bounce(e: float = 0.7) -> Scene:
    """A disc rising at 1 towards the wall y = 1: contact at t = 0.8."""
    return Scene(
        horizon=1.0,
        steps=7,
        restitution=e,
        discs=(Disc("a", (0.0, 0.0), 0.2, velocity=(0.0, 1.0), actuated=True, target=(0, 0)),),
        walls=(Wall((0.0, 1.0), (0.0, -1.0)),),
    )


def zeros(scene: Scene) -> torch.Tensor:
    return torch.zeros(scene.steps, scene.n_controls, dtype=F64)


@pytest.mark.parametrize("toi", TOI_MODES)
def test_head_on_exchanges_velocities(toi: str) -> None:
    sc = head_on()
    x = Simulator(sc, toi=toi).rollout(zeros(sc))[0, -1].numpy()
    np.testing.assert_allclose(x[4:], [0.0, 0.0, 1.0, 0.0], atol=1e-14)
    if toi in ("position", "both"):
        # the position correction makes the free flight exact: contact at t = 0.6
        np.testing.assert_allclose(x[:4], [-0.4, 0.0, 0.4, 0.0], atol=1e-13)
    else:
        assert abs(x[2] - 0.4) <= sc.dt + 1e-12
        assert abs(x[2] - 0.4) > 1e-3  # uncorrected: off by a fraction of a step


@pytest.mark.parametrize("toi", TOI_MODES)
def test_wall_bounce(toi: str) -> None:
    sc = wall_bounce(0.7)
    x = Simulator(sc, toi=toi).rollout(zeros(sc))[0, -1].numpy()
    np.testing.assert_allclose(x[2:], [0.0, -0.7], atol=1e-14)
    if toi in ("position", "both"):
        np.testing.assert_allclose(x[:2], [0.0, 0.8 - 0.7 * 0.2], atol=1e-13)


def test_no_contact_is_symplectic_euler() -> None:
    sc = hybridoc.load_scene("single-collision").with_steps(40)
    rng = np.random.default_rng(0)
    u = rng.normal(size=(40, 2))
    u[:, 1] = -np.abs(u[:, 1])  # push the striker away from the other disc
    states = Simulator(sc).rollout(torch.tensor(u))[0].numpy()
    p, v = np.array(sc.initial_state()[:4]), np.zeros(4)
    for k in range(40):
        v = v + np.concatenate([u[k], [0.0, 0.0]]) * sc.dt
        p = p + v * sc.dt
        np.testing.assert_allclose(states[k + 1], np.concatenate([p, v]), atol=1e-14)


@pytest.mark.parametrize("impulse", ["direct", "lcp", "convex"])
@pytest.mark.parametrize("toi", TOI_MODES)
def test_momentum_conserved_unequal_masses(impulse: str, toi: str) -> None:
    sc = hybridoc.load_scene("three-disc-chain")
    u = torch.tensor(sc.initial_controls())
    states = Simulator(sc, contact=impulse, toi=toi).rollout(u)[0].numpy()
    m = np.repeat([d.mass for d in sc.discs], 2)
    mom = (states[:, 6:] * m).reshape(-1, 3, 2).sum(1)
    # only the striker's force changes the total momentum
    expected = np.vstack([np.zeros(2), np.cumsum(sc.initial_controls() * sc.dt, 0)])
    np.testing.assert_allclose(mom, expected, atol=1e-12)
    ev_speed = np.abs(states[-1, 6:]).max()
    assert ev_speed > 0.1  # the impulse did travel along the chain


@pytest.mark.parametrize("name", ["single-collision", "multiple-collision", "damped-walls"])
@pytest.mark.parametrize("toi", TOI_MODES)
def test_casadi_step_equals_torch(name: str, toi: str) -> None:
    # a quarter of the grid (damped-walls: 120 of 200 steps), the same events: both paths
    # run step by step in Python
    sc = hybridoc.load_scene(name).with_steps(120)
    u = sc.initial_controls()
    torch_states = Simulator(sc, toi=toi).rollout(torch.tensor(u))[0].numpy()
    step = make_step(sc, toi=toi)
    x = sc.initial_state()
    for k in range(sc.steps):
        x = np.asarray(step(x, u[k])).ravel()
        np.testing.assert_allclose(x, torch_states[k + 1], rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ["single-collision", "multiple-collision"])
@pytest.mark.parametrize("toi", ["none", "both"])
def test_compiled_equals_torch(name: str, toi: str) -> None:
    sc = hybridoc.load_scene(name).with_steps(120)  # the same events on a quarter of the grid
    rng = np.random.default_rng(1)
    u0 = sc.initial_controls() + 0.1 * rng.normal(size=(sc.steps, 2))
    sim, comp = Simulator(sc, toi=toi), CompiledLoss(sc, toi=toi)
    u = torch.tensor(u0, requires_grad=True)
    x0 = torch.tensor(sc.initial_state(), requires_grad=True)
    loss = sim.loss(u, x0)
    gu, gx = torch.autograd.grad(loss, (u, x0))
    u2 = torch.tensor(u0, requires_grad=True)
    x2 = torch.tensor(sc.initial_state(), requires_grad=True)
    loss2 = comp.loss(u2, x2)
    gu2, gx2 = torch.autograd.grad(loss2, (u2, x2))
    assert abs(loss.item() - loss2.item()) <= 1e-12 * abs(loss.item())
    np.testing.assert_allclose(gu2.numpy(), gu.numpy(), rtol=1e-12, atol=1e-12 * gu.abs().max())
    np.testing.assert_allclose(gx2.numpy(), gx.numpy(), rtol=1e-12, atol=1e-12 * gx.abs().max())
    states = sim.rollout(torch.tensor(u0))
    np.testing.assert_allclose(comp.rollout(u0).numpy(), states.numpy(), atol=1e-12)


def _central_fd(f, x: torch.Tensor, d: torch.Tensor, h: float = 1e-6) -> float:
    return (f(x + h * d).item() - f(x - h * d).item()) / (2 * h)


@pytest.mark.parametrize("toi", ["position", "both"])
def test_gradients_match_finite_differences(toi: str) -> None:
    # a collision in mid-step, far from a grid point: the loss is smooth here
    sc = hybridoc.load_scene("single-collision").with_steps(60)
    sim = Simulator(sc, toi=toi)
    rng = np.random.default_rng(2)
    u0 = torch.tensor(sc.initial_controls() + 0.05 * rng.normal(size=(60, 2)))
    u = u0.clone().requires_grad_(True)
    x0 = sim.x0.clone().requires_grad_(True)
    g_u, g_x = torch.autograd.grad(sim.loss(u, x0), (u, x0))
    du = torch.tensor(rng.normal(size=(60, 2)))
    fd = _central_fd(lambda w: sim.loss(w), u0, du)
    assert abs((g_u * du).sum().item() - fd) <= 1e-6 * abs(fd)
    for k in range(8):
        e = torch.zeros(8, dtype=F64)
        e[k] = 1.0
        fd = _central_fd(lambda x: sim.loss(u0, x), sim.x0, e)
        assert abs(g_x[k].item() - fd) <= 1e-6 * max(abs(fd), 1e-3)


def test_gradients_wrt_scene_parameters() -> None:
    sc = hybridoc.load_scene("multiple-collision").with_steps(60)
    sim = Simulator(sc)
    u = torch.tensor(sc.initial_controls())
    names = ["radii", "masses", "restitution", "targets"]
    base = {k: getattr(sim, k).clone() for k in names}
    params = {k: v.clone().requires_grad_(True) for k, v in base.items()}
    for k, v in params.items():
        setattr(sim, k, v)
    grads = torch.autograd.grad(sim.loss(u), [params[k] for k in names])
    rng = np.random.default_rng(3)
    for k, g in zip(names, grads, strict=True):
        d = torch.tensor(rng.normal(size=base[k].shape))
        if k == "restitution":
            d = -d.abs()  # stay in [0, 1]

        def f(val: torch.Tensor, k: str = k) -> torch.Tensor:
            setattr(sim, k, val)
            return sim.loss(u)

        fd = _central_fd(f, base[k], d, h=1e-7)
        setattr(sim, k, base[k])
        assert abs(g.ravel() @ d.ravel() - fd) <= 1e-5 * max(abs(fd), 1e-4), k
        assert abs(fd) > 1e-6, k  # the parameter does matter


def test_float32_and_batches() -> None:
    # the same collisions on a quarter of the grid: seven torch rollouts step by step
    sc = hybridoc.load_scene("multiple-collision").with_steps(120)
    rng = np.random.default_rng(4)
    u = sc.initial_controls() + 0.2 * rng.normal(size=(3, sc.steps, 2))
    s64 = Simulator(sc).rollout(torch.tensor(u))
    assert s64.shape == (3, sc.steps + 1, 8) and s64.dtype == F64
    for b in range(3):
        single = Simulator(sc).rollout(torch.tensor(u[b]))
        assert single.shape == (1, sc.steps + 1, 8)
        np.testing.assert_allclose(single[0].numpy(), s64[b].numpy(), atol=1e-14)
    sim32 = Simulator(sc, dtype=torch.float32)
    s32 = sim32.rollout(torch.tensor(u, dtype=torch.float32))
    assert s32.dtype == torch.float32
    np.testing.assert_allclose(s32.numpy(), s64.numpy(), atol=2e-3)
    loss = sim32.loss(torch.tensor(u, dtype=torch.float32))
    assert loss.shape == (3,) and loss.dtype == torch.float32
    x0 = torch.tensor(np.tile(sc.initial_state(), (3, 1)))
    np.testing.assert_allclose(
        Simulator(sc).rollout(torch.tensor(u), x0).numpy(), s64.numpy(), atol=0
    )


def test_input_errors() -> None:
    sc = hybridoc.load_scene("single-collision")
    sim = Simulator(sc)
    with pytest.raises(ControlsError, match="shape"):
        sim.rollout(torch.zeros(10, 2))
    bad = torch.zeros(sc.steps, 2, dtype=F64)
    bad[3, 1] = float("nan")
    with pytest.raises(ControlsError, match="NaN"):
        sim.loss(bad)
    with pytest.raises(SceneError, match="toi"):
        Simulator(sc, toi="sometimes")
    with pytest.raises(SceneError, match="contact"):
        Simulator(sc, contact="glue")
    with pytest.raises(SceneError, match="unknown contact model"):
        make_step(sc, contact="glue")
    with pytest.raises(ControlsError, match="shape"):
        CompiledLoss(sc).value(np.zeros((3, 2)))


@pytest.mark.parametrize("contact", ["compliant", "pbd"])
def test_non_impulse_models_run_and_differentiate(contact: str) -> None:
    sc = hybridoc.load_scene("head-on")
    sim = Simulator(sc, contact=contact)
    u = torch.tensor(sc.initial_controls(), requires_grad=True)
    loss = sim.loss(u)
    (g,) = torch.autograd.grad(loss, u)
    assert torch.isfinite(g).all() and g.abs().max() > 0
    final = sim.rollout(u.detach())[0, -1].numpy()
    assert final[6] > 0.5 * final[4]  # the target disc was struck and moves on


@pytest.mark.parametrize("name", ["single-collision", "multiple-collision", "three-disc-chain"])
def test_exact_integrator_matches_the_evaluator(name: str) -> None:
    # exact flow + exact time of impact: the discrete loss is the continuous cost (on 120
    # steps, the same events as on the scenes' 240 or 480)
    sc = hybridoc.load_scene(name).with_steps(120)
    u = sc.initial_controls()
    sim = Simulator(sc, integrator="exact")
    ut = torch.tensor(u, requires_grad=True)
    loss = sim.loss(ut)
    (g,) = torch.autograd.grad(loss, ut)
    exact = hybridoc.gradient(sc, u)
    assert loss.item() == pytest.approx(exact.cost, rel=1e-12)
    np.testing.assert_allclose(
        g.numpy(), exact.d_controls, rtol=0, atol=1e-9 * g.abs().max().item()
    )
    comp = CompiledLoss(sc, integrator="exact")
    np.testing.assert_allclose(
        comp.rollout_numpy(u), sim.rollout(ut.detach())[0].numpy(), atol=1e-12
    )
    with pytest.raises(SceneError, match="exact"):
        Simulator(sc, integrator="exact", toi="none")
