"""Tests of ``hybridoc gradcheck`` / ``compare-contacts`` (hybridoc.solvers.gradcheck)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import hybridoc
from hybridoc.cli import main
from hybridoc.problems.paper import PAPER_SETTINGS
from hybridoc.solvers.contacts import contact_model
from hybridoc.solvers.gradcheck import compared_models, gradient_errors, paper_gd_settings


@pytest.fixture(scope="module")
def single():
    scene = hybridoc.load_scene("single-collision")
    u = scene.initial_controls()
    return scene, u, hybridoc.gradient(scene, u)


def test_toi_both_gradient_beats_plain_direct(single):
    # the paper's claim, measured: with the TOI corrections the discrete gradient is much
    # closer to the exact gradient of the continuous cost
    scene, u, exact = single
    both = gradient_errors(scene, u, contact_model("direct/both"), exact)
    none = gradient_errors(scene, u, contact_model("direct", toi="none"), exact)
    for key in ("err_position", "err_velocity", "err_controls"):
        assert both[key] < 0.2 * none[key]
    assert both["err_controls"] < 0.01
    assert both["cost"] == pytest.approx(exact.cost)
    # discrete and continuous objectives agree to O(dt)
    assert both["loss"] == pytest.approx(exact.cost, rel=1e-2)


def test_cli_gradcheck_json(capsys):
    models = "direct/none,direct/both,convex/both,pbd"
    code = main(["gradcheck", "single-collision", "--json", "--iters", "5", "--contact", models])
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert out["points"] == ["initial", "gd-5"]
    assert len(out["entries"]) == 2 * 4
    for e in out["entries"]:
        for key in ("err_position", "err_velocity", "err_controls", "loss", "cost"):
            assert math.isfinite(e[key])
    by = {(e["point"], e["model"]): e for e in out["entries"]}
    assert (
        by[("initial", "direct/both")]["err_controls"]
        < by[("initial", "direct/none")]["err_controls"]
    )


def test_cli_compare_contacts_json_and_figures(capsys, tmp_path):
    code = main(
        [
            "compare-contacts",
            "single-collision",
            "--json",
            "--iters",
            "3",
            "--contact",
            "direct/both,compliant",
            "--out",
            str(tmp_path),
        ]
    )
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert out["lr"] == 200.0 and out["iters"] == 3
    assert [m["model"] for m in out["models"]] == ["direct/both", "compliant"]
    for m in out["models"]:
        assert len(m["loss_history"]) == 4
        assert math.isfinite(m["cost"]) and math.isfinite(m["loss"])
    # with the TOI corrections plain gd at the paper's rate lowers the loss, and the discrete
    # loss is close to the true cost (the compliant model's stiff gradient overshoots at lr 200)
    direct = out["models"][0]
    assert direct["loss_history"][-1] < direct["loss_history"][0]
    assert direct["cost"] == pytest.approx(direct["loss"], rel=0.01)
    stem = "single-collision_compare-contacts"
    assert (tmp_path / f"{stem}_learning_curves.png").stat().st_size > 0
    assert (tmp_path / f"{stem}_controls.png").stat().st_size > 0
    sol = hybridoc.Solution.load(tmp_path / f"{stem}_direct-both")
    assert np.isfinite(sol.controls).all()


def test_cli_unknown_model_is_a_user_error(capsys):
    assert main(["gradcheck", "single-collision", "--contact", "magic"]) == 2
    assert "unknown contact model" in capsys.readouterr().err


def test_models_cover_the_paper_list():
    names = {m.label for m in compared_models()}
    assert {"direct/none", "direct/both", "lcp/both", "convex/both", "compliant", "pbd"} <= names


def test_paper_gd_settings_read_the_paper_numbers():
    for name, settings in PAPER_SETTINGS.items():
        assert paper_gd_settings(hybridoc.load_scene(name)) == settings
    assert paper_gd_settings(hybridoc.load_scene("head-on")) == (50.0, 500)


def test_compare_contacts_reports_through_the_progress_protocol():
    from hybridoc.solvers.gradcheck import compare_contacts

    class Recorder:
        def __init__(self):
            self.stages, self.counts, self.closed = [], [], False

        def stage(self, text):
            self.stages.append(text)

        def detail(self, text):
            pass

        def count(self, done, total, text=""):
            self.counts.append((done, total))

        def close(self):
            self.closed = True

    rec = Recorder()
    models = [contact_model("direct/both"), contact_model("pbd")]
    sols = compare_contacts(hybridoc.load_scene("single-collision"), models=models, iters=2,
                            progress=rec)  # fmt: skip
    assert list(sols) == ["direct/both", "pbd"]
    assert rec.stages == ["direct/both (1/2)", "pbd (2/2)"]
    assert (2, 2) in rec.counts and not rec.closed  # a caller's Progress stays open
