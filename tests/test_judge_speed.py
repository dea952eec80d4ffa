"""Speed changes of issue #18 that must not change a judged number or lose a sequence.

* the multi-start stops judging once a result repeats a judged event sequence
  (``explore(..., repeats=)``): the results it still judges are the same evaluations as
  before, and a sequence the full judging finds among the first results is still found;
* ``evaluate_callable`` reports a time control at the cell midpoints without evaluating the
  integrator's dense output (the control does not read the state): the same values, and a
  state feedback still reads the state.
"""

from __future__ import annotations

import numpy as np

from hybridoc.callable_eval import evaluate_callable
from hybridoc.problem import as_ocp
from hybridoc.problems import load_problem
from hybridoc.solvers.gd import exploration_loss
from hybridoc.solvers.multistart import explore


def test_multistart_stops_judging_at_a_repeated_sequence() -> None:
    ocp = as_ocp(load_problem("bouncing-ball-2"))
    kw = {"steps": 80, "iters": 20, "judge": 4, "loss_for": exploration_loss}
    full_rows: list[dict] = []
    full = explore(ocp, 8, report=full_rows, **kw)
    rows: list[dict] = []
    few = explore(ocp, 8, report=rows, repeats=1, **kw)
    judged = [r for r in rows if "cost" in r]
    skipped = [r for r in rows if "repeated" in str(r.get("not_judged", ""))]
    # the four best distinct losses are one sequence: the first two judged, two skipped
    assert len({tuple(r["sequence"]) for r in full_rows if "cost" in r}) == 1
    assert len(judged) == 2 and len(skipped) == 2
    # what is still judged is judged exactly as before (same start, same cost, same events)
    before = {r["start"]: r for r in full_rows if "cost" in r}
    for r in judged:
        assert r["cost"] == before[r["start"]]["cost"]
        assert r["sequence"] == before[r["start"]]["sequence"]
    assert few[0]["cost"] == full[0]["cost"]
    assert {tuple(r["sequence"]) for r in few} == {tuple(r["sequence"]) for r in full}


def test_multistart_repeats_do_not_stop_a_new_sequence() -> None:
    # repeats counts results in a row without a new sequence: with a large count every
    # picked result is judged, as without it
    ocp = as_ocp(load_problem("bouncing-ball-2"))
    kw = {"steps": 80, "iters": 20, "judge": 4, "loss_for": exploration_loss}
    rows: list[dict] = []
    explore(ocp, 8, report=rows, repeats=10, **kw)
    assert sum("cost" in r for r in rows) == 4


def test_callable_controls_at_midpoints_are_the_control_itself() -> None:
    ocp = as_ocp(load_problem("bouncing-ball"))

    def u(t: float) -> np.ndarray:
        return np.array([3.0 * np.sin(7.0 * t) + 1.0])

    ev = evaluate_callable(ocp, u, breakpoints=[0.3, 0.5])
    mids = (np.arange(ocp.steps) + 0.5) * ocp.dt
    expected = np.array([u(float(t)) for t in mids])
    assert np.array_equal(ev.controls, expected)
    assert ev.events  # the ball bounces: several integration pieces


def test_callable_feedback_controls_read_the_state() -> None:
    ocp = as_ocp(load_problem("bouncing-ball"))
    ev = evaluate_callable(ocp, state_feedback=lambda t, s: np.array([-2.0 * s[1]]))
    # the reported feedback control at each midpoint is -2 v there, v from the trajectory
    mids = (np.arange(ocp.steps) + 0.5) * ocp.dt
    v = np.interp(mids, ev.times, ev.states[:, 1])
    assert np.max(np.abs(ev.controls[:, 0] + 2.0 * v)) < 0.05 * np.max(np.abs(v))
    assert np.std(ev.controls[:, 0]) > 0
