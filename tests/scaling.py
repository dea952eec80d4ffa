"""The same physical disc scene in other units, or moved: the transforms of issue #32.

Lengths scaled by ``L`` scale every position, radius, target, wall point, velocity (by
``L / T``) and force (by ``M L / T**2``); times by ``T`` scale the horizon; masses by ``M``
scale every mass; the control weight scales by ``T**3 / M**2`` so that the running cost
keeps its units. The optimal cost then scales by exactly ``L**2``, event
times by ``T``, and a shift of every position (and target and wall point) changes nothing.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from hybridoc.problems import Scene


def transform(
    scene: Scene,
    *,
    length: float = 1.0,
    time: float = 1.0,
    mass: float = 1.0,
    shift: tuple[float, float] = (0.0, 0.0),
) -> Scene:
    """``scene`` with lengths x ``length``, times x ``time``, masses x ``mass``, moved by
    ``shift`` (after scaling)."""
    s = np.asarray(shift, dtype=float)
    force = mass * length / time**2
    discs = []
    for d in scene.discs:
        kw: dict = dict(
            position=tuple(np.asarray(d.position) * length + s),
            radius=d.radius * length,
            velocity=tuple(np.asarray(d.velocity) * length / time),
            mass=d.mass * mass,
        )
        if d.initial_control is not None:
            kw["initial_control"] = np.asarray(d.initial_control, dtype=float) * force
        if d.target is not None:
            kw["target"] = tuple(np.asarray(d.target) * length + s)
        discs.append(dataclasses.replace(d, **kw))
    walls = [
        dataclasses.replace(w, point=tuple(np.asarray(w.point) * length + s)) for w in scene.walls
    ]
    return dataclasses.replace(
        scene,
        discs=tuple(discs),
        walls=tuple(walls),
        horizon=scene.horizon * time,
        control_weight=scene.control_weight * time**3 / mass**2,
    )


def transform_controls(
    u: np.ndarray, *, length: float = 1.0, time: float = 1.0, mass: float = 1.0
) -> np.ndarray:
    """Controls (forces) of the original scene in the transformed scene's units."""
    return np.asarray(u, dtype=float) * (mass * length / time**2)


def cost_factor(*, length: float = 1.0, **_: object) -> float:
    """How the cost scales: ``length**2`` (times, masses and shifts change nothing)."""
    return length**2


# The corners the property tests sweep (issue #32: each factor over [1e-6, 1e6], shifts up to 1e6).
CORNERS = [
    dict(length=1e-6),
    dict(length=1e6),
    dict(time=1e-3),
    dict(time=1e3),
    dict(mass=1e-6),
    dict(mass=1e6),
    dict(shift=(1e6, -1e6)),
    dict(length=1e-3, time=1e2, mass=1e4, shift=(-3e5, 2e5)),
]


def moved_back(scene: Scene, shift: tuple[float, float]) -> Scene:
    """``scene`` (already moved by ``shift``) moved back by ``-shift``: the near scene whose
    move is ``scene`` exactly where the coordinates lie within a factor two of the shift
    (Sterbenz), and to an ulp of the near coordinates elsewhere. ``transform(s, shift=...)``
    itself rounds each coordinate to the spacing of the shift, a change of the physical
    scene (about 1e-10 at a shift of 1e6) that compares against this one, not against
    ``s``."""
    return transform(scene, shift=(-shift[0], -shift[1]))
