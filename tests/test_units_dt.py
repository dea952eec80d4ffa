"""dt gives the same answer in any units and place (issue #32).

The same physical scene with lengths, times or masses scaled, or moved far from the origin
(:mod:`scaling`), must give ``dt``'s cost times ``length**2`` within ``1e-9`` relative,
the same events and the same status. Before the NLP was built in the problem's own units
(``ocp.scales``), single-collision with lengths x ``1e-6`` gave ``best-found`` at 0.788
instead of 0.31142, with lengths x ``1e6`` a ``ConvergenceError``, and moved by ``1e6`` a
``not-optimal`` 2.0 with no event.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scene_generator as sg
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scaling import CORNERS, cost_factor, transform

import hybridoc
from hybridoc.problem import as_ocp
from hybridoc.problems import load_scene
from hybridoc.solution import Status

EPS = float(np.finfo(float).eps)
SCENES = ("single-collision", "multiple-collision", "gen-inelastic", "gen-chain")
# generated scenes (tests/scene_generator.py): 5, family "inelastic", one contact with
# restitution < 1; 7, family "chain", four events
GENERATED = {"gen-inelastic": 5, "gen-chain": 7}


def _ratio(corner: dict) -> float:
    """How far the corner moves the scene, in its own lengths."""
    return float(np.max(np.abs(corner.get("shift", (0.0, 0.0))))) / corner.get("length", 1.0)


# the corners whose data keep the scene's numbers to 1e-9: moved by at most 1e6 lengths
# (a position is rounded to eps |shift|, 2.2e-10 of a length at 1e6 lengths)
EXACT = [c for c in CORNERS if _ratio(c) <= 1e6]
FAR = [c for c in CORNERS if _ratio(c) > 1e6]


def _scene(name: str, tmp_path_factory: pytest.TempPathFactory) -> hybridoc.Scene:
    if name in GENERATED:
        path = tmp_path_factory.mktemp("gen") / f"{name}.toml"
        path.write_text(sg.generate(GENERATED[name]).to_toml())
        return load_scene(str(path))
    return load_scene(name)


@pytest.fixture(scope="module")
def bases(tmp_path_factory):
    out = {}
    for name in SCENES:
        scene = _scene(name, tmp_path_factory)
        out[name] = (scene, hybridoc.solve(scene, method="dt"))
    return out


def _events(sol) -> list[tuple[str, ...]]:
    return [tuple(e["bodies"]) for e in sol.events]


def _same_answer(base, sol, corner: dict, rtol: float) -> None:
    cost = sol.cost / cost_factor(**corner)
    assert math.isclose(cost, base.cost, rel_tol=rtol), (corner, cost, base.cost, sol.message)
    assert _events(sol) == _events(base), corner
    assert sol.status == base.status, (corner, sol.status, sol.message)


def _cases() -> list:
    """Every scene at every corner; the larger scenes' times and masses (which dt got right
    before too) only in the slow run, to keep CI's share small."""
    out = []
    for name in SCENES:
        for c in EXACT:
            slow = name in ("multiple-collision", "gen-chain") and set(c) <= {"time", "mass"}
            marks = [pytest.mark.slow] if slow else []
            out.append(pytest.param(name, c, marks=marks, id=f"{name}-{c}"))
    return out


@pytest.mark.parametrize(("name", "corner"), _cases())
def test_dt_same_answer_in_other_units(bases, name, corner):
    scene, base = bases[name]
    assert base.status is Status.BEST_FOUND and base.events
    sol = hybridoc.solve(transform(scene, **corner), method="dt")
    _same_answer(base, sol, corner, 1e-9)
    # the event times scale with the times
    t = np.array([e["time"] for e in sol.events]) / corner.get("time", 1.0)
    np.testing.assert_allclose(t, [e["time"] for e in base.events], rtol=1e-8)


@pytest.mark.parametrize("corner", FAR, ids=str)
def test_dt_far_from_origin_within_the_data_rounding(bases, corner):
    """Moved by more than 1e6 of its lengths (3e5 with lengths 1e-3), the scene's own data
    are rounded to ``eps |shift|``, ``6.7e-8`` of a length: the same events, the cost within
    ``64 eps |shift| / length``, the same status (never ``success``)."""
    scene, base = bases["single-collision"]
    sol = hybridoc.solve(transform(scene, **corner), method="dt")
    cost = sol.cost / cost_factor(**corner)
    assert math.isclose(cost, base.cost, rel_tol=64 * EPS * _ratio(corner)), (cost, sol.message)
    assert _events(sol) == _events(base)
    assert sol.status == base.status and sol.status is not Status.SUCCESS, sol.message


