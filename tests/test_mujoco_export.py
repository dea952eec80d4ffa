"""The MuJoCo export (hybridoc.workflows.mujoco, ``hybridoc export mjcf``) against closed
forms, finite differences and the exact reference (issue #19)."""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys

import numpy as np
import pytest

import hybridoc
from hybridoc.errors import ControlsError, HybridocError, SceneError
from hybridoc.problems import Disc, Scene, load_scene
from hybridoc.workflows import mujoco as mj

mujoco = pytest.importorskip("mujoco")


@pytest.fixture(scope="module")
def optimum() -> hybridoc.Solution:
    """single-collision's exact optimum (the extremal of its one-event sequence, which the
    reference's search finds to be the optimum; 1 s instead of the search's 4 s)."""
    return hybridoc.solve("single-collision", "reference", sequence=["ball1|ball2"])


def _with_velocity(scene: Scene, name: str, velocity: tuple[float, float], **changes) -> Scene:
    discs = tuple(
        dataclasses.replace(d, velocity=velocity) if d.name == name else d for d in scene.discs
    )
    return dataclasses.replace(scene, discs=discs, **changes)


def test_export_loads_with_the_scene_s_data():
    scene = load_scene("single-collision")
    text = mj.scene_to_mjcf(scene, substeps=10, stiffness=1e6)
    m = mujoco.MjModel.from_xml_string(text)
    assert (m.nq, m.nv, m.nu) == (4, 4, 2)
    assert m.opt.timestep == pytest.approx(1.0 / 4800, rel=1e-15)
    assert np.all(m.opt.gravity == 0.0)
    motors = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_ACTUATOR, i) for i in range(m.nu)]
    assert motors == scene.control_labels()
    for disc in scene.discs:
        g = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, disc.name)
        assert m.geom_size[g][0] == disc.radius
        assert m.geom_condim[g] == 1
        assert m.body_mass[m.geom_bodyid[g]] == pytest.approx(disc.mass, rel=1e-12)
    model = mj.load_model(scene)
    data = model.new_data()
    assert np.array_equal(model.state(data), scene.initial_state())
    # qpos0 (a plain mj_resetData) is the scene's start too, through the joints' ref
    assert np.array_equal(m.qpos0, scene.initial_state()[:4])


def test_free_text_names_are_escaped():
    scene = dataclasses.replace(load_scene("head-on"), name='a "b" & <c> -- d')
    m = mujoco.MjModel.from_xml_string(mj.scene_to_mjcf(scene))
    assert m.nu == 2


def test_walls_are_planes_on_the_free_side():
    scene = load_scene("damped-walls")
    m = mujoco.MjModel.from_xml_string(mj.scene_to_mjcf(scene))
    for w in scene.walls:
        g = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, w.name)
        assert m.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        normal = d.geom_xmat[g].reshape(3, 3)[:, 2]  # a plane's normal is its local z axis
        assert np.allclose(normal[:2], w.normal, atol=1e-12)
        assert np.allclose(d.geom_xpos[g][:2], w.point, atol=1e-12)


@pytest.mark.parametrize(
    ("name", "disc", "velocity", "substeps", "horizon", "steps"),
    [
        # single-collision's discs head on (ball2 sits 1 above ball1), e = 1
        ("single-collision", "ball1", (0.0, 2.0), 10, 0.5, 240),
        # damped-walls' puck into the right wall, e = 0.7: a damped contact needs
        # sqrt(k) h = 0.05 for 1% (docs/mujoco.rst)
        ("damped-walls", "puck", (2.0, 0.0), 20, 0.5, 500),
    ],
)
def test_head_on_bounce_keeps_the_restitution(name, disc, velocity, substeps, horizon, steps):
    scene = _with_velocity(load_scene(name), disc, velocity, horizon=horizon, steps=steps)
    model = mj.load_model(scene, substeps=substeps, stiffness=1e6)
    roll = model.rollout(np.zeros((scene.steps, scene.n_controls)))
    assert roll.contact_steps > 10  # resolved in many steps, and over by the end
    n = scene.n_discs
    v_end = roll.states[-1, 2 * n :].reshape(n, 2)
    v0 = np.linalg.norm(velocity)
    if n == 2:  # relative normal velocity after / before (the normal is y)
        ratio = (v_end[1, 1] - v_end[0, 1]) / v0
        energy = np.sum(v_end**2) / v0**2
        assert energy == pytest.approx(scene.restitution**2, rel=0.01)
    else:
        ratio = -v_end[0, 0] / v0
    assert ratio == pytest.approx(scene.restitution, rel=0.01)


