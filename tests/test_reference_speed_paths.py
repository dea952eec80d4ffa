"""The fast paths of the reference's re-simulations give the same numbers as the slow ones.

The judge calls a continuous control ``u(t)`` at every stage of its integrator, one time at
a time; the transcription's polynomial control and the reference's HMP control law are
evaluated there by twins of their vectorised forms (issue #18). These tests hold the twins
to the originals bit for bit.
"""

from __future__ import annotations

import threading

import casadi as ca
import numpy as np
import pytest

from hybridoc.problems import load_problem
from hybridoc.reference import solve_reference
from hybridoc.reference._nodes import buffer_call as _buffer_call
from hybridoc.solution import lagrange_pieces
from hybridoc.solvers.transcription import control_function, solve_dt
from hybridoc.solvers.transcription.collocation import pieces_at_one_time


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return a.shape == b.shape and np.array_equal(a.view(np.int64), b.view(np.int64))


def _probe_times(bounds: np.ndarray, rng: np.random.Generator, n: int) -> np.ndarray:
    """Random times, the element bounds and their neighbours on both sides (the element
    chosen at a bound is the one that starts there), and times outside [0, T]."""
    T = float(bounds[-1])
    return np.concatenate(
        [
            rng.uniform(-0.05 * T, 1.05 * T, n),
            bounds,
            np.nextafter(bounds, -np.inf),
            np.nextafter(bounds, np.inf),
        ]
    )


@pytest.mark.parametrize("degree", range(1, 10))
def test_polynomial_control_at_one_time_is_lagrange_pieces_bit_for_bit(degree):
    # the weighted sum's rounding depends on einsum's SIMD kernel (not left to right from
    # degree 3 on): the twin must make the same call, whatever the degree
    rng = np.random.default_rng(degree)
    nodes = np.array(ca.collocation_points(degree, "radau"))
    for nu, bounded in ((1, False), (2, True), (3, False)):
        E = int(rng.integers(1, 25))
        bounds = np.cumsum(np.r_[0.0, rng.uniform(0.01, 1.0, E)]) * rng.uniform(0.1, 10.0)
        values = rng.standard_normal((nu, E, degree)) * 30.0
        lo, hi = (np.full(nu, -20.0), np.full(nu, 25.0)) if bounded else (-np.inf, np.inf)
        u = pieces_at_one_time(bounds, nodes, values, lo, hi)
        for t in _probe_times(bounds, rng, 80):
            want = lagrange_pieces(np.array([t]), bounds, nodes, values, lo, hi)[0]
            assert _same_bits(u(float(t)), want), (degree, nu, t)


def test_dt_solution_control_function_is_its_saved_control_bit_for_bit():
    # a bounded problem: the clip of the polynomial into the bounds is part of u(t)
    ocp = load_problem("bounded-shuttle")
    sol = solve_dt(ocp)
    a = sol.arrays
    bounds = np.asarray(a["element_bounds"], dtype=float)
    nodes = np.asarray(a["control_nodes"], dtype=float)
    flat = np.asarray(a["radau_controls"], dtype=float)
    vals = flat.reshape(flat.shape[0], -1, nodes.size)
    nu = vals.shape[0]
    lo = np.asarray(a.get("u_min", np.full(nu, -np.inf)), dtype=float)
    hi = np.asarray(a.get("u_max", np.full(nu, np.inf)), dtype=float)
    u = control_function(sol)
    rng = np.random.default_rng(0)
    for t in _probe_times(bounds, rng, 300):
        want = lagrange_pieces(np.array([t]), bounds, nodes, vals, lo, hi)[0]
        assert _same_bits(u(float(t)), want)
    # and the judge's cost of the saved Solution is the transcription's own
    assert sol.cost == ocp_cost(ocp, sol)


def ocp_cost(ocp, sol) -> float:
    import hybridoc

    return float(hybridoc.evaluate(ocp, sol).cost)


@pytest.fixture(scope="module")
def bouncing_ball():
    ocp = load_problem("bouncing-ball")
    return ocp, solve_reference(ocp, sequence=["floor"])


def test_reference_law_through_buffers_is_the_casadi_call_bit_for_bit(bouncing_ball):
    _, sol = bouncing_ball
    res = sol.reference
    law = res.system.core.flow.dense_u
    call = _buffer_call(law)
    rng = np.random.default_rng(1)
    for nodes in res.nodes:
        for node in nodes:
            for tau in rng.uniform(0.0, 0.05, 5):
                want = np.asarray(law(node, tau), dtype=float).ravel()
                assert _same_bits(call(node, float(tau)), want)


