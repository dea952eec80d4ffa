"""The problem library (``problems/library``) against optima computed without hybridoc's solvers.

For each configuration of :data:`library_optima.CONFIGS` the optimum of the claimed event
sequence is computed independently (``tests/library_optima.py``: exact sequence-fixed optima of
the double integrators, NLP plus indirect HMP shooting for the pendulum) and checked here:

- the hand-written restatement of each problem matches the library's CasADi functions;
- the optimal control, as a callable ``u(t)`` given to :func:`hybridoc.evaluate_callable`,
  reproduces the independent cost to 1e-9 relative and exactly the claimed events, all
  transversal;
- every alternative sequence (0 to 3 events) costs more;
- the HMP conditions (costate jump with a multiplier, Hamiltonian continuity, ``u = argmin H``)
  hold at the double-integrator optima to 1e-8;
- ``ocp.meta["claimed_sequence"]`` states the same sequence.

:data:`EXPECTED` collects the numbers (cost, sequence, event times) as the tests compute them,
for comparison with the project's solvers.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from library_optima import (
    CLAIMED_EVENTS,
    CONFIGS,
    build,
    build_mode_problem,
    expected_table,
    independent_optimum,
    library,
    linear_model,
    pendulum_rhs,
)

import hybridoc

NAMES = list(CONFIGS)
LINEAR = [n for n in NAMES if CONFIGS[n][0] != "pendulum_wall"]
PENDULUM = [n for n in NAMES if CONFIGS[n][0] == "pendulum_wall"]

#: name -> {"cost", "sequence", "event_times", "alternatives"}, filled by the tests below
EXPECTED: dict[str, dict] = {}


@pytest.fixture(scope="module", params=NAMES)
def optimum(request: pytest.FixtureRequest) -> dict:
    r = independent_optimum(request.param)
    EXPECTED[request.param] = {
        "cost": r["cost"],
        "sequence": list(r["sequence"]),
        "event_times": list(r["event_times"]),
        "alternatives": dict(r["alternatives"]),
    }
    return r


def _num(fn: ca.Function, *args: np.ndarray) -> np.ndarray:
    return np.array(fn(*args), dtype=float).ravel()


@pytest.mark.parametrize("name", NAMES)
def test_restatement_matches_library(name: str) -> None:
    ocp = build(name)
    rng = np.random.default_rng(7)
    for _ in range(5):
        x = rng.normal(size=ocp.nx)
        u = rng.normal(size=ocp.nu)
        (g,) = ocp.guards
        if CONFIGS[name][0] == "pendulum_wall":
            P = ocp.meta["params"]
            f = np.array(pendulum_rhs(P, x, u[0]))
            L = P["eps"] * u @ u
            phi = (
                P["weight_angle"] * (x[0] - P["target_angle"]) ** 2
                + P["weight_velocity"] * (x[1] - P["target_velocity"]) ** 2
            )
            psi = P["wall_angle"] - x[0]
            reset = np.array([x[0], -P["restitution"] * x[1]])
        else:
            mod = linear_model(ocp)
            f, L = mod.f(x, u), mod.eps * u @ u
            phi = (x - mod.xt) @ mod.W @ (x - mod.xt)
            psi, reset = mod.guards[g.name] @ x, mod.resets[g.name] @ x
            np.testing.assert_allclose(ocp.x0, mod.x0, rtol=0, atol=0)
            assert ocp.horizon == mod.T
        np.testing.assert_allclose(_num(ocp.f, x, u), f, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(_num(ocp.L, x, u), L, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(_num(ocp.phi, x), phi, rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(_num(g.psi, x), psi, rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(_num(g.reset, x), reset, rtol=1e-14, atol=1e-14)


def test_library_api() -> None:
    lib = library()
    assert set(lib.LIBRARY) == {
        "bouncing-ball",
        "bouncing-ball-2",
        "ball-on-slope",
        "juggling-paddle",
        "pendulum-wall",
        "hopper",
        "coulomb-block",
        "friction-patch",
        "friction-patch-free-time",
        "bounded-shuttle",
        "two-tanks",
    }
    assert all(lib.describe(name) for name in lib.LIBRARY)
    for fn in lib.LIBRARY.values():
        ocp = fn()
        assert isinstance(ocp, hybridoc.HybridOCP)
        assert ocp.u_guess.shape == (ocp.steps, ocp.nu)
        assert ocp.meta["claimed_sequence"] is not None
        assert len(ocp.state_labels) == ocp.nx and len(ocp.control_labels) == ocp.nu
    # outside the verified configurations there is no claim
    assert (
        lib.bouncing_ball(1, 0.8, horizon=2.0, target_height=0.5).meta["claimed_sequence"] is None
    )
    assert lib.juggling_paddle(0.9).meta["claimed_sequence"] is None
    with pytest.raises(ValueError, match="restitution"):
        lib.bouncing_ball(restitution=1.5)
    with pytest.raises(ValueError, match="target_height"):
        lib.bouncing_ball(horizon=1.0)
    with pytest.raises(ValueError, match="initial_angle"):
        lib.pendulum_wall(initial_angle=0.5)


@pytest.mark.parametrize("name", LINEAR)
def test_polynomial_guard_degree_and_flow_map(name: str) -> None:
    """The guard is a quadratic in time along the exact flow map, which matches the ODE."""
    ocp = build(name)
    (g,) = ocp.guards
    assert g.degree == 2
    rng = np.random.default_rng(3)
    x, u = rng.normal(size=ocp.nx), rng.normal(size=ocp.nu)
    hs = np.linspace(0.0, 1.0, 6)
    ends = [np.array(ocp.flow_map(x, u, h)[0], dtype=float).ravel() for h in hs]
    psi = [float(_num(g.psi, s)[0]) for s in ends]
    coef = np.polyfit(hs, psi, 5)
    np.testing.assert_allclose(coef[:3], 0.0, atol=1e-10)
    assert abs(coef[3]) > 1e-3
    # piecewise-constant controls: the flow-map evaluator equals the ODE-based one
    uu = ocp.u_guess + 0.3 * rng.normal(size=ocp.u_guess.shape)
    a = hybridoc.evaluate(ocp, uu)
    grid = ocp.time_grid()
    b = hybridoc.evaluate_callable(
        ocp, lambda t: uu[min(int(t / ocp.dt), ocp.steps - 1)], breakpoints=grid[1:-1]
    )
    assert a.cost == pytest.approx(b.cost, rel=1e-9)
    np.testing.assert_allclose(
        [e.time for e in a.events], [e.time for e in b.events], rtol=0, atol=1e-9
    )


def test_pendulum_guard_is_not_polynomial() -> None:
    ocp = build(PENDULUM[0])
    assert ocp.guards[0].degree is None


@pytest.mark.parametrize("name", NAMES)
def test_initial_guess_is_reasonable(name: str) -> None:
    """The zero initial guess gives the claimed sequence (one impact only for the light paddle,
    whose optimum has two)."""
    ocp = build(name)
    ev = hybridoc.evaluate(ocp)
    names = [ocp.guards[e.guard].name for e in ev.events]
    claimed = ocp.meta["claimed_sequence"]
    if name == "juggling_paddle(e=0.8, mu=0.5)":
        assert names == claimed[:1]
    else:
        assert names == claimed
    assert all(e.approach_speed < -1.0 for e in ev.events)


def test_claim_matches_library(optimum: dict) -> None:
    ocp = optimum["ocp"]
    assert len(optimum["sequence"]) == CLAIMED_EVENTS[optimum["name"]]
    assert ocp.meta["claimed_sequence"] == optimum["sequence"]


def test_callable_reproduces_cost_and_events(optimum: dict) -> None:
    ocp = optimum["ocp"]
    ev = hybridoc.evaluate_callable(
        ocp, optimum["control_callable"], breakpoints=optimum["breakpoints"]
    )
    assert ev.cost == pytest.approx(optimum["cost"], rel=1e-9)
    assert [ocp.guards[e.guard].name for e in ev.events] == optimum["sequence"]
    np.testing.assert_allclose(
        [e.time for e in ev.events], optimum["event_times"], rtol=0, atol=1e-9
    )
    # transversal impacts: no grazing at the optimum
    assert all(e.approach_speed < -1.0 for e in ev.events)
    np.testing.assert_allclose(
        [e.approach_speed for e in ev.events], optimum["hmp"]["approach_speeds"], rtol=1e-8
    )


def test_claimed_sequence_is_optimal(optimum: dict) -> None:
    """Every alternative number of events (0 to 3) costs more. For the double integrators the
    alternatives' numbers are lower bounds (relaxations), so this is a proof up to the search
    over event times; for the pendulum they are NLP optima."""
    alts = optimum["alternatives"]
    assert set(alts) | {len(optimum["sequence"])} >= {0, 1, 2}
    assert min(alts.values()) > 1.2 * optimum["cost"]


@pytest.mark.parametrize("name", LINEAR)
def test_hmp_conditions(name: str) -> None:
    r = independent_optimum(name)
    hmp = r["hmp"]
    assert hmp["control"] < 1e-8  # u = argmin H along lambda, with its jumps
    assert hmp["hamiltonian"] < 1e-8  # H(gamma-) = H(gamma+)
    assert len(hmp["multipliers"]) == len(r["sequence"])
    assert np.all(np.isfinite(hmp["multipliers"]))


@pytest.mark.parametrize("name", PENDULUM)
def test_pendulum_nlp_agrees_with_indirect_solution(name: str) -> None:
    """The RK4 NLP (piecewise-constant torque) and the indirect HMP solution describe the same
    optimum: the NLP's cost is above, by its discretisation error."""
    r = independent_optimum(name)
    nlp = r["nlp"]
    assert r["hmp"]["residual"] < 1e-10
    assert r["cost"] <= nlp["cost"] <= r["cost"] * (1 + 1e-3)
    np.testing.assert_allclose(nlp["event_times"], r["event_times"], rtol=0, atol=1e-4)
    ev = hybridoc.evaluate_callable(
        r["ocp"], nlp["control_callable"], breakpoints=nlp["breakpoints"]
    )
    assert ev.cost == pytest.approx(nlp["cost"], rel=1e-8)
    assert [r["ocp"].guards[e.guard].name for e in ev.events] == r["sequence"]


