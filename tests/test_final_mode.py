"""Terminal constraints tied to a final mode (issue #15): ``HybridOCP.final_mode``.

The test problem is a lap counter with a closed form. An angle ``theta' = u`` with cost
``integral u^2 dt`` over ``T = 1`` starts at 0 in mode ``even``; the transition ``lap``
fires when ``theta`` reaches ``2 pi`` from below, resets it to 0 and toggles the mode
(``even`` <-> ``odd``). With the terminal constraint ``theta(T) = pi`` the free optimum is
``u = pi`` (cost ``pi^2``, no lap, ending in ``even``). Requiring the final mode ``odd``
forces one lap: the angle travels ``3 pi`` at constant speed, ``u = 3 pi``, ``J* = 9 pi^2``,
with the lap at ``t = 2/3`` crossing transversally (a required mode reached by turning at
a guard would only touch it, a degenerate optimum).
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest

import hybridoc
from hybridoc import Guard, HybridOCP, SceneError
from hybridoc.reference.candidates import enumerate_sequences

TWO_PI = 2 * math.pi


def _laps(**kwargs) -> HybridOCP:
    s, u = ca.SX.sym("s"), ca.SX.sym("u")
    args = dict(
        modes={"even": (u, u**2), "odd": (u, u**2)},
        transitions=[
            Guard.from_expressions(
                f"lap_{a}", s, TWO_PI - s, s - TWO_PI, degree=1, source=a, target=b
            )
            for a, b in (("even", "odd"), ("odd", "even"))
        ],
        initial_mode="even",
        phi=ca.SX(0),
        x0=[0.0],
        horizon=1.0,
        steps=100,
        terminal_eq=s - math.pi,
        name="laps",
    )
    args.update(kwargs)
    if callable(args["phi"]):  # a terminal cost written in the problem's own symbol
        args["phi"] = args["phi"](s)
    return HybridOCP.from_modes(s, u, **args)


def test_final_mode_is_checked_against_the_modes() -> None:
    with pytest.raises(SceneError, match="final_mode 'middle' is not one of the modes"):
        _laps(final_mode="middle")
    s, u = ca.SX.sym("s"), ca.SX.sym("u")
    with pytest.raises(SceneError, match="needs a problem with modes"):
        HybridOCP.from_expressions(
            s, u, f=u, L=u**2, phi=s**2, guards=[], x0=[0.0], horizon=1.0, steps=4,
            final_mode="low",
        )  # fmt: skip


def test_the_judge_reports_a_wrong_final_mode_as_an_infinite_violation() -> None:
    p = _laps(final_mode="odd")
    direct = hybridoc.evaluate(p, np.full((100, 1), math.pi))
    assert direct.final_mode == "even" and direct.sequence == []
    assert direct.terminal_violation == math.inf and not direct.feasible
    assert p.terminal_violation(direct.final_state) == math.inf
    lap = hybridoc.evaluate(p, np.full((100, 1), 3 * math.pi))
    assert lap.sequence == ["lap_even"] and lap.final_mode == "odd"
    assert lap.events[0].time == pytest.approx(2 / 3, abs=1e-12)
    assert lap.terminal_violation < 1e-12 and lap.feasible
    assert lap.cost == pytest.approx(9 * math.pi**2, rel=1e-12)
    # without the requirement the direct control is judged on theta(T) alone
    assert hybridoc.evaluate(_laps(), np.full((100, 1), math.pi)).terminal_violation < 1e-12


def test_sequences_are_admissible_only_when_they_end_in_the_final_mode() -> None:
    p = _laps(final_mode="odd")
    assert p.sequence_feasible([]) and not p.sequence_admissible([])
    assert p.sequence_admissible(["lap_even"])
    assert not p.sequence_admissible(["lap_even", "lap_odd"])
    assert not p.sequence_admissible(["lap_odd"])  # leaves 'odd' while in 'even'
    assert p.admissible_sequence("lap_even") == ["lap_even"]
    with pytest.raises(SceneError, match=r"ends in mode 'even' \(even -> odd -> even\)"):
        p.admissible_sequence(["lap_even", "lap_odd"])
    # the search extends prefixes through 'even' but yields only sequences ending in 'odd'
    assert list(enumerate_sequences(p, 3)) == [["lap_even"], ["lap_even", "lap_odd", "lap_even"]]
    assert list(enumerate_sequences(_laps(), 2)) == [[], ["lap_even"], ["lap_even", "lap_odd"]]


def test_the_reference_and_dt_meet_the_closed_form_in_the_required_mode() -> None:
    free = hybridoc.solve(_laps(), method="reference")
    assert free.success and free.sequence == []
    assert free.cost == pytest.approx(math.pi**2, rel=1e-9)
    p = _laps(final_mode="odd")
    ref = hybridoc.solve(p, method="reference")
    # issue #29: the success must be proven; its extremal was reached from 1 start of Newton,
    # 2 needed, so best-found (the closed-form cost and event time are checked)
    assert ref.status in (hybridoc.Status.SUCCESS, hybridoc.Status.BEST_FOUND), ref.message
    assert (ref.status is hybridoc.Status.SUCCESS) == ref.info["coverage"]["proven"]
    assert ref.sequence == ["lap_even"] and ref.modes[-1] == "odd"
    assert ref.cost == pytest.approx(9 * math.pi**2, rel=1e-9)
    assert ref.events[0]["time"] == pytest.approx(2 / 3, abs=1e-9)
    dt = hybridoc.solve(p, method="dt", sequence=["lap_even"])
    assert dt.status is hybridoc.Status.EXTREMAL, dt.message  # a given sequence
    assert dt.cost == pytest.approx(9 * math.pi**2, rel=1e-7)
    with pytest.raises(SceneError, match="requires the final mode 'odd'"):
        hybridoc.solve(p, method="dt", sequence=[])


def test_a_method_that_ends_in_another_mode_is_infeasible_whatever_it_is() -> None:
    """Only a final mode, no terminal constraint (a penalty pulls theta towards pi): gd from
    zero never laps and says so instead of a success; the reference laps once (its cost
    from the judge, c^2 + 10 (c - 3 pi)^2 at c = 30 pi / 11)."""
    p = _laps(terminal_eq=None, phi=lambda s: 10 * (s - math.pi) ** 2, final_mode="odd")
    gd = hybridoc.solve(p, "gd", iters=30)
    assert gd.status == "infeasible" and not gd.success
    assert "the required final mode 'odd' (it ends in 'even')" in gd.message
    ref = hybridoc.solve(p, "reference")
    # issue #29: best-found, not success: its extremal was reached from 1 start of Newton, 2
    # needed for the proof (the closed-form cost below is checked)
    assert ref.status in (hybridoc.Status.SUCCESS, hybridoc.Status.BEST_FOUND), ref.message
    assert (ref.status is hybridoc.Status.SUCCESS) == ref.info["coverage"]["proven"]
    assert ref.modes[-1] == "odd"
    c = 30 * math.pi / 11
    assert ref.cost == pytest.approx(c**2 + 10 * (c - 3 * math.pi) ** 2, rel=1e-9)