def test_reference_control_is_the_judged_control_and_thread_safe(bouncing_ball):
    ocp, sol = bouncing_ball
    res = sol.reference
    u = res.control_function()
    times = np.linspace(0.0, ocp.horizon, 401)
    want = np.array([u(float(t)) for t in times])
    # its shooting cost and the judge's re-simulation of u(t) agree (what the verification
    # checked with this very function)
    assert abs(sol.cost - res.cost) <= 1e-9 * abs(res.cost)
    # one Num per thread: concurrent callers get their own buffers
    got: dict[int, np.ndarray] = {}

    def work(k: int) -> None:
        got[k] = np.array([u(float(t)) for t in times[::-1]])[::-1]

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    for k in range(4):
        assert _same_bits(got[k], want)


@pytest.mark.parametrize(
    ("name", "sequence"),
    [
        ("coulomb-block", ["reverse"]),
        # about 5 s (two discoveries on a free final time)
        pytest.param("friction-patch-free-time", ["enter-rough"], marks=pytest.mark.slow),
    ],
)
def test_a_given_sequence_newton_misses_from_the_guess_is_found_by_the_discovery(name, sequence):
    # coulomb-block: Newton from the guess converges to a worse extremal (1.41) whose
    # re-simulation chatters between the friction guards; friction-patch-free-time: Newton
    # from the guess does not converge. Both failed with the sequence given, while the
    # default solve finds that very sequence's extremal: the given sequence now gets the
    # same extremal, reported as an extremal of that sequence
    ocp = load_problem(name)
    found = solve_reference(ocp)
    # issue #29: best-found (a cheaper extremal of another sequence does not re-simulate to
    # its events: coulomb-block's and the patch's no-event extremals)
    assert found.info["sequence"] == sequence and found.status.value == "best-found"
    given = solve_reference(ocp, sequence=sequence)
    assert given.status.value == "extremal"
    assert given.info["sequence"] == sequence
    # the same extremal: the steps per phase a structure remembers from its last solve
    # move the last digit of a second solve
    assert abs(given.cost - found.cost) <= 1e-12 * abs(found.cost)
    np.testing.assert_allclose(given.info["event_times"], found.info["event_times"], rtol=1e-9)
    assert any("discovery" in c["origin"] for c in given.info["candidates"])


def _no_resimulation(monkeypatch):
    import hybridoc.callable_eval as ce

    def refuse(*args, **kwargs):
        raise AssertionError("the Solution was judged again")

    monkeypatch.setattr(ce, "evaluate_callable", refuse)
    monkeypatch.setattr("hybridoc.evaluator.evaluate_callable", refuse)


@pytest.mark.parametrize(
    ("name", "sequence"), [("bouncing-ball", ["floor"]), ("single-collision", ["ball1|ball2"])]
)
def test_to_solution_takes_the_verifications_judged_cost_bit_for_bit(name, sequence, monkeypatch):
    # a generic problem (the HMP law from nodes) and a disc scene (phase-linear): the
    # verification's re-simulation is the judge's evaluation of the saved Solution
    import hybridoc

    ocp = load_problem(name)
    res = solve_reference(ocp, sequence=sequence).reference
    assert res.judged is not None
    with monkeypatch.context() as m:
        _no_resimulation(m)
        sol = res.to_solution()
    ev = hybridoc.evaluate(ocp, sol)
    assert (sol.cost, sol.terminal_cost, sol.running_cost) == (
        ev.cost,
        ev.terminal_cost,
        ev.running_cost,
    )


def test_to_solution_judges_again_where_the_control_is_not_provably_the_same():
    import dataclasses

    import hybridoc

    ocp = load_problem("bouncing-ball")
    res = solve_reference(ocp, sequence=["floor"]).reference
    assert res.judged is not None
    # nodes that the Solution's arrays do not rebuild: its u(t) is another function, so the
    # verification's cost is not its judged cost
    other = dataclasses.replace(res, nodes=[n * (1 + 1e-9) for n in res.nodes])
    fake = dataclasses.replace(res.judged, cost=res.judged.cost + 1.0)
    other.judged = fake
    sol = other.to_solution()
    assert sol.cost != fake.cost
    assert sol.cost == hybridoc.evaluate(ocp, sol).cost


def test_a_sequence_no_control_has_is_pruned_not_solved():
    # ball2 is passive and at rest: nothing can send it into the wall first (an infinite
    # lower bound); the given sequence says so without Newton, the NLP or a transcription
    import hybridoc
    from hybridoc.errors import ConvergenceError

    scene = hybridoc.load_scene("multiple-collision")
    with pytest.raises(ConvergenceError, match="no control has these events") as info:
        solve_reference(scene, sequence=["ball2|wall"])
    assert "hint" in str(info.value) and "Newton" not in str(info.value)


