"""The numerical tolerances of hybridoc, named and documented in one table.

Each is a number that decides something a user sees: whether a control is feasible, whether
two costs agree, whether a result earns ``success``. Modules take them from here by name
(:data:`TOLERANCES`, or the constants below) instead of writing the literal, so that one
value has one meaning and one place. The options a user can set (a method's ``tolerance``,
``rtol``, ...) default to these; the table is not a setting.

Relative tolerances compare with the larger magnitude of the two numbers (or with the
problem's own scale, :mod:`hybridoc.scales`); absolute ones are in the problem's units.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

__all__ = ["TOLERANCES", "Tolerance", "value"]


@dataclass(frozen=True)
class Tolerance:
    """One named tolerance: its value, whether it is relative, and what it decides."""

    name: str
    value: float
    relative: bool
    meaning: str


_TABLE = (
    Tolerance(
        "feasibility",
        1e-9,
        False,
        "a judged violation of a control bound (and of the reference's path "
        "constraints) above which a result is infeasible",
    ),
    Tolerance(
        "path",
        1e-6,
        False,
        "a judged path-constraint violation above which a transcription's result is "
        "infeasible (its mesh resolves the path to about this)",
    ),
    Tolerance(
        "terminal",
        1e-8,
        False,
        "a terminal equality or inequality residual within which the constraint holds",
    ),
    Tolerance(
        "cheaper",
        1e-9,
        True,
        "a known control cheaper than a result by more than this makes it not optimal",
    ),
    Tolerance(
        "crossval",
        5e-3,
        True,
        "the cost gap to the reference within which a method agrees with it in "
        "crossval, unless the method declares its own",
    ),
    Tolerance(
        "shooting", 1e-9, True, "the reference's Newton residual, relative to the problem's scales"
    ),
    Tolerance(
        "integration", 1e-13, True, "the adaptive Runge-Kutta error of the judge's generic flow"
    ),
    Tolerance("costate", 1e-13, True, "the integration of a Solution's costates between events"),
    Tolerance(
        "commute",
        1e-9,
        True,
        "two simultaneous jumps whose results differ by more than this do not commute",
    ),
    Tolerance(
        "stall", 1e-9, True, "gd's loss change per window below which the descent has stalled"
    ),
    Tolerance(
        "refine",
        1e-7,
        True,
        "the transcription's cost change between meshes below which it has converged",
    ),
    Tolerance(
        "defect",
        1e-4,
        False,
        "a transcription phase's defect above which its events are not those judged",
    ),
    Tolerance(
        "penetration",
        1e-9,
        False,
        "a guard below minus this at a step's end was crossed unseen: the judge refuses "
        "(and a compiled rollout's cell was not resolved)",
    ),
    Tolerance(
        "active",
        1e-9,
        False,
        "a path row within this of 0 under the reference's control is on an active arc",
    ),
    Tolerance(
        "rollout",
        1e-9,
        True,
        "a compiled closed-loop rollout's cost within this of the judge's is certified",
    ),
    Tolerance(
        "bound_sign",
        1e-9,
        True,
        "a final time at its bound is a minimum in T when H(T) has the right sign to this",
    ),
    Tolerance(
        "saturation",
        1e-7,
        True,
        "how far (relative to 1 plus the largest bound magnitude) argmin H may lie past "
        "a bound on an arc",
    ),
    Tolerance(
        "touch",
        1e-6,
        True,
        "a boundary arc shorter than this fraction of the horizon is a touch point",
    ),
    Tolerance(
        "discrete",
        1e-6,
        True,
        "gd's discrete loss within this of its own discrete optimum agrees in crossval",
    ),
    Tolerance(
        "kink",
        1e-6,
        True,
        "a point at a kink is stationary when the least convex combination of the "
        "gradients around it is below this",
    ),
)

TOLERANCES: Mapping[str, Tolerance] = MappingProxyType({t.name: t for t in _TABLE})
"""Every tolerance by name."""


def value(name: str) -> float:
    """The value of the tolerance ``name`` (:data:`TOLERANCES`)."""
    return TOLERANCES[name].value


FEASIBILITY = value("feasibility")
PATH = value("path")
TERMINAL = value("terminal")
CHEAPER = value("cheaper")
CROSSVAL = value("crossval")
