"""``hybridoc train-policy`` trains from the command line and saves an MLP policy file that
``validate-policy`` loads and judges."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from small_scenes import strike_scene

import hybridoc
from hybridoc.cli import main
from hybridoc.problems import load_scene
from hybridoc.workflows.policy_format import load_mlp_policy

SCENE = strike_scene("sc-train", steps=60)


def test_train_policy_then_validate_policy(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    scene_file = tmp_path / "sc.toml"
    scene_file.write_text(SCENE)
    out = tmp_path / "out"
    code = main(["train-policy", str(scene_file), "--samples", "1", "--iters", "2",
                 "--hidden", "4", "--layers", "1", "--out", str(out), "--json",
                 "--no-progress"])  # fmt: skip
    trained = json.loads(capsys.readouterr().out)
    assert code == 0
    assert trained["seed"] == 8 and trained["toi"] == "both" and len(trained["losses"]) == 2
    assert trained["final_loss"] < trained["initial_loss"]
    path = out / "sc-train_train-policy.json"
    assert trained["policy"] == str(path) and (out / "sc-train_train-policy.npz").is_file()
    policy = load_mlp_policy(path)  # no torch, no code run
    assert policy.layers == [9, 4, 2]  # (t, 8 states) -> 4 -> 2 controls

    code = main(["validate-policy", str(scene_file), "--policy", str(path), "--samples", "1",
                 "--workers", "1", "--json", "--no-progress", "--rollouts", "judge"])  # fmt: skip
    report = json.loads(capsys.readouterr().out)
    assert code == 0 and report["summary"]["compared"] == 1
    # the judged cost is the judge's closed-loop cost of draw 0 under the saved policy
    scene = load_scene(str(scene_file))
    draw = scene.distribution.draw(scene, 0, scene.distribution.seed)
    ev = hybridoc.evaluate(draw.to_ocp(), policy=policy)
    worst = report["worst"][0]
    assert worst["index"] == 0 and worst["policy_cost"] == pytest.approx(ev.cost, rel=1e-12)
    assert np.isfinite(worst["reference_cost"]) and worst["gap"] > 0


def test_train_policy_refuses_what_it_cannot_train(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["train-policy", "single-collision", "--samples", "2", "--out", str(tmp_path)])
    assert code == 2 and "no [distribution] table" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(["train-policy", "single-collision", "--samples", "2"])
    assert exc.value.code == 2 and "--out" in capsys.readouterr().err
