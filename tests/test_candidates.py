"""The reference's candidates interface (:mod:`hybridoc.reference.sources`).

The reference imports no solver: candidate sequences and controls come from sources passed
in or registered (the solvers register theirs when :mod:`hybridoc.solvers` is imported), and
the result says which sources it used.
"""

from __future__ import annotations

import ast
import warnings
from pathlib import Path

import numpy as np
import pytest

import hybridoc
import hybridoc.solvers  # noqa: F401  (registers the solvers' candidate sources)
from hybridoc.errors import ConvergenceError, SceneError
from hybridoc.problems import load_problem
from hybridoc.reference import (
    Proposal,
    register_source,
    registered_sources,
    solve_reference,
    unregister_source,
)
from hybridoc.reference.solve import METHOD, ReferenceOptions, parse_budget, parse_search
from hybridoc.solvers.candidates import MultiStartSource, TranscriptionSource

REFERENCE = Path(__file__).resolve().parents[1] / "reference"
#: multiple-collision's optimum (independently: tests/test_reference.py, the paper's issue)
OPTIMUM = 0.356279430543373
OPTIMAL_SEQUENCE = ["ball1|ball2", "ball2|wall", "ball1|ball2"]


def _imported_modules(path: Path) -> set[str]:
    """Every module a file imports, at any depth (imports inside functions count)."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module is not None:
            found.add(node.module)
            found |= {f"{node.module}.{alias.name}" for alias in node.names}
    return found


def test_no_reference_module_imports_a_solver() -> None:
    files = sorted(REFERENCE.glob("*.py"))
    assert len(files) >= 6
    for path in files:
        bad = sorted(m for m in _imported_modules(path) if m.startswith("hybridoc.solvers"))
        assert not bad, f"{path.name} imports {bad}"


class _Oracle:
    """Proposes multiple-collision's optimal sequence, with no control."""

    name = "oracle"

    def propose(self, ocp, context):
        assert context.evaluation.cost > 0 and context.controls.shape == (ocp.steps, ocp.nu)
        return [Proposal(self.name, OPTIMAL_SEQUENCE)]


class _Useless:
    name = "useless"

    def propose(self, ocp, context):
        return []


class _Broken:
    name = "broken"

    def propose(self, ocp, context):
        raise ConvergenceError("nothing converged")


def _at_rest() -> tuple[hybridoc.HybridOCP, np.ndarray]:
    # from zero controls nothing moves: the guess proposes no event, and its one-event
    # neighbours are not realisable, so only a source can reach the optimum
    ocp = hybridoc.as_ocp("multiple-collision")
    return ocp, np.zeros((ocp.steps, ocp.nu))


def _found(sol: hybridoc.Solution) -> bool:
    """The reference's answer of a search: success exactly where its coverage proves it,
    best-found otherwise (issue #29)."""
    cov = sol.info["coverage"]
    return sol.status.value in ("success", "best-found") and (
        (sol.status.value == "success") == cov["proven"]
    )


def test_a_source_passed_in_proposes_the_optimal_sequence() -> None:
    ocp, zero = _at_rest()
    sol = solve_reference(ocp, initial=zero, sources=[_Oracle()])
    # issue #29: multiple-collision's optimum is best-found (some two-event sequences have
    # no extremal), success only where the coverage proves it
    assert _found(sol) and sol.sequence == OPTIMAL_SEQUENCE
    assert sol.cost == pytest.approx(OPTIMUM, rel=1e-9)
    origins = {tuple(c["sequence"]): c["origin"] for c in sol.info["candidates"]}
    assert origins[tuple(OPTIMAL_SEQUENCE)] == "oracle"
    names = [s["name"] for s in sol.info["sources"]]
    assert names == ["initial guess", "oracle", "enumeration"]
    row = sol.info["sources"][1]
    assert row["kind"] == "given" and row["proposals"] == 1
    assert sol.info["warm_starts"] == []  # no source given that starts the shooting


def test_a_useless_or_broken_source_still_runs() -> None:
    ocp, zero = _at_rest()
    sol = solve_reference(ocp, initial=zero, sources=[_Useless(), _Broken()])
    assert sol.cost > OPTIMUM * 1.5  # the no-event extremal: nothing proposed better
    rows = {s["name"]: s for s in sol.info["sources"]}
    assert rows["useless"]["proposals"] == 0 and "failed" not in rows["useless"]
    assert rows["broken"]["failed"] == "nothing converged"


