"""Scene files that several test modules write: the paper's two-disc strike with a
distribution over the target disc's position (one draw per sample)."""

from __future__ import annotations


def strike_scene(name: str, steps: int = 480) -> str:
    """The TOML text of ball1 (actuated) striking ball2 towards the origin, horizon 1 s,
    ``steps`` grid steps, ball2's position drawn uniformly within 0.3 (seed 7)."""
    return f"""
name = "{name}"
horizon = 1.0
steps = {steps}
control_weight = 0.01

[[discs]]
name = "ball1"
position = [-1.0, -2.0]
radius = 0.2
actuated = true
initial_control = [0.0, 3.0]

[[discs]]
name = "ball2"
position = [-1.0, -1.0]
radius = 0.2
target = [0.0, 0.0]

[distribution]
seed = 7
[distribution.discs.ball2]
position = {{ uniform = [0.3, 0.3] }}
"""
