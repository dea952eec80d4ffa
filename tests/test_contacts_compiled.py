"""Every contact model on the compiled CasADi path equals its torch step (1e-10, relative).

For each registered model with each setting that the torch simulator supports (every TOI
correction of the impulse models, the exact integrator with ``toi="both"``), on the paper's
two scenes and on random scenes of three or four discs with walls: (a) one step from random,
contact-rich states (the step of :class:`~hybridoc.solvers.compiled.CompiledLoss`, built by
:func:`hybridoc.solvers.casadi_step.make_step`, against ``Simulator.step``); (b) the whole
loss and its gradient with respect to the controls and the
initial state (:class:`~hybridoc.solvers.compiled.CompiledLoss` against torch autograd through
:class:`~hybridoc.solvers.simulator.Simulator`). Also the limits and errors of the compiled
path and what ``compare-contacts`` prints.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import hybridoc
from hybridoc.cli import main
from hybridoc.errors import SceneError
from hybridoc.problems import Scene
from hybridoc.problems.scene import Disc, Wall
from hybridoc.solvers.casadi_step import MAX_ENUMERATED_CONTACTS, make_step
from hybridoc.solvers.compiled import CompiledLoss
from hybridoc.solvers.contacts import CONTACT_MODELS, TOI_MODES, contact_model
from hybridoc.solvers.simulator import Simulator

RTOL = 1e-10


def settings() -> list[tuple[str, str, str]]:
    """``(model, toi, integrator)`` of every registered model, as the torch path runs them."""
    out = []
    for name, cls in CONTACT_MODELS.items():
        if cls.impulse_based:
            out += [(name, toi, "symplectic-euler") for toi in TOI_MODES]
            out.append((name, "both", "exact"))
        else:
            out.append((name, "both", "symplectic-euler"))
    return out


SETTINGS = settings()


def random_scene(seed: int, n_discs: int, n_walls: int, steps: int = 60) -> Scene:
    """Discs with random radii and masses around the origin, walls of a box around them."""
    rng = np.random.default_rng(seed)
    discs = []
    x = [0.75 * i - 0.375 * (n_discs - 1) for i in range(n_discs)]
    for i in range(n_discs):
        # the actuated discs are pushed at the target disc and towards a wall
        push = (8.0 * np.sign(x[1] - x[i]), float(rng.choice([-6.0, 6.0])))
        discs.append(
            Disc(
                name=f"d{i}",
                position=(x[i], 0.0),
                radius=float(rng.uniform(0.15, 0.3)),
                mass=float(rng.uniform(0.5, 2.0)),
                actuated=i != 1,
                initial_control=None if i == 1 else push,
                target=(0.3, 0.2) if i == 1 else None,
            )
        )
    box = [((0.0, 1.0), (0.0, -1.0)), ((0.0, -1.0), (0.0, 1.0)), ((-2.5, 0.0), (1.0, 0.0))]
    walls = []
    for k in range(n_walls):
        (px, py), (nx, ny) = box[k]
        angle = float(rng.uniform(-0.3, 0.3))  # tilted, so that normals are not axis-aligned
        c, s = np.cos(angle), np.sin(angle)
        walls.append(Wall(point=(px, py), normal=(c * nx - s * ny, s * nx + c * ny)))
    return Scene(
        horizon=0.5,
        discs=tuple(discs),
        walls=tuple(walls),
        steps=steps,
        restitution=float(rng.uniform(0.3, 1.0)),
        name=f"random-{n_discs}-{n_walls}",
    )


SCENES = {
    "single-collision": lambda: hybridoc.load_scene("single-collision"),
    "multiple-collision": lambda: hybridoc.load_scene("multiple-collision"),
    "random-3-1": lambda: random_scene(3, 3, 1),  # 6 contacts: lcp and convex compile
    "random-4-2": lambda: random_scene(4, 4, 2),  # 14 contacts: beyond their enumeration
}


def contact_rich_states(scene: Scene, rng: np.random.Generator, count: int) -> np.ndarray:
    """States whose discs overlap, touch or approach each other and the walls.

    The disc centres are drawn in a small region (about one diameter per disc), so that many
    contacts are detected in one step, several at once; velocities are large enough to cross
    a gap of a few millimetres in one step.
    """
    n = scene.n_discs
    r = max(d.radius for d in scene.discs)
    states = np.empty((count, 4 * n))
    for b in range(count):
        centre = np.zeros(2)
        if scene.walls and b % 2:
            # next to a wall: the centre one radius off it
            w = scene.walls[b % len(scene.walls)]
            centre = np.asarray(w.point) + (r + rng.uniform(-0.02, 0.02)) * np.asarray(w.normal)
        spread = 1.2 * r * max(n - 1, 1) ** 0.5
        states[b, : 2 * n] = (centre + rng.uniform(-spread, spread, size=(n, 2))).ravel()
        states[b, 2 * n :] = rng.normal(scale=4.0, size=2 * n)
    return states


def compiled_ok(scene: Scene, model: str, toi: str, integrator: str) -> bool:
    """Whether the model's CasADi step serves this scene (else the one-line reason is checked)."""
    reason = contact_model(model, toi=toi).casadi_unsupported(scene, integrator)
    if reason is None:
        return True
    assert "torch" in reason and "\n" not in reason
    with pytest.raises(SceneError, match=str(MAX_ENUMERATED_CONTACTS)):
        make_step(scene, contact_model(model, toi=toi), integrator)
    return False