def test_restitution_formula_closed_forms():
    assert mj.restitution_of_damping(0.0) == 1.0
    assert mj.restitution_of_damping(1.0) == pytest.approx(math.exp(-2.0), rel=1e-15)
    # continuous across the critical damping ratio, and decreasing
    below, above = mj.restitution_of_damping(1 - 1e-9), mj.restitution_of_damping(1 + 1e-9)
    assert below == pytest.approx(math.exp(-2.0), rel=1e-6)
    assert above == pytest.approx(math.exp(-2.0), rel=1e-6)
    zs = np.linspace(0.0, 5.0, 51)
    es = [mj.restitution_of_damping(z) for z in zs]
    assert np.all(np.diff(es) < 0)
    for e in (0.9, 0.7, 0.3, 0.05):
        b = mj.contact_damping(e, 1e6)
        assert mj.restitution_of_damping(b / 2e3) == pytest.approx(e, rel=1e-12)


def test_restitution_formula_against_an_ode():
    """The clamped spring-damper integrated with a fine RK4, an independent check."""
    zeta, w = 0.3, 1.0

    def acc(r, v):
        return -2 * zeta * w * v - w * w * r

    r, v, dt = 0.0, -1.0, 1e-4
    while True:
        k1 = (v, acc(r, v))
        k2 = (v + 0.5 * dt * k1[1], acc(r + 0.5 * dt * k1[0], v + 0.5 * dt * k1[1]))
        k3 = (v + 0.5 * dt * k2[1], acc(r + 0.5 * dt * k2[0], v + 0.5 * dt * k2[1]))
        k4 = (v + dt * k3[1], acc(r + dt * k3[0], v + dt * k3[1]))
        r += dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        v += dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        if acc(r, v) <= 0.0 and v > 0:  # the contact would pull: it has ended
            break
    assert v == pytest.approx(mj.restitution_of_damping(zeta), rel=1e-4)


def test_the_exact_optimum_costs_within_one_percent_in_mujoco(optimum):
    model = mj.load_model("single-collision", substeps=10, stiffness=1e6)
    roll = model.rollout(optimum.controls)
    assert abs(roll.cost / optimum.cost - 1) < 0.01
    assert 0 < roll.max_penetration < 0.005  # v / sqrt(k): about 2 mm
    # the same control given on MuJoCo's steps (N K rows) is the same rollout
    fine = np.repeat(optimum.controls, 10, axis=0)
    assert model.cost(fine) == roll.cost


def test_euler_position_offset_closed_form():
    """MuJoCo's semi-implicit Euler ends a constant push at x = a T^2/2 (1 + 1/M)."""
    scene = Scene(
        horizon=1.0,
        discs=(Disc("puck", (0.0, 0.0), 0.2, mass=2.0, actuated=True, target=(1.0, 0.0)),),
        steps=50,
    )
    model = mj.load_model(scene, substeps=4)  # one disc: nothing to touch, any step does
    u = np.tile([5.0, -1.0], (50, 1))
    end = model.rollout(u).states[-1, :2]
    a, steps, h = u[0] / 2.0, 200, 1.0 / 200
    assert np.allclose(end, a / 2 * (1 + 1 / steps), rtol=1e-12, atol=1e-15)
    exact = hybridoc.evaluate(scene, u).final_state[:2]
    assert np.allclose(exact, a / 2, rtol=1e-12)
    assert np.allclose(end - exact, a * h / 2, rtol=1e-9)  # the O(h) offset, a h T / 2


def test_gradient_matches_finite_differences_without_contact():
    scene = load_scene("damped-walls").with_steps(12)
    model = mj.load_model(scene, substeps=3, stiffness=1e3)  # a coarse grid: a soft contact
    rng = np.random.default_rng(0)
    u = rng.uniform(-1.0, 1.0, (12, 2))
    cost, grad = model.cost_and_gradient(u)
    assert model.rollout(u).contact_steps == 0  # smooth: the puck stays off the walls
    assert cost == model.cost(u)
    fd = np.empty_like(u)
    step = 1e-6
    for idx in np.ndindex(*u.shape):
        du = np.zeros_like(u)
        du[idx] = step
        fd[idx] = (model.cost(u + du) - model.cost(u - du)) / (2 * step)
    assert np.allclose(grad, fd, rtol=1e-6, atol=1e-9)
    # per MuJoCo step: the (N, nu) gradient is the sum over the K steps of each interval
    _, fine = model.cost_and_gradient(np.repeat(u, 3, axis=0))
    assert fine.shape == (36, 2)
    assert np.allclose(fine.reshape(12, 3, 2).sum(axis=1), grad, rtol=1e-12, atol=1e-15)


