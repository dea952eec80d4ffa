"""gd asks the problem, not its name (issue #30): the learning rate and iterations of plain
gradient descent come from the problem's hints (``capabilities.hints_for("gd")``), each
option is declared once (GDOptions), and a bad option is one OptionError line."""

from __future__ import annotations

import dataclasses
import inspect

import numpy as np
import pytest

import hybridoc
from hybridoc.capabilities import Capabilities
from hybridoc.errors import OptionError
from hybridoc.problems import load_problem
from hybridoc.problems.paper import PAPER_SETTINGS
from hybridoc.solvers.gd import GDOptions, checked_options, default_settings, solve_gd
from hybridoc.solvers.gradcheck import DEFAULT_GD_SETTINGS, paper_gd_settings


def _with_hints(ocp: hybridoc.HybridOCP, hints: dict) -> hybridoc.HybridOCP:
    caps = ocp.capabilities
    return ocp.replace(
        capabilities=Capabilities(caps.flow, caps.geometry, caps.spec, {"gd": hints})
    )


def test_the_paper_scenes_keep_the_paper_settings() -> None:
    for name, (lr, iters) in PAPER_SETTINGS.items():
        ocp = hybridoc.as_ocp(name)
        assert default_settings(ocp, "gd") == (lr, iters)
        o = checked_options(ocp, GDOptions(optimizer="gd"))
        assert (o.lr, o.iters) == (lr, iters)
        assert paper_gd_settings(load_problem(name)) == (lr, iters)


def test_a_scene_named_like_a_paper_problem_gets_no_paper_settings() -> None:
    """The name decides nothing: a user's scene called single-collision, without hints,
    gets the generic defaults (it got the paper's lr 200 by its name before)."""
    scene = dataclasses.replace(load_problem("head-on"), name="single-collision")
    ocp = scene.to_ocp()
    assert ocp.name == "single-collision" and not ocp.capabilities.hints_for("gd")
    assert default_settings(ocp, "gd") == default_settings(hybridoc.as_ocp("head-on"), "gd")
    assert default_settings(ocp, "gd")[0] != PAPER_SETTINGS["single-collision"][0]
    assert paper_gd_settings(scene) == DEFAULT_GD_SETTINGS


def test_hints_of_any_problem_set_plain_gds_defaults_only() -> None:
    ocp = _with_hints(hybridoc.as_ocp("bouncing-ball"), {"lr": 7.0, "iters": 3})
    assert default_settings(ocp, "gd") == (7.0, 3)
    assert default_settings(ocp, "lbfgs") == (0.1, 300)  # the hints are plain gd's
    assert default_settings(ocp, "adam") == (0.05, 1000)
    o = checked_options(ocp, GDOptions(optimizer="gd", lr=2.0))  # a user's option wins
    assert (o.lr, o.iters) == (2.0, 3)
    sol = solve_gd(ocp, optimizer="gd")
    assert sol.settings["lr"] == 7.0 and sol.settings["iters"] == 3
    # one hint alone: the other default stays
    only_lr = _with_hints(hybridoc.as_ocp("bouncing-ball"), {"lr": 7.0})
    assert default_settings(only_lr, "gd") == (7.0, 1000)


def test_a_bad_hint_is_an_option_error() -> None:
    ocp = _with_hints(hybridoc.as_ocp("bouncing-ball"), {"lr": -1.0})
    with pytest.raises(OptionError, match="lr must be a positive finite number, got -1.0"):
        checked_options(ocp, GDOptions(optimizer="gd"))
    checked_options(ocp, GDOptions(optimizer="gd", lr=0.5))  # given: the hint is not read


@pytest.mark.parametrize(
    ("options", "match"),
    [
        ({"starts": 0}, "starts must be an integer >= 1"),
        ({"iters": 1.5}, "iters must be an integer >= 0"),
        ({"lr": "1e-3"}, "lr must be a positive finite number"),
        ({"optimizer": "sgd"}, "unknown optimizer 'sgd'; choose one of gd, adam, lbfgs"),
        ({"integrator": "rk4"}, "unknown integrator 'rk4'"),
        ({"path": "gpu"}, "unknown path 'gpu'; choose one of auto, compiled, torch"),
        ({"terminal_iters": 0}, "terminal_iters must be an integer >= 1"),
        ({"smoothing": "1e-4"}, "smoothing weights must be finite numbers >= 0"),
        ({"time_limit": -1}, "time_limit must be a positive number of seconds"),
    ],
)
def test_options_are_checked_once_on_construction(options: dict, match: str) -> None:
    with pytest.raises(OptionError, match=match) as err:
        GDOptions(**options)
    assert "\n" not in str(err.value)
    with pytest.raises(OptionError, match=match):  # the same check, through the wrapper
        solve_gd("head-on", **options)


def test_the_wrapper_takes_exactly_the_options() -> None:
    params = inspect.signature(solve_gd).parameters
    names = [f.name for f in dataclasses.fields(GDOptions)]
    assert list(params) == ["problem", "initial", "progress", *names]
    with pytest.raises(TypeError, match="unexpected keyword argument 'learning_rate'"):
        solve_gd("head-on", learning_rate=1.0)


def _plain(ocp: hybridoc.HybridOCP) -> hybridoc.HybridOCP:
    """The same functions and capabilities in a plain HybridOCP (no disc type)."""
    plain = hybridoc.HybridOCP(
        f=ocp.f, L=ocp.L, phi=ocp.phi, guards=list(ocp.guards), x0=ocp.x0,
        horizon=ocp.horizon, steps=ocp.steps, u_guess=ocp.u_guess,
        capabilities=ocp.capabilities,
    )  # fmt: skip
    assert type(plain) is hybridoc.HybridOCP
    return plain


def test_aimed_starts_follow_the_geometry_not_the_type() -> None:
    """The multi-start's aimed starts, the reference's rich-scene test and crossval's start
    count read capabilities.geometry: a plain HybridOCP with a disc scene's geometry gets
    the same starts bit for bit, a disc scene without one gets none."""
    from hybridoc.solvers.candidates import rich_scene
    from hybridoc.solvers.gd.method import _crossval_defaults
    from hybridoc.solvers.multistart import diverse_controls

    ocp = hybridoc.as_ocp("damped-walls")
    plain, bare = _plain(ocp), ocp.replace(capabilities=Capabilities())
    want = diverse_controls(ocp)
    got = diverse_controls(plain)
    assert want and [k for k, _ in got] == [k for k, _ in want]
    for (_, a), (_, b) in zip(got, want, strict=True):
        np.testing.assert_array_equal(a, b)
    assert rich_scene(plain) == rich_scene(ocp) != ""
    assert diverse_controls(bare) == [] and rich_scene(bare) == ""
    assert _crossval_defaults(plain, {})["starts"] == _crossval_defaults(ocp, {})["starts"] == 32
    assert _crossval_defaults(bare, {})["starts"] == 16
