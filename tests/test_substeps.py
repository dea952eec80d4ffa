"""Controls logged at K substeps per grid interval (another simulator's ``ctrl``), judged on
the K times finer grid: the same cost as the coarse control when the rows repeat, a closed
form when they do not, and one clear error for a file of N*K rows read without ``substeps``."""

from __future__ import annotations

import numpy as np
import pytest

import hybridoc
from hybridoc.errors import ControlsError
from hybridoc.io import load_controls, read_array, save_controls, substep_problem
from hybridoc.problems.library.bouncing_ball import bouncing_ball
from hybridoc.solution import Solution
from hybridoc.workflows.validation import validate_controls

K = 4


@pytest.fixture(scope="module")
def single():
    return hybridoc.problem.as_ocp("single-collision")


def test_substep_problem_is_the_finer_grid(single):
    fine = substep_problem(single, K)
    assert fine.steps == K * single.steps and fine.horizon == single.horizon
    assert fine.name == single.name and np.array_equal(fine.x0, single.x0)
    assert substep_problem(single, 1) is single
    for bad in (0, -2, 1.5, True, "3"):
        with pytest.raises(ControlsError, match="substeps must be a positive integer"):
            substep_problem(single, bad)
    with pytest.raises(ControlsError, match="MAX_STEPS"):
        substep_problem(single, 10**6)


@pytest.mark.parametrize("suffix", [".npy", ".csv"])
def test_repeated_rows_judge_as_the_coarse_control(tmp_path, single, suffix):
    rng = np.random.default_rng(3)
    u = single.u_guess + 0.2 * rng.normal(size=single.u_guess.shape)
    path = save_controls(tmp_path / f"ctrl{suffix}", np.repeat(u, K, axis=0))
    fine_u = load_controls(path, single, substeps=K)
    assert fine_u.shape == (K * single.steps, 2)
    coarse = hybridoc.evaluate(single, u)
    fine = hybridoc.evaluate(substep_problem(single, K), fine_u)
    assert len(coarse.events) == len(fine.events) == 1
    # the same piecewise-constant function of time; only the flow's rounding differs
    assert fine.cost == pytest.approx(coarse.cost, rel=1e-12, abs=0)
    assert fine.events[0].time == pytest.approx(coarse.events[0].time, rel=1e-12, abs=0)


def test_finer_control_has_the_closed_form_cost():
    # no bounce within this horizon: h' = v, v' = u - g integrate exactly cell by cell
    ocp = bouncing_ball(bounces=0, steps=20)
    fine = substep_problem(ocp, K)
    rng = np.random.default_rng(0)
    u = 5.0 + rng.uniform(-2.0, 2.0, size=(fine.steps, 1))
    ev = hybridoc.evaluate(fine, u)
    assert ev.events == []
    g = 9.81
    h, v, running = float(ocp.x0[0]), float(ocp.x0[1]), 0.0
    dt = ocp.horizon / fine.steps
    for uk in u[:, 0]:
        h, v = h + v * dt + 0.5 * (uk - g) * dt**2, v + (uk - g) * dt
        running += float(ocp.L(ocp.x0, uk)) * dt  # eps u^2: no state in it
    closed = float(ocp.phi(np.array([h, v]))) + running
    assert ev.cost == pytest.approx(closed, rel=1e-12)
    # and it is not the cost of the coarse control of cell means
    coarse = hybridoc.evaluate(ocp, u.reshape(ocp.steps, K).mean(axis=1)[:, None])
    assert abs(coarse.cost - ev.cost) > 1e-6


def test_n_times_k_rows_without_substeps_name_k(tmp_path, single):
    path = save_controls(tmp_path / "ctrl.npy", np.repeat(single.u_guess, 10, axis=0))
    with pytest.raises(ControlsError) as info:
        load_controls(path, single)
    msg = str(info.value)
    assert "got shape (4800, 2)" in msg and "substeps=10" in msg
    with pytest.raises(ControlsError, match="--substeps 10"):
        load_controls(path, single, flag="--substeps")
    # the wrong K: the shape error names the finer grid
    with pytest.raises(ControlsError, match=r"expected shape \(1440, 2\): 1440 rows \(480 grid"):
        load_controls(path, single, substeps=3)
    # rows that are no multiple of N: no hint
    odd = save_controls(tmp_path / "odd.npy", single.u_guess[:-1])
    with pytest.raises(ControlsError) as info:
        load_controls(odd, single)
    assert "substeps" not in str(info.value)


def test_read_array_errors(tmp_path):
    with pytest.raises(ControlsError, match="gradient file .* does not exist"):
        read_array(tmp_path / "nope.npy", what="gradient")
    with pytest.raises(ControlsError, match="unsupported file type '.txt'"):
        read_array(tmp_path / "a.txt", what="gradient")
    bad = tmp_path / "bad.csv"
    bad.write_text("1,2\n3,x\n")
    with pytest.raises(ControlsError, match="line 2: 'x' is not a number"):
        read_array(bad)
    swapped = tmp_path / "swapped.csv"
    swapped.write_text("b,a\n1,2\n3,4\n")
    assert read_array(swapped, labels=["a", "b"]).tolist() == [[2.0, 1.0], [4.0, 3.0]]


def test_validate_controls_with_substeps(single):
    # a stand-in for the reference (validate_controls reads its cost, controls and events):
    # the coarse control itself, so that its K-fold repetition has no gap and no error
    u = single.u_guess
    ref = Solution.from_evaluation(hybridoc.evaluate(single, u), method="reference", scene="x")
    rep = validate_controls(single, np.repeat(u, K, axis=0), reference=ref, substeps=K)
    assert rep["substeps"] == K
    assert abs(rep["cost_gap_relative"]) < 1e-12
    assert rep["control_error"] == {"l2": 0.0, "max": 0.0}
    assert rep["sequence_matches"] and abs(rep["event_time_errors"][0]) < 1e-12
    # one substep changed by d over dt/K: L2 error d sqrt(dt/K)
    moved = np.repeat(u, K, axis=0)
    moved[7, 1] += 0.5
    rep = validate_controls(single, moved, reference=ref, substeps=K)
    assert rep["control_error"]["max"] == 0.5
    assert rep["control_error"]["l2"] == pytest.approx(0.5 * np.sqrt(single.dt / K), rel=1e-14)
    expected = hybridoc.evaluate(substep_problem(single, K), moved).cost
    assert rep["cost"] == expected
    with pytest.raises(ControlsError, match=r"expected shape \(1920, 2\)"):
        validate_controls(single, u, reference=ref, substeps=K)
