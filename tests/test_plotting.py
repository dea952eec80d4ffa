"""Figures: produced, to scale, saved as non-empty PNG."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.figure import Figure
from matplotlib.patches import Circle

import hybridoc
from hybridoc.plotting import plot_controls, plot_costates, plot_scene, save_figure

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def multiple():
    scene = hybridoc.load_scene("multiple-collision")
    return scene, hybridoc.gradient(scene)


def _is_png(path) -> bool:
    data = path.read_bytes()
    return len(data) > 5000 and data[:8] == PNG_MAGIC


def _circles(ax):
    return [p for p in ax.patches if isinstance(p, Circle)]


def test_scene_without_evaluation(tmp_path):
    scene = hybridoc.load_scene("single-collision")
    fig = plot_scene(scene)
    ax = fig.axes[0]
    assert ax.get_aspect() == 1.0
    circles = _circles(ax)
    assert len(circles) == 2
    for c, d in zip(circles, scene.discs, strict=True):  # drawn to scale at t = 0
        assert c.get_radius() == d.radius
        assert np.allclose(c.center, d.position)
    assert _is_png(save_figure(fig, tmp_path / "a" / "scene.png"))


def test_scene_with_events_and_wall(tmp_path, multiple):
    scene, g = multiple
    ev = g.evaluation
    fig = plot_scene(scene, ev, title="custom")
    ax = fig.axes[0]
    assert ax.get_title() == "custom" and ax.get_aspect() == 1.0
    # initial discs, final discs, and one faint disc per body in each event
    n_event_discs = sum(sum(b in {"ball1", "ball2"} for b in e.bodies) for e in ev.events)
    assert len(_circles(ax)) == 2 + 2 + n_event_discs
    # the paths start at the initial positions and end at s(T)
    paths = [ln for ln in ax.lines if len(ln.get_xdata()) > 100]
    assert len(paths) == 2
    for i, ln in enumerate(paths):
        xy = np.column_stack([ln.get_xdata(), ln.get_ydata()])
        assert np.allclose(xy[0], scene.discs[i].position)
        assert np.allclose(xy[-1], ev.final_state[2 * i : 2 * i + 2], atol=1e-12)
    # the wall y = 1 is drawn across the view, and the wall contact marker lies on it
    wall = [ln for ln in ax.lines if np.allclose(ln.get_ydata(), 1.0) and ln.get_linewidth() > 2]
    assert len(wall) == 1
    crosses = [ln for ln in ax.lines if ln.get_marker() == "x"]
    assert len(crosses) == len(ev.events)
    assert np.isclose(crosses[1].get_ydata()[0], 1.0, atol=1e-9)  # event 2: ball2 / wall
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "wall" in legend and "target" in legend
    assert any("ball2 / wall" in t for t in legend)
    assert _is_png(save_figure(fig, tmp_path / "multi.png"))


def test_scene_into_given_axes():
    fig = Figure()
    ax = fig.add_subplot()
    out = plot_scene("head-on", ax=ax)
    assert out is fig and len(_circles(ax)) == 2


def test_the_scene_is_drawn_from_the_problems_geometry(tmp_path, multiple):
    """plot_scene asks the problem for its geometry, not its type: a scene and its compiled
    problem give the same PNG bytes; a problem without a geometry is one clear error, and
    plot_trajectories draws it as states against time instead."""
    from hybridoc.errors import SceneError
    from hybridoc.plotting import plot_trajectories

    scene, g = multiple
    ocp = hybridoc.as_ocp(scene)
    assert ocp.capabilities.geometry is not None
    pngs = [
        save_figure(plot_scene(p, g.evaluation), tmp_path / f"{k}.png").read_bytes()
        for k, p in enumerate([scene, ocp])
    ]
    assert pngs[0] == pngs[1]
    ball = hybridoc.as_ocp("bouncing-ball")
    with pytest.raises(SceneError, match="no geometry"):
        plot_scene(ball)
    fig = plot_trajectories(ball, {"guess": hybridoc.evaluate(ball)})
    assert len(fig.axes) >= ball.nx and not _circles(fig.axes[0])


def test_controls_overlay(tmp_path, multiple):
    scene, g = multiple
    u = scene.initial_controls()
    grid = scene.time_grid()
    events = [e.time for e in g.evaluation.events]
    fig = plot_controls(
        grid,
        {"guess": u, "step": u - 10 * g.d_controls},
        scene.control_labels(),
        title="t",
        event_times=events,
    )
    axes = fig.axes
    assert len(axes) == 2
    for k, ax in enumerate(axes):
        assert ax.get_ylabel() == scene.control_labels()[k]
        stairs = ax.patches
        assert len(stairs) == 2
        assert np.array_equal(stairs[0].get_data().values, u[:, k])
        assert np.array_equal(stairs[1].get_data().edges, grid)
        vlines = [ln for ln in ax.lines if ln.get_linestyle() == "--"]
        assert len(vlines) == len(events)
    assert _is_png(save_figure(fig, tmp_path / "controls.png"))
    with pytest.raises(ValueError, match="expected \\(480, 2\\)"):
        plot_controls(grid, {"bad": u[:-1]}, scene.control_labels())


def test_costates_split_at_jumps(tmp_path, multiple):
    scene, g = multiple
    labels = scene.to_ocp().state_labels
    events = [e.time for e in g.evaluation.events]
    fig = plot_costates(g.costate_times, g.costates, labels, events)
    visible = [a for a in fig.axes if a.get_visible()]
    assert len(visible) == len(labels) == 8
    solid = [ln for ln in visible[0].lines if ln.get_linestyle() == "-"]
    assert len(solid) == len(events) + 1  # one piece per inter-event interval
    assert _is_png(save_figure(fig, tmp_path / "costates.png"))
    fig = plot_costates(
        {"a": g.costate_times, "b": g.costate_times}, {"a": g.costates, "b": g.costates}, labels
    )
    assert fig.axes[0].get_legend() is not None
