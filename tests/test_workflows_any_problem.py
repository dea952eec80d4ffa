"""Datasets and policy validation on any HybridOCP whose initial-state distribution is
declared in Python (HybridOCP.distribution or make_dataset's argument), from Python and from
the command line."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import hybridoc
from hybridoc.cli import main
from hybridoc.errors import SceneError
from hybridoc.workflows.datasets import (
    distribution_problem,
    draw_initial_states,
    load_dataset,
    make_dataset,
)

PROBLEM = """
import numpy as np
import hybridoc

def ball():
    p = hybridoc.as_ocp("bouncing-ball")
    spread = lambda rng, M: p.x0 + rng.uniform(-0.05, 0.05, (M, p.nx))
    return p.replace(name="ball-dist", distribution=spread)

def still(t, s):
    return np.array([0.0])
"""


def _spread(rng: np.random.Generator, m: int) -> np.ndarray:
    return np.array([1.0, 0.0]) + rng.uniform(-0.05, 0.05, (m, 2))


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("anyproblem")
    (d / "prob.py").write_text(PROBLEM)
    return d


def test_draws_are_their_own_streams() -> None:
    """Draw i is distribution(default_rng([seed, i]), 1): independent of how many are made."""
    p = hybridoc.as_ocp("bouncing-ball").replace(distribution=_spread)
    x5 = draw_initial_states(p, 5, seed=3)
    assert np.array_equal(draw_initial_states(p, 2, seed=3), x5[:2])
    assert np.array_equal(x5[4], _spread(np.random.default_rng([3, 4]), 1)[0])
    with pytest.raises(SceneError, match="returned shape"):
        draw_initial_states(p.replace(distribution=lambda rng, m: np.zeros((m, 3))), 1, 0)
    with pytest.raises(SceneError, match="has no distribution of initial states"):
        make_dataset("bouncing-ball", 1, "unused-dir")


@pytest.fixture(scope="module")
def dataset(files: Path) -> Any:
    """Two draws of the Python problem's distribution, made by 'hybridoc dataset' (each draw
    with the reference's full discovery: the bouncing ball's warm start is never accepted)."""
    out = files / "ds"
    code = main(["dataset", f"{files / 'prob.py'}:ball", "--samples", "2", "--workers", "1",
                 "--full", "--out", str(out), "--json", "--no-progress"])  # fmt: skip
    assert code == 0
    return load_dataset(out)


def test_dataset_of_a_python_distribution_is_each_draws_reference(
    files: Path, dataset: Any
) -> None:
    p = hybridoc.as_ocp(f"{files / 'prob.py'}:ball")
    assert list(dataset["status"]) == ["success", "success"]
    x0 = draw_initial_states(p, 2, seed=0)
    assert np.array_equal(dataset["x0"], x0)
    # draw 1's optimum, solved here on its own
    one = hybridoc.solve(p.replace(x0=x0[1], distribution=None), "reference")
    assert dataset["cost"][1] == pytest.approx(one.cost, rel=1e-9)
    assert dataset["sequence"][1] == ",".join(one.sequence)
    assert dataset.manifest["settings"]["problem"] == "ball-dist"
    with pytest.raises(hybridoc.errors.HybridocError, match="not from a scene"):
        _ = dataset.scene
    # make_dataset's distribution argument stands for the problem's own
    q = distribution_problem("bouncing-ball", _spread)
    assert q.distribution is _spread and q.name == hybridoc.as_ocp("bouncing-ball").name


def test_cli_validate_policy_on_a_python_problem(
    files: Path, dataset: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    spec = f"{files / 'prob.py'}:ball"
    code = main(["validate-policy", spec, "--policy", f"{files / 'prob.py'}:still",
                 "--samples", "2", "--dataset", str(dataset.path), "--workers", "1",
                 "--json", "--no-progress", "--out", str(tmp_path)])  # fmt: skip
    report = json.loads(capsys.readouterr().out)
    assert code == 0
    assert report["summary"]["compared"] == 2
    # the policy's cost is the judge's closed-loop cost of each draw
    p = hybridoc.as_ocp(spec)
    for i in range(2):
        ev = hybridoc.evaluate(p.replace(x0=dataset["x0"][i]), policy=lambda t, s: np.array([0.0]))
        assert any(
            w["index"] == i and w["policy_cost"] == pytest.approx(ev.cost, rel=1e-12)
            for w in report["worst"]
        )
    for suffix in (".json", ".npz", "_gap_hist.png", "_gap_scatter.png"):
        assert (tmp_path / f"ball-dist_validate-policy{suffix}").stat().st_size > 0