def rel_err(a: np.ndarray, b: np.ndarray) -> float:
    """``max |a - b| / max |b|``: the error relative to the size of the reference ``b``."""
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


def _loss_and_grads(loss_fn, u0: np.ndarray, x0: np.ndarray):
    u = torch.tensor(u0, requires_grad=True)
    x = torch.tensor(x0, requires_grad=True)
    value = loss_fn(u, x)
    gu, gx = torch.autograd.grad(value.sum(), (u, x))
    return value.detach().numpy(), gu.numpy(), gx.numpy()


@pytest.mark.parametrize("scene_name", list(SCENES))
def test_compiled_path_equals_torch(scene_name: str) -> None:
    scene = SCENES[scene_name]()
    if scene.steps > 60:
        scene = scene.with_steps(60)  # the same collisions on a coarser grid: faster in torch
    n, N, nu = scene.n_discs, scene.steps, scene.n_controls
    rng = np.random.default_rng(7)
    # (a) one step from contact-rich states
    states = contact_rich_states(scene, rng, 40)
    controls = rng.normal(scale=20.0, size=(len(states), nu))
    p = torch.tensor(states[:, : 2 * n].reshape(-1, n, 2))
    v = torch.tensor(states[:, 2 * n :].reshape(-1, n, 2))
    u_step = torch.tensor(controls)
    # (b) rollouts that collide, from perturbed initial states
    B = 3
    u0 = scene.initial_controls()[None] + rng.normal(scale=1.0, size=(B, N, nu))
    x0 = scene.initial_state() + np.concatenate(
        [rng.normal(scale=0.05, size=(B, 2 * n)), rng.normal(scale=0.5, size=(B, 2 * n))], 1
    )
    rollout = Simulator(scene, toi="none").rollout(torch.tensor(u0), torch.tensor(x0))
    penetrated = Simulator(scene).gaps(rollout[:, :, : 2 * n].reshape(-1, n, 2))
    assert float(penetrated.min()) < 0  # the plain direct step leaves contacts penetrated
    for model, toi, integrator in SETTINGS:
        if not compiled_ok(scene, model, toi, integrator):
            continue
        label = f"{model}/{toi}/{integrator}"
        obj = contact_model(model, toi=toi)  # one object through both paths
        sim = Simulator(scene, contact=obj, integrator=integrator)
        comp = CompiledLoss(scene, obj, integrator)
        assert comp.simulation == "disc"
        # (a)
        pt, vt = sim.step(p, v, sim.accelerations(u_step))
        free_v = v + sim.accelerations(u_step) * scene.dt
        changed = (vt - free_v).abs().amax((1, 2)) > 1e-9
        assert float(changed.double().mean()) > 0.2, f"{label}: too few contacts"
        expected = torch.cat([pt.reshape(len(states), -1), vt.reshape(len(states), -1)], 1)
        got = np.asarray(comp.step.map(len(states))(states.T, controls.T)[0]).T
        err = rel_err(got, expected.numpy())
        assert err <= RTOL, f"{label}: one step off by {err:.3g}"
        # (b)
        J_t, gu_t, gx_t = _loss_and_grads(sim.loss, u0, x0)
        J_c, gu_c, gx_c = _loss_and_grads(comp.loss, u0, x0)
        assert rel_err(J_c, J_t) <= RTOL, f"{label}: loss off by {rel_err(J_c, J_t):.3g}"
        assert rel_err(gu_c, gu_t) <= RTOL, f"{label}: d/du off by {rel_err(gu_c, gu_t):.3g}"
        assert rel_err(gx_c, gx_t) <= RTOL, f"{label}: d/dx0 off by {rel_err(gx_c, gx_t):.3g}"