def test_early_screens_leave_the_search_as_it_was(monkeypatch):
    # the screens of an explicit search start before the guess's candidates (in worker
    # processes); the enumeration takes their outcomes as its own: the same
    # landscape, verdicts, origins and coverage as with every screen started in order
    import hybridoc
    import hybridoc.reference.search.enumeration as rsolve

    scene = hybridoc.load_scene("multiple-collision")
    started = []
    real_start = rsolve._EarlyScreens.start

    def spy(*args, **kwargs):
        early = real_start(*args, **kwargs)
        started.append(early)
        return early

    monkeypatch.setattr(rsolve._EarlyScreens, "start", spy)
    kwargs = dict(search=2, multistart=0, transcription=False)
    with_early = solve_reference(scene, **kwargs)
    if started[0] is None:
        pytest.skip("no second usable core or no fork: the screens run in order anyway")
    assert started[0].workers  # the screens started in worker processes
    monkeypatch.setattr(rsolve._EarlyScreens, "start", lambda *a, **k: None)
    in_order = solve_reference(scene, **kwargs)

    def rows(sol):
        keys = ("sequence", "cost", "verdict", "origin")
        return [tuple(r[k] for k in keys) for r in sol.info["landscape"]]

    assert rows(with_early) == rows(in_order)
    assert with_early.cost == in_order.cost
    assert with_early.info["coverage"] == in_order.info["coverage"]


def test_no_sequence_is_solved_twice_from_the_same_start(monkeypatch):
    # friction-patch-free-time: the guess's own sequence fails from the guess, and the
    # known control of the guess (the guess itself) used to start the very same solve again
    import hybridoc.reference.search.book as rsolve

    calls = []
    real = rsolve.solve_sequence

    def spy(ocp, sequence, gamma0, u_guess, **kw):
        calls.append(
            (
                tuple(sequence),
                np.asarray(u_guess, dtype=float).tobytes(),
                np.asarray(gamma0, dtype=float).tobytes(),
                bool(kw.get("estimate")),
                kw.get("grad") is not None,
                id(kw.get("guess_ev")),
                id(kw.get("warm_start")),
            )
        )
        return real(ocp, sequence, gamma0, u_guess, **kw)

    monkeypatch.setattr(rsolve, "solve_sequence", spy)
    sol = solve_reference(load_problem("friction-patch-free-time"))
    assert sol.status.value == "best-found" and sol.info["sequence"] == ["enter-rough"]
    assert len(calls) == len(set(calls)), "a sequence was solved twice from one start"


def test_the_disc_residual_of_one_length_is_each_sequence_s_own_bit_for_bit():
    # the disc shooting residual is built once per number of events, each event's guard
    # chosen by a parameter (issue #18); against the residual, Jacobian and trajectory
    # built for the sequence alone, with its own guard functions, at random points: the
    # same bits but for the sign of a zero (a structural zero there, a product with the
    # unselected guards' zeros here)
    from hybridoc.reference import shooting as sh

    def same(a, b):
        return _same_bits(np.asarray(a, dtype=float) + 0.0, np.asarray(b, dtype=float) + 0.0)

    ocp = load_problem("multiple-collision").to_ocp()
    names = [g.name for g in ocp.guards]
    rng = np.random.default_rng(7)
    seqs = [[a] for a in names] + [[a, b] for a in names for b in names]
    seqs += [list(rng.choice(names, 3)) for _ in range(3)] + [list(rng.choice(names, 5))]
    shared: dict[int, object] = {}
    for seq in seqs:
        S = sh.shooting_system(ocp, seq)
        own = sh._DiscCore(ocp, seq)  # a core of its own, outside the cache
        F, traj = own._assemble(ocp, lambda k, j, s, lam, h, c=own: c.phase(s, lam, h), ca.SX)
        # one compiled function per length, whatever the guards
        assert shared.setdefault(len(seq), S.core.F.fn) is S.core.F.fn
        for _ in range(3):
            z = rng.normal(size=S.core.nz)
            for k, t in enumerate(np.sort(rng.uniform(0.0, S.T, S.K))):
                z[S.core.nx + k * (S.core.nx + 2)] = t
            for a, b in zip(S.core.F(z, S.x0, S.T), F(z, S.x0, S.T), strict=True):
                assert same(a, b), seq
            # through the buffer API: the shared function's own call, bit for bit
            idx = np.asarray(S.core.guard_index, dtype=float)
            for a, b in zip(S.core.F(z, S.x0, S.T), S.core.F.fn(z, S.x0, S.T, idx), strict=True):
                assert _same_bits(a, np.asarray(b)), seq
            for a, b in zip(S.core.traj(z, S.x0, S.T), traj(z, S.x0, S.T), strict=True):
                assert same(a, b), seq
    assert sorted(shared) == [1, 2, 3, 5]
