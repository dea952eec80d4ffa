"""Gradient descent as a registered method: its options (GDOptions), contact models as
objects, its crossval hooks and the one progress protocol (hybridoc.solvers.gd)."""

from __future__ import annotations

import dataclasses
import inspect
from typing import Any

import numpy as np
import pytest

import hybridoc
from hybridoc.errors import SceneError
from hybridoc.methods import option_specs
from hybridoc.solvers import gd
from hybridoc.solvers.contacts import TOI_MODES, contact_model, model_names
from hybridoc.solvers.contacts.compliant import Compliant
from hybridoc.solvers.contacts.lcp import LCP
from hybridoc.solvers.gd import METHOD, GDOptions, checked_options, parse_smoothing, solve_gd


class Recorder:
    """A Progress that records every call."""

    def __init__(self) -> None:
        self.calls: list[tuple[Any, ...]] = []

    def stage(self, text: str) -> None:
        self.calls.append(("stage", text))

    def detail(self, text: str) -> None:
        self.calls.append(("detail", text))

    def count(self, done: int, total: int, text: str = "") -> None:
        self.calls.append(("count", done, total, text))

    def close(self) -> None:
        self.calls.append(("close",))

    def stages(self) -> list[str]:
        return [c[1] for c in self.calls if c[0] == "stage"]

    def counts(self) -> list[tuple[Any, ...]]:
        return [c[1:] for c in self.calls if c[0] == "count"]


def test_the_run_function_takes_exactly_the_options() -> None:
    METHOD.check_signature()
    assert METHOD.name == "gd" and METHOD.options is GDOptions and METHOD.tolerance == 5e-3
    assert hybridoc.methods.METHODS["gd"] is METHOD
    # solve_gd's keyword defaults are the options' defaults
    params = inspect.signature(solve_gd).parameters
    for f in dataclasses.fields(GDOptions):
        assert params[f.name].default == f.default, f.name


def test_option_fields_defaults_and_choices() -> None:
    specs = {s.name: s for s in option_specs(GDOptions)}
    assert list(specs)[:10] == [
        "contact", "toi", "integrator", "optimizer", "smoothing", "iters", "lr", "starts",
        "seed", "hops",
    ]  # fmt: skip
    assert all(specs[n].cli for n in list(specs)[:10])
    assert not any(specs[n].cli for n in ("callback", "path", "max_step", "path_weight"))
    assert specs["contact"].default == "direct"
    assert specs["contact"].choices == tuple(model_names())
    assert specs["toi"].default is None and specs["toi"].choices == TOI_MODES
    assert specs["integrator"].choices == gd.INTEGRATORS
    assert specs["optimizer"].default == "lbfgs" and specs["optimizer"].choices == gd.OPTIMIZERS
    assert specs["starts"].default == 1 and specs["seed"].default == 0
    assert specs["hops"].default == 0 and specs["path"].choices == gd.PATHS
    assert specs["iters"].parse("0") == 0 and specs["lr"].parse("0.5") == 0.5
    for name, text in (("iters", "-1"), ("lr", "0"), ("starts", "0"), ("hops", "x")):
        with pytest.raises(ValueError, match="expected"):
            specs[name].parse(text)
    assert all(s.help and "\n" not in s.help for s in specs.values())


def test_parse_smoothing() -> None:
    assert parse_smoothing("none") == () and parse_smoothing("") == ()
    assert parse_smoothing("1e-4,1e-5") == (1e-4, 1e-5)
    with pytest.raises(ValueError, match="comma-separated numbers or 'none'") as err:
        parse_smoothing("1e-4;x")
    assert "\n" not in str(err.value)


def test_checked_options_resolve_the_defaults() -> None:
    ocp = hybridoc.as_ocp("head-on")
    o = checked_options(ocp, GDOptions())
    assert o.contact == contact_model("direct", toi="both") and o.toi is None
    assert (o.integrator, o.optimizer, o.iters, o.lr) == ("exact", "lbfgs", 300, 0.1)
    assert o.smoothing is None
    o = checked_options(ocp, GDOptions(contact="lcp", toi="none", smoothing=np.array([1e-5])))
    assert o.contact.label == "lcp/none" and o.integrator == "symplectic-euler"
    assert o.smoothing == (1e-5,)
    with pytest.raises(SceneError, match="starts must be"):
        checked_options(ocp, GDOptions(starts=0))
    with pytest.raises(SceneError, match="integrator"):
        checked_options(ocp, GDOptions(integrator="rk4"))
    with pytest.raises(SceneError, match="smoothing"):
        checked_options(ocp, GDOptions(smoothing="1e-4"))