def test_expected_table_complete() -> None:
    table = expected_table()
    assert set(table) == set(NAMES)
    for name, row in table.items():
        EXPECTED.setdefault(
            name, {k: row[k] for k in ("cost", "sequence", "event_times", "alternatives")}
        )
        assert EXPECTED[name]["cost"] == row["cost"] > 0
        assert len(row["event_times"]) == len(row["sequence"])
        assert np.all(np.diff([0.0, *row["event_times"], build(name).horizon]) > 0)


@pytest.mark.parametrize(
    "name",
    LINEAR,  # the pendulum takes 3 s each
)
def test_default_reference_finds_the_independent_optimum(name: str) -> None:
    """The reference's default discovery, with no sequence given, reaches the independently
    computed optimum (it once returned juggling_paddle(mu=0.5)'s one-impact extremal, 74%
    above the two-impact optimum, as success)."""
    from hybridoc.reference import solve_reference

    opt = independent_optimum(name)
    sol = solve_reference(build(name))
    assert sol.success
    assert sol.sequence == opt["sequence"]
    assert sol.cost == pytest.approx(opt["cost"], rel=1e-9)


def test_hopper_transcription_solves_only_sequences_the_modes_admit(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The transcription from the hopper's guess (touchdown, liftoff, touchdown, liftoff)
    tries that sequence and those with one event dropped; three of these fire a transition
    outside its source mode (two touchdowns in a row, ...): they are recorded, not solved
    (their NLPs have no feasible point), and the answer is the one found when every
    candidate is solved, bit for bit."""
    from hybridoc.solvers import transcription
    from hybridoc.solvers.transcription import solve_dt

    ocp = build_mode_problem("hopper")
    sol = solve_dt(ocp)
    rows = sol.info["candidates"]
    skipped = [r["sequence"] for r in rows if r["status"].startswith("not solved")]
    assert skipped == [
        ["liftoff", "touchdown", "liftoff"],
        ["touchdown", "touchdown", "liftoff"],
        ["touchdown", "liftoff", "liftoff"],
    ]
    assert not any(ocp.sequence_admissible(s) for s in skipped)
    assert all(r["nlp_cost"] is not None for r in rows if r["sequence"] not in skipped)
    monkeypatch.setattr(transcription.solve, "admissible_candidates", lambda ocp, c: (c, []))
    every = solve_dt(ocp)
    failed = [r["sequence"] for r in every.info["candidates"] if r["nlp_cost"] is None]
    assert failed == skipped  # IPOPT: infeasible, each of them
    assert sol.sequence == every.sequence == ["touchdown", "liftoff", "touchdown", "liftoff"]
    assert sol.cost == every.cost
    np.testing.assert_array_equal(sol.controls, every.controls)
