"""The disc physics written once (hybridoc.problems.physics): CasADi and torch agree, and the
simulator's and the generic time-of-impact simulation's steps agree on disc scenes."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import hybridoc
from hybridoc.problems import physics as ph

torch = pytest.importorskip("torch")


def _both(fn, *args, **kw):
    """The function on CasADi numbers and on torch tensors (a batch of one)."""
    c = fn(*[ca.DM(a) if isinstance(a, np.ndarray) else a for a in args], ph.CASADI, **kw)
    t = fn(*[torch.as_tensor(a)[None] if isinstance(a, np.ndarray) else a for a in args],
           ph.TORCH, **kw)  # fmt: skip
    return c, t


def _num(x):
    if isinstance(x, torch.Tensor):
        return x.detach().numpy().ravel()
    return np.asarray(ca.evalf(x)).ravel()


@pytest.mark.parametrize("seed", range(20))
def test_casadi_and_torch_physics_agree_on_random_states(seed: int) -> None:
    rng = np.random.default_rng(seed)
    dp, dv, da = rng.normal(size=(3, 2))
    R = float(rng.uniform(0.1, 1.0))
    (gc, nc), (gt, nt) = _both(ph.pair_gap, dp, R)
    np.testing.assert_allclose(_num(gt), _num(gc), rtol=0, atol=1e-12)
    np.testing.assert_allclose(_num(nt), _num(nc), rtol=0, atol=1e-12)
    c, t = _both(ph.pair_detector, dp, R)
    np.testing.assert_allclose(_num(t), _num(c), rtol=0, atol=1e-12)
    point, normal = rng.normal(size=2), rng.normal(size=2)
    normal /= np.linalg.norm(normal)
    c, t = _both(ph.wall_gap, dp, point, normal, R)
    np.testing.assert_allclose(_num(t), _num(c), rtol=0, atol=1e-12)
    c, t = _both(ph.target_cost, dp, point)
    np.testing.assert_allclose(_num(t), _num(c), rtol=0, atol=1e-12)
    w_c = ph.normal_speed(ca.DM(dv), nc, ph.CASADI)
    w_t = ph.normal_speed(torch.as_tensor(dv)[None], nt, ph.TORCH)
    np.testing.assert_allclose(_num(w_t), _num(w_c), rtol=0, atol=1e-12)
    e, inv = float(rng.uniform(0, 1)), float(rng.uniform(0.2, 3))
    np.testing.assert_allclose(
        _num(ph.impulse(w_t, inv, e)), _num(ph.impulse(w_c, inv, e)), rtol=0, atol=1e-12
    )
    # the time of impact of a penetrated step, linear estimate and Newton refinement
    dt = 0.01
    rel_p = np.array([R + 0.004, 0.0]) + 1e-3 * rng.normal(size=2)
    rel_v = np.array([-1.0, 0.0]) + 0.1 * rng.normal(size=2)
    d_hat = float(np.linalg.norm(rel_p + rel_v * dt)) - R
    w_hat = float((rel_v @ (rel_p + rel_v * dt)) / np.linalg.norm(rel_p + rel_v * dt))
    toi_c = ph.toi_linear(ca.DM(d_hat), ca.DM(w_hat), dt, ca.DM(1), ph.CASADI)
    f64 = torch.float64
    toi_t = ph.toi_linear(torch.tensor([d_hat], dtype=f64), torch.tensor([w_hat], dtype=f64), dt,
                          torch.tensor([True]),
                          ph.TORCH)  # fmt: skip
    np.testing.assert_allclose(_num(toi_t), _num(toi_c), rtol=0, atol=1e-15)
    tau_c = ph.refine_impact_time(
        ca.DM(rel_p), ca.DM(rel_v), ca.DM(da), dt - toi_c, ca.DM(1), dt, ph.CASADI, R=R
    )
    tau_t = ph.refine_impact_time(
        torch.as_tensor(rel_p)[None], torch.as_tensor(rel_v)[None], torch.as_tensor(da)[None],
        dt - toi_t, torch.tensor([True]), dt, ph.TORCH, R=torch.tensor(R, dtype=torch.float64),
    )  # fmt: skip
    np.testing.assert_allclose(_num(tau_t), _num(tau_c), rtol=0, atol=1e-14)


@pytest.mark.parametrize("name", ["single-collision", "multiple-collision", "three-disc-chain"])
def test_generic_toi_simulation_agrees_with_the_disc_simulator(name: str) -> None:
    """On disc scenes the generic TOI step (any HybridOCP) equals the disc step with the
    exact integrator: losses and gradients to 1e-10."""
    from hybridoc.solvers.compiled import CompiledLoss

    ocp = hybridoc.as_ocp(name)
    rng = np.random.default_rng(3)
    disc = CompiledLoss(ocp, integrator="exact")
    generic = CompiledLoss(ocp, simulation="generic")
    for k in range(3):
        u = ocp.u_guess * (1 + 0.1 * k) + 0.2 * k * rng.standard_normal(ocp.u_guess.shape)
        Jd, gd, xd = disc.value_and_grad(u)
        Jg, gg, xg = generic.value_and_grad(u)
        assert Jg == pytest.approx(Jd, rel=1e-10, abs=1e-12)
        np.testing.assert_allclose(gg, gd, rtol=0, atol=1e-10 * max(1.0, np.abs(gd).max()))
        np.testing.assert_allclose(xg, xd, rtol=0, atol=1e-10 * max(1.0, np.abs(xd).max()))
        # and the exact-flow loss is the judge's continuous cost
        assert Jd == pytest.approx(hybridoc.evaluate(ocp, u).cost, rel=1e-10)


def test_disc_simulator_torch_step_equals_the_compiled_step() -> None:
    """The torch simulator and the CasADi step share the physics: equal to 1e-12."""
    from hybridoc.solvers.compiled import CompiledLoss
    from hybridoc.solvers.simulator import Simulator

    for integrator in ("symplectic-euler", "exact"):
        sim = Simulator("multiple-collision", integrator=integrator)
        comp = CompiledLoss("multiple-collision", integrator=integrator)
        u = hybridoc.as_ocp("multiple-collision").u_guess
        states = sim.rollout(torch.as_tensor(u))[0].numpy()
        np.testing.assert_allclose(states, comp.rollout_numpy(u), rtol=0, atol=1e-12)
