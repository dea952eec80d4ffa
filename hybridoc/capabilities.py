"""What a problem offers beyond the model: :class:`Capabilities`.

A :class:`~hybridoc.HybridOCP` is functions and data. Some problems offer more, and methods
and workflows use it when it is there:

* a closed-form flow (:class:`LinearControlFlow`): ``f = (v, A u)`` and ``L = eps |u|^2``,
  which the reference's exact polynomial phases need;
* a geometry of round bodies and planes (:class:`Geometry`), for plots and aimed starts;
* a serialisable spec (:attr:`Capabilities.spec`), from which the problem is rebuilt (the
  datasets and worker processes);
* solver hints (:attr:`Capabilities.hints`), option defaults per method that the problem's
  author tuned.

The compilers fill the record (a disc scene fills all four); a problem a user writes has
none of them unless the user gives it. Code above ``problems/`` asks for a capability
(``ocp.capabilities.flow is not None``), never for a type: the architecture test forbids
importing the disc classes there, outside the disc simulator and the contact models.

The record describes the problem's *structure*: :meth:`HybridOCP.replace
<hybridoc.HybridOCP.replace>` keeps it when only data change (``x0``, ``steps``, ...) and
drops it when the functions change. Positions and velocities are data, so the geometry does
not hold them: :meth:`Geometry.position` reads them from a state.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from hybridoc.errors import SceneError

__all__ = ["Body", "Capabilities", "Geometry", "LinearControlFlow", "Plane"]


def _frozen_array(value: Any, what: str, ndim: int) -> np.ndarray:
    a = np.array(value, dtype=float)
    if a.ndim != ndim or not np.all(np.isfinite(a)):
        raise SceneError(f"{what} must be a finite {ndim}-D array, got {value!r}")
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class LinearControlFlow:
    """A flow ``f(s, u) = (v, A u)`` on a state ``s = (q, v)`` of two equal halves, with the
    running cost ``L = eps |u|^2``: the phases between events are polynomials in time.

    Attributes
    ----------
    A
        ``(nx / 2, nu)``, the constant map from controls to accelerations.
    eps
        The control weight, positive.
    """

    A: np.ndarray
    eps: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "A", _frozen_array(self.A, "LinearControlFlow.A", 2))
        eps = float(self.eps)
        if not (math.isfinite(eps) and eps > 0):
            raise SceneError(f"LinearControlFlow.eps must be positive and finite, got {eps}")
        object.__setattr__(self, "eps", eps)


@dataclass(frozen=True)
class Body:
    """A round body of a :class:`Geometry`.

    Attributes
    ----------
    name
        Its name (the guards' names are ``"a|b"`` of two bodies or a body and a plane).
    radius, mass
        Positive.
    actuated
        Whether a control force acts on it (two controls, in the order of the bodies).
    target
        The point its terminal cost pulls it to, or ``None``.
    """

    name: str
    radius: float
    mass: float
    actuated: bool = False
    target: tuple[float, float] | None = None


@dataclass(frozen=True)
class Plane:
    """A fixed line (a wall) of a :class:`Geometry`, through ``point`` and perpendicular to
    the unit ``normal``; the bodies are on the side the normal points to."""

    name: str
    point: tuple[float, float]
    normal: tuple[float, float]


@dataclass(frozen=True)
class Geometry:
    """Round bodies in the plane and fixed planes, with impacts of restitution
    ``restitution``. Body ``i``'s position is ``s[2 i : 2 i + 2]`` and its velocity
    ``s[2 n + 2 i : 2 n + 2 i + 2]`` for ``n`` bodies; the controls are the actuated bodies'
    forces, two each, in body order."""

    bodies: tuple[Body, ...]
    planes: tuple[Plane, ...] = ()
    restitution: float = 1.0

    @property
    def n_bodies(self) -> int:
        """The number of bodies."""
        return len(self.bodies)

    @property
    def actuated_indices(self) -> tuple[int, ...]:
        """The indices of the actuated bodies, in control order."""
        return tuple(i for i, b in enumerate(self.bodies) if b.actuated)

    def position(self, state: np.ndarray, i: int) -> np.ndarray:
        """Body ``i``'s position in ``state`` (shape ``(..., 4 n)``)."""
        return np.asarray(state)[..., 2 * i : 2 * i + 2]

    def velocity(self, state: np.ndarray, i: int) -> np.ndarray:
        """Body ``i``'s velocity in ``state`` (shape ``(..., 4 n)``)."""
        n = self.n_bodies
        return np.asarray(state)[..., 2 * n + 2 * i : 2 * n + 2 * i + 2]


def _frozen_mapping(value: Mapping[str, Any] | None, what: str) -> Mapping[str, Any]:
    if value is None:
        return MappingProxyType({})
    if not isinstance(value, Mapping):
        raise SceneError(f"{what} must be a mapping, got {type(value).__name__}")
    return MappingProxyType(dict(value))


@dataclass(frozen=True, eq=False)
class Capabilities:
    """What a problem offers beyond its functions (module notes). Every field is optional.

    Attributes
    ----------
    flow
        The closed-form flow data, or ``None``.
    geometry
        The bodies and planes, or ``None``.
    spec
        A JSON-serialisable mapping with a ``"kind"`` key from which
        :func:`hybridoc.problems.from_spec` rebuilds the problem as it was compiled, or
        ``None`` where the problem cannot be rebuilt from data (a Python problem file). A
        data-only ``replace`` keeps it: the data it was compiled with (``x0``, ``steps``,
        ``horizon``) may then differ from the problem's, which
        :func:`hybridoc.problems.spec_of` takes into account for disc scenes.
    hints
        Per method name, option defaults the problem's author tuned (for example the paper's
        learning rates for gd). A method reads only its own entry; a user's option wins.
    """

    flow: LinearControlFlow | None = None
    geometry: Geometry | None = None
    spec: Mapping[str, Any] | None = None
    hints: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.flow is not None and not isinstance(self.flow, LinearControlFlow):
            raise SceneError(f"Capabilities.flow must be a LinearControlFlow, got {self.flow!r}")
        if self.geometry is not None and not isinstance(self.geometry, Geometry):
            raise SceneError(f"Capabilities.geometry must be a Geometry, got {self.geometry!r}")
        if self.spec is not None:
            spec = _frozen_mapping(self.spec, "Capabilities.spec")
            if "kind" not in spec:
                raise SceneError('Capabilities.spec needs a "kind" key')
            try:
                json.dumps(dict(spec))
            except (TypeError, ValueError) as exc:
                raise SceneError(f"Capabilities.spec must be JSON-serialisable: {exc}") from None
            object.__setattr__(self, "spec", spec)
        hints = _frozen_mapping(self.hints, "Capabilities.hints")
        object.__setattr__(
            self,
            "hints",
            MappingProxyType(
                {k: _frozen_mapping(v, f"Capabilities.hints[{k!r}]") for k, v in hints.items()}
            ),
        )

    def __reduce__(self) -> tuple[Any, ...]:
        # mapping proxies do not pickle; worker processes receive problems by pickle
        spec = None if self.spec is None else dict(self.spec)
        hints = {k: dict(v) for k, v in self.hints.items()}
        return (Capabilities, (self.flow, self.geometry, spec, hints))

    def hints_for(self, method: str) -> Mapping[str, Any]:
        """The option defaults this problem suggests to ``method`` (empty when none)."""
        return self.hints.get(method, MappingProxyType({}))
