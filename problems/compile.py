"""Compile a :class:`~hybridoc.problems.Scene` to a :class:`~hybridoc.HybridOCP`.

State layout ``s = [x_1, y_1, ..., x_n, y_n, vx_1, vy_1, ..., vx_n, vy_n]``; controls are the
forces of the actuated discs in scene order. Guards: one per contact of
:func:`hybridoc.problems.physics.contacts` (disc pairs, then disc-wall, disc-major), with the
gaps, normals and impulses of :mod:`hybridoc.problems.physics`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from hybridoc.capabilities import Body, Capabilities, Geometry, LinearControlFlow, Plane
from hybridoc.ocp import Guard
from hybridoc.problems import physics as ph
from hybridoc.problems.disc_ocp import DiscOCP
from hybridoc.resources import check_judge
from hybridoc.scales import disc_scales

if TYPE_CHECKING:  # pragma: no cover
    from hybridoc.problems.scene import Scene

__all__ = ["disc_accelerations", "disc_capabilities", "scene_to_ocp"]


def scene_to_ocp(scene: Scene) -> DiscOCP:
    """Build the hybrid OCP of a disc scene (exact polynomial flow map, impulse resets)."""
    ops = ph.CASADI
    n = scene.n_discs
    # every pair's guard enters the judge's kernels (about 200 kB each): refuse at once a
    # scene whose judge cannot fit (202 discs: 4.3 GB, hybridoc.resources.JUDGE_GUARD_BYTES)
    check_judge(n, len(scene.walls), scene.steps)
    nx = 4 * n
    s = ca.SX.sym("s", nx)
    u = ca.SX.sym("u", scene.n_controls)
    p = [s[2 * i : 2 * i + 2] for i in range(n)]
    v = [s[2 * n + 2 * i : 2 * n + 2 * i + 2] for i in range(n)]
    masses = [d.mass for d in scene.discs]

    a_flat = ca.vertcat(*disc_accelerations(scene, u))
    f = ca.vertcat(s[2 * n :], a_flat)
    L = scene.control_weight * ca.sumsqr(u)
    phi = ca.SX(0)
    for i, d in enumerate(scene.discs):
        if d.target is not None:
            phi += ph.target_cost(p[i], ca.DM(d.target), ops)
    flow_map = _flow_map(s, u, a_flat, L, n)
    guards = [_contact_guard(scene, c, s, p, v, masses) for c in ph.contacts(n, len(scene.walls))]

    labels = [f"{d.name}.{c}" for d in scene.discs for c in ("x", "y")]
    labels += [f"{d.name}.{c}" for d in scene.discs for c in ("vx", "vy")]
    ocp = DiscOCP(
        f=ca.Function("f", [s, u], [f]),
        L=ca.Function("L", [s, u], [L]),
        phi=ca.Function("phi", [s], [phi]),
        guards=guards,
        x0=scene.initial_state(),
        horizon=scene.horizon,
        steps=scene.steps,
        u_guess=scene.initial_controls(),
        flow_map=flow_map,
        state_labels=labels,
        control_labels=scene.control_labels(),
        name=scene.name,
        source_scene=scene,
        scales=disc_scales(
            [d.position for d in scene.discs],
            [d.radius for d in scene.discs],
            masses,
            [d.target for d in scene.discs if d.target is not None],
            scene.horizon,
            [d.mass for d in scene.discs if d.actuated],
            [w.point for w in scene.walls],
        ),
        capabilities=disc_capabilities(scene, a_flat, u),
        meta={
            "n_discs": n,
            "disc_names": [d.name for d in scene.discs],
            "masses": np.array(masses),
            "radii": np.array([d.radius for d in scene.discs]),
            "restitution": scene.restitution,
            "control_weight": scene.control_weight,
        },
    )
    ocp.mark_compiled()  # its functions are the scene's: DiscOCP.local_frame may move it
    return ocp


def disc_capabilities(scene: Scene, a_flat: ca.SX, u: ca.SX) -> Capabilities:
    """What a compiled scene offers (:class:`~hybridoc.capabilities.Capabilities`): its
    closed-form flow ``f = (v, A u)``, ``L = eps |u|^2``, its geometry, its spec and its
    solver hints (the scene's ``[hints.<method>]`` tables)."""
    A = np.asarray(ca.DM(ca.jacobian(a_flat, u)), dtype=float).reshape(a_flat.numel(), u.numel())
    geometry = Geometry(
        bodies=tuple(Body(d.name, d.radius, d.mass, d.actuated, d.target) for d in scene.discs),
        planes=tuple(Plane(w.name, w.point, w.normal) for w in scene.walls),
        restitution=scene.restitution,
    )
    return Capabilities(
        flow=LinearControlFlow(A, scene.control_weight),
        geometry=geometry,
        spec={"kind": "scene", "toml": scene.to_toml()},
        hints=scene.hints,
    )


def disc_accelerations(scene: Scene, u: ca.SX) -> list[ca.SX]:
    """Each disc's acceleration, a 2-vector of the control symbols ``u`` (the actuated discs'
    forces in scene order): force / mass for the actuated discs, zero for the others."""
    acc = []
    k = 0
    for d in scene.discs:
        if d.actuated:
            acc.append(u[k : k + 2] / d.mass)
            k += 2
        else:
            acc.append(ca.SX.zeros(2))
    return acc


def _flow_map(s: ca.SX, u: ca.SX, a_flat: ca.SX, L: ca.SX, n: int) -> ca.Function:
    """The exact flow over a duration ``h`` under constant forces, and its running cost."""
    h = ca.SX.sym("h")
    p_end = s[: 2 * n] + s[2 * n :] * h + 0.5 * a_flat * h**2
    v_end = s[2 * n :] + a_flat * h
    return ca.Function(
        "flow_map", [s, u, h], [ca.vertcat(p_end, v_end), L * h], ["s", "u", "h"], ["s_end", "cost"]
    )


def _contact_guard(
    scene: Scene, c: ph.Contact, s: ca.SX, p: list[ca.SX], v: list[ca.SX], masses: list[float]
) -> Guard:
    """The guard of one contact: its gap, the impulse reset of the velocities and its detector."""
    ops = ph.CASADI
    e = scene.restitution
    i = c.i
    di = scene.discs[i]
    new_v = list(v)
    if c.is_pair:
        assert c.j is not None
        j = c.j
        dj = scene.discs[j]
        dp = p[i] - p[j]
        R = di.radius + dj.radius
        psi, nrm = ph.pair_gap(dp, R, ops)
        w = ph.normal_speed(v[i] - v[j], nrm, ops)
        J = ph.impulse(w, 1 / masses[i] + 1 / masses[j], e)
        new_v[i] = v[i] + J / masses[i] * nrm
        new_v[j] = v[j] - J / masses[j] * nrm
        name, kind, bodies = f"{di.name}|{dj.name}", "disc-disc", (di.name, dj.name)
        detector, degree = ph.pair_detector(dp, R, ops), 4
    else:
        assert c.wall is not None
        wall = scene.walls[c.wall]
        nw = ca.DM(wall.normal)
        psi = ph.wall_gap(p[i], ca.DM(wall.point), nw, di.radius, ops)
        w = ph.normal_speed(v[i], nw, ops)
        new_v[i] = v[i] + ph.impulse(w, 1 / masses[i], e) / masses[i] * nw
        name, kind, bodies = f"{di.name}|{wall.name}", "disc-wall", (di.name, wall.name)
        detector, degree = None, 2
    reset = ca.vertcat(*p, *new_v)
    return Guard.from_expressions(
        name, s, psi, reset, kind=kind, bodies=bodies, detector=detector, degree=degree
    )
