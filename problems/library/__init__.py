"""A library of classic hybrid optimal control problems beyond disc scenes.

Each function returns a :class:`~hybridoc.HybridOCP` with keyword parameters and documented
defaults; ``ocp.meta`` holds ``"family"``, ``"params"`` (all parameters, defaults resolved)
and ``"claimed_sequence"``: for the configurations checked independently, without hybridoc's
solvers, in ``tests/library_optima.py``, the optimal event sequence (guard names in event
order); ``None`` for any other configuration (no claim).

- :func:`bouncing_ball`: 1-D ball with thrust, floor bounces (0, 1 or 2 bounces optimal).
- :func:`ball_on_slope`: 2-D ball with 2-D thrust bouncing on an inclined plane.
- :func:`juggling_paddle`: an actuated paddle that drives a passive ball only by impacts.
- :func:`pendulum_wall`: a torque-controlled pendulum bouncing on a wall (non-polynomial).

All have a running cost quadratic in ``u`` and a flow affine in ``u``, so the HMP minimiser
``u* = argmin_u H`` is explicit.
"""

from functools import partial

from .ball_on_slope import ball_on_slope
from .bouncing_ball import bouncing_ball
from .juggling_paddle import juggling_paddle
from .pendulum_wall import pendulum_wall

__all__ = [
    "LIBRARY",
    "ball_on_slope",
    "bouncing_ball",
    "describe",
    "juggling_paddle",
    "pendulum_wall",
]

#: built-in name (as ``hybridoc problems`` lists it) -> function returning the problem with
#: its defaults; other configurations: ``path/to/file.py:function`` or the functions in Python
LIBRARY = {
    "bouncing-ball": bouncing_ball,
    "bouncing-ball-2": partial(bouncing_ball, bounces=2),
    "ball-on-slope": ball_on_slope,
    "juggling-paddle": juggling_paddle,
    "pendulum-wall": pendulum_wall,
}


def describe(name: str) -> str:
    """One line about a built-in library problem (its function's summary)."""
    fn = LIBRARY[name]
    doc = getattr(fn, "func", fn).__doc__ or ""
    line = doc.strip().splitlines()[0] if doc.strip() else name
    return line + (" (two bounces)" if name.endswith("-2") else "")
