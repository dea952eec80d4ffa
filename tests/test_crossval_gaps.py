"""crossval separates a method's discretisation error (the best control it can represent)
from a disagreement, takes mesh, starts and tolerances on the command line, and turns a
method that raises into a row while the others run and the files are written."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import hybridoc
from hybridoc.cli import main
from hybridoc.methods import Method
from hybridoc.solution import Solution
from hybridoc.workflows.validation import crossval


def _boom(ocp: Any, *, initial: Any = None, progress: Any = None) -> Any:
    raise RuntimeError("boom: this method always breaks")


def _returns(controls: np.ndarray, name: str) -> Any:
    """A method that answers with ``controls`` (judged)."""

    def run(ocp: Any, *, initial: Any = None, progress: Any = None) -> Solution:
        return Solution.from_evaluation(hybridoc.evaluate(ocp, controls), method=name, scene=ocp)

    return run


def test_the_grid_projection_is_not_a_disagreement(registered: Any) -> None:
    """A piecewise-constant method that answers J*'s cell averages exactly is as good as a
    method on the N-grid can be expected to be: its gap to J* (the grid's discretisation
    error, about 1e-3 here) is far beyond a tolerance of 1e-6, yet it agrees; one that is
    10% off the cell averages disagrees, measured against them."""
    ocp = hybridoc.as_ocp("bouncing-ball")
    ref = hybridoc.solve(ocp, "reference")
    grid = hybridoc.evaluate(ocp, ref.controls).cost  # the yardstick, computed here
    registered(Method("held", "J*'s cell averages", run=_returns(ref.controls, "held")))
    registered(Method("off", "10% off them", run=_returns(0.9 * ref.controls, "off")))
    report, _ = crossval(ocp, methods=("held", "off"), tolerances={"held": 1e-6, "off": 1e-6})
    held, off = report["held"], report["off"]
    assert report["grid_cost"] == grid
    assert report["grid_gap_relative"] == pytest.approx((grid - ref.cost) / ref.cost)
    assert held["cost"] == grid and held["representable_cost"] == grid
    assert held["cost_gap_relative"] > 1e-4  # far beyond its tolerance of J*...
    assert held["discretisation_gap_relative"] == held["cost_gap_relative"]
    assert held["representable_gap_relative"] == 0.0  # ...and exactly the best it can be
    assert held["converged"] is True
    assert off["representable_gap_relative"] == pytest.approx((off["cost"] - grid) / grid)
    assert off["representable_gap_relative"] > 1e-6
    assert not report["agree"]
    assert report["reasons"] == [
        r for r in report["reasons"] if r.startswith("off is ") and "beyond its tolerance" in r
    ]
    assert len(report["reasons"]) == 1


@pytest.mark.slow
def test_crossval_agrees_on_the_hopper_with_the_grid_gap_apart() -> None:
    """The hopper (a generic two-mode problem): gd's gap to J* is mostly the N-grid's
    (+5.8e-3 of +6.7e-3, above gd's tolerance 5e-3), dt's at mesh 16 is its mesh's; both
    agree."""
    report, sols = crossval("hopper", options={"dt": {"mesh": 16}})
    assert report["agree"], report["reasons"]
    gd, dt = report["gd"], report["dt"]
    grid = hybridoc.evaluate(hybridoc.as_ocp("hopper"), sols["reference"].controls).cost
    assert gd["representable_cost"] == grid
    assert gd["discretisation_gap_relative"] > 1e-3
    assert abs(gd["representable_gap_relative"]) < 5e-3
    assert abs(dt["representable_gap_relative"]) < 1e-6
    assert dt["representable"].startswith("dt re-solved")


def test_a_method_that_raises_is_a_row_and_files_are_written(
    tmp_path: Path, registered: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    registered(Method("boom", "always raises", run=_boom))
    code = main(["crossval", "bouncing-ball", "--methods", "boom", "--json", "--no-progress",
                 "--out", str(tmp_path)])  # fmt: skip
    assert code == 1
    out = json.loads(capsys.readouterr().out)
    assert out["boom"]["error"] == "boom: this method always breaks"
    assert out["boom"]["error_type"] == "RuntimeError"
    assert out["boom"]["converged"] is False
    assert out["reference"]["status"] == "success"
    assert not out["agree"] and any("boom failed" in r for r in out["reasons"])
    names = sorted(p.name for p in tmp_path.iterdir())
    assert "bouncing-ball_crossval.json" in names  # the registry name, not the long name
    assert "bouncing-ball_crossval_controls.png" in names
    saved = json.loads((tmp_path / "bouncing-ball_crossval.json").read_text())
    assert saved["boom"]["error_type"] == "RuntimeError"


def test_crossval_flags_reach_the_methods(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """--set METHOD.OPTION=VALUE and --tolerance METHOD=VALUE map onto crossval's options and
    tolerances (crossval itself is replaced: this is about the parsing)."""
    import hybridoc.workflows.validation as val

    seen: dict[str, Any] = {}

    def fake(ocp: Any, **kwargs: Any) -> Any:
        seen.update(kwargs)
        return {"problem": ocp.name, "agree": True, "reasons": []}, {}

    monkeypatch.setattr(val, "crossval", fake)
    code = main(["crossval", "bouncing-ball", "--set", "dt.mesh=16", "--set", "gd.starts=3",
                 "--tolerance",
                 "gd=0.02", "--tolerance", "dt=1e-5", "--no-progress", "--json"])  # fmt: skip
    assert code == 0
    assert seen["options"]["dt"] == {"mesh": 16}
    assert seen["options"]["gd"] == {"starts": 3}
    assert seen["tolerances"] == {"gd": 0.02, "dt": 1e-5}
    assert seen["progress"] is False
    capsys.readouterr()
    for bad in (["--tolerance", "gd"], ["--tolerance", "nope=1"], ["--tolerance", "gd=-1"]):
        with pytest.raises(SystemExit) as exc:
            main(["crossval", "bouncing-ball", *bad])
        assert exc.value.code == 2
        assert "--tolerance" in capsys.readouterr().err


def test_the_grid_projection_reports_its_terminal_violation() -> None:
    """friction-patch (x(T) = 1, v(T) = 0): the reference meets the constraints, its cell
    averages on the grid miss them a little, and the report says by how much (so that a
    negative gap to the projection reads as what it is)."""
    from hybridoc.workflows.validation import representable

    ocp = hybridoc.as_ocp("friction-patch")
    ref = hybridoc.solve(ocp, "reference")
    # best-found (issue #29): the cheaper no-event extremal crosses the patch
    assert ref.status in (hybridoc.Status.SUCCESS, hybridoc.Status.BEST_FOUND), ref.message
    assert hybridoc.evaluate(ocp, ref).terminal_violation < 1e-8
    best = representable(ocp, "gd", ref)
    grid = hybridoc.evaluate(ocp, ref.to_grid(problem=ocp))
    assert best["representable_cost"] == grid.cost
    assert best["representable_terminal_violation"] == grid.terminal_violation > 1e-8
    plain = representable(
        "single-collision",
        "gd",
        hybridoc.solve("single-collision", "reference", sequence=["ball1|ball2"]),
    )
    assert "representable_terminal_violation" not in plain
