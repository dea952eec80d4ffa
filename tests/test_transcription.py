"""Multi-phase direct transcription against the HMP reference and the event-exact evaluator."""

from __future__ import annotations

import dataclasses
import json

import casadi as ca
import numpy as np
import pytest
from paper_references import paper_reference

import hybridoc
from hybridoc import Guard, HybridOCP
from hybridoc.errors import HybridocError
from hybridoc.solution import Solution
from hybridoc.solvers.transcription import control_function, solve_dt

PAPER = ("single-collision", "multiple-collision")


@pytest.fixture(scope="module")
def solved() -> dict[str, tuple[Solution, Solution]]:
    # the references are shared with test_reference (one solve per worker)
    return {name: (solve_dt(hybridoc.load_scene(name)), paper_reference(name)) for name in PAPER}


@pytest.mark.parametrize("name", PAPER)
def test_dt_matches_reference(solved, name):
    dt, ref = solved[name]
    assert dt.method == "dt"
    assert dt.info["sequence"] == ref.info["sequence"]
    assert abs(dt.cost - ref.cost) <= 1e-6 * ref.cost
    np.testing.assert_allclose(dt.info["event_times"], ref.info["event_times"], atol=1e-5, rtol=0)
    # in fact both are exact for disc scenes (cubic flows): much tighter than the target
    assert abs(dt.cost - ref.cost) <= 1e-10 * ref.cost


def test_multiple_collision_two_event_sequence_matches_reference(solved):
    from hybridoc.reference import solve_reference

    scene = hybridoc.load_scene("multiple-collision")
    seq = ["ball1|ball2", "ball2|wall"]
    dt = solve_dt(scene, sequence=seq)
    ref = solve_reference(scene, sequence=seq)
    assert abs(dt.cost - ref.cost) <= 1e-6 * ref.cost
    np.testing.assert_allclose(dt.info["event_times"], ref.info["event_times"], atol=1e-5)
    # the paper's one-collision-plus-bounce optimum lies above the three-event one (dt's
    # default solve, from the fixture)
    assert dt.cost > solved["multiple-collision"][0].cost + 0.01


@pytest.mark.parametrize("name", PAPER)
def test_cost_is_the_resimulated_continuous_cost(solved, name):
    dt, _ = solved[name]
    scene = hybridoc.load_scene(name)
    ev = hybridoc.evaluate_callable(
        scene.to_ocp(), control_function(dt), breakpoints=dt.arrays["element_bounds"][1:-1]
    )
    assert ev.cost == pytest.approx(dt.cost, rel=1e-12)
    assert abs(dt.info["nlp_cost"] - dt.cost) <= 1e-9 * dt.cost
    assert [e["time"] for e in dt.events] == pytest.approx(dt.info["event_times"], abs=1e-8)
    # the grid cell averages, judged piecewise constant, cost O(dt^2) more
    pwc = hybridoc.evaluate(scene, dt.controls).cost
    assert 0 <= pwc - dt.cost < 1e-3


