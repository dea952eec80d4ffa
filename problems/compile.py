"""Compile a :class:`~hybridoc.problems.Scene` to a :class:`~hybridoc.HybridOCP`.

State layout ``s = [x_1, y_1, ..., x_n, y_n, vx_1, vy_1, ..., vx_n, vy_n]``; controls are the
forces of the actuated discs in scene order. Guards: one per disc pair (in scene order
``(i, j)``, ``i < j``), then one per disc and wall (disc-major). That order is the order in
which simultaneous events are resolved.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from hybridoc.ocp import Guard, HybridOCP
from hybridoc.problems.scene import Scene

__all__ = ["scene_to_ocp"]


def scene_to_ocp(scene: Scene) -> HybridOCP:
    """Build the hybrid OCP of a disc scene (exact polynomial flow map, impulse resets)."""
    n = scene.n_discs
    nx = 4 * n
    s = ca.SX.sym("s", nx)
    u = ca.SX.sym("u", scene.n_controls)
    p = ca.reshape(s[: 2 * n], 2, n)  # column i: position of disc i
    v = ca.reshape(s[2 * n :], 2, n)
    masses = [d.mass for d in scene.discs]
    eps = scene.control_weight
    e = scene.restitution

    # accelerations: B u / m, as a 2 x n matrix
    acc_cols = []
    k = 0
    for i, d in enumerate(scene.discs):
        if d.actuated:
            acc_cols.append(u[k : k + 2] / masses[i])
            k += 2
        else:
            acc_cols.append(ca.SX.zeros(2))
    a = ca.horzcat(*acc_cols)
    a_flat = ca.reshape(a, 2 * n, 1)
    f = ca.vertcat(s[2 * n :], a_flat)
    L = eps * ca.sumsqr(u)
    phi = ca.SX(0)
    for i, d in enumerate(scene.discs):
        if d.target is not None:
            phi += ca.sumsqr(p[:, i] - ca.DM(d.target))

    h = ca.SX.sym("h")
    p_end = s[: 2 * n] + s[2 * n :] * h + 0.5 * a_flat * h**2
    v_end = s[2 * n :] + a_flat * h
    flow_map = ca.Function(
        "flow_map", [s, u, h], [ca.vertcat(p_end, v_end), L * h], ["s", "u", "h"], ["s_end", "cost"]
    )

    guards: list[Guard] = []
    for i in range(n):
        for j in range(i + 1, n):
            di, dj = scene.discs[i], scene.discs[j]
            dp = p[:, i] - p[:, j]
            dist = ca.norm_2(dp)
            R = di.radius + dj.radius
            nrm = dp / dist
            w = ca.dot(v[:, i] - v[:, j], nrm)
            J = -(1 + e) * w / (1 / masses[i] + 1 / masses[j])
            vnew = ca.horzcat(
                *[
                    v[:, m] + J / masses[i] * nrm
                    if m == i
                    else v[:, m] - J / masses[j] * nrm
                    if m == j
                    else v[:, m]
                    for m in range(n)
                ]
            )
            reset = ca.vertcat(s[: 2 * n], ca.reshape(vnew, 2 * n, 1))
            guards.append(
                Guard.from_expressions(
                    f"{di.name}|{dj.name}",
                    s,
                    dist - R,
                    reset,
                    kind="disc-disc",
                    bodies=(di.name, dj.name),
                    detector=ca.sumsqr(dp) - R**2,
                    degree=4,
                )
            )
    for i, d in enumerate(scene.discs):
        for wall in scene.walls:
            nw = ca.DM(wall.normal)
            psi = ca.dot(p[:, i] - ca.DM(wall.point), nw) - d.radius
            w = ca.dot(v[:, i], nw)
            vnew = ca.horzcat(
                *[v[:, m] - (1 + e) * w * nw if m == i else v[:, m] for m in range(n)]
            )
            reset = ca.vertcat(s[: 2 * n], ca.reshape(vnew, 2 * n, 1))
            guards.append(
                Guard.from_expressions(
                    f"{d.name}|{wall.name}",
                    s,
                    psi,
                    reset,
                    kind="disc-wall",
                    bodies=(d.name, wall.name),
                    degree=2,
                )
            )

    labels = [f"{d.name}.{c}" for d in scene.discs for c in ("x", "y")]
    labels += [f"{d.name}.{c}" for d in scene.discs for c in ("vx", "vy")]
    return HybridOCP(
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
        meta={
            "scene": scene,
            "n_discs": n,
            "disc_names": [d.name for d in scene.discs],
            "masses": np.array(masses),
            "radii": np.array([d.radius for d in scene.discs]),
            "restitution": e,
            "control_weight": eps,
        },
    )