def test_guard_rows_are_measured_in_lengths():
    """The NLP divides a disc pair's guard by the length scale (its gradient's norm is
    sqrt(2) L), and the identity problems keep their NLP unscaled."""
    from hybridoc.solvers.transcription.nlp import PhaseNLP, guard_scales

    scene = load_scene("single-collision")
    assert as_ocp(scene).scales.is_identity
    np.testing.assert_array_equal(guard_scales(as_ocp(scene)), [1.0])
    small = as_ocp(transform(scene, length=1e-6, shift=(3.0, 4.0)))
    np.testing.assert_array_equal(guard_scales(small), [small.scales.length])
    nlp = PhaseNLP(small, [0], 3, [2, 2])
    h = np.array([0.4, 0.6])
    X = [np.tile(small.x0[:, None], (1, 7)), np.tile(small.x0[:, None], (1, 7))]
    force = small.scales.control_array[:, None]  # forces of the scene's own size
    U = [np.ones((small.nu, 6)) * force, -np.ones((small.nu, 6)) * force]
    w = nlp.pack(h, X, U)
    # the variables are of order one, and unpack gives the physical values back
    assert np.max(np.abs(w)) <= 1024
    h2, X2, U2 = nlp.unpack(w)
    np.testing.assert_allclose(h2, h, rtol=1e-15)
    np.testing.assert_allclose(X2[1], X[1], rtol=1e-15)
    np.testing.assert_allclose(U2[0], U[0], rtol=1e-15)


@settings(
    max_examples=6,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    length=st.floats(-6, 6),
    time=st.floats(-6, 6),
    mass=st.floats(-6, 6),
    shift=st.tuples(st.floats(-1e6, 1e6), st.floats(-1e6, 1e6)),
)
def test_dt_property_any_units_and_place(bases, length, time, mass, shift):
    """Random factors in [1e-6, 1e6] (log-uniform) and a move by up to 1e6 of the scene's
    lengths: the same cost times length**2 within 1e-9, the same events and status."""
    scene, base = bases["single-collision"]
    corner = dict(
        length=10.0**length,
        time=10.0**time,
        mass=10.0**mass,
        shift=(shift[0] * 10.0**length, shift[1] * 10.0**length),
    )
    sol = hybridoc.solve(transform(scene, **corner), method="dt")
    _same_answer(base, sol, corner, 1e-9)


@pytest.fixture(scope="module")
def discrete_base():
    from hybridoc.solvers.discrete_transcription import solve_discrete

    scene = load_scene("single-collision").with_steps(60)
    return scene, solve_discrete(scene)


@pytest.mark.parametrize(
    "corner",
    [dict(length=1e-6), dict(time=1e3), dict(mass=1e-6), dict(shift=(1e6, -1e6))],
    ids=str,
)
def test_discrete_transcription_in_other_units(discrete_base, corner):
    """The exact N-step problem (gd's floor) in other units: the same discrete loss and
    judged cost times length**2 (before: lengths x 1e-6 a ConvergenceError, times x 1e3 and
    masses x 1e-6 a higher local optimum, +2.1e-3 in the loss; moved by 1e6, 2e-9 of the
    loss lost to rollouts rounded at 1e6)."""
    from hybridoc.solvers.discrete_transcription import solve_discrete

    scene, base = discrete_base
    sol = solve_discrete(transform(scene, **corner))
    f = cost_factor(**corner)
    assert math.isclose(sol.info["discrete_loss"] / f, base.info["discrete_loss"], rel_tol=1e-9)
    assert math.isclose(sol.cost / f, base.cost, rel_tol=1e-9)
    assert sol.info["converged"] and base.info["converged"]


@pytest.mark.parametrize(
    "corner",
    [dict(length=1e-6), dict(length=1e3, time=1e-2, mass=1e5, shift=(1e3, 2e3))],
    ids=str,
)
def test_dt_costates_in_other_units(bases, corner):
    """The multipliers come back in the problem's units: a position's costate scales as
    cost / length = L, a velocity's as cost / (length / time) = L T, the jump multiplier of
    a gap (a length) as L, and the costate times as T (the reference starts from them)."""
    scene, base = bases["single-collision"]
    sol = hybridoc.solve(transform(scene, **corner), method="dt")
    L, T = corner.get("length", 1.0), corner.get("time", 1.0)
    n = scene.n_discs
    fac = np.array([L] * (2 * n) + [L * T] * (2 * n))
    scale = np.max(np.abs(base.costates))
    np.testing.assert_allclose(sol.costates / fac, base.costates, rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(
        np.array(sol.info["lambda0"]) / fac, base.info["lambda0"], atol=1e-10 * scale
    )
    np.testing.assert_allclose(
        np.array(sol.info["jump_multipliers"]) / L, base.info["jump_multipliers"], rtol=1e-10
    )
    np.testing.assert_allclose(sol.costate_times / T, base.costate_times, rtol=0, atol=1e-12)