def test_a_proposed_control_is_known_and_leads_to_the_optimum() -> None:
    """A proposal's control is one the result must not be worse than."""
    ocp = hybridoc.as_ocp("multiple-collision")
    best = solve_reference(ocp, sources=[])
    assert best.cost == pytest.approx(OPTIMUM, rel=1e-9)

    class Known:
        name = "known"

        def propose(self, ocp, context):
            ev = hybridoc.evaluate(ocp, best.controls)
            return [Proposal(self.name, ev.sequence, best.controls, ev, solve=False, label="a")]

    ocp2, zero = _at_rest()
    sol = solve_reference(ocp2, initial=zero, sources=[Known()])
    # the trust step solves the sequence of the cheaper known control again, from it
    assert _found(sol) and sol.cost == pytest.approx(OPTIMUM, rel=1e-9)  # issue #29
    assert {"source": "a", "cost": pytest.approx(OPTIMUM, rel=1e-3),
            "sequence": OPTIMAL_SEQUENCE} in sol.info["known_controls"]  # fmt: skip
    origins = {tuple(c["sequence"]): c["origin"] for c in sol.info["candidates"]}
    assert origins[tuple(OPTIMAL_SEQUENCE)] == "cheaper a"


def test_registered_sources_are_the_default_and_recorded() -> None:
    names = [s.name for s in registered_sources()]
    # both built in, in the order solvers/candidates.py registers them
    assert set(names[:2]) == {"transcription", "multi-start"}
    sol = solve_reference("single-collision")
    assert sol.cost == pytest.approx(0.31141687035847165, rel=1e-9)
    used = [(s["name"], s["kind"]) for s in sol.info["sources"]]
    assert ("transcription", "registered") in used and ("multi-start", "registered") in used
    assert sol.info["warm_starts"] == ["transcription"]
    # the legacy switches turn the built-in sources off
    off = solve_reference("single-collision", transcription=False, multistart=0)
    assert [s["name"] for s in off.info["sources"]] == ["initial guess", "enumeration"]
    assert off.info["warm_starts"] == []


def test_an_empty_registry_warns(monkeypatch: pytest.MonkeyPatch) -> None:
    saved = registered_sources()
    try:
        for s in saved:
            unregister_source(s.name)
        with pytest.warns(UserWarning, match="no candidate sources are registered"):
            sol = solve_reference("single-collision")
        assert [s["name"] for s in sol.info["sources"]] == ["initial guess", "enumeration"]
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            solve_reference("single-collision", sources=[])  # an explicit choice: no warning
    finally:
        for s in saved:
            register_source(s)
    assert registered_sources() == saved


def test_bad_sources_are_scene_errors() -> None:
    with pytest.raises(SceneError, match="candidate source needs a name"):
        solve_reference("single-collision", sources=[object()])
    with pytest.raises(SceneError, match="list of candidate sources"):
        solve_reference("single-collision", sources="transcription")
    with pytest.raises(TypeError, match="candidate source needs a name"):
        register_source(object())


def test_the_transcription_starts_the_shooting_of_a_given_sequence() -> None:
    """The fallback of :func:`solve_sequence` goes through the SequenceStarter protocol."""
    from hybridoc.reference.sequence import solve_sequence

    ocp = hybridoc.as_ocp("bouncing-ball-2")
    ev = hybridoc.evaluate(ocp)
    src = TranscriptionSource()
    proposal = src.start(ocp, ev.sequence, ev, np.asarray(ocp.u_guess, dtype=float))
    assert proposal.warm_start is not None and not proposal.known
    res, why = solve_sequence(
        ocp, ev.sequence, proposal.warm_start.event_times, np.asarray(ocp.u_guess, dtype=float),
        warm_start=proposal.warm_start,
    )  # fmt: skip
    assert res is not None, why


def test_the_method_declares_its_options() -> None:
    METHOD.check_signature()
    assert METHOD.name == "reference" and METHOD.tolerance == 1e-9
    assert METHOD.options is ReferenceOptions
    cli = [s.name for s in METHOD.specs() if s.cli]
    assert cli == ["sequence", "search", "budget", "time_limit", "verbose", "rtol"]
    assert parse_budget("2.5") == 2.5
    for bad in ("0", "-1", "x", "inf", "nan"):
        with pytest.raises(ValueError, match="budget must be"):
            parse_budget(bad)
    assert parse_search("3") == 3
    for bad, match in (("-1", ">= 0"), ("x", ">= 0"), ("9", "at most 8")):
        with pytest.raises(ValueError, match=match):
            parse_search(bad)
    assert isinstance(MultiStartSource().name, str)