def test_every_model_is_compiled_and_unsupported_settings_say_why() -> None:
    assert all(cls.compiled for cls in CONTACT_MODELS.values())
    scene = hybridoc.load_scene("multiple-collision")
    for name in ("compliant", "pbd", "lcp/none"):
        with pytest.raises(SceneError, match="exact") as info:
            make_step(scene, name, toi=name.partition("/")[2] or "both", integrator="exact")
        assert "\n" not in str(info.value)
    with pytest.raises(SceneError, match="integrator"):
        make_step(scene, "pbd", integrator="rk4")
    with pytest.raises(SceneError, match="unknown contact model"):
        make_step(scene, "glue")


def test_gradient_descent_uses_the_compiled_path_within_the_limit() -> None:
    from hybridoc.solvers.gd import make_loss

    small = hybridoc.load_scene("multiple-collision").to_ocp()
    for name in CONTACT_MODELS:
        _, path = make_loss(small, contact_model(name), "symplectic-euler")
        assert path == "compiled", name
    big = random_scene(4, 4, 2).to_ocp()
    _, path = make_loss(big, contact_model("lcp/both"), "symplectic-euler")
    assert path == "torch"  # beyond the enumeration limit the torch path takes over
    with pytest.raises(SceneError, match="torch"):
        make_loss(big, contact_model("convex/both"), "symplectic-euler", path="compiled")


def test_compare_contacts_names_the_models(capsys, tmp_path, monkeypatch) -> None:
    import hybridoc.progress

    monkeypatch.setattr(hybridoc.progress, "QUIET_LOG_S", 0.0)  # progress lines from the start
    monkeypatch.setattr(hybridoc.progress, "QUIET_S", 0.0)
    code = main(
        ["compare-contacts", "single-collision", "--iters", "2", "--contact", "lcp/both,pbd"]
    )
    assert code == 0
    captured = capsys.readouterr()
    for label in ("lcp/both (1/2)", "pbd (2/2)"):
        assert label in captured.err  # the progress line names the model it runs
    assert "lcp/both" in captured.out and "pbd" in captured.out
    assert "no contact" not in captured.out  # the initial guess strikes the target disc
    # discs far apart, pushed away from each other: nothing ever collides
    far = Scene(
        horizon=1.0,
        steps=40,
        discs=(
            Disc(name="a", position=(-2.0, 0.0), radius=0.2, actuated=True,
                 initial_control=(-1.0, 0.0)),
            Disc(name="b", position=(2.0, 0.0), radius=0.2, target=(2.0, 0.5)),
        ),
        name="far",
    )  # fmt: skip
    path = tmp_path / "far.toml"
    path.write_text(far.to_toml())
    code = main(["compare-contacts", str(path), "--iters", "1", "--contact", "convex/none,pbd"])
    assert code == 0
    out = capsys.readouterr().out
    assert "convex/none: no contact in the final trajectory" in out
    assert "pbd: no contact in the final trajectory" in out
    code = main(["compare-contacts", str(path), "--iters", "1", "--contact", "compliant", "--json"])
    result = json.loads(capsys.readouterr().out)
    assert result["models"][0]["note"] == "compliant: no contact in the final trajectory"
