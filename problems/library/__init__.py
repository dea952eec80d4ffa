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

from .ball_on_slope import ball_on_slope
from .bouncing_ball import bouncing_ball
from .juggling_paddle import juggling_paddle
from .pendulum_wall import pendulum_wall

__all__ = ["ball_on_slope", "bouncing_ball", "juggling_paddle", "pendulum_wall", "LIBRARY"]

#: name -> problem function
LIBRARY = {
    "bouncing_ball": bouncing_ball,
    "ball_on_slope": ball_on_slope,
    "juggling_paddle": juggling_paddle,
    "pendulum_wall": pendulum_wall,
}