def test_the_built_in_sources_serve_every_entry_point() -> None:
    """Reached directly, without anything importing hybridoc.solvers first, the reference
    still runs with the transcription and multi-start sources (hybridoc.methods.
    BUILTIN_SOURCES registers them on first use), so no entry point gets a weaker search."""
    import subprocess
    import sys

    code = (
        "import sys; from hybridoc.reference import solve_reference; "
        "sol = solve_reference('head-on'); "
        "print(','.join(s['name'] for s in sol.info['sources'])); "
        "print('hybridoc.solvers.transcription' in sys.modules)"
    )
    out = subprocess.run(
        [sys.executable, "-W", "error::UserWarning", "-c", code],
        capture_output=True, text=True, timeout=300, check=True,
    ).stdout.splitlines()  # fmt: skip
    assert "transcription" in out[0] and "multi-start" in out[0]


class _WrongTimes:
    """Proposes the optimal sequence (3 events) with the event times of another one (issue
    #21: the transcription paired its judged sequence with its modelled times)."""

    name = "wrong-times"

    def propose(self, ocp, context):
        return [Proposal(self.name, OPTIMAL_SEQUENCE, event_times=np.array([0.3, 0.6]))]


def test_event_times_of_another_length_are_guessed_anew(capsys) -> None:
    # before issue #21 the shooting's to_z raised a CasADi RuntimeError (4-by-1 vs 9-by-1)
    ocp, zero = _at_rest()
    sol = solve_reference(ocp, initial=zero, sources=[_WrongTimes()], verbose=True)
    # issue #29: multiple-collision's optimum is best-found (some two-event sequences have
    # no extremal), success only where the coverage proves it
    assert _found(sol) and sol.sequence == OPTIMAL_SEQUENCE
    assert sol.cost == pytest.approx(OPTIMUM, rel=1e-9)
    assert "2 event times for the 3-event sequence" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["two-tanks", "hopper"])
def test_mode_slots_give_the_same_loss_bit_for_bit(name: str) -> None:
    """The multi-start's loss on a problem with modes (one guard per slot of the current
    mode's transitions) equals the loss with one guard per transition on controls that fire
    several transitions (and on one that fires none): the values bit for bit, the gradients
    bit for bit on the two tanks and to an ulp or so on the hopper."""
    from hybridoc.solvers.compiled import CompiledLoss
    from hybridoc.solvers.multistart import cached_exploration_loss, mode_slots

    ocp = load_problem(name).replace(steps=30)
    slotted = mode_slots(ocp)
    assert len(slotted.guards) == {"two-tanks": 2, "hopper": 1}[name] < len(ocp.guards)
    rng = np.random.default_rng(1)
    u0 = np.asarray(ocp.u_guess, dtype=float)
    U = np.stack([u0, 0 * u0 - 1.0, *(u0 + rng.standard_normal((4, *u0.shape)))])
    plain, slots = CompiledLoss(ocp), CompiledLoss(slotted)
    J, gU, gx = plain.value_and_grad_batch(U)
    Js, gUs, gxs = slots.value_and_grad_batch(U)
    assert np.array_equal(J, Js)
    if name == "two-tanks":
        assert np.array_equal(gU, gUs) and np.array_equal(gx, gxs)
    else:  # the hopper's adjoint adds a few terms in another order: an ulp here and there
        np.testing.assert_allclose(gU, gUs, rtol=0, atol=4 * np.finfo(float).eps * abs(gU).max())
        np.testing.assert_allclose(gx, gxs, rtol=0, atol=4 * np.finfo(float).eps * abs(gx).max())
    assert np.ptp(J) > 0  # the controls differ in what they do
    assert len(hybridoc.evaluate(ocp, U[0]).events) >= 2  # the guess fires transitions
    assert cached_exploration_loss(ocp) is cached_exploration_loss(ocp.replace(name="x"))


def test_mode_slots_keep_problems_they_cannot_help() -> None:
    """No modes, or a guard that is not masked outside its source mode: the problem as is."""
    import casadi as ca

    from hybridoc.ocp import Guard
    from hybridoc.solvers.multistart import mode_slots

    ball = load_problem("bouncing-ball")
    assert mode_slots(ball) is ball
    tanks = load_problem("two-tanks")
    x = ca.SX.sym("x", tanks.nx)
    g = tanks.guards[0]
    unmasked = Guard(g.name, ca.Function("psi", [x], [0.5 - x[0]]), g.reset, source=g.source,
                     target=g.target)  # fmt: skip
    other = tanks.replace(guards=[unmasked, *tanks.guards[1:]])
    assert mode_slots(other) is other