def test_bad_controls_and_scenes_are_user_errors():
    model = mj.load_model("single-collision", substeps=2, stiffness=1e5)
    with pytest.raises(ControlsError, match=r"480 or 960 rows"):
        model.rollout(np.zeros((100, 2)))
    bad = np.zeros((480, 2))
    bad[3, 1] = np.nan
    with pytest.raises(ControlsError, match="finite"):
        model.cost(bad)
    sticky = dataclasses.replace(load_scene("damped-walls"), restitution=0.0)
    with pytest.raises(SceneError, match="restitution"):
        mj.scene_to_mjcf(sticky)
    with pytest.raises(SceneError, match=r"substeps >= 3"):
        mj.scene_to_mjcf("single-collision", substeps=1, stiffness=1e6)
    with pytest.raises(SceneError, match="not a disc scene"):
        mj.scene_to_mjcf("bouncing-ball")
    bounded = load_scene("single-collision").to_ocp().replace(u_min=[-5.0, -5.0])
    with pytest.raises(SceneError, match="control bounds"):
        mj.scene_to_mjcf(bounded)


def test_missing_mujoco_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "mujoco", None)  # import mujoco raises ImportError
    with pytest.raises(HybridocError, match=r"pip install hybridoc\[mujoco\]"):
        mj.load_model("single-collision")
    assert "<mujoco" in mj.scene_to_mjcf("single-collision")  # the text needs no MuJoCo


def test_importing_hybridoc_does_not_import_mujoco():
    code = (
        "import sys, hybridoc, hybridoc.workflows.mujoco, hybridoc.cli; "
        "hybridoc.cli.build_parser(); assert 'mujoco' not in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd="/")


def test_cli_export_writes_a_model_that_loads(tmp_path, capsys, optimum):
    from hybridoc.cli import main

    out = tmp_path / "sc.xml"
    assert main(["export", "mjcf", "single-collision", "--substeps", "10", "--out", str(out)]) == 0
    assert "compiles it" in capsys.readouterr().out
    model = mj.load_model("single-collision", xml=out)
    assert model.substeps == 10
    fresh = mj.load_model("single-collision", substeps=10)
    assert model.cost(optimum.controls) == fresh.cost(optimum.controls)
    # a folder: <problem>.xml in it; --json describes the file
    argv = ["export", "mjcf", "damped-walls", "--substeps", "40", "--out", str(tmp_path)]
    assert main([*argv, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["path"] == str(tmp_path / "damped-walls.xml")
    assert report["damping"] == mj.contact_damping(0.7, mj.DEFAULT_STIFFNESS)
    assert f"default {mj.DEFAULT_SUBSTEPS})" in " ".join(
        subprocess.run(
            [sys.executable, "-m", "hybridoc", "export", "--help"],
            capture_output=True, text=True, check=True, cwd="/",
        ).stdout.split()
    )  # fmt: skip


@pytest.mark.parametrize(
    "argv",
    [
        ["export", "mjcf", "single-collision", "--substeps", "0"],
        ["export", "mjcf", "single-collision", "--substeps", "1", "--stiffness", "1e6"],
        ["export", "mjcf", "no-such-scene"],
        ["export", "mjcf", "bouncing-ball"],
        ["export", "stl", "single-collision"],
        ["export", "mjcf", "single-collision", "--json"],
    ],
)
def test_cli_export_bad_input_exits_2(argv, capsys):
    from hybridoc.cli import main

    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("hybridoc: error:") and len(err.strip().splitlines()) == 1


def test_a_mujoco_ctrl_log_is_judged_through_the_cli(tmp_path, capsys, optimum):
    """MuJoCo's N K rows of ``ctrl`` (``evaluate --substeps K``) judge to the cost of the
    N-row control they hold."""
    from hybridoc.cli import main

    model = mj.load_model("single-collision", substeps=10)
    log = model.rollout(optimum.controls).controls  # one row per MuJoCo step
    assert log.shape == (4800, 2)
    np.save(tmp_path / "ctrl.npy", log)
    argv = ["evaluate", "single-collision", "--controls", str(tmp_path / "ctrl.npy")]
    assert main([*argv, "--substeps", "10", "--json"]) == 0
    judged = json.loads(capsys.readouterr().out)["cost"]
    assert judged == pytest.approx(
        hybridoc.evaluate("single-collision", optimum.controls).cost, rel=1e-12
    )


def test_gradcheck_against_reports_mujoco_s_gradient_cosine(tmp_path, capsys):
    from hybridoc.cli import main

    scene = load_scene("single-collision")
    u = scene.initial_controls()
    _, grad = mj.load_model(scene, substeps=10, stiffness=1e6).cost_and_gradient(u)
    exact = hybridoc.gradient(scene, u).d_controls
    cosine = np.sum(grad * exact) / (np.linalg.norm(grad) * np.linalg.norm(exact))
    np.save(tmp_path / "grad.npy", grad)
    argv = ["gradcheck", "single-collision", "--against", str(tmp_path / "grad.npy")]
    assert main([*argv, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["cosine"] == pytest.approx(cosine, rel=1e-12)
    assert 0.9 < cosine < 0.95  # the sawtooth's mismatch (issue #19 measured 0.929)
