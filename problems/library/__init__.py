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

A new problem is one module here whose function carries :func:`library_problem`.

All have a running cost quadratic in ``u`` and a flow affine in ``u``, so the HMP minimiser
``u* = argmin_u H`` is explicit.
"""

import importlib
import pkgutil

from hybridoc.problems.library.ball_on_slope import ball_on_slope
from hybridoc.problems.library.bouncing_ball import bouncing_ball
from hybridoc.problems.library.juggling_paddle import juggling_paddle
from hybridoc.problems.library.pendulum_wall import pendulum_wall
from hybridoc.problems.library.registry import LIBRARY, NOTES, library_problem

__all__ = [
    "LIBRARY",
    "ball_on_slope",
    "bouncing_ball",
    "describe",
    "juggling_paddle",
    "library_problem",
    "pendulum_wall",
]

# every module of the package registers its problems (adding a problem is adding a file)
for _info in pkgutil.iter_modules(__path__):
    if not _info.name.startswith("_"):
        importlib.import_module(f"{__name__}.{_info.name}")


def describe(name: str) -> str:
    """One line about a built-in library problem (its function's summary)."""
    fn = LIBRARY[name]
    doc = getattr(fn, "func", fn).__doc__ or ""
    line = doc.strip().splitlines()[0] if doc.strip() else name
    return line + (f" ({NOTES[name]})" if name in NOTES else "")