@pytest.mark.parametrize("name", ["two-tanks", "hopper"])
def test_mode_switch_evaluates_one_mode_with_the_same_loss(name: str) -> None:
    """The multi-start's flow map as a switch over the modes: each branch is the flow map at
    that mode index, bit for bit (the index rounded and clipped as the selection does), and
    costs fewer operations than all modes together; the MX step built around it gives the
    SX step's loss values and gradients to rounding, on controls that fire transitions (the
    values differ at all only where the SX step folded its constant step length into the
    flow's operations at build time: an ulp of a step cost on the hopper). By default the
    hopper keeps its SX flow (its branches save too little)."""
    import casadi as ca

    from hybridoc.solvers.compiled import CompiledLoss
    from hybridoc.solvers.multistart import mode_slots, mode_switch

    ocp = load_problem(name).replace(steps=30)
    slotted = mode_slots(ocp)
    switched = mode_switch(slotted, min_saving=0)
    assert switched.flow_map.is_a("MXFunction") and slotted.flow_map.is_a("SXFunction")
    assert (mode_switch(slotted) is slotted) == (name == "hopper")
    rng = np.random.default_rng(2)
    n_modes = len(ocp.modes)
    for q in [*range(n_modes), -1.0, n_modes + 2.0, n_modes - 1.4]:
        for _ in range(3):
            x = np.r_[rng.uniform(-1.0, 1.0, ocp.nx - 1), q]
            u, h = rng.uniform(-1.0, 1.0, ocp.nu), rng.uniform(0.0, 0.1)
            want = [np.asarray(v) for v in slotted.flow_map(x, u, h)]
            got = [np.asarray(v) for v in switched.flow_map(x, u, h)]
            assert all(np.array_equal(a, b) for a, b in zip(want, got, strict=True)), (q, x)
    x, u, h = ca.SX.sym("x", ocp.nx), ca.SX.sym("u", ocp.nu), ca.SX.sym("h")
    whole = ca.Function("f", [x, u, h], slotted.flow_map(x, u, h)).n_instructions()
    for k in range(n_modes):
        one = ca.substitute(ca.vertcat(*slotted.flow_map(x, u, h)), x[-1], ca.SX(float(k)))
        assert ca.Function("f", [x, u, h], [one]).n_instructions() < whole
    u0 = np.asarray(ocp.u_guess, dtype=float)
    U = np.stack([u0, 0 * u0 - 1.0, *(u0 + rng.standard_normal((4, *u0.shape)))])
    J, gU, gx = CompiledLoss(slotted).value_and_grad_batch(U)
    Jm, gUm, gxm = CompiledLoss(switched).value_and_grad_batch(U)
    eps = np.finfo(float).eps
    np.testing.assert_allclose(Jm, J, rtol=16 * eps, atol=0)
    np.testing.assert_allclose(gUm, gU, rtol=0, atol=16 * eps * abs(gU).max())
    np.testing.assert_allclose(gxm, gx, rtol=0, atol=16 * eps * abs(gx).max())
    assert np.ptp(J) > 0


def test_batched_lbfgs_evaluates_only_the_starts_still_searching() -> None:
    """Backtracking trials of a few starts go to ``some`` (those starts only), and the
    iterates, values and call count are those of the all-batch descent, bit for bit."""
    from hybridoc.solvers.multistart import batched_lbfgs

    rng = np.random.default_rng(4)
    c = rng.standard_normal((1, 6))
    w = np.linspace(1.0, 30.0, 6)[None, :]

    def vg(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = X - c
        return (w * d**2).sum(axis=1) + (d**4).sum(axis=1), 2 * w * d + 4 * d**3

    sizes: list[int] = []

    def some(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sizes.append(len(X))
        return vg(X)

    # the far starts need many halvings (the quartic), the near ones none
    X0 = np.concatenate(
        [c + 0.1 * rng.standard_normal((6, 6)), c + 8 * rng.standard_normal((2, 6))]
    )
    plain = batched_lbfgs(vg, X0, iters=25)
    fewer = batched_lbfgs(vg, X0, iters=25, some=some)
    assert sizes and max(sizes) <= 4  # at most half the batch
    np.testing.assert_array_equal(plain[0], fewer[0])
    np.testing.assert_array_equal(plain[1], fewer[1])
    assert plain[2] == fewer[2]
    assert np.all(plain[1] < 1e-10)  # the minimum, 0 at c