def test_a_contact_object_equals_its_name() -> None:
    by_name = solve_gd("head-on", contact="lcp", toi="both", optimizer="gd", iters=3)
    by_object = solve_gd("head-on", contact=LCP(toi="both"), optimizer="gd", iters=3)
    assert by_object.info["loss"] == pytest.approx(by_name.info["loss"], rel=1e-12, abs=1e-12)
    np.testing.assert_array_equal(by_object.controls, by_name.controls)
    assert by_object.settings == by_name.settings
    assert by_name.settings["contact"] == "lcp" and by_name.settings["toi"] == "both"
    # toi beside an instance: the instance with that setting
    other = solve_gd("head-on", contact=LCP(toi="none"), toi="both", optimizer="gd", iters=3)
    assert other.info["loss"] == by_name.info["loss"]


def test_a_compliant_instance_with_its_own_stiffness() -> None:
    # raised "options cannot be given with a contact model instance" before
    sol = hybridoc.solve(
        "head-on", "gd", contact=contact_model("compliant", stiffness=2e4), optimizer="adam",
        iters=3,
    )  # fmt: skip
    assert sol.settings["contact"] == "compliant" and sol.settings["stiffness"] == 2e4
    assert sol.settings["integrator"] == "symplectic-euler"
    stiffer = solve_gd("head-on", contact=Compliant(stiffness=5e4), optimizer="adam", iters=3)
    assert stiffer.settings["stiffness"] == 5e4
    assert stiffer.info["loss"] != sol.info["loss"]  # the stiffness reached the simulation


def test_contact_models_apply_to_disc_scenes_only() -> None:
    with pytest.raises(SceneError, match="apply to disc scenes"):
        solve_gd("bouncing-ball", contact=LCP(), iters=1)


def test_one_progress_object_serves_the_smoothing_stages() -> None:
    rec = Recorder()
    sol = solve_gd("head-on", iters=3, progress=rec)
    assert rec.stages() == [
        "stage 1 of 4, smoothing mu 0.0001", "stage 2 of 4, smoothing mu 1e-05",
        "stage 3 of 4, smoothing mu 1e-06", "stage 4 of 4, descent (lbfgs) after smoothing",
    ]  # fmt: skip
    counts = rec.counts()
    # the iteration limit is no total: a stage may stop sooner (issue #16)
    assert len(counts) == sol.info["iterations"] and all(c[1] is None for c in counts)
    assert [c[0] for c in counts[:3]] == [1, 2, 3] and counts[0][2].startswith("iterations, loss ")
    assert ("close",) not in rec.calls  # the caller's own progress stays open
    plain = Recorder()
    solve_gd("head-on", optimizer="gd", iters=2, progress=plain)
    assert plain.stages() == ["descent (gd)"] and [c[0] for c in plain.counts()] == [1, 2]


def test_progress_must_be_a_progress() -> None:
    with pytest.raises(TypeError, match="progress"):
        solve_gd("head-on", iters=1, progress="yes")


def test_crossval_defaults() -> None:
    disc, generic = hybridoc.as_ocp("head-on"), hybridoc.as_ocp("bouncing-ball")
    assert METHOD.crossval_defaults(disc, {}) == {"starts": gd.GD_STARTS["disc"]}
    assert METHOD.crossval_defaults(generic, {}) == {"starts": gd.GD_STARTS["generic"]}
    assert METHOD.crossval_defaults(disc, {"starts": 1, "integrator": "symplectic-euler"}) == {
        "starts": 1,
        "integrator": "symplectic-euler",
        "hops": gd.GD_HOPS,
    }
    given = {"hops": 0}
    assert METHOD.crossval_defaults(disc, given)["hops"] == 0 and given == {"hops": 0}


def test_crossval_check_of_the_discrete_gap(monkeypatch: pytest.MonkeyPatch) -> None:
    from hybridoc.solvers import discrete_transcription

    ocp = hybridoc.as_ocp("head-on")
    sol = solve_gd(ocp, optimizer="gd", iters=1)
    assert METHOD.crossval_check(ocp, sol) == ({}, [])  # exact: no discrete objective
    sol.settings["integrator"] = "symplectic-euler"
    gap = {"discrete_loss": 1.0, "discrete_optimum": 1.0, "discrete_gap_relative": 2e-6}
    monkeypatch.setattr(discrete_transcription, "discrete_gap", lambda o, s: dict(gap))
    entry, reasons = METHOD.crossval_check(ocp, sol)
    assert entry == gap and len(reasons) == 1 and "+2.000e-06" in reasons[0]
    gap["discrete_gap_relative"] = 0.5 * gd.DISCRETE_TOLERANCE
    assert METHOD.crossval_check(ocp, sol)[1] == []


def test_summary_lines() -> None:
    sol = solve_gd("head-on", optimizer="gd", iters=2)
    lines = METHOD.summary_lines(sol)
    assert [label for label, _ in lines] == ["loss", "iterations", "settings"]
    assert lines[0][1].endswith("(the simulation's discrete loss)")
    assert lines[1][1] == "2" and "contact direct, toi both" in lines[2][1]
    assert METHOD.supports(hybridoc.as_ocp("head-on")) is None
