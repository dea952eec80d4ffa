"""The exact discrete N-step problem: step fidelity, optimality floor under gradient descent."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import hybridoc
from hybridoc.solvers.casadi_step import make_step
from hybridoc.solvers.discrete_transcription import (
    _frozen_step,
    discrete_gap,
    discrete_loss,
    solve_discrete,
)

N_SMALL = 120  # a coarser grid keeps the file fast; the structure is the same as N = 480


@pytest.fixture(scope="module")
def scene():
    return hybridoc.load_scene("single-collision").with_steps(N_SMALL)


@pytest.fixture(scope="module")
def floor(scene):
    return solve_discrete(scene)


def test_frozen_step_with_true_branches_is_make_step(scene):
    # the branch-frozen step used inside the NLP equals the simulator's step when the flags
    # are the true ones, along a whole rollout with a collision
    step = make_step(scene)
    fstep, tests = _frozen_step(scene, "both")
    s = scene.initial_state()
    u = scene.initial_controls()
    hits = 0
    for n in range(scene.steps):
        flags = np.asarray(tests(s, u[n])[0]).ravel()
        hits += int(flags.sum())
        a = np.asarray(step(s, u[n])).ravel()
        b = np.asarray(fstep(s, u[n], flags)[0]).ravel()
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-13)
        s = a
    assert hits == 1


def test_discrete_loss_matches_torch_simulator(scene):
    torch = pytest.importorskip("torch")
    from hybridoc.solvers.simulator import Simulator

    u = scene.initial_controls() + 0.3
    sim = Simulator(scene)
    assert discrete_loss(scene, u) == pytest.approx(
        float(sim.loss(torch.tensor(u, dtype=torch.float64))), rel=1e-12
    )


def test_floor_is_a_converged_local_optimum(scene, floor):
    assert floor.method == "discrete"
    assert floor.info["converged"] and floor.info["branches_consistent"]
    assert floor.info["discrete_loss"] <= floor.info["warm_start_loss"]
    # reported loss is a fresh rollout of the returned controls
    assert floor.info["discrete_loss"] == pytest.approx(discrete_loss(scene, floor.controls))
    # small random perturbations never go below it (local optimality, piecewise smooth)
    rng = np.random.default_rng(0)
    for _ in range(5):
        du = 1e-4 * rng.standard_normal(floor.controls.shape)
        assert discrete_loss(scene, floor.controls + du) >= floor.info["discrete_loss"] - 1e-12


def test_floor_below_gradient_descent(scene, floor):
    from hybridoc.solvers.gd import solve_gd

    gd = solve_gd(scene, integrator="symplectic-euler")
    assert floor.info["discrete_loss"] <= gd.info["loss"] + 1e-12


def test_floor_near_continuous_optimum(scene, floor):
    from hybridoc.reference import solve_reference

    ref = solve_reference(scene)
    # the discrete problem is an O(dt) approximation of the continuous one
    assert abs(floor.info["discrete_loss"] - ref.cost) < 0.01 * ref.cost
    # its controls, judged by the event-exact evaluator, cost at least the optimum
    assert floor.cost >= ref.cost - 1e-12


def test_bad_warm_start_is_a_clear_error(scene):
    with pytest.raises(hybridoc.ControlsError):
        solve_discrete(scene, warm_start=np.zeros((3, 2)))


def test_discrete_gap_of_the_floor_is_zero(scene, floor):
    # a gd-like solution whose loss is the floor's: warm-started there, IPOPT finds no lower
    sol = dataclasses.replace(floor, info={**floor.info, "loss": floor.info["discrete_loss"]})
    gap = discrete_gap(scene, sol)
    assert gap["discrete_loss"] == floor.info["discrete_loss"]
    assert gap["discrete_optimum"] <= gap["discrete_loss"]
    assert 0.0 <= gap["discrete_gap_relative"] < 1e-9


def test_discrete_gap_of_a_problem_without_a_simulator_says_why(floor):
    gap = discrete_gap("bouncing-ball-2", floor)  # a generic HybridOCP, not a disc scene
    assert set(gap) == {"discrete_loss", "discrete_error"}
    assert "not a disc scene" in gap["discrete_error"]