def _split_phases(times: np.ndarray, values: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Split a costate record at its repeated (event) times."""
    cuts = np.flatnonzero(np.diff(times) <= 1e-14) + 1
    return list(zip(np.split(times, cuts), np.split(values, cuts), strict=True))


@pytest.mark.parametrize("name", PAPER)
def test_costates_match_reference(solved, name):
    dt, ref = solved[name]
    ref_phases = _split_phases(ref.costate_times, ref.costates)
    dt_phases = _split_phases(dt.costate_times, dt.costates)
    assert len(ref_phases) == len(dt_phases) == len(dt.events) + 1
    scale = np.abs(ref.costates).max()
    for (tr, lr), (td, ld) in zip(ref_phases, dt_phases, strict=True):
        for k in range(lr.shape[1]):
            # disc costates are affine in t inside a phase: linear interpolation is exact
            interp = np.interp(td, tr, lr[:, k])
            np.testing.assert_allclose(ld[:, k], interp, atol=1e-7 * scale)
    np.testing.assert_allclose(dt.info["lambda0"], ref.costates[0], atol=1e-7 * scale)


@pytest.mark.parametrize("name", PAPER)
def test_costate_transversality_and_initial_gradient(solved, name):
    dt, _ = solved[name]
    ocp = hybridoc.load_scene(name).to_ocp()
    s_T = dt.states[-1]
    s = ca.SX.sym("s", ocp.nx)
    grad_phi = np.asarray(ca.Function("gp", [s], [ca.gradient(ocp.phi(s), s)])(s_T)).ravel()
    np.testing.assert_allclose(dt.costates[-1], grad_phi, atol=1e-9)


def test_lambda0_is_the_sensitivity_of_the_optimal_cost():
    # lambda(0) from the initial-condition multiplier equals dJ*/ds(0) (envelope theorem):
    # central differences of the re-solved optimum
    ocp = hybridoc.load_scene("single-collision").to_ocp()
    seq = ["ball1|ball2"]
    lam0 = np.array(solve_dt(ocp, sequence=seq).info["lambda0"])
    h = 1e-5
    fd = np.zeros(ocp.nx)
    for i in range(ocp.nx):
        e = np.zeros(ocp.nx)
        e[i] = h
        plus = solve_dt(dataclasses.replace(ocp, x0=ocp.x0 + e), sequence=seq).info["nlp_cost"]
        minus = solve_dt(dataclasses.replace(ocp, x0=ocp.x0 - e), sequence=seq).info["nlp_cost"]
        fd[i] = (plus - minus) / (2 * h)
    np.testing.assert_allclose(lam0, fd, atol=1e-6)


def test_mesh_and_degree_independence(solved):
    scene = hybridoc.load_scene("single-collision")
    base = solved["single-collision"][0]  # the default mesh and degree
    for kw in ({"mesh": 1}, {"mesh": 9}, {"degree": 4, "mesh": 2}):
        other = solve_dt(scene, **kw)
        assert other.cost == pytest.approx(base.cost, rel=1e-11)


def test_sequence_from_another_solution_and_discovery_record(solved):
    dt, ref = solved["multiple-collision"]
    again = solve_dt(hybridoc.load_scene("multiple-collision"), initial=ref)
    assert again.info["sequence"] == ref.info["sequence"]
    assert again.cost == pytest.approx(ref.cost, rel=1e-10)
    cands = {tuple(c["sequence"]): c for c in dt.info["candidates"]}
    assert cands[("ball1|ball2", "ball2|wall")]["nlp_cost"] > dt.cost


def test_saved_solution_keeps_its_continuous_control(solved, tmp_path):
    dt, _ = solved["single-collision"]
    dt.save(tmp_path / "dt")
    back = Solution.load(tmp_path / "dt")
    u1, u2 = control_function(dt), control_function(back)
    for t in (0.0, 0.2, 0.46, 0.9):
        np.testing.assert_array_equal(u1(t), u2(t))


def test_unknown_guard_is_a_clear_error():
    with pytest.raises(HybridocError, match="unknown guard"):
        solve_dt(hybridoc.load_scene("single-collision"), sequence=["ball1|moon"])


def test_generic_ocp_bouncing_ball():
    s, u = ca.SX.sym("s", 2), ca.SX.sym("u")
    ocp = HybridOCP.from_expressions(
        s,
        u,
        f=ca.vertcat(s[1], u - 9.81),
        L=0.01 * u**2,
        phi=(s[0] - 1.0) ** 2,
        guards=[Guard.from_expressions("ground", s, s[0], ca.vertcat(s[0], -0.9 * s[1]))],
        x0=[1.0, 0.0],
        horizon=2.0,
        steps=200,
    )
    sol = solve_dt(ocp)
    assert sol.info["sequence"] == ["ground", "ground"]
    # the optimum beats the initial guess by far and is mesh independent (exact polynomials)
    assert sol.cost < 0.1 * hybridoc.evaluate(ocp).cost
    assert solve_dt(ocp, mesh=8).cost == pytest.approx(sol.cost, rel=1e-9)
    # transversality at T
    np.testing.assert_allclose(sol.costates[-1][0], 2 * (sol.states[-1][0] - 1.0), atol=1e-9)


def test_cli_solve_dt_json(capsys, monkeypatch, tmp_path):
    # in this process: tests/test_conventions.py runs `solve --method dt --json` as a real
    # process (a subprocess here paid ~3 s of imports again)
    from hybridoc.cli import main

    monkeypatch.chdir(tmp_path)
    # best-found (exit 1): dt compared only its guess's sequences, without proof (issue #29)
    assert main(["solve", "single-collision", "--method", "dt", "--json"]) == 1
    data = json.loads(capsys.readouterr().out)
    for key in ("cost", "terminal_cost", "running_cost", "events", "status", "timings"):
        assert key in data
    assert data["status"] == "best-found" and data["timings"]["solve_time_s"] > 0
    assert data["cost"] == pytest.approx(0.311416870358, rel=1e-10)
    assert data["events"][0]["bodies"] == ["ball1", "ball2"]


def test_dt_options_and_method_are_consistent(solved):
    import inspect

    from hybridoc.methods import METHODS
    from hybridoc.solvers.transcription import MAX_DEGREE, MAX_MESH, METHOD, DTOptions

    assert METHODS["dt"] is METHOD and METHOD.options is DTOptions
    METHOD.check_signature()  # solve_dt takes initial, progress and exactly the options
    assert METHOD.tolerance == 1e-6
    params = inspect.signature(solve_dt).parameters
    for f in dataclasses.fields(DTOptions):  # the options' defaults are solve_dt's
        assert params[f.name].default == f.default, f.name
    specs = {s.name: s for s in METHOD.specs()}
    assert [s.flag for s in specs.values() if s.cli] == [
        "--sequence", "--mesh", "--degree", "--time-limit", "--terminal-tol"
    ]  # fmt: skip
    assert not specs["verbose"].cli
    assert specs["mesh"].parser("8") == 8 and specs["degree"].parser("4") == 4
    assert specs["time_limit"].parser("2.5") == 2.5
    with pytest.raises(ValueError, match=rf"^mesh .*from 1 to {MAX_MESH}, got '100000000'$"):
        specs["mesh"].parser("100000000")
    for bad in ("0", "x", "1.5"):
        with pytest.raises(ValueError, match="mesh"):
            specs["mesh"].parser(bad)
    with pytest.raises(ValueError, match=f"degree must be an integer from 1 to {MAX_DEGREE}"):
        specs["degree"].parser("99")
    for bad in ("0", "-1", "nan", "inf"):
        with pytest.raises(ValueError, match="finite number > 0"):
            specs["time_limit"].parser(bad)
    # what hybridoc solve prints for dt besides status, cost and events
    dt, _ = solved["single-collision"]
    lines = METHOD.summary_lines(dt)
    assert [label for label, _ in lines] == ["iterations", "nlp cost", "settings"]
    assert lines[1][1] == f"{dt.info['nlp_cost']:.12g} (the transcription's)"
    assert lines[2][1] == "degree 3, mesh 4"
